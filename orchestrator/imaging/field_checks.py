"""Checks that the two slices show what the model assumes, each failing with one sentence that says what to do.

- The whole cross-section is inside the field of view: where the leg touches the image's edge, the segmented
  skin is the edge of the image, and the garment would press on a line that is not the skin.
- The garment compresses: in plane strain the tissues barely change in area (nearly incompressible), but the
  garment squeezes fluid out and the leg loses about 1 % of its area (the phantom: 1.1 %). A loaded leg larger
  than the unloaded one by more than `MAX_GROWTH` (segmentation jitter is about 0.2 %) is the signature of
  the two images swapped, and no garment model can fit it.
- Each slice holds at least `MIN_GREY_LEVELS` grey levels (background, soft tissue and bone): a blank export, or a
  mask saved in the image's place, holds one or two, and no threshold can tell a tissue from another there.
- Pixels with no value (NaN in a float image, given the background's grey level when read) lie in the
  background: within `MISSING_MARGIN_MM` of the leg they would be segmented and measured as if they were
  tissue or skin.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import ImagingError

MAX_BORDER_CONTACT_MM = 1.0
MAX_GROWTH = 0.005
MISSING_MARGIN_MM = 2.0
MIN_GREY_LEVELS = 3


def check_grey_levels(image: np.ndarray, image_name: str) -> None:
    """ImagingError when the image holds fewer than MIN_GREY_LEVELS grey levels (its finite pixels)."""
    values = np.unique(np.asarray(image)[np.isfinite(image)])
    if len(values) >= MIN_GREY_LEVELS:
        return
    held = (f"a single grey level ({values[0]:g} in every pixel)" if len(values) == 1 else
            f"only {len(values)} grey levels ({', '.join(f'{v:g}' for v in values)})")
    raise ImagingError(f"{image_name} holds {held}, so no tissue can be told from another; export the MRI slice "
                       "itself again (this file is blank or a mask, not an image of the calf)")


def check_leg_in_view(labels: np.ndarray, pixel_size_mm, image_name: str) -> None:
    leg = np.asarray(labels) > 0
    dy, dx = pixel_size_mm
    edges = {"top": leg[0, :].sum() * dx, "bottom": leg[-1, :].sum() * dx,
             "left": leg[:, 0].sum() * dy, "right": leg[:, -1].sum() * dy}
    touching = {side: length for side, length in edges.items() if length > MAX_BORDER_CONTACT_MM}
    if touching:
        where = ", ".join(f"{length:.1f} mm along the {side} edge" for side, length in touching.items())
        raise ImagingError(f"the leg in {image_name} touches the image border ({where}): the whole cross-section "
                           "must be inside the field of view, or the skin there is the image's edge; export the "
                           "slice with a larger field of view")


def check_compression(leg_unloaded: np.ndarray, leg_loaded: np.ndarray, unloaded_name: str, loaded_name: str) -> float:
    """Relative change of the leg's area from I0 to I1 (negative: the garment compresses); ImagingError when
    the leg grows by more than MAX_GROWTH."""
    area0, area1 = float(np.count_nonzero(leg_unloaded)), float(np.count_nonzero(leg_loaded))
    change = area1 / area0 - 1.0
    if change > MAX_GROWTH:
        raise ImagingError(f"the leg in {loaded_name} (with the garment) is {100 * change:.1f} % larger than in "
                           f"{unloaded_name} (without): a garment compresses the leg; are the unloaded and loaded "
                           "images swapped? Rename them, or check that both are the same slice")
    return change


def check_missing_pixels(missing: np.ndarray | None, leg: np.ndarray, pixel_size_mm, image_name: str) -> int:
    """Number of pixels with no value; ImagingError when any lies in the leg or within MISSING_MARGIN_MM of it."""
    from scipy import ndimage

    if missing is None or not missing.any():
        return 0
    distance_mm = ndimage.distance_transform_edt(~np.asarray(leg, bool), sampling=pixel_size_mm)
    near = missing & (distance_mm <= MISSING_MARGIN_MM)
    if near.any():
        rows, cols = np.nonzero(near)
        x_mm, y_mm = cols.mean() * pixel_size_mm[1], rows.mean() * pixel_size_mm[0]
        raise ImagingError(f"{image_name} has {int(near.sum())} pixels with no value (NaN) in the leg or within "
                           f"{MISSING_MARGIN_MM:g} mm of its skin, around (x, y) = ({x_mm:.1f}, {y_mm:.1f}) mm: "
                           "they would be measured as tissue; export the slice without a mask over the leg")
    return int(missing.sum())
