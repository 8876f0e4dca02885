"""Synthetic calf slices for the demo and the tests: geometry, T1 appearance, loaded images, case folders.

Two phantoms, drawn and rendered independently: `CalfPhantom` (`geometry`, `appearance`, `render`) and
`MRIPhantom` (`mri`); both go through `render_unloaded`, `make_loaded_image` and `write_case`."""

from .appearance import T1Contrast
from .case import write_case
from .geometry import COMPARTMENTS, LANDMARK_NAMES, CalfGeometry, CalfShape, Tissue
from .mri import LegGeometry, LegShape, MRIContrast, MRIPhantom
from .render import (CalfPhantom, Phantom, as_displacement_fn, bone_clamped_compression, loaded_labels,
                     make_loaded_image, material_points, render_unloaded)

__all__ = ["COMPARTMENTS", "LANDMARK_NAMES", "CalfGeometry", "CalfPhantom", "CalfShape", "LegGeometry", "LegShape",
           "MRIContrast", "MRIPhantom", "Phantom", "T1Contrast", "Tissue", "as_displacement_fn",
           "bone_clamped_compression", "loaded_labels", "make_loaded_image", "material_points", "render_unloaded",
           "write_case"]
