"""Meshing: from region boundaries to a conforming triangle mesh, its deck include and VTU.

Two sources of geometry share one triangulation path (triangulate.py): a label image
(labels.py: 0 background, 1 fat with skin, 2 muscle, 3 bone, >= 4 muscle
compartments) and the analytic leg-like slice used to verify and benchmark the
engine (leg_slice.py). Conventions (positions in mm in the image frame, elements
counter-clockwise in deck coordinates, face numbering, set names) are in mesh.py.
"""

from ..core.errors import MeshingError
from .curves import Curve, SpacingRules
from .garment import GarmentBand, band_constants_for_tension, band_hoop_tension, garment_band
from .labels import (
                     TissueCurves,
                     fat_muscle_normals,
                     interface_curves,
                     mesh_from_labels,
                     mesh_tissue_curves,
                     region_image,
                     tissue_curves,
                     with_fat_moved_back,
)
from .leg_slice import (
                     DEFAULT_MATERIALS,
                     DEFAULT_PRESSURE_MPA,
                     LegSliceGeometry,
                     elements_for_dof,
                     leg_slice_deck,
                     leg_slice_geometry,
                     leg_slice_mesh,
                     leg_slice_mesh_for_dof,
)
from .mesh import Mesh, corner_angles_deg, read_include, signed_areas
from .triangulate import BONE_KEY_OFFSET, mesh_curves

__all__ = [
    "BONE_KEY_OFFSET",
    "Curve",
    "DEFAULT_MATERIALS",
    "DEFAULT_PRESSURE_MPA",
    "LegSliceGeometry",
    "GarmentBand",
    "Mesh",
    "MeshingError",
    "SpacingRules",
    "corner_angles_deg",
    "band_constants_for_tension",
    "band_hoop_tension",
    "elements_for_dof",
    "garment_band",
    "interface_curves",
    "leg_slice_deck",
    "leg_slice_geometry",
    "leg_slice_mesh",
    "leg_slice_mesh_for_dof",
    "mesh_curves",
    "mesh_from_labels",
    "fat_muscle_normals",
    "mesh_tissue_curves",
    "tissue_curves",
    "with_fat_moved_back",
    "TissueCurves",
    "read_include",
    "region_image",
    "signed_areas",
]
