"""Digital image correlation between the unloaded and the loaded slice (second paper, sections 2.2 and 3.1).

Each image pair is partitioned into correlation windows; the window of the
reference image is searched for in the deformed image, and the correlation
peak, the maximum of similarity, gives the displacement of the window centre
(section 2.2). As in section 3.1: square windows (16, 32 or 64 pixels), a
search area 4 times the window side (so +-1.5 windows around the start),
windows placed on regions of interest (aponeuroses/fascia, skin, vessels)
or on a grid, one displacement per window.

Relative to the bones. The leg moves rigidly in the scanner between the two
acquisitions; the second paper removes that motion first (section 3.1). Here
the rigid motion M found on the bones (`align.align_on_bones`) is composed
into every window's warp instead of resampling the loaded image: the loaded
image g is sampled at M(x + a(x)), a the window's affine displacement in the
frame of the unloaded image. The displacement measured is then directly that
of the tissue relative to the bones, and g is interpolated once, not twice
(a resampled image carries interpolation noise and bias into the correlation).

Similarity is the zero-normalised cross-correlation
ZNCC(p) = sum f^(x) g^(x + p), with f^ = (f - mean f) / ||f - mean f|| over the window
(skimage.feature.match_template computes it for every integer shift). The
integer peak is refined to sub-pixel by a 3-point parabola per axis, then by
inverse-compositional Gauss-Newton (IC-GN) on the zero-normalised sum of
squared differences with a first-order (affine) window shape function and
cubic-spline interpolation of g. The affine shape removes the peak-locking
bias of the parabola and the bias of a translation-only window in a strained
field.

Window deformation. An affine window cannot follow a field that bends inside
it (the fat compressed against stiffer muscle, the skin's edge), and then the
match is off by more than the noise, by an amount no linear model of the
window reproduces (a 64-pixel window on the phantom calf: 4 times the noise
variance). As PIV does (Scarano, Meas. Sci. Technol. 13, 2002), a second pass
deforms every window by a smooth prior field w interpolated from the first
pass: g is sampled at M(x + w(x) + a(x)) and the affine a only corrects what
w misses, which is nearly affine; the displacement reported is w + a at the
centre.

What each window reports (as DICe does: users see what was trusted):
- `confidence`: the ZNCC at the final position (1 = perfect match; windows of
  pure noise give low values);
- `covariance_mm2`: the 2x2 covariance of the centre displacement. Linearised,
  IC-GN returns p = H^-1 S^T e for image noise e, with S the steepest-descent
  images (grad f times the affine basis) and H = S^T S, so Cov p = s_e^2 H^-1,
  s_e^2 = s_f^2 + (|f|/|g|)^2 s_g^2 the variance of the noise of the two
  images, each estimated from its own pixels (`estimate_noise_sigma`), not
  from the match residual, which interpolation smooths (a sub-pixel shift of
  a noisy image lowers the residual while it raises the error); the larger of
  the two estimates is kept, so a window whose motion is not affine (a
  sliding interface) also reports it. H is built from the gradients of the
  noisy reference, whose noise looks like texture: its expectation is
  H_s + s_f^2 g^2 M (H_s of the noiseless image, g^2 the white-noise gain of
  the spline derivative, M the moments of the affine basis), and the error
  is -(S^T S_s)^-1 S^T e, so Cov p = s_e^2 H_s^-1 H H_s^-1 with
  H_s = H - s_f^2 g^2 M (errors in variables; without it the predicted
  variance is 30-70 % short on texture as weak as muscle's in T1);
- `uncertainty_px`, `anisotropy`: the largest standard deviation and the ratio
  of the largest to the smallest (large along a lone edge: the aperture problem).

`WindowOperators` holds, per window, the linear map from a displacement field
to what the window measures of it, and the cross-covariance of overlapping
windows; see its text.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.feature import match_template

from .case import DisplacementPoints
from .frame import RigidMotion, index_to_mm
from .mismatch import FAT, MUSCLE, contour_pixels, tissue_mask

SEARCH_FACTOR = 4
GAUSS_NEWTON_ITERATIONS = 20
GAUSS_NEWTON_TOLERANCE_PX = 1e-4
MAX_REFINEMENT_PX = 3.0   # Gauss-Newton may leave the integer peak of a ridge-shaped ZNCC, not wander off
# Gauss-Newton has failed when it ends at a lower ZNCC than the integer peak it started from; both are interpolated
# (the search patch is resampled through the priors), so a hair lower is not a failure
ZNCC_SLACK = 0.02


def _spline_derivative_noise_gain() -> float:
    """Variance of the cubic-spline derivative at the pixels of unit white noise: the derivative filter has the
    frequency response i sin(w) 6 / (4 + 2 cos w) (spline prefilter times the central difference of B-spline
    coefficients), and the gain is its mean square over the band."""
    w = np.linspace(-np.pi, np.pi, 4096, endpoint=False)
    return float(np.mean((6.0 * np.sin(w) / (4.0 + 2.0 * np.cos(w))) ** 2))


SPLINE_DERIVATIVE_NOISE_GAIN = _spline_derivative_noise_gain()
# Immerkaer (1996): the 3x3 mask below annihilates linear (and most smooth) intensity, white noise of variance
# s^2 passes with variance 36 s^2
_NOISE_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
_MAD_TO_SIGMA = 1.4826


def estimate_noise_sigma(image: np.ndarray, mask: np.ndarray | None = None, smoothing_px: float = 2.0) -> float:
    """Standard deviation of white noise in an image, from the median absolute response to Immerkaer's mask
    (J. Immerkaer, Fast noise variance estimation, CVIU 64, 1996) over the calmer half of `mask` (default:
    everywhere): the pixels whose gradient magnitude, smoothed over `smoothing_px`, is below its median there,
    so that edges, vessels and texture do not pass for noise (on the phantom: 1.4 % above the true noise of
    the leg, against 9 % over all of it). Inside tissue the Rician noise of a magnitude image is Gaussian with
    the channel's standard deviation."""
    image = np.asarray(image, float)
    region = np.asarray(mask, bool) if mask is not None else np.ones(image.shape, bool)
    if region.sum() < 16:
        raise ValueError("too few pixels to estimate the image noise from")
    gradient = ndimage.gaussian_gradient_magnitude(image, smoothing_px)
    calm = region & (gradient <= np.median(gradient[region]))
    values = ndimage.convolve(image, _NOISE_MASK, mode="reflect")[calm]
    return float(_MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))) / 6.0)


@dataclass(frozen=True)
class DICResult:
    """One displacement per window; NaN displacement and zero confidence where a window could not be correlated.
    Displacements are in the frame of the reference (unloaded) image, relative to the prior rigid motion."""

    centre_rc: np.ndarray         # (N, 2) continuous (row, column) index of the window centres in the reference
    position_mm: np.ndarray       # (N, 2) (x, y) of the window centres, mm
    displacement_px: np.ndarray   # (N, 2) (along columns, along rows), pixels
    displacement_mm: np.ndarray   # (N, 2) (ux, uy), mm
    confidence: np.ndarray        # (N,) ZNCC at the final sub-pixel position, in [0, 1]
    covariance_mm2: np.ndarray    # (N, 2, 2) covariance of (ux, uy), mm^2; inf where unknown
    uncertainty_px: np.ndarray    # (N,) standard deviation of the displacement (largest direction), pixels; inf if unknown
    anisotropy: np.ndarray        # (N,) ratio of the largest to the smallest standard deviation; large along a lone edge
    window_px: int
    search_px: int
    pixel_size_mm: tuple[float, float]
    noise_sigma: tuple[float, float] = (0.0, 0.0)   # image noise of (reference, deformed), intensity units
    intensity_variance: np.ndarray | None = None    # (N,) s_e^2 of each window (covariance = s_e^2 H^-1), intensity^2
    gradient: np.ndarray | None = None              # (N, 2, 2) displacement gradient d(ux, uy)/d(x, y) of the affine fit

    def reliable(self, min_confidence: float = 0.9, max_uncertainty_px: float = 0.05, max_anisotropy: float = 3.0) -> np.ndarray:
        """Windows with a good match (ZNCC), a small predicted uncertainty, and texture in both directions
        (not a lone edge, where the displacement along the edge is weakly determined: the aperture problem)."""
        return (self.confidence >= min_confidence) & (self.uncertainty_px <= max_uncertainty_px) & (self.anisotropy <= max_anisotropy)

    def to_points(self, min_confidence: float = 0.9, max_uncertainty_px: float = 0.05, max_anisotropy: float = 3.0) -> DisplacementPoints:
        """The reliable windows as measured displacements (the rows of a points.csv), sigma from the uncertainty."""
        keep = self.reliable(min_confidence, max_uncertainty_px, max_anisotropy)
        pixel_mm = float(np.sqrt(self.pixel_size_mm[0] * self.pixel_size_mm[1]))
        return DisplacementPoints(self.position_mm[keep].copy(), self.displacement_mm[keep].copy(), self.uncertainty_px[keep] * pixel_mm)


def index_affine(motion: RigidMotion | None, pixel_size_mm) -> np.ndarray:
    """The 3x3 matrix of a rigid motion (mm, image frame) acting on (column, row, 1) pixel indices."""
    if motion is None:
        return np.eye(3)
    dy, dx = (float(v) for v in pixel_size_mm)
    scale = np.diag([dx, dy])
    half = 0.5 * np.array([dx, dy])
    rotation = motion.rotation
    centre, translation = np.asarray(motion.centre_mm, float), np.asarray(motion.translation_mm, float)
    matrix = np.eye(3)
    matrix[:2, :2] = np.linalg.solve(scale, rotation @ scale)
    matrix[:2, 2] = np.linalg.solve(scale, rotation @ (half - centre) + centre + translation - half)
    return matrix


def correlate(reference: np.ndarray, deformed: np.ndarray, centres_rc, pixel_size_mm, *, window_px: int = 16,
              search_factor: int = SEARCH_FACTOR, prior: RigidMotion | None = None,
              prior_field_mm: np.ndarray | None = None, noise_sigma: tuple[float, float] | None = None) -> DICResult:
    """Correlate square windows of `window_px` centred at integer pixels `centres_rc` ((N, 2) rows, columns).

    prior: the rigid motion M of the bones (`align_on_bones`: I1(M(x)) ~ I0(x)), composed into every warp, so
    that the displacements are relative to the bones. prior_field_mm: a displacement field (2, H, W) (mm, I0's
    frame, relative to the bones) by which every window is deformed before it is matched (module text, window
    deformation); the displacement returned is the prior's at the centre plus the affine correction.
    noise_sigma: the image noise of (reference, deformed); default: estimated from each image where it has signal."""
    reference = np.asarray(reference, float)
    deformed = np.asarray(deformed, float)
    if reference.shape != deformed.shape:
        raise ValueError("the reference and deformed images must have the same shape")
    centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
    if noise_sigma is None:
        noise_sigma = (_signal_noise(reference), _signal_noise(deformed))
    search_px = search_factor * window_px
    spline = ndimage.spline_filter(deformed, order=3)
    grad_rows, grad_cols = spline_gradient(reference)
    to_deformed = index_affine(prior, pixel_size_mm)
    dy, dx = pixel_size_mm
    prior_px = None if prior_field_mm is None else np.stack([prior_field_mm[0] / dx, prior_field_mm[1] / dy])
    displacement = np.full((len(centres), 2), np.nan)
    confidence = np.zeros(len(centres))
    covariance = np.full((len(centres), 2, 2), np.inf)
    variance = np.full(len(centres), np.inf)
    gradient = np.full((len(centres), 2, 2), np.nan)
    for k, (row, col) in enumerate(centres):
        found = _correlate_window(reference, spline, grad_rows, grad_cols, row, col, window_px, search_px, to_deformed,
                                  noise_sigma, prior_px)
        if found is not None:
            displacement[k], confidence[k], covariance[k], variance[k], gradient[k] = found
    corner = centres - window_px // 2
    centre_rc = corner + (window_px - 1) / 2.0
    if prior_px is not None:
        displacement += np.stack([ndimage.map_coordinates(prior_px[c], centre_rc.T, order=1, mode="nearest")
                                  for c in range(2)], axis=1)
    x, y = index_to_mm(centre_rc[:, 0], centre_rc[:, 1], pixel_size_mm)
    to_mm = np.diag([dx, dy])
    covariance_mm2 = np.where(np.isfinite(covariance), to_mm @ np.nan_to_num(covariance, posinf=0.0) @ to_mm, np.inf)
    uncertainty, anisotropy = _spread(covariance)
    return DICResult(centre_rc, np.stack([x, y], axis=1), displacement, displacement * np.array([dx, dy]),
                     np.clip(confidence, 0.0, 1.0), covariance_mm2, uncertainty, anisotropy, window_px, search_px,
                     (float(dy), float(dx)), (float(noise_sigma[0]), float(noise_sigma[1])), variance,
                     to_mm @ gradient @ np.linalg.inv(to_mm))


def _signal_noise(image: np.ndarray) -> float:
    """Noise of an image where it has signal (the Rician noise of the background is not Gaussian)."""
    level = np.percentile(image, 99)
    signal = ndimage.binary_erosion(image > 0.2 * level, iterations=2)
    return estimate_noise_sigma(image, signal if signal.sum() > 100 else None)


def _spread(covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest standard deviation and the anisotropy ratio of each 2x2 covariance (inf where unknown)."""
    uncertainty = np.full(len(covariance), np.inf)
    anisotropy = np.full(len(covariance), np.inf)
    known = np.all(np.isfinite(covariance), axis=(1, 2))
    if known.any():
        eigenvalues = np.linalg.eigvalsh(covariance[known])
        uncertainty[known] = np.sqrt(eigenvalues[:, 1])
        anisotropy[known] = np.sqrt(eigenvalues[:, 1] / np.maximum(eigenvalues[:, 0], 1e-300))
    return uncertainty, anisotropy


def spline_gradient(image: np.ndarray, step: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """(d/drow, d/dcolumn) at the pixels of the cubic-spline interpolant of the image, the interpolant used for
    the deformed image: Gauss-Newton then converges to the exact minimum even on sharp band-limited edges,
    where central differences are too inaccurate and stall it."""
    coefficients = ndimage.spline_filter(np.asarray(image, float), order=3)
    rows, cols = np.indices(image.shape, dtype=float)

    def at(r, c):
        return ndimage.map_coordinates(coefficients, [r, c], order=3, prefilter=False, mode="nearest")

    return (at(rows + step, cols) - at(rows - step, cols)) / (2 * step), (at(rows, cols + step) - at(rows, cols - step)) / (2 * step)


def _sample(spline: np.ndarray, to_deformed: np.ndarray, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The deformed image at the points (cols, rows) of the reference frame moved by the prior rigid motion."""
    moved_cols = to_deformed[0, 0] * cols + to_deformed[0, 1] * rows + to_deformed[0, 2]
    moved_rows = to_deformed[1, 0] * cols + to_deformed[1, 1] * rows + to_deformed[1, 2]
    return ndimage.map_coordinates(spline, [moved_rows.ravel(), moved_cols.ravel()], order=3, prefilter=False,
                                   mode="nearest").reshape(np.shape(cols))


def _prior_at(prior_px, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The prior field (d_col, d_row) px at integer pixels (zero without one; held constant beyond the edge)."""
    if prior_px is None:
        return np.zeros(rows.shape), np.zeros(rows.shape)
    r = np.clip(rows, 0, prior_px.shape[1] - 1)
    c = np.clip(cols, 0, prior_px.shape[2] - 1)
    return prior_px[0][r, c], prior_px[1][r, c]


def _correlate_window(reference, spline, grad_rows, grad_cols, row, col, window_px, search_px, to_deformed, noise_sigma,
                      prior_px=None):
    """(displacement (d_col, d_row) px, ZNCC, 2x2 covariance px^2, s_e^2, displacement gradient) of one window, or
    None if it does not fit or is flat. With a prior field the displacement is the affine correction to it."""
    height, width = reference.shape
    r0, c0 = row - window_px // 2, col - window_px // 2
    if r0 < 0 or c0 < 0 or r0 + window_px > height or c0 + window_px > width:
        return None
    template = reference[r0:r0 + window_px, c0:c0 + window_px]
    if template.std() < 1e-12:
        return None
    margin = (search_px - window_px) // 2
    search_rows, search_cols = np.mgrid[r0 - margin:r0 + window_px + margin, c0 - margin:c0 + window_px + margin]
    prior_cols, prior_rows = _prior_at(prior_px, search_rows, search_cols)
    score = match_template(_sample(spline, to_deformed, search_cols + prior_cols, search_rows + prior_rows), template)
    peak_row, peak_col = np.unravel_index(int(np.argmax(score)), score.shape)
    start = np.array([peak_col + _parabola_offset(score[peak_row, :], peak_col) - margin,
                      peak_row + _parabola_offset(score[:, peak_col], peak_row) - margin])
    window = (slice(r0, r0 + window_px), slice(c0, c0 + window_px))
    window_prior = (prior_cols[margin:margin + window_px, margin:margin + window_px].ravel(),
                    prior_rows[margin:margin + window_px, margin:margin + window_px].ravel())
    refined = _inverse_compositional(template, grad_cols[window], grad_rows[window], spline, to_deformed, r0, c0, start,
                                     noise_sigma, window_prior)
    peak_score = float(score[peak_row, peak_col])
    if (refined is None or np.max(np.abs(refined[0] - start)) > MAX_REFINEMENT_PX
            or refined[1] < peak_score - ZNCC_SLACK):
        return start, peak_score, np.full((2, 2), np.inf), np.inf, np.full((2, 2), np.nan)
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


def steepest_descent(grad_cols: np.ndarray, grad_rows: np.ndarray) -> np.ndarray:
    """(n, 6) steepest-descent images grad f . d(x + a_p(x))/dp of a square window, for the affine parameters
    p = (u, du/dx, du/dy, v, dv/dx, dv/dy), offsets measured from the window centre."""
    size = grad_cols.shape[0]
    offset_rows, offset_cols = np.mgrid[0:size, 0:size].astype(float) - (size - 1) / 2.0
    fx, fy = grad_cols.ravel(), grad_rows.ravel()
    dxs, dys = offset_cols.ravel(), offset_rows.ravel()
    return np.stack([fx, fx * dxs, fx * dys, fy, fy * dxs, fy * dys], axis=1)


def _inverse_compositional(template, grad_cols, grad_rows, spline, to_deformed, r0, c0, start, noise_sigma, prior):
    """IC-GN with a first-order (affine) window shape function on the zero-normalised SSD, the deformed image
    sampled through the prior motion and the prior field (`prior`: (d_col, d_row) px at the window's pixels). Returns the displacement of the window centre (d_col, d_row) px, the ZNCC
    there, the 2x2 covariance (px^2) of that displacement, the intensity variance s_e^2 behind it (module text) and
    the displacement gradient of the affine warp."""
    f_hat, f_norm = _normalise(template)
    if f_norm == 0.0:
        return None
    size = template.shape[0]
    steepest_raw = steepest_descent(grad_cols, grad_rows)
    hessian_raw = steepest_raw.T @ steepest_raw
    if np.linalg.cond(hessian_raw) > 1e10:
        return None
    signal_hessian = denoised_hessian(hessian_raw, size, noise_sigma[0])
    steepest, hessian = steepest_raw / f_norm, hessian_raw / f_norm ** 2
    centre_row, centre_col = r0 + (size - 1) / 2.0, c0 + (size - 1) / 2.0
    offset_rows, offset_cols = np.mgrid[0:size, 0:size].astype(float) - (size - 1) / 2.0
    points = np.stack([offset_cols.ravel(), offset_rows.ravel(), np.ones(size * size)])
    warp = _affine(np.array([start[0], 0.0, 0.0, start[1], 0.0, 0.0]))

    def sample(warp):
        moved = warp @ points
        return _normalise(_sample(spline, to_deformed, centre_col + moved[0] + prior[0], centre_row + moved[1] + prior[1]))

    for _ in range(GAUSS_NEWTON_ITERATIONS):
        g_hat, g_norm = sample(warp)
        if g_norm == 0.0:
            return None
        step = np.linalg.solve(hessian, steepest.T @ (g_hat - f_hat.ravel()))
        warp = warp @ np.linalg.inv(_affine(step))
        if max(abs(step[0]), abs(step[3])) < GAUSS_NEWTON_TOLERANCE_PX and np.max(np.abs(step[[1, 2, 4, 5]])) < 1e-5:
            break
    g_hat, g_norm = sample(warp)
    residual = (g_hat - f_hat.ravel()) * f_norm                   # in the reference's intensity units
    residual_variance = float(residual @ residual) / max(residual.size - 6, 1)
    noise_variance = noise_sigma[0] ** 2 + (f_norm / g_norm * noise_sigma[1]) ** 2
    variance = max(noise_variance, residual_variance)
    if signal_hessian is None:   # the window's texture does not rise above the noise
        return np.array([warp[0, 2], warp[1, 2]]), float(f_hat.ravel() @ g_hat), np.full((2, 2), np.inf), np.inf, np.full((2, 2), np.nan)
    inverse = np.linalg.inv(signal_hessian)
    sandwich = (inverse @ hessian_raw @ inverse)[np.ix_([0, 3], [0, 3])]
    return (np.array([warp[0, 2], warp[1, 2]]), float(f_hat.ravel() @ g_hat), variance * sandwich, variance,
            warp[:2, :2] - np.eye(2))


def affine_moments(size: int) -> np.ndarray:
    """M = sum over a square window of X^T X, X = [1, dx, dy] per pixel, for both displacement components (6x6)."""
    offsets = np.arange(size, dtype=float) - (size - 1) / 2.0
    second = float(np.sum(offsets ** 2)) * size
    block = np.diag([float(size * size), second, second])
    moments = np.zeros((6, 6))
    moments[:3, :3] = moments[3:, 3:] = block
    return moments


def denoised_hessian(hessian: np.ndarray, size: int, reference_noise_sigma: float) -> np.ndarray | None:
    """H_s = H - s_f^2 g^2 M, the Gauss-Newton matrix of the noiseless reference (module text); None when it is
    not positive definite, i.e. the window holds less texture than noise."""
    signal = hessian - reference_noise_sigma ** 2 * SPLINE_DERIVATIVE_NOISE_GAIN * affine_moments(size)
    try:
        np.linalg.cholesky(signal)
    except np.linalg.LinAlgError:
        return None
    return signal


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
