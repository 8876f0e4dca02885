"""Segmentation of a T1-weighted calf slice into background, fat, muscle and bone.

The first paper segments the T1 slice into tibia, fibula, fat and muscle
(section 2.1.1); the second thresholds fat first, as it is bright in T1
(section 3.2). Here, on the image smoothed by a Gaussian of `smoothing_mm` (lengths in mm, so that
a finer matrix of the same leg segments the same):

1. three-class Otsu thresholds (`skimage.filters.threshold_multiotsu`) split
   dark (air, cortex, flowing blood, fascia), intermediate (muscle, skin) and
   bright (fat, fatty marrow) grey levels;
2. the leg is the largest non-dark component with its holes filled;
3. bones are the dark components inside the leg, opened to drop thin fascia,
   holes filled (so the bright marrow joins its cortex), larger than
   `min_bone_area_mm2` (veins are smaller);
4. muscle is the largest component of the non-bright, non-bone leg opened by
   a disk of `skin_opening_mm` (which cuts the thin skin ring away from it),
   grown back inside the non-bright mask, small holes (veins) filled;
5. fat is the rest of the leg: skin and superficial veins count as fat, as in
   the first paper's model (section 2.2.4).

Labels: 0 background, 1 fat, 2 muscle, 3 bone.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage import filters, morphology

from .errors import ImagingError

BACKGROUND, FAT, MUSCLE, BONE = 0, 1, 2, 3


def largest_component(mask: np.ndarray) -> np.ndarray:
    labelled, count = ndimage.label(mask)
    if count == 0:
        return np.zeros_like(mask, dtype=bool)
    sizes = np.bincount(labelled.ravel())
    sizes[0] = 0
    return labelled == int(np.argmax(sizes))


def segment_t1(image: np.ndarray, pixel_size_mm: tuple[float, float], *, smoothing_mm: float = 0.36,
               skin_opening_mm: float = 0.8, min_bone_area_mm2: float = 40.0,
               max_vein_hole_mm2: float = 30.0) -> np.ndarray:
    """Label map (uint8) of a T1 slice: 0 background, 1 fat (with skin), 2 muscle, 3 bone."""
    image = np.asarray(image, dtype=float)
    pixel_area = pixel_size_mm[0] * pixel_size_mm[1]
    # lengths in mm, not pixels: a 2048-pixel slice of the same leg has the same anatomy and the same noise per pixel
    scale_px = smoothing_mm / min(pixel_size_mm)
    smooth = ndimage.gaussian_filter(image, scale_px)
    dark_level, bright_level = filters.threshold_multiotsu(smooth, classes=3)

    leg = ndimage.binary_fill_holes(largest_component(smooth > dark_level))
    if leg.sum() * pixel_area < 100.0:
        raise ImagingError("no leg found in the image: it has no large region brighter than the background")

    dark = ndimage.binary_opening(leg & (smooth <= dark_level), structure=morphology.disk(max(1, int(round(scale_px)))))
    components, count = ndimage.label(dark)
    bone = np.zeros_like(leg)
    for index, piece in enumerate(ndimage.find_objects(components), start=1):
        filled = ndimage.binary_fill_holes(components[piece] == index)
        if filled.sum() * pixel_area >= min_bone_area_mm2:
            bone[piece] |= filled
    if not bone.any():
        raise ImagingError(f"no bone found: no dark ring inside the leg encloses {min_bone_area_mm2} mm^2")

    not_bright = leg & (smooth <= bright_level) & ~bone
    radius = max(1, int(round(skin_opening_mm / min(pixel_size_mm))))
    core = largest_component(ndimage.binary_opening(not_bright, structure=morphology.disk(radius)))
    muscle = not_bright & ndimage.binary_dilation(core, structure=morphology.disk(radius + 1))
    muscle = largest_component(muscle)
    max_hole = max(1, int(max_vein_hole_mm2 / pixel_area))
    muscle = morphology.remove_small_holes(muscle | bone, max_size=max_hole) & ~bone

    labels = np.zeros(image.shape, dtype=np.uint8)
    labels[leg] = FAT
    labels[muscle] = MUSCLE
    labels[bone] = BONE
    return labels


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice overlap 2|A n B| / (|A| + |B|) of two masks."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    total = a.sum() + b.sum()
    return 1.0 if total == 0 else 2.0 * np.logical_and(a, b).sum() / total
