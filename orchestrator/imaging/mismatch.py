"""Contour mismatch between the warped image and the unloaded image (first paper, section 2.2.5, Fig. 4).

For each pixel (x_k, y_k) of a fat or muscle contour in the warped image I,
d_k is the distance to the closest contour pixel of the same tissue in I0,
and the mismatch is M = sum_k d_k^2. Distances are in millimetres (the
Euclidean distance transform is sampled with the pixel size), so M is in
mm^2 and does not depend on the pixel size; divide d_k by the pixel size to
get the paper's pixel units. Matching each tissue with its own contours is
our reading of "the closest pixel belonging to a contour of fat or muscles":
it keeps a fat contour from being matched to a nearby muscle contour.

A contour pixel of a tissue is a pixel of that tissue with a 4-neighbour
outside it (the image border counts as outside), so identical label maps
give M = 0 exactly. The per-pixel map of d_k is Fig. 4 of the paper; the
signed distance is +d_k where the warped tissue lies outside the tissue of
I0 (it overshoots) and -d_k where it lies inside (it falls short), for the
diagnosis of where and in which direction the model is wrong.

The distance transforms of I0 and the smoothed tissue fields of I1 are
computed once (`ContourMismatch(...)`); each evaluation then costs two
linear interpolations on the pixel grid and a few array operations: the
inner loop of the identification.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..core.frame import displacement_on_grid
from ..core.tissues import FAT, FIRST_COMPARTMENT, MUSCLE

TISSUE_NAMES = {FAT: "fat", MUSCLE: "muscle"}


def tissue_mask(labels: np.ndarray, tissue: int) -> np.ndarray:
    """Pixels of a tissue; muscle includes the compartments (labels >= 4)."""
    if tissue == MUSCLE:
        return (labels == MUSCLE) | (labels >= FIRST_COMPARTMENT)
    return labels == tissue


def contour_pixels(region: np.ndarray) -> np.ndarray:
    """Pixels of the region with at least one 4-neighbour outside it (the border counts as outside)."""
    inner = region.copy()
    inner[1:, :] &= region[:-1, :]
    inner[:-1, :] &= region[1:, :]
    inner[:, 1:] &= region[:, :-1]
    inner[:, :-1] &= region[:, 1:]
    inner[0, :] = inner[-1, :] = False
    inner[:, 0] = inner[:, -1] = False
    return region & ~inner


class _SmoothTissue:
    """A tissue mask of I1 smoothed into phi (its 1/2 level follows the boundary), for sampling at x + u(x).

    phi is padded with zeros (outside the image there is no tissue). Bilinear interpolation of phi is > 1/2
    wherever the four corners of the cell are, and <= 1/2 wherever none is, so only the cells that the
    boundary crosses are interpolated: a few thousand pixels instead of the whole grid."""

    PAD = 2

    def __init__(self, mask: np.ndarray, smoothing_px: float):
        self.phi = np.pad(ndimage.gaussian_filter(mask.astype(float), smoothing_px), self.PAD)
        above = self.phi > 0.5
        corners = (above[:-1, :-1], above[1:, :-1], above[:-1, 1:], above[1:, 1:])
        all_above = corners[0] & corners[1] & corners[2] & corners[3]
        any_above = corners[0] | corners[1] | corners[2] | corners[3]
        self.cell_state = np.where(all_above, 1, np.where(any_above, 2, 0)).astype(np.int8)   # 2: boundary cell

    def inside(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Whether bilinear phi exceeds 1/2 at the continuous (row, column) indices of I1."""
        r = np.clip(rows + self.PAD, 0.0, self.phi.shape[0] - 2.0)
        c = np.clip(cols + self.PAD, 0.0, self.phi.shape[1] - 2.0)
        r0, c0 = r.astype(np.intp), c.astype(np.intp)
        state = self.cell_state[r0, c0]
        inside = state == 1
        boundary = np.nonzero(state == 2)
        i, j = r0[boundary], c0[boundary]
        fr, fc = r[boundary] - i, c[boundary] - j
        phi = self.phi
        top = phi[i, j] + (phi[i, j + 1] - phi[i, j]) * fc
        bottom = phi[i + 1, j] + (phi[i + 1, j + 1] - phi[i + 1, j]) * fc
        inside[boundary] = top + (bottom - top) * fr > 0.5
        return inside


@dataclass(frozen=True)
class MismatchResult:
    """M = sum d_k^2 (mm^2) and the maps behind it. Maps are (H, W), NaN off the contours of the warped image."""

    value_mm2: float
    per_tissue_mm2: dict[str, float]
    contour_pixel_count: int
    distance_mm: np.ndarray
    signed_distance_mm: np.ndarray

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(self.value_mm2 / self.contour_pixel_count)) if self.contour_pixel_count else 0.0


class ContourMismatch:
    """M(u) for one pair of label maps: I0's contours are fixed, I1's tissues are warped by u (section 2.2.5).

    The tissues of the warped image are found as in section 2.1.2, at the sub-pixel positions x + u(x) with
    linear interpolation: each tissue mask of I1 is smoothed into a field phi (Gaussian, `smoothing_px`)
    whose 1/2 level follows the boundary between pixels, phi is interpolated linearly at x + u(x), and the
    pixel belongs to the tissue where it exceeds 1/2. Unlike nearest-neighbour label warping this does not
    round the boundary to the pixels of I1, which halves M at the true displacement.
    """

    def __init__(self, labels_unloaded: np.ndarray, labels_loaded: np.ndarray | None, pixel_size_mm: tuple[float, float],
                 tissues: tuple[int, ...] = (FAT, MUSCLE), smoothing_px: float = 1.0, margin_mm: float = 15.0):
        self.labels_unloaded = np.asarray(labels_unloaded)
        self.pixel_size_mm = tuple(float(v) for v in pixel_size_mm)
        self.tissues = tissues
        # Work in the box around the leg, grown by margin_mm: displacements larger than that are not compression.
        rows, cols = np.nonzero(self.labels_unloaded > 0)
        if rows.size == 0:
            raise ValueError("the unloaded label map is empty")
        grow = [int(np.ceil(margin_mm / size)) for size in self.pixel_size_mm]
        self._box = (slice(max(rows.min() - grow[0], 0), rows.max() + grow[0] + 1),
                     slice(max(cols.min() - grow[1], 0), cols.max() + grow[1] + 1))
        self._inside = {}
        self._distance = {}
        for tissue in tissues:
            region = tissue_mask(self.labels_unloaded, tissue)
            contour = contour_pixels(region)
            if not contour.any():
                raise ValueError(f"the unloaded label map has no {TISSUE_NAMES.get(tissue, tissue)} contour")
            self._inside[tissue] = region[self._box]
            self._distance[tissue] = ndimage.distance_transform_edt(~contour, sampling=self.pixel_size_mm)[self._box]
        self._loaded_tissues = {}
        if labels_loaded is not None:
            if np.shape(labels_loaded) != self.labels_unloaded.shape:
                raise ValueError("the loaded and unloaded label maps must have the same shape")
            self._loaded_tissues = {tissue: _SmoothTissue(tissue_mask(np.asarray(labels_loaded), tissue), smoothing_px)
                                    for tissue in tissues}
        self._box_rows, self._box_cols = np.mgrid[self._box].astype(float)

    def __call__(self, displacement) -> MismatchResult:
        """M for the displacement u (mm, (2, H, W) on I0's grid or a callable): warp I1's tissues, compare contours."""
        if not self._loaded_tissues:
            raise ValueError("ContourMismatch was built without the loaded label map; pass labels_loaded")
        field = displacement_on_grid(displacement, self.labels_unloaded.shape, self.pixel_size_mm)[(slice(None), *self._box)]
        dy, dx = self.pixel_size_mm
        rows, cols = self._box_rows + field[1] / dy, self._box_cols + field[0] / dx
        return self._compare_in_box({tissue: loaded.inside(rows, cols) for tissue, loaded in self._loaded_tissues.items()})

    def compare(self, labels_warped: np.ndarray) -> MismatchResult:
        """M of any label map on I0's grid (e.g. the segmentation of an already warped image)."""
        labels_warped = np.asarray(labels_warped)
        outside = np.ones(labels_warped.shape, bool)
        outside[self._box] = False
        if np.any(labels_warped[outside] > 0):
            raise ValueError("the warped label map has tissue farther than the margin from the unloaded leg")
        return self._compare_in_box({tissue: tissue_mask(labels_warped[self._box], tissue) for tissue in self.tissues})

    def _compare_in_box(self, masks: dict[int, np.ndarray]) -> MismatchResult:
        distance_map = np.full(self.labels_unloaded.shape, np.nan)
        signed_map = np.full(self.labels_unloaded.shape, np.nan)
        per_tissue = {}
        count = 0
        for tissue in self.tissues:
            contour = contour_pixels(masks[tissue])
            d = self._distance[tissue][contour]
            distance_map[self._box][contour] = d
            signed_map[self._box][contour] = np.where(self._inside[tissue][contour], -d, d)
            per_tissue[TISSUE_NAMES.get(tissue, str(tissue))] = float(d @ d)
            count += d.size
        return MismatchResult(sum(per_tissue.values()), per_tissue, count, distance_map, signed_map)
