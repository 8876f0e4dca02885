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

Prefilter. Both images are smoothed by a Gaussian of about a pixel first
(`prefilter`, Pan 2013): the spline interpolation and differentiation below
are exact only on band-limited images, and an image made with partial volume
has aliased edges whose staircase does not move with the tissue (windows on
the skin of such images were wrong by 5-20 times their predicted error).

Similarity is the zero-normalised cross-correlation
ZNCC(p) = sum f^(x) g^(x + p), with f^ = (f - mean f) / ||f - mean f|| over the window
(skimage.feature.match_template computes it for every integer shift). The
integer peak is refined to sub-pixel by a 3-point parabola per axis, then by
inverse-compositional Gauss-Newton (IC-GN) on the zero-normalised sum of
squared differences with a first-order (affine) window shape function, or a
second-order one (`shape`: quadratic, for fields that bend inside a window),
and cubic-spline interpolation of g. The affine shape removes the peak-locking
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
- `confidence`: the ZNCC of the raw images at the final position (1 = perfect
  match; windows of pure noise give low values, which prefiltered noise,
  correlated over a few pixels, would not);
- `covariance_mm2`: the 2x2 covariance of the centre displacement. Linearised,
  IC-GN returns p = H^-1 S^T P e for image noise e, with S the steepest-descent
  images (grad f times the shape function's basis), P the projection that the zero
  normalisation makes (`zero_normalised_steepest_descent`) and H = S^T P S.
  The noise e of a prefiltered pixel is G * e_raw, so
  Cov p = s_e^2 H_s^-1 (G * PS)^T rho (G * PS) H_s^-1 (`prefilter`), with
  s_e^2 = s_f^2 + (|f|/|g|)^2 s_g^2 the variance of the noise of the two
  images, each estimated from its own raw pixels (`estimate_noise_sigma`),
  and rho its Rician share at each pixel (0.43 in air). H is built from the
  gradients of the noisy reference, whose noise looks like texture: its
  expectation is H_s + s_f^2 g^2 M (H_s of the noiseless image, g^2 the noise
  gain of the spline derivative of the prefiltered image, M the moments of the
  shape function's basis weighted by rho), hence H_s = H - s_f^2 g^2 M (errors in
  variables; without it the predicted variance is 30-70 % short on texture as
  weak as muscle's in T1; with M unweighted, windows half in air over-predicted
  the variance along the skin 1.6 times, tests/measure/test_window_noise.py). The
  error of the images' edges (`prefilter`) is added by
  `DICResult.with_edge_variance` once the windows' residuals have calibrated it;
- `uncertainty_px`, `anisotropy`: the largest standard deviation and the ratio
  of the largest to the smallest (large along a lone edge: the aperture problem).

Compiled loops. The integer search, the Gauss-Newton iterations and each window's error terms run in C++
(correlation_cpp/, the module `orchestrator._correlation`, on `workers` threads without the GIL): they read the
prefiltered and raw images, the spline coefficients scipy computed, the gradients and the error model's maps from
here, and return each window's start, its integer peak's ZNCC, the warp Gauss-Newton converged to and, at that warp,
the ZNCCs, the covariances and the residual's sums (correlation_cpp/src/error_model.hpp). The checks that reject a
window are made here on them (`_finished`), by the rules of the loops in Python, which stay the reference
(`correlate(..., compiled=False)`, or CALFIT_DIC_COMPILED=0 in the environment). The two agree to 1e-6 px and to
rounding in the error model (tests/measure/test_compiled_windows.py). Computed in Python from each window's warp,
the error terms took twice the time of the compiled search and iterations.

`WindowOperators` holds, per window, the linear map from a displacement field
to what the window measures of it, and the cross-covariance of overlapping
windows; see its text.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from skimage.feature import match_template

from ..case.folder import DisplacementPoints
from ..core.frame import RigidMotion, index_to_mm
from ..core.tissues import FAT, MUSCLE
from ..imaging.mismatch import contour_pixels, tissue_mask
from .prefilter import EdgeResiduals, Prefilter, rician_variance_ratio
from .shape import AFFINE, WindowShape

SEARCH_FACTOR = 4
GAUSS_NEWTON_ITERATIONS = 20
GAUSS_NEWTON_TOLERANCE_PX = 1e-4
GAUSS_NEWTON_GRADIENT_TOLERANCE = 1e-5   # on the step of the displacement gradient
MAX_REFINEMENT_PX = 3.0   # Gauss-Newton may leave the integer peak of a ridge-shaped ZNCC, not wander off
# Gauss-Newton has failed when it ends at a lower ZNCC than the integer peak it started from; both are interpolated
# (the search patch is resampled through the priors), so a hair lower is not a failure
ZNCC_SLACK = 0.02


# the gradient noise gain of the raw image (no prefilter): the mean square of the spline derivative's response
SPLINE_DERIVATIVE_NOISE_GAIN = Prefilter(0.0).derivative_noise_gain
# Immerkaer (1996): the 3x3 mask below annihilates linear (and most smooth) intensity, white noise of variance
# s^2 passes with variance 36 s^2
_NOISE_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
_MAD_TO_SIGMA = 1.4826
SPLINE_STEP_PX = 1e-3   # the cubic spline differentiated by a central difference of this step (pixels)
COMPILED_ENV = "CALFIT_DIC_COMPILED"   # "0": the windows' loops in Python by default (the reference), not compiled


def compiled_windows():
    """The compiled windows' module (`orchestrator._correlation`), or None when this installation has none."""
    try:
        from .. import _correlation
    except ImportError:
        return None
    return _correlation


def windows_module(compiled: bool | None = None):
    """The compiled module to match the windows with, or None for the Python loops: `compiled` if given, else the
    compiled loops unless CALFIT_DIC_COMPILED=0 or this installation has none."""
    if compiled is None:
        compiled = os.environ.get(COMPILED_ENV, "1").strip() not in ("0", "false", "no", "off")
        return compiled_windows() if compiled else None
    if not compiled:
        return None
    module = compiled_windows()
    if module is None:
        raise RuntimeError("the compiled DIC windows (orchestrator._correlation) are not installed: rebuild the "
                           "package (pip install -e .) or correlate with compiled=False")
    return module


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
    prefilter_px: float = 0.0                       # sigma of the Gaussian both images were smoothed with
    edge_residuals: list | None = None              # (N,) `prefilter.EdgeResiduals` of each converged window
    edge_covariance_mm2: np.ndarray | None = None   # (N, 2, 2) the covariance's part per unit s_edge^2 (px^2)
    edge_variance_px2: float = 0.0                  # s_edge^2 already in covariance_mm2 (`calibrated`)

    def calibrated(self, edge_variance_px2: float, noise_scale: float = 1.0,
                   window_excess: np.ndarray | None = None) -> "DICResult":
        """The same windows with their error model calibrated on the images (`prefilter`, module text): the error of
        the edges' position added to their covariance, and the noise's part (and the intensity variance) scaled by
        noise_scale, what the windows' residuals say of the noise the images' own estimate gave, and by each
        window's own `window_excess` (N,) where its residual exceeds even that."""
        if self.edge_variance_px2 != 0.0:
            raise ValueError("these windows' error model is calibrated already")
        scale = noise_scale * (np.ones(len(self.confidence)) if window_excess is None else np.asarray(window_excess, float))
        covariance = scale[:, None, None] * self.covariance_mm2 + edge_variance_px2 * self.edge_covariance_mm2
        dy, dx = self.pixel_size_mm
        to_px = np.diag([1.0 / dx, 1.0 / dy])
        uncertainty, anisotropy = _spread(np.where(np.isfinite(covariance), to_px @ np.nan_to_num(covariance, posinf=0.0)
                                                   @ to_px, np.inf))
        return replace(self, covariance_mm2=covariance, uncertainty_px=uncertainty, anisotropy=anisotropy,
                       intensity_variance=scale * self.intensity_variance,
                       noise_sigma=tuple(float(np.sqrt(noise_scale) * s) for s in self.noise_sigma),
                       edge_variance_px2=float(edge_variance_px2))

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


@dataclass(frozen=True)
class _Pair:
    """What every window of one correlation reads: the prefiltered reference, the spline coefficients of the
    prefiltered deformed image, the reference's gradients, the prior motion, the images' raw noise, the prefilter
    and the map q = G^2 * |grad I0|^2 of where an edge's error of position becomes intensity (`prefilter`)."""

    reference: np.ndarray
    spline: np.ndarray
    raw_reference: np.ndarray   # the images as given: the ZNCC reported is theirs (`correlate`)
    raw_spline: np.ndarray
    grad_rows: np.ndarray
    grad_cols: np.ndarray
    to_deformed: np.ndarray
    noise_sigma: tuple[float, float]
    prefilter: Prefilter
    edge_q: np.ndarray      # G^2 * |grad I0|^2
    noise_q: np.ndarray     # G^2 * rho: a prefiltered pixel's noise variance per unit s^2
    edge_raw: np.ndarray    # |grad I0|^2 of the raw reference, padded by the prefilter's radius
    rho_raw: np.ndarray     # rho of the raw reference (`prefilter.rician_variance_ratio`), padded likewise

    def around(self, raw: np.ndarray, r0: int, c0: int, size: int) -> np.ndarray:
        """A padded raw map on the window grown by the prefilter's radius (the support of `Prefilter.spread`)."""
        reach = self.prefilter.radius
        return raw[r0:r0 + size + 2 * reach, c0:c0 + size + 2 * reach]


def correlate(reference: np.ndarray, deformed: np.ndarray, centres_rc, pixel_size_mm, *, window_px: int = 16,
              search_factor: int = SEARCH_FACTOR, max_displacement_px: int | None = None,
              prior: RigidMotion | None = None,
              prior_field_mm: np.ndarray | None = None, noise_sigma: tuple[float, float] | None = None,
              prefilter: Prefilter | None = None, pixel_masks=None, workers: int = 1,
              compiled: bool | None = None, shape: WindowShape = AFFINE) -> DICResult:
    """Correlate square windows of `window_px` centred at integer pixels `centres_rc` ((N, 2) rows, columns).

    The integer search covers a square of search_factor x window_px pixels about each window, i.e. a displacement
    of up to (search_factor - 1) window_px / 2 from the priors, or, given max_displacement_px, up to that many pixels
    (the motion a user knows to be small searched for no further: most of a window's time is its search).

    prior: the rigid motion M of the bones (`align_on_bones`: I1(M(x)) ~ I0(x)), composed into every warp, so
    that the displacements are relative to the bones. prior_field_mm: a displacement field (2, H, W) (mm, I0's
    frame, relative to the bones) by which every window is deformed before it is matched (module text, window
    deformation); the displacement returned is the prior's at the centre plus the affine correction.
    noise_sigma: the raw image noise of (reference, deformed); default: estimated from each image where it has
    signal. prefilter: the Gaussian both images are smoothed with first (default `prefilter.Prefilter()`, one
    pixel; `Prefilter(0)` for none). pixel_masks: per window, None (every pixel of the square) or a (window_px,
    window_px) boolean array of the pixels it matches (`measure.window_pixel_masks`: a window inside the tissue
    leaves out the leg's outline). workers: local processes the windows are shared among (`_match_windows`), and the
    compiled loops' threads. compiled: the search and Gauss-Newton in C++ (True), in Python (False, the reference), or
    (None) compiled unless CALFIT_DIC_COMPILED=0 or not installed (module text). shape: the windows' shape function,
    affine (default) or quadratic (`shape.WindowShape`)."""
    reference = np.asarray(reference, float)
    deformed = np.asarray(deformed, float)
    if reference.ndim != 2 or reference.shape != deformed.shape:
        raise ValueError(f"the reference and deformed images must be 2-D of the same shape, not {reference.shape} and "
                         f"{deformed.shape}")
    for name, image in (("reference", reference), ("deformed", deformed)):
        if not np.all(np.isfinite(image)):
            raise ValueError(f"the {name} image holds {int(np.sum(~np.isfinite(image)))} NaN or infinite pixels: "
                             "the correlation needs a grey level at every pixel")
    if prior_field_mm is not None and (np.shape(prior_field_mm) != (2, *reference.shape)
                                       or not np.all(np.isfinite(prior_field_mm))):
        raise ValueError(f"the prior field must be finite and (2, {reference.shape[0]}, {reference.shape[1]}) mm, "
                         f"not {np.shape(prior_field_mm)}")
    module = windows_module(compiled)
    prefilter = Prefilter() if prefilter is None else prefilter
    centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
    if noise_sigma is None:
        noise_sigma = (_signal_noise(reference), _signal_noise(deformed))
    if max_displacement_px is not None and not (isinstance(max_displacement_px, (int, np.integer))
                                                and max_displacement_px >= 0):
        raise ValueError(f"the windows' largest displacement is a whole number of pixels, not {max_displacement_px}")
    search_px = (search_factor * window_px if max_displacement_px is None
                 else window_px + 2 * int(max_displacement_px))
    smooth_reference = prefilter(reference)
    grad_rows, grad_cols = spline_gradient(smooth_reference, module=module)
    # |grad I0|^2 of the raw reference: the gradients' own when nothing was smoothed
    edges_raw = edge_strength(reference, module) if prefilter.sigma_px > 0 else grad_rows ** 2 + grad_cols ** 2
    rho = rician_variance_ratio(reference, noise_sigma[0])
    pair = _Pair(smooth_reference, ndimage.spline_filter(prefilter(deformed), order=3), reference,
                 ndimage.spline_filter(deformed, order=3) if prefilter.sigma_px > 0 else None, grad_rows, grad_cols,
                 index_affine(prior, pixel_size_mm), (float(noise_sigma[0]), float(noise_sigma[1])), prefilter,
                 prefilter.squared_kernel_response(edges_raw), prefilter.squared_kernel_response(rho),
                 np.pad(edges_raw, prefilter.radius, mode="edge"), np.pad(rho, prefilter.radius, mode="edge"))
    dy, dx = pixel_size_mm
    prior_px = None if prior_field_mm is None else np.stack([prior_field_mm[0] / dx, prior_field_mm[1] / dy])
    displacement = np.full((len(centres), 2), np.nan)
    confidence = np.zeros(len(centres))
    covariance = np.full((len(centres), 2, 2), np.inf)
    variance = np.full(len(centres), np.inf)
    gradient = np.full((len(centres), 2, 2), np.nan)
    edges = [EdgeResiduals() for _ in range(len(centres))]
    edge_covariance = np.zeros((len(centres), 2, 2))
    pixel_sets = window_pixel_sets(pixel_masks, len(centres), window_px)
    if module is None:
        matches = _match_windows((pair, centres, window_px, search_px, prior_px, pixel_sets, shape), workers)
    else:   # the compiled loops computed every window's error terms too, on `workers` threads
        matches = [None if searched is None else _finished(searched) for searched in
                   _compiled_search(module, pair, centres, window_px, search_px, prior_px, pixel_sets, workers, shape)]
    for k, match in enumerate(matches):
        if match is not None:
            displacement[k], confidence[k], covariance[k] = match.displacement, match.confidence, match.covariance
            variance[k], gradient[k], edges[k], edge_covariance[k] = (match.variance, match.gradient, match.edges,
                                                                       match.edge_covariance)
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
                     (float(dy), float(dx)), pair.noise_sigma, variance,
                     to_mm @ gradient @ np.linalg.inv(to_mm), prefilter.sigma_px, edges,
                     to_mm @ edge_covariance @ to_mm)


# Windows are independent: with workers > 1 they are shared among forked processes in this many chunks each (the
# windows' costs differ, the skin's more than the muscle's), every window matched exactly as in one process. Fewer
# windows than MIN_WINDOWS_PER_WORKER a process are matched here: forking costs more than they take.
CHUNKS_PER_WORKER = 4
MIN_WINDOWS_PER_WORKER = 50
_WORKER_WINDOWS = None   # a forked worker's (pair, centres, window_px, search_px, prior_px, pixel_sets, shape)


def _compiled_search(module, pair: _Pair, centres: np.ndarray, window_px: int, search_px: int, prior_px,
                     pixel_sets: list, threads: int, shape: WindowShape = AFFINE) -> list:
    """Per window, what the compiled loops found and its error terms (`_Searched`), on `threads` threads."""
    used = (np.stack(pixel_sets) if pixel_sets else np.zeros((0, window_px * window_px), bool)).astype(bool)

    def grid(a):
        return None if a is None else np.ascontiguousarray(a, dtype=float)

    found = module.match_windows(
        *(grid(a) for a in (pair.reference, pair.spline, pair.grad_rows, pair.grad_cols, pair.to_deformed)),
        grid(prior_px), np.ascontiguousarray(centres, dtype=np.int64).reshape(-1, 2), np.ascontiguousarray(used),
        int(window_px), int(search_px), GAUSS_NEWTON_ITERATIONS, GAUSS_NEWTON_TOLERANCE_PX,
        GAUSS_NEWTON_GRADIENT_TOLERANCE, max(int(threads), 1), shape.order,
        raw_reference=None if pair.raw_spline is None else grid(pair.raw_reference), raw_spline=grid(pair.raw_spline),
        noise_q=grid(pair.noise_q), edge_q=grid(pair.edge_q), rho_raw=grid(pair.rho_raw), edge_raw=grid(pair.edge_raw),
        kernel=grid(pair.prefilter.kernel), noise_gain=pair.prefilter.noise_gain,
        derivative_noise_gain=pair.prefilter.derivative_noise_gain, noise_sigma_reference=pair.noise_sigma[0],
        noise_sigma_deformed=pair.noise_sigma[1], max_refinement_px=MAX_REFINEMENT_PX, zncc_slack=ZNCC_SLACK)
    searched = []
    for k, (status, start, peak, warp) in enumerate(zip(found["status"], found["start"], found["peak_score"],
                                                       found["warp"])):
        status = int(status)
        if status in (module.OUTSIDE, module.FLAT, module.NOT_FINITE):
            searched.append(None)   # matched by nobody: the window is rejected as when it does not fit
            continue
        full = shape.from_rows(warp) if status == module.MATCHED else None
        textured, at_start = (bool(v) for v in found["flags"][k, 1:])   # (the first: conditioned, in at_start)
        confidence, start_confidence, variance = (float(v) for v in found["scores"][k, 1:])   # (the first: the ZNCC)
        terms = _ErrorTerms(textured, at_start, confidence, start_confidence, variance,
                            found["covariances"][k, 0].copy(), found["covariances"][k, 1].copy(),
                            EdgeResiduals(int(found["edge_sums"][k, 0]), *(float(v) for v in found["edge_sums"][k, 1:])))
        searched.append(_Searched(start.copy(), float(peak), full, terms))
    return searched


@dataclass(frozen=True)
class _ErrorTerms:
    """A window's error terms from the compiled loops (correlation_cpp/src/error_model.hpp), what
    `_inverse_compositional` computes from the same warp: whether its texture rises above the noise, whether the
    window is measured at its search's start (`_finished`), the ZNCC of the raw images at the match and at the
    start, s_e^2, the covariance under the noise and per unit s_edge^2 (px^2)
    and the sums its residual adds to the edges' estimate."""

    textured: bool
    at_start: bool   # measured at the search's start: no warp, not conditioned, or by the rules of `_finished`
    confidence: float
    start_confidence: float
    variance: float
    covariance: np.ndarray
    edge_covariance: np.ndarray
    edges: EdgeResiduals


@dataclass(frozen=True)
class _Searched:
    """A window's integer search, Gauss-Newton iterations and error terms from the compiled loops: the start (d_col,
    d_row) px, the integer peak's ZNCC, the final warp's matrix (`shape.WindowShape.matrix`; None where Gauss-Newton
    could not proceed) and the `_ErrorTerms` at it."""

    start: np.ndarray
    peak_score: float
    warp: np.ndarray | None
    terms: _ErrorTerms


def _match_windows(job: tuple, workers: int) -> list:
    """Every window's `_Match` (or None) of job = (pair, centres, window_px, search_px, prior_px, pixel_sets, shape)
    by the Python loops, in order; in `workers` forked processes when the platform forks (the images reach them by
    the fork, not a pipe)."""
    count = len(job[1])
    workers = min(int(workers), count // MIN_WINDOWS_PER_WORKER)
    if workers <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return _match_chunk(range(count), job)
    chunks = [chunk for chunk in np.array_split(np.arange(count), workers * CHUNKS_PER_WORKER) if len(chunk)]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"), initializer=_hold_windows,
                             initargs=(job,)) as pool:
        return [match for part in pool.map(_match_chunk, chunks) for match in part]


def _hold_windows(job: tuple) -> None:
    global _WORKER_WINDOWS
    _WORKER_WINDOWS = job


def _match_chunk(indices, job: tuple | None = None) -> list:
    pair, centres, window_px, search_px, prior_px, pixel_sets, shape = _WORKER_WINDOWS if job is None else job
    return [_correlate_window(pair, centres[k][0], centres[k][1], window_px, search_px, prior_px, pixel_sets[k],
                              shape=shape) for k in indices]


def attainable_confidence(reference: np.ndarray, centres_rc, window_px: int, noise_sigma: tuple[float, float],
                          pixel_masks=None) -> np.ndarray:
    """(N,) the ZNCC each window can reach between two noisy images of the same texture: S / sqrt((S + s_0^2)
    (S + s_1^2)), S the variance of the window's texture in the raw reference less its noise s_0^2, s_1 the loaded
    image's noise (0 where the window holds no texture above the noise). A weakly textured window (the muscle of a
    T1 image) matches at a low ZNCC that is all its noise allows, and its covariance says how little it knows; a
    false match reaches far less than its texture allows (`measure`: the match check)."""
    reference = np.asarray(reference, float)
    centres = np.atleast_2d(np.asarray(centres_rc, dtype=int))
    pixel_sets = window_pixel_sets(pixel_masks, len(centres), window_px)
    half = window_px // 2
    variance = np.zeros(len(centres))
    for k, ((row, col), used) in enumerate(zip(centres, pixel_sets)):
        block = reference[max(row - half, 0):row - half + window_px, max(col - half, 0):col - half + window_px]
        values = block.ravel()[used] if block.size == used.size else block.ravel()
        variance[k] = values.var() if values.size > 1 else 0.0
    s0, s1 = (float(v) for v in noise_sigma)
    texture = np.maximum(variance - s0 ** 2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.nan_to_num(texture / np.sqrt((texture + s0 ** 2) * (texture + s1 ** 2)))


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


def spline_gradient(image: np.ndarray, step: float = SPLINE_STEP_PX, module=None) -> tuple[np.ndarray, np.ndarray]:
    """(d/drow, d/dcolumn) at the pixels of the cubic-spline interpolant of the image, the interpolant used for
    the deformed image: Gauss-Newton then converges to the exact minimum even on sharp band-limited edges,
    where central differences are too inaccurate and stall it. module: the compiled windows' module, which takes
    the same differences of the same spline (scipy's coefficients) in a third of the time, or None (scipy)."""
    coefficients = ndimage.spline_filter(np.asarray(image, float), order=3)
    if module is not None:
        return module.spline_gradient(np.ascontiguousarray(coefficients), float(step))
    rows, cols = np.indices(image.shape, dtype=float)
    return spline_derivatives(coefficients, rows, cols, step)


def edge_strength(reference: np.ndarray, module=None) -> np.ndarray:
    """|grad I|^2 of the raw reference (intensity^2 per px^2, cubic-spline gradient): where an error of position
    becomes an error of intensity (`prefilter`). module: as for `spline_gradient`."""
    grad_rows, grad_cols = spline_gradient(reference, module=module)
    return grad_rows ** 2 + grad_cols ** 2


def spline_derivatives(coefficients: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                       step: float = SPLINE_STEP_PX) -> tuple[np.ndarray, np.ndarray]:
    """(d/drow, d/dcolumn) of the cubic spline of these coefficients (`ndimage.spline_filter`, order 3) at the
    points (rows, cols), by a central difference of `step` pixels of the spline itself."""
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


@dataclass(frozen=True)
class _Match:
    """One window's match: displacement (d_col, d_row) px (the affine correction to the prior field when there is
    one), the ZNCC of the raw images there, the 2x2 covariance (px^2) under the images' noise, the raw intensity
    variance s_e^2 behind it, the displacement gradient, the window's `EdgeResiduals` and its covariance's part per
    unit s_edge^2 (px^2)."""

    displacement: np.ndarray
    confidence: float
    covariance: np.ndarray
    variance: float
    gradient: np.ndarray
    edges: EdgeResiduals
    edge_covariance: np.ndarray

    @classmethod
    def unmeasured(cls, displacement: np.ndarray, confidence: float) -> "_Match":
        """Where the window matched but its error cannot be told (no texture above the noise, or Gauss-Newton left
        its integer peak)."""
        return cls(displacement, confidence, np.full((2, 2), np.inf), np.inf, np.full((2, 2), np.nan), EdgeResiduals(),
                   np.zeros((2, 2)))


def _correlate_window(pair: _Pair, row, col, window_px, search_px, prior_px, used: np.ndarray,
                      shape: WindowShape = AFFINE) -> _Match | None:
    """One window's `_Match` by the Python loops (the compiled loops' reference), or None if it does not fit or is
    flat. used: the pixels it matches (flat boolean over its square, `window_pixel_sets`); the integer search that
    starts Gauss-Newton uses the whole square."""
    height, width = pair.reference.shape
    r0, c0 = row - window_px // 2, col - window_px // 2
    if r0 < 0 or c0 < 0 or r0 + window_px > height or c0 + window_px > width:
        return None
    template = pair.reference[r0:r0 + window_px, c0:c0 + window_px]
    if template.std() < 1e-12:
        return None
    margin = (search_px - window_px) // 2
    search_rows, search_cols = np.mgrid[r0 - margin:r0 + window_px + margin, c0 - margin:c0 + window_px + margin]
    prior_cols, prior_rows = _prior_at(prior_px, search_rows, search_cols)
    score = match_template(_sample(pair.spline, pair.to_deformed, search_cols + prior_cols,
                                   search_rows + prior_rows), template)
    peak_row, peak_col = np.unravel_index(int(np.argmax(score)), score.shape)
    start = np.array([peak_col + _parabola_offset(score[peak_row, :], peak_col) - margin,
                      peak_row + _parabola_offset(score[:, peak_col], peak_row) - margin])
    window_prior = (prior_cols[margin:margin + window_px, margin:margin + window_px].ravel(),
                    prior_rows[margin:margin + window_px, margin:margin + window_px].ravel())
    peak_score = float(score[peak_row, peak_col])
    found = _inverse_compositional(pair, template, r0, c0, start, window_prior, used, shape)
    if found is None or np.max(np.abs(found[0].displacement - start)) > MAX_REFINEMENT_PX or found[1] < peak_score - ZNCC_SLACK:
        return _Match.unmeasured(start, _raw_zncc(pair, r0, c0, window_px, start, window_prior, used=used,
                                                  shape=shape))
    return found[0]


def _finished(searched: _Searched) -> _Match:
    """A window's `_Match` from the compiled loops' warp and error terms. The loops applied `_correlate_window`'s
    rules (MAX_REFINEMENT_PX and ZNCC_SLACK, passed to them) and `_inverse_compositional`'s (the condition number,
    the texture above the noise) and say which held."""
    terms, start, warp = searched.terms, searched.start, searched.warp
    if warp is None or terms.at_start:
        return _Match.unmeasured(start, terms.start_confidence)
    displacement = np.array([warp[-3, -1], warp[-2, -1]])
    if not terms.textured:
        return _Match.unmeasured(displacement, terms.confidence)
    return _Match(displacement, terms.confidence, terms.covariance, terms.variance, warp[-3:-1, -3:-1] - np.eye(2),
                  terms.edges, terms.edge_covariance)


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


def zero_normalised_steepest_descent(template: np.ndarray, grad_cols: np.ndarray, grad_rows: np.ndarray,
                                     used: np.ndarray | None = None,
                                     shape: WindowShape = AFFINE) -> tuple[np.ndarray, np.ndarray]:
    """(P S, (P S)^T (P S)): the steepest-descent images of a window with the window's mean and its own grey levels
    f^ projected out, P = I - 11^T/n - f^ f^T, and the Gauss-Newton matrix they make. The zero-normalised SSD
    compares mean-free, unit-norm windows, so a change of the deformed image along a constant or along f itself
    does not move the match: linearised at the match, the parameters' error is (S^T P S)^-1 S^T P e for image noise
    e, and what the window sees of a field u is (S^T P S)^-1 S^T P (grad f . u) (`windows`). Without P, a window
    across a bright edge (net gradient, brighter on one side) had its errors' correlation with its neighbours
    predicted 50 % too high (half-overlapping 16-pixel windows: 0.47 against 0.30 measured over 300 noise draws).
    used: the window's pixels (flat boolean over the square, all by default); the rows are theirs. shape: the
    window's shape function (affine by default)."""
    steepest = steepest_descent(grad_cols, grad_rows, shape)
    values = np.asarray(template, float).ravel()
    if used is not None:
        steepest, values = steepest[used], values[used]
    f_hat, _ = _normalise(values)
    projected = steepest - steepest.mean(axis=0) - np.outer(f_hat, f_hat @ steepest)
    return projected, projected.T @ projected


def window_pixel_sets(pixel_masks, count: int, window_px: int) -> list[np.ndarray]:
    """The pixels each of `count` windows matches, flat booleans over its square: all of them where pixel_masks
    (a sequence of None or (window_px, window_px) booleans, `measure.window_pixel_masks`) is None or gives None."""
    masks = [None] * count if pixel_masks is None else list(pixel_masks)
    if len(masks) != count:
        raise ValueError(f"{len(masks)} pixel masks for {count} windows")
    sets = [np.ones(window_px * window_px, bool) if mask is None else np.asarray(mask, bool).ravel() for mask in masks]
    for k, used in enumerate(sets):
        if used.size != window_px * window_px:
            raise ValueError(f"window {k}'s pixel mask holds {used.size} pixels, not the {window_px} x {window_px} of "
                             "its square")
    return sets


def on_window_square(rows_of_used: np.ndarray, used: np.ndarray, size: int) -> np.ndarray:
    """(k, size, size) maps holding (k, n_used) values at a window's pixels `used` and zero elsewhere."""
    rows_of_used = np.atleast_2d(rows_of_used)
    full = np.zeros((rows_of_used.shape[0], size * size))
    full[:, used] = rows_of_used
    return full.reshape(-1, size, size)


def steepest_descent(grad_cols: np.ndarray, grad_rows: np.ndarray, shape: WindowShape = AFFINE) -> np.ndarray:
    """(n, parameters) steepest-descent images grad f . d(x + u_p(x))/dp of a square window, p the shape
    function's parameters (`shape.WindowShape`; affine: (u, du/dx, du/dy, v, dv/dx, dv/dy)), offsets measured from
    the window centre."""
    basis = shape.window_basis(grad_cols.shape[0])
    return np.concatenate([(grad_cols.ravel() * basis).T, (grad_rows.ravel() * basis).T], axis=1)


def _inverse_compositional(pair: _Pair, template, r0, c0, start, prior, used: np.ndarray,
                           shape: WindowShape = AFFINE) -> tuple[_Match, float] | None:
    """IC-GN with the window shape function `shape` (affine or quadratic) on the zero-normalised SSD of the
    prefiltered images, the deformed image sampled through the prior motion and the prior field (`prior`: (d_col,
    d_row) px at the window's pixels), over the window's pixels `used` (flat boolean). Returns the window's `_Match`
    (module text) and the ZNCC of the prefiltered images there. The compiled loops compute the same
    (correlation_cpp/src/error_model.hpp, `_finished`)."""
    f_hat, f_norm = _normalise(template.ravel()[used])
    if f_norm == 0.0:
        return None
    size = template.shape[0]
    window = (slice(r0, r0 + size), slice(c0, c0 + size))
    steepest_raw, hessian_raw = zero_normalised_steepest_descent(template, pair.grad_cols[window], pair.grad_rows[window],
                                                                 used, shape)
    if np.linalg.cond(hessian_raw) > 1e10:
        return None
    noise_q = np.where(used.reshape(size, size), pair.noise_q[window], 0.0)
    signal_hessian = denoised_hessian(hessian_raw, size, pair.noise_sigma[0], pair.prefilter.derivative_noise_gain,
                                      noise_q / pair.prefilter.noise_gain, shape)
    steepest, hessian = steepest_raw / f_norm, hessian_raw / f_norm ** 2
    centre_row, centre_col = r0 + (size - 1) / 2.0, c0 + (size - 1) / 2.0
    points = shape.window_monomials(size)[:, used]
    prior_used = (prior[0][used], prior[1][used])
    warp = shape.translated(start)
    translation = shape.translation

    def sample(warp):
        moved = warp[-3:-1] @ points
        return _normalise(_sample(pair.spline, pair.to_deformed, centre_col + moved[0] + prior_used[0],
                                  centre_row + moved[1] + prior_used[1]))

    for _ in range(GAUSS_NEWTON_ITERATIONS):
        g_hat, g_norm = sample(warp)
        if g_norm == 0.0:
            return None
        step = np.linalg.solve(hessian, steepest.T @ (g_hat - f_hat))
        warp = warp @ np.linalg.inv(shape.matrix(step))
        if (np.max(np.abs(step[translation])) < GAUSS_NEWTON_TOLERANCE_PX
                and np.max(np.abs(step[shape.deformation])) < GAUSS_NEWTON_GRADIENT_TOLERANCE):
            break
    g_hat, g_norm = sample(warp)
    displacement, zncc = np.array([warp[-3, -1], warp[-2, -1]]), float(f_hat.ravel() @ g_hat)
    # the raw noise of the two images as it enters the normalised difference (the deformed one scaled to the reference)
    variance = pair.noise_sigma[0] ** 2 + (f_norm / g_norm * pair.noise_sigma[1]) ** 2
    confidence = (_raw_zncc(pair, r0, c0, size, displacement, prior, warp, used, shape)
                  if pair.raw_spline is not None else zncc)
    if signal_hessian is None:   # the window's texture does not rise above the noise
        return _Match.unmeasured(displacement, confidence), zncc
    # p = H_s^-1 S^T (G * e) for raw noise e of variance s_e^2 rho: Cov p = s_e^2 H_s^-1 (G * S)^T rho (G * S) H_s^-1
    # (`prefilter`), and the part of an error of the edges' position per unit s_edge^2 likewise
    spread = pair.prefilter.spread(on_window_square(steepest_raw.T, used, size)).reshape(shape.parameters, -1)
    edge_raw = pair.around(pair.edge_raw, r0, c0, size).ravel()
    edge_q = pair.edge_q[window].ravel()[used]
    noise_raw = pair.around(pair.rho_raw, r0, c0, size).ravel()
    # (G * S)^T diag(w) (G * S) of each error, for the share the match takes and for the parameters' covariance
    edge_gram, noise_gram = ((spread * weights) @ spread.T for weights in (edge_raw, noise_raw))
    normalisation = _normalisation_spread(pair.prefilter, f_hat, used, size)
    # what the residual keeps of each error: the match takes a larger share of the edges' than of the noise's
    edge_kept = 1.0 - _absorbed_share(hessian_raw, edge_gram, normalisation, edge_raw, edge_q.sum())
    noise_kept = 1.0 - _absorbed_share(hessian_raw, noise_gram, normalisation, noise_raw, noise_q.sum())
    edges = EdgeResiduals()
    edges.add((g_hat - f_hat) * f_norm, edge_kept * edge_q, variance * noise_kept * noise_q.ravel()[used])
    inverse = np.linalg.inv(signal_hessian)
    centre_block = np.ix_(translation, translation)

    def sandwich(gram: np.ndarray) -> np.ndarray:
        return (inverse @ gram @ inverse)[centre_block]

    noise_sandwich = sandwich(noise_gram)
    edge_sandwich = sandwich(edge_gram)
    return (_Match(displacement, confidence, variance * noise_sandwich, variance, warp[-3:-1, -3:-1] - np.eye(2), edges,
                   edge_sandwich), zncc)


def _normalisation_spread(prefilter: Prefilter, f_hat: np.ndarray, used: np.ndarray, size: int) -> np.ndarray:
    """(2, m) the two directions the zero-normalised SSD removes from a window, its mean 1 / sqrt(n) and its template
    f^ (over the window's pixels `used`, flat boolean over its size x size square), spread by the prefilter as the
    steepest-descent images are (`_absorbed_share`)."""
    f_hat = np.asarray(f_hat, float)
    directions = np.stack([np.full(f_hat.shape, 1.0 / np.sqrt(f_hat.size)), f_hat])
    return prefilter.spread(on_window_square(directions, used, size)).reshape(2, -1)


def _absorbed_share(hessian: np.ndarray, gram: np.ndarray, normalisation: np.ndarray, variance_raw: np.ndarray,
                    total: float) -> float:
    """tr(P C) / tr(C): the share of an error of the raw pixels (variance map `variance_raw`, C = G diag(w) G^T
    once prefiltered, `total` = tr(C) over the window) that a window's own fit takes into its parameters, and so
    leaves out of its residual (`prefilter`, module text). P projects the prefiltered window onto what its match
    adjusts: the shape function's directions S (six affine, twelve quadratic; projected, `zero_normalised_steepest_descent`; H = S^T S), the mean and
    the template f^ that the zero-normalised SSD removes, so tr(P C) = tr(H^-1 (G * S)^T diag(w) (G * S)) + the
    same for 1 / sqrt(n) and f^ (orthogonal to S and to each other). gram: (G * S)^T diag(w) (G * S);
    normalisation: G * (1 / sqrt(n), f^) (`_normalisation_spread`). For the edges' error (w = |grad I0|^2 per unit
    s_edge^2) it is large, since that error lies where the steepest-descent images are largest; for the noise
    (w = rho) it is 5-7 % of a 32-pixel window on the phantoms and the other program's images, which a count of
    8 fitted values times the pixels one prefiltered value spreads over put at 4.9 %."""
    if total <= 0.0:
        return 0.0
    taken = np.trace(np.linalg.solve(hessian, gram)) + float(np.sum(normalisation ** 2 * variance_raw))
    return float(np.clip(taken / total, 0.0, 1.0))


def _raw_zncc(pair: _Pair, r0: int, c0: int, size: int, displacement, prior, warp: np.ndarray | None = None,
              used: np.ndarray | None = None, shape: WindowShape = AFFINE) -> float:
    """The ZNCC of the raw (not prefiltered) windows at the match: the quality the user reads. Smoothed noise
    correlates by chance (a 16-pixel window of air prefiltered by one pixel holds some 40 independent values, and
    the best of a search's 4,000 positions reaches a ZNCC of 0.9); raw noise does not."""
    if pair.raw_spline is None:   # no prefilter: the raw images are the ones matched
        spline, reference = pair.spline, pair.reference
    else:
        spline, reference = pair.raw_spline, pair.raw_reference
    if warp is None:
        warp = shape.translated(displacement)
    used = np.ones(size * size, bool) if used is None else used
    moved = warp[-3:-1] @ shape.window_monomials(size)[:, used]
    deformed = _sample(spline, pair.to_deformed, c0 + (size - 1) / 2.0 + moved[0] + np.asarray(prior[0])[used],
                       r0 + (size - 1) / 2.0 + moved[1] + np.asarray(prior[1])[used])
    f_hat, f_norm = _normalise(reference[r0:r0 + size, c0:c0 + size].ravel()[used])
    g_hat, g_norm = _normalise(deformed)
    return float(f_hat @ g_hat) if f_norm > 0 and g_norm > 0 else 0.0


def denoised_hessian(hessian: np.ndarray, size: int, reference_noise_sigma: float,
                     derivative_noise_gain: float = SPLINE_DERIVATIVE_NOISE_GAIN,
                     noise_ratio: np.ndarray | None = None, shape: WindowShape = AFFINE) -> np.ndarray | None:
    """H_s = H - s_f^2 g^2 M_rho, the Gauss-Newton matrix of the noiseless reference (module text; g^2 the gradient
    noise gain of the prefiltered image, `prefilter.Prefilter.derivative_noise_gain`; M_rho the moments of the
    window's shape function (`shape.WindowShape.moments`) weighted by each pixel's share rho of the noise variance,
    (size, size) `noise_ratio`, 1 if not given: the Rician noise of the air beside the skin is 0.43 of the tissue's,
    and a window half in air, the tissue's noise taken away everywhere, over-predicted the variance along the skin
    1.6 times); None when it is not positive definite, i.e. the window holds less texture than noise."""
    signal = hessian - reference_noise_sigma ** 2 * derivative_noise_gain * shape.moments(size, noise_ratio)
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
