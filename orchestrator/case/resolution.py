"""The resolution a case is worked at: slices finer than `FINEST_WORKING_PIXEL_MM` are averaged over blocks of
pixels before anything else reads them.

Why: the DIC windows are counted in pixels (16 to 64, with error models measured at 0.36 mm pixels), and a
window must span several grains of the texture (fat lobules, muscle fascicles) to be tracked. On a 2048x2048
slice of a 151 mm field of view (0.074 mm pixels) a 32-pixel window spans 2.4 mm: 526 of 6,666 windows of the
phantom calf were kept, and the segmentation's memory grew with the matrix (1.1 GiB). Averaged over 3x3 blocks
(0.22 mm, windows of 7.1 mm) 753 of 796 are kept in 11 s; 0.18 mm pixels (windows of 5.8 mm) still keep 88 %
of them, so coarser slices are worked as they are. Blocks also divide the noise by their side and bound the
memory by the working matrix. The image frame is unchanged (a block's centre is the centre of its pixels), so
points.csv and the landmarks, given in mm, stay where they were; the last partial row and column of blocks,
at the image's edge, are dropped.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .folder import Case

FINEST_WORKING_PIXEL_MM = 0.18


def block_factor(pixel_size_mm) -> int:
    """Pixels per block side: the smallest that makes the pixel at least FINEST_WORKING_PIXEL_MM."""
    return max(1, math.ceil(FINEST_WORKING_PIXEL_MM / min(pixel_size_mm) - 1e-9))


def working_resolution(case: Case) -> Case:
    """The case with its slices, labels and missing-pixel masks over blocks of `block_factor` pixels (the case
    itself when its pixels are coarse enough)."""
    factor = block_factor(case.pixel_size_mm)
    if factor == 1:
        return case
    return replace(case, pixel_size_mm=(case.pixel_size_mm[0] * factor, case.pixel_size_mm[1] * factor),
                   unloaded=coarsen_image(case.unloaded, factor), loaded=coarsen_image(case.loaded, factor),
                   labels=None if case.labels is None else coarsen_labels(case.labels, factor),
                   missing={role: _blocks(mask, factor).any(axis=(1, 3)) for role, mask in case.missing.items()},
                   block_factor=factor)


def _blocks(array: np.ndarray, factor: int) -> np.ndarray:
    """(rows // factor, factor, cols // factor, factor) view of an array's whole factor x factor blocks."""
    rows, cols = (np.shape(array)[0] // factor) * factor, (np.shape(array)[1] // factor) * factor
    return np.asarray(array)[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor)


def coarsen_labels(labels: np.ndarray, factor: int) -> np.ndarray:
    """Labels of factor x factor blocks (the most frequent in each)."""
    blocks = _blocks(labels, factor)
    values = np.unique(blocks)
    counts = np.stack([(blocks == v).sum(axis=(1, 3)) for v in values])
    return values[np.argmax(counts, axis=0)].astype(np.asarray(labels).dtype)


def coarsen_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean grey level of factor x factor blocks (as `coarsen_labels` cuts them)."""
    return _blocks(np.asarray(image, float), factor).mean(axis=(1, 3))
