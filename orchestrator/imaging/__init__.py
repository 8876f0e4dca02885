"""Imaging room: read case folders, align, segment, warp, contour mismatch, digital image correlation.

Conventions (DESIGN.md): positions in mm in the frame of the unloaded image I0 (x right along columns,
y down along rows, pixel (i, j) centred at ((j + 0.5) dx, (i + 0.5) dy)); pixel_size_mm = (dy, dx);
displacement fields are (2, H, W) arrays in mm (u_x, u_y) or callables u(x_mm, y_mm) -> (u_x, u_y);
labels 0 background, 1 fat (with skin), 2 muscle, 3 bone, >= 4 muscle compartments.
"""

from ..case.folder import Case, DisplacementPoints, ModelChoice, read_case, read_model_choice, write_case_folder
from ..core.errors import CaseError, ImagingError
from ..core.frame import RigidMotion, displacement_on_grid, pixel_centres_mm
from ..measure.dic import DICResult, correlate, grid_centres, roi_centres
from .align import align_on_bones, bone_centroids, resample_rigid
from .mismatch import ContourMismatch, MismatchResult, contour_pixels
from .segment import dice, segment_t1
from .warp import warp_image, warp_labels

__all__ = ["Case", "CaseError", "ContourMismatch", "DICResult", "DisplacementPoints", "ImagingError",
           "MismatchResult", "ModelChoice", "RigidMotion", "align_on_bones", "bone_centroids", "contour_pixels",
           "correlate", "dice", "displacement_on_grid", "grid_centres", "pixel_centres_mm", "read_case",
           "read_model_choice", "resample_rigid", "roi_centres", "segment_t1", "warp_image", "warp_labels",
           "write_case_folder"]
