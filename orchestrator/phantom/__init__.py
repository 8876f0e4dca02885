"""Synthetic calf slices for the demo and the tests: geometry, T1 appearance, loaded images, case folders."""

from .appearance import T1Contrast
from .case import write_case
from .geometry import COMPARTMENTS, LANDMARK_NAMES, CalfGeometry, CalfShape, Tissue
from .render import (CalfPhantom, as_displacement_fn, bone_clamped_compression, loaded_labels, make_loaded_image,
                     material_points, render_unloaded)

__all__ = ["COMPARTMENTS", "LANDMARK_NAMES", "CalfGeometry", "CalfPhantom", "CalfShape", "T1Contrast", "Tissue",
           "as_displacement_fn", "bone_clamped_compression", "loaded_labels", "make_loaded_image", "material_points",
           "render_unloaded", "write_case"]
