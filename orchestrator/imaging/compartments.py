"""Muscle compartments found in a T1 slice: the septa between muscle groups are thin dark lines.

The second paper gives each muscle group its own material (section 3.2, Table 1); a user's segmentation
usually holds only fat, muscle and bone. The intermuscular septa and the interosseous membrane are fascia,
dark on T1 and about half a millimetre thick, so they can be found in the unloaded image:

1. a dark-ridge (Sato) filter at the septum's width, scored as a robust z value against the muscle's own
   texture (median and MAD inside the muscle, `margin_mm` away from its edge, where the deep fascia is);
2. a line integral of that score along `line_mm` in 24 directions, keeping the best: a septum is long and
   straight at that scale, the texture's ridges are short and point anywhere, so the septa stand out by
   about the square root of the line's length over the texture's correlation length;
3. hysteresis (`low_z`, `high_z`) and pieces longer than `min_septum_mm`, thinned to one pixel: the septa;
4. watershed of the muscle on its distance to the septa and to its own edge, seeded by the parts farther than
   `neck_mm` from both: a septum that stops short of a bone or of the fascia still closes its compartment
   where the muscle narrows;
5. compartments smaller than `min_compartment_mm2` join the neighbour they share most boundary with.

The result is the case's labels with the muscle (2) replaced by compartments 4, 5, ... numbered counter-clockwise
from the image's +x axis about the muscle's centroid; `figures.compartments_figure` draws them for the user
to check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage import draw, filters, measure, morphology, segmentation

from ..core.tissues import FIRST_COMPARTMENT, MUSCLE

LINE_DIRECTIONS = 24


@dataclass
class Compartments:
    """Labels with the muscle cut into compartments, and what the cut rests on."""

    labels: np.ndarray          # 0 background, 1 fat, 3 bone, 4, 5, ... compartments (2 where none was found)
    septa: np.ndarray           # bool, the septa found (one pixel wide)
    line_score: np.ndarray      # the line-integrated ridge z value (step 2 of the module text)

    @property
    def count(self) -> int:
        return int(len(np.unique(self.labels[self.labels >= FIRST_COMPARTMENT])))

    def areas_mm2(self, pixel_size_mm) -> dict[int, float]:
        return compartment_areas_mm2(self.labels, pixel_size_mm)


def compartment_areas_mm2(labels: np.ndarray, pixel_size_mm) -> dict[int, float]:
    """Area of each compartment label (>= FIRST_COMPARTMENT) of a label map."""
    values, counts = np.unique(labels[labels >= FIRST_COMPARTMENT], return_counts=True)
    return {int(v): float(c * pixel_size_mm[0] * pixel_size_mm[1]) for v, c in zip(values, counts)}


def _robust_z(values: np.ndarray, where: np.ndarray) -> np.ndarray:
    sample = values[where]
    median = np.median(sample)
    spread = 1.4826 * np.median(np.abs(sample - median))
    return np.where(where, (values - median) / max(spread, 1e-12), 0.0)


def _line_kernel(length_px: int, angle: float) -> np.ndarray:
    half = length_px // 2
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    dr, dc = -half * np.sin(angle), half * np.cos(angle)
    rows, cols = draw.line(int(round(half - dr)), int(round(half - dc)), int(round(half + dr)), int(round(half + dc)))
    kernel[rows, cols] = 1.0
    return kernel / kernel.sum()


def line_score(image: np.ndarray, muscle: np.ndarray, pixel_size_mm, *, septum_mm: float = 0.5,
               margin_mm: float = 1.8, line_mm: float = 6.0) -> np.ndarray:
    """Steps 1-2 of the module text: the best line-integrated dark-ridge z value at each muscle pixel."""
    pixel = float(min(pixel_size_mm))
    width = septum_mm / pixel
    ridge = filters.sato(np.asarray(image, float), sigmas=[0.5 * width, 0.72 * width, width], black_ridges=True)
    inner = ndimage.binary_erosion(muscle, iterations=max(1, int(round(margin_mm / pixel))))
    if inner.sum() < 100:
        return np.zeros(np.shape(image))
    z = _robust_z(ridge, inner)
    length = max(3, int(round(line_mm / pixel)))
    best = np.full(np.shape(image), -np.inf)
    for angle in np.linspace(0.0, np.pi, LINE_DIRECTIONS, endpoint=False):
        best = np.maximum(best, ndimage.convolve(z, _line_kernel(length, angle), mode="constant"))
    return _robust_z(best, inner)


def find_compartments(image: np.ndarray, labels: np.ndarray, pixel_size_mm, *, low_z: float = 3.0,
                      high_z: float = 6.0, min_septum_mm: float = 10.0, neck_mm: float = 3.0,
                      min_compartment_mm2: float = 150.0, **score_options) -> Compartments:
    """The muscle (label 2) of `labels` cut into compartments at the septa of `image` (module text)."""
    labels = np.asarray(labels)
    muscle = labels == MUSCLE
    pixel = float(min(pixel_size_mm))
    score = line_score(image, muscle, pixel_size_mm, **score_options)
    candidate = filters.apply_hysteresis_threshold(score, low_z, high_z) if score.any() else np.zeros_like(muscle)
    pieces, _ = ndimage.label(candidate, structure=np.ones((3, 3)))
    septa = np.zeros_like(muscle)
    for piece in measure.regionprops(pieces):
        if piece.axis_major_length * pixel >= min_septum_mm:
            septa[pieces == piece.label] = True
    septa = morphology.skeletonize(septa)

    free = muscle & ~ndimage.binary_dilation(septa)
    distance = ndimage.distance_transform_edt(free) * pixel
    seeds, count = ndimage.label(distance > neck_mm)
    result = labels.copy()
    if count < 2:
        return Compartments(result, septa, score)
    basins = segmentation.watershed(-distance, seeds, mask=muscle)
    basins = _merge_small(basins, min_compartment_mm2 / (pixel_size_mm[0] * pixel_size_mm[1]))
    result[muscle] = 0
    for number, basin in enumerate(_counter_clockwise(basins, pixel_size_mm)):
        result[basins == basin] = FIRST_COMPARTMENT + number
    if len(np.unique(basins[basins > 0])) < 2:
        result[muscle] = MUSCLE
    return Compartments(result, septa, score)


def _merge_small(basins: np.ndarray, min_pixels: float) -> np.ndarray:
    """Join every basin smaller than min_pixels to the neighbour it shares the longest boundary with."""
    basins = basins.copy()
    while True:
        values, counts = np.unique(basins[basins > 0], return_counts=True)
        if len(values) < 2 or counts.min() >= min_pixels:
            return basins
        smallest = values[np.argmin(counts)]
        ring = ndimage.binary_dilation(basins == smallest) & (basins > 0) & (basins != smallest)
        neighbours, shared = np.unique(basins[ring], return_counts=True)
        basins[basins == smallest] = neighbours[np.argmax(shared)] if len(neighbours) else 0


def _counter_clockwise(basins: np.ndarray, pixel_size_mm) -> list[int]:
    """Basin values ordered by the display angle of their centroid about the muscle's centroid."""
    rows, cols = np.nonzero(basins > 0)
    centre = np.array([rows.mean(), cols.mean()])
    angles = {}
    for value in np.unique(basins[basins > 0]):
        r, c = np.nonzero(basins == value)
        dy, dx = (r.mean() - centre[0]) * pixel_size_mm[0], (c.mean() - centre[1]) * pixel_size_mm[1]
        angles[int(value)] = np.degrees(np.arctan2(-dy, dx)) % 360.0
    return sorted(angles, key=angles.get)
