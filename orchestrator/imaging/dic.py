"""Digital image correlation between the unloaded and the loaded slice (second paper, sections 2.2 and 3.1).

Each image pair is partitioned into correlation windows; the window of the
reference image is searched for in the deformed image, and the correlation
peak, the maximum of similarity, gives the displacement of the window centre
(section 2.2). As in section 3.1: square windows of 64x64 or 16x16 pixels, a
search area 4 times the window side (so +-1.5 windows around the start),
windows placed on regions of interest (aponeuroses/fascia, skin, vessels)
or on a grid, one displacement per window.

Similarity is the zero-normalised cross-correlation
ZNCC(p) = sum f^(x) g^(x + p), with f^ = (f - mean f) / ||f - mean f|| over the window
(skimage.feature.match_template computes it for every integer shift). The
integer peak is refined to sub-pixel by a 3-point parabola per axis, then by
inverse-compositional Gauss-Newton on the zero-normalised sum of squared
differences with a first-order (affine) window shape function and
cubic-spline interpolation of g. The affine shape removes the peak-locking
bias of the parabola and the bias of a translation-only window in a strained
field whose texture is not centred (a window on the skin sees texture on one
side only). Each window reports its confidence, the ZNCC at the final
position (1 = perfect match, windows of pure noise give low values), and its
uncertainty, the standard deviation of the centre displacement from the
least-squares covariance (large where texture lacks in one direction, as
along a straight edge). `reliable()` keeps windows good on both counts.

Displacements are those of the reference window centre, in mm in the image
frame (ux along x/columns, uy along y/rows), and in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.feature import match_template

from .case import DisplacementPoints
from .frame import index_to_mm
from .mismatch import FAT, MUSCLE, contour_pixels, tissue_mask

SEARCH_FACTOR = 4
GAUSS_NEWTON_ITERATIONS = 20
GAUSS_NEWTON_TOLERANCE_PX = 1e-4
MAX_REFINEMENT_PX = 3.0   # Gauss-Newton may leave the integer peak of a ridge-shaped ZNCC, not wander off


@dataclass(frozen=True)
class DICResult:
    """One displacement per window; NaN displacement and zero confidence where a window could not be correlated."""

    centre_rc: np.ndarray         # (N, 2) continuous (row, column) index of the window centres in the reference
    position_mm: np.ndarray       # (N, 2) (x, y) of the window centres, mm
    displacement_px: np.ndarray   # (N, 2) (along columns, along rows), pixels
    displacement_mm: np.ndarray   # (N, 2) (ux, uy), mm
    confidence: np.ndarray        # (N,) ZNCC at the final sub-pixel position, in [0, 1]
    uncertainty_px: np.ndarray    # (N,) standard deviation of the displacement (largest direction), pixels; inf if unknown
    anisotropy: np.ndarray        # (N,) ratio of the largest to the smallest standard deviation; large along a lone edge
    window_px: int
    search_px: int
    pixel_size_mm: tuple[float, float]

    def reliable(self, min_confidence: float = 0.9, max_uncertainty_px: float = 0.05, max_anisotropy: float = 3.0) -> np.ndarray:
        """Windows with a good match (ZNCC), a small predicted uncertainty, and texture in both directions
        (not a lone edge, where the displacement along the edge is weakly determined: the aperture problem)."""
        return (self.confidence >= min_confidence) & (self.uncertainty_px <= max_uncertainty_px) & (self.anisotropy <= max_anisotropy)

    def to_points(self, min_confidence: float = 0.9, max_uncertainty_px: float = 0.05, max_anisotropy: float = 3.0) -> DisplacementPoints:
        """The reliable windows as measured displacements (the rows of a points.csv), sigma from the uncertainty."""
        keep = self.reliable(min_confidence, max_uncertainty_px, max_anisotropy)
        pixel_mm = float(np.sqrt(self.pixel_size_mm[0] * self.pixel_size_mm[1]))
        return DisplacementPoints(self.position_mm[keep].copy(), self.displacement_mm[keep].copy(), self.uncertainty_px[keep] * pixel_mm)


def correlate(reference: np.ndarray, deformed: np.ndarray, centres_rc, pixel_size_mm, *, window_px: int = 16,
              search_factor: int = SEARCH_FACTOR) -> DICResult:
    """Correlate square windows of `window_px` centred at integer pixels `centres_rc` ((N, 2) rows, columns)."""
    reference = np.asarray(reference, float)
    deformed = np.asarray(deformed, float)
    if reference.shape != deformed.shape:
        raise ValueError("the reference and deformed images must have the same shape")
    centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
    search_px = search_factor * window_px
    spline = ndimage.spline_filter(deformed, order=3)
    grad_rows, grad_cols = spline_gradient(reference)
    displacement = np.full((len(centres), 2), np.nan)
    confidence = np.zeros(len(centres))
    uncertainty = np.full(len(centres), np.inf)
    anisotropy = np.full(len(centres), np.inf)
    for k, (row, col) in enumerate(centres):
        found = _correlate_window(reference, deformed, spline, grad_rows, grad_cols, row, col, window_px, search_px)
        if found is not None:
            displacement[k], confidence[k], uncertainty[k], anisotropy[k] = found
    corner = centres - window_px // 2
    centre_rc = corner + (window_px - 1) / 2.0
    x, y = index_to_mm(centre_rc[:, 0], centre_rc[:, 1], pixel_size_mm)
    dy, dx = pixel_size_mm
    return DICResult(centre_rc, np.stack([x, y], axis=1), displacement, displacement * np.array([dx, dy]),
                     np.clip(confidence, 0.0, 1.0), uncertainty, anisotropy, window_px, search_px,
                     (float(dy), float(dx)))


def spline_gradient(image: np.ndarray, step: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """(d/drow, d/dcolumn) at the pixels of the cubic-spline interpolant of the image, the interpolant used for
    the deformed image: Gauss-Newton then converges to the exact minimum even on sharp band-limited edges,
    where central differences are too inaccurate and stall it."""
    coefficients = ndimage.spline_filter(np.asarray(image, float), order=3)
    rows, cols = np.indices(image.shape, dtype=float)

    def at(r, c):
        return ndimage.map_coordinates(coefficients, [r, c], order=3, prefilter=False, mode="nearest")

    return (at(rows + step, cols) - at(rows - step, cols)) / (2 * step), (at(rows, cols + step) - at(rows, cols - step)) / (2 * step)


def _correlate_window(reference, deformed, spline, grad_rows, grad_cols, row, col, window_px, search_px):
    """(displacement (d_col, d_row) px, ZNCC, uncertainty px) of one window, or None if it does not fit or is flat."""
    height, width = reference.shape
    r0, c0 = row - window_px // 2, col - window_px // 2
    if r0 < 0 or c0 < 0 or r0 + window_px > height or c0 + window_px > width:
        return None
    template = reference[r0:r0 + window_px, c0:c0 + window_px]
    if template.std() < 1e-12:
        return None
    margin = (search_px - window_px) // 2
    top, left = max(r0 - margin, 0), max(c0 - margin, 0)
    bottom, right = min(r0 + window_px + margin, height), min(c0 + window_px + margin, width)
    score = match_template(deformed[top:bottom, left:right], template)
    peak_row, peak_col = np.unravel_index(int(np.argmax(score)), score.shape)
    start = np.array([peak_col + _parabola_offset(score[peak_row, :], peak_col) + left - c0,
                      peak_row + _parabola_offset(score[:, peak_col], peak_row) + top - r0])
    window = (slice(r0, r0 + window_px), slice(c0, c0 + window_px))
    refined = _inverse_compositional(template, grad_cols[window], grad_rows[window], spline, r0, c0, start)
    peak_score = float(score[peak_row, peak_col])
    if refined is None or np.max(np.abs(refined[0] - start)) > MAX_REFINEMENT_PX or refined[1] < peak_score:
        return start, peak_score, np.inf, np.inf
    return refined


def _parabola_offset(profile: np.ndarray, peak: int) -> float:
    """Sub-pixel offset of the maximum of a parabola through the peak and its two neighbours."""
    if peak == 0 or peak == len(profile) - 1:
        return 0.0
    left, centre, right = profile[peak - 1], profile[peak], profile[peak + 1]
    curvature = left - 2.0 * centre + right
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


def _normalise(values: np.ndarray) -> tuple[np.ndarray, float]:
    centred = values - values.mean()
    norm = float(np.sqrt(np.sum(centred ** 2)))
    return centred / norm, norm


def _affine(p: np.ndarray) -> np.ndarray:
    """3x3 matrix of the first-order window shape function, p = (u, du/dx, du/dy, v, dv/dx, dv/dy)."""
    u, ux, uy, v, vx, vy = p
    return np.array([[1.0 + ux, uy, u], [vx, 1.0 + vy, v], [0.0, 0.0, 1.0]])


def _inverse_compositional(template, grad_cols, grad_rows, spline, r0, c0, start):
    """Inverse-compositional Gauss-Newton with a first-order (affine) window shape function on the zero-normalised
    SSD. Returns the displacement of the window centre (d_col, d_row) px, the ZNCC there, and the standard
    deviation (px, largest direction) of the displacement from the least-squares covariance."""
    f_hat, f_norm = _normalise(template)
    if f_norm == 0.0:
        return None
    size = template.shape[0]
    offset_rows, offset_cols = np.mgrid[0:size, 0:size].astype(float) - (size - 1) / 2.0
    fx, fy = grad_cols.ravel() / f_norm, grad_rows.ravel() / f_norm
    dxs, dys = offset_cols.ravel(), offset_rows.ravel()
    steepest = np.stack([fx, fx * dxs, fx * dys, fy, fy * dxs, fy * dys], axis=1)
    hessian = steepest.T @ steepest
    if np.linalg.cond(hessian) > 1e10:
        return None
    centre_row, centre_col = r0 + (size - 1) / 2.0, c0 + (size - 1) / 2.0
    warp = _affine(np.array([start[0], 0.0, 0.0, start[1], 0.0, 0.0]))
    points = np.stack([dxs, dys, np.ones_like(dxs)])

    def sample(warp):
        moved = warp @ points
        g = ndimage.map_coordinates(spline, [centre_row + moved[1], centre_col + moved[0]], order=3, prefilter=False, mode="nearest")
        return _normalise(g)

    for _ in range(GAUSS_NEWTON_ITERATIONS):
        g_hat, g_norm = sample(warp)
        if g_norm == 0.0:
            return None
        step = np.linalg.solve(hessian, steepest.T @ (g_hat - f_hat.ravel()))
        warp = warp @ np.linalg.inv(_affine(step))
        if max(abs(step[0]), abs(step[3])) < GAUSS_NEWTON_TOLERANCE_PX and np.max(np.abs(step[[1, 2, 4, 5]])) < 1e-5:
            break
    g_hat, _ = sample(warp)
    residual = g_hat - f_hat.ravel()
    variance = float(residual @ residual) / max(residual.size - 6, 1)
    eigenvalues = np.linalg.eigvalsh(variance * np.linalg.inv(hessian)[np.ix_([0, 3], [0, 3])])
    uncertainty = float(np.sqrt(eigenvalues[-1]))
    anisotropy = float(np.sqrt(eigenvalues[-1] / max(eigenvalues[0], 1e-300)))
    return np.array([warp[0, 2], warp[1, 2]]), float(f_hat.ravel() @ g_hat), uncertainty, anisotropy


def grid_centres(shape: tuple[int, int], window_px: int, step_px: int, mask: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) integer (row, column) centres on a regular grid whose windows fit in the image (and whose centre is in mask)."""
    half = window_px // 2
    rows = np.arange(half, shape[0] - (window_px - half) + 1, step_px)
    cols = np.arange(half, shape[1] - (window_px - half) + 1, step_px)
    centres = np.array([(r, c) for r in rows for c in cols], dtype=int).reshape(-1, 2)
    if mask is not None:
        centres = centres[np.asarray(mask, bool)[centres[:, 0], centres[:, 1]]]
    return centres


def roi_centres(labels: np.ndarray, pixel_size_mm, spacing_mm: float = 5.0, *, skin: bool = True, fascia: bool = True,
                vessels_mm=()) -> np.ndarray:
    """Window centres on the regions of interest of section 3.1: the skin (leg outline), the fascia
    (fat/muscle interface) every `spacing_mm` along them, and the given vessel positions (x, y) in mm."""
    leg = labels > 0
    picked = []
    if skin:
        picked.append(_spaced(np.argwhere(contour_pixels(leg)), spacing_mm / min(pixel_size_mm)))
    if fascia:
        fat_next_to_muscle = tissue_mask(labels, FAT) & ndimage.binary_dilation(tissue_mask(labels, MUSCLE))
        picked.append(_spaced(np.argwhere(fat_next_to_muscle), spacing_mm / min(pixel_size_mm)))
    dy, dx = pixel_size_mm
    vessels = [(int(round(y / dy - 0.5)), int(round(x / dx - 0.5))) for x, y in vessels_mm]
    if vessels:
        picked.append(np.array(vessels, dtype=int))
    return np.concatenate(picked).astype(int) if picked else np.empty((0, 2), int)


def _spaced(points: np.ndarray, spacing_px: float) -> np.ndarray:
    """A subset of the points at least spacing_px apart, taken in order of angle about their centroid."""
    if len(points) == 0:
        return points.reshape(0, 2)
    centre = points.mean(axis=0)
    order = np.argsort(np.arctan2(points[:, 0] - centre[0], points[:, 1] - centre[1]), kind="stable")
    kept = []
    for point in points[order]:
        if all(np.hypot(*(point - other)) >= spacing_px for other in kept[-8:]) and (
                not kept or np.hypot(*(point - kept[0])) >= spacing_px):
            kept.append(point)
    return np.array(kept, dtype=int)
