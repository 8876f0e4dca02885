"""Synthetic calf slices for the demo and the tests: geometry, T1 appearance, loaded images, case folders.

Two phantoms, drawn and rendered independently: `CalfPhantom` (`geometry`, `appearance`, `render`) and
`MRIPhantom` (`mri`); both go through `render_unloaded`, `make_loaded_image` and `write_case`. A third,
`KspacePhantom` (`kspace3d`), is a 3D leg solved in 3D by CalculiX and imaged as a scanner does (slice profile,
chemical shift, coil, acquired k-space); it writes its own cases (`make_kspace_case`, `write_kspace_volume_case`)."""

from .appearance import T1Contrast
from .case import write_case
from .geometry import COMPARTMENTS, LANDMARK_NAMES, CalfGeometry, CalfShape, Tissue
from .kspace3d import KspacePhantom, Leg3D, LegMotion, make_kspace_case, write_kspace_volume_case
from .mri import LegGeometry, LegShape, MRIContrast, MRIPhantom
from .render import (
                     CalfPhantom,
                     Phantom,
                     as_displacement_fn,
                     bone_clamped_compression,
                     loaded_labels,
                     make_loaded_image,
                     material_points,
                     render_unloaded,
)

__all__ = ["COMPARTMENTS", "LANDMARK_NAMES", "CalfGeometry", "CalfPhantom", "CalfShape", "KspacePhantom", "Leg3D",
           "LegGeometry", "LegMotion", "LegShape", "MRIContrast", "MRIPhantom", "Phantom", "T1Contrast", "Tissue",
           "as_displacement_fn", "bone_clamped_compression", "loaded_labels", "make_loaded_image", "make_kspace_case",
           "material_points", "render_unloaded", "write_case", "write_kspace_volume_case"]
