"""The loaded slice's texture that is not the unloaded slice's moved: its autocovariance, and the windows' error it
makes.

Why. A window's error model (`windows.WindowOperators`) takes the loaded image to be the unloaded one moved, plus
noise. A scanner's loaded slice is not that. The slice is several millimetres thick, and the garment slides the
tissue along the leg through it, so structures that run obliquely through the slice (fat septa, muscle bundles)
move by their slope times that slide. The band-limited image's ringing is that of the deformed leg, not the
unloaded ringing deformed. Each window matches what it sees, and the match follows the change: the error this
leaves is invisible to the window's own residual. On calfit's k-space renderer it made the fat's windows err by
1.9-2.0 times their predicted variance (docs/validation/scanner-images.md).

What is measured. Sample the loaded image through the kept windows' field and the bones' motion, take away the
unloaded image at the local gain (the coil is fixed to the scanner and the leg moves in it, so the gain varies
smoothly across the leg), and high-pass it at the windows' scale (ZNCC takes out each window's mean and scale):

    D = hp(I1(phi(x)) - g(x) I0(x)),   g = G * (I1(phi) I0) / G * (I0^2),

less its local least-squares fit on I0's texture and on its Laplacian (`without_contrast_and_sharpness`): a change
of contrast or sharpness is even about each feature and moves no match. D then holds the images' noise through the
same warp and filters, the error of the edges' position that the windows' residuals calibrated (s_edge^2 |grad I0|^2,
`prefilter`), and the texture change. Per tissue, the autocovariance of D less that of what the error model already
holds (simulated: the images' own noise sigmas and the edges' error sent through the same warp, gain and filters) is
the change's, c_t(lag). It is taken only where it stands out of the noise estimate's own scatter (SIGNIFICANCE
standard errors at lag 0) and is made a valid autocovariance (`valid_autocovariance`). Its local amplitude a_t (the
local excess variance over the tissue's, over half a window) says where it is larger.

Only the part that moves features counts. A change that keeps each feature's centroid (a box-averaged thin septum
moved by a fraction of a pixel) changes D without moving any window. So the patches of a quarter window show, by
Lucas-Kanade, the displacements that D makes (`patch_displacements`); their mean square over the noise's, divided by
what a random field of autocovariance c_t and amplitude a_t would make of them, is the share of the change that
moves features (`_displacement_share`), itself tested at SIGNIFICANCE standard errors. c_t is scaled by that share.

What it does to the windows. A window reports p = B e for an intensity error e of its raw pixels
(`windows.WindowOperators.B`, the linearised IC-GN with the prefilter). An error of that autocovariance makes

    Cov(p_i, p_j) = sum_t sum_{x, y in t} B_i(x) a_t(x) c_t(x - y) a_t(y) B_j(y)^T,

added to the measurements' covariance as a factor F (F F^T, as the drawing model's: `drawing`). On images whose
loaded texture is the unloaded one moved, or changed in ways that move nothing (calfit's 2D renderers, the other
programs' calves drawn pixel by pixel and blind-51), nothing is added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal
from scipy.spatial import cKDTree

from .dic import edge_strength, spline_gradient
from .prefilter import PREFILTER_SIGMA_PX

LAG_PX = 10             # the autocovariance is kept to lags of +-10 px: septa and bundles are a few pixels wide
GAIN_SMOOTHING_PX = 6.0  # the local gain's Gaussian: a coil profile varies over centimetres, the texture over pixels
SIGNIFICANCE = 3.0       # standard errors of the noise's own lag-0 estimate the excess must exceed
NOISE_DRAWS = 2          # simulated noise images the noise's autocovariance is averaged over
NOISE_SEED = 20261203    # fixed: the same images give the same error model
EIGEN_FLOOR = 1e-12      # relative: eigenvalues of the windows' covariance below it are round-off
TISSUES = {"fat": 1, "muscle": 2}
PATCH_MIN_PX = 6         # the patches that show whether the change moves features: a quarter window, at least 6 px
PATCH_CONDITION = 50.0   # a patch whose gradients run mostly one way cannot show a displacement across them
PATCH_MIN_COUNT = 20     # fewer patches than this say nothing: their mean square would scatter by a third or more


@dataclass
class TissueChange:
    """The texture change measured in one tissue."""

    tissue: str
    pixels: int
    residual_variance: float      # of D (intensity^2)
    noise_variance: float         # of the noise alone through the same warp and filters
    excess_variance: float        # lag 0 of the change's autocovariance (0 when not significant)
    standard_error: float         # of the noise's lag-0 estimate
    significant: bool
    displacement_share: float = 0.0   # the part of the change that moves features (`_displacement_share`)
    patches: int = 0

    def as_dict(self) -> dict:
        return {"tissue": self.tissue, "pixels": self.pixels, "residual_variance": self.residual_variance,
                "noise_variance": self.noise_variance, "excess_variance": self.excess_variance,
                "standard_error": self.standard_error, "significant": self.significant,
                "displacement_share": self.displacement_share, "patches": self.patches,
                "excess_over_noise": self.excess_variance / max(self.noise_variance, 1e-300)}


def high_pass(image: np.ndarray, sigma_px: float) -> np.ndarray:
    return image - ndimage.gaussian_filter(image, sigma_px)


def _residual(unloaded: np.ndarray, warped_loaded: np.ndarray, valid: np.ndarray,
              sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """D of the module text before the contrast's fit (zero where the warp left the loaded image), and the gain g."""
    moved = np.where(valid, warped_loaded, 0.0)
    reference = np.where(valid, unloaded, 0.0)
    gain = (ndimage.gaussian_filter(moved * reference, GAIN_SMOOTHING_PX)
            / np.maximum(ndimage.gaussian_filter(reference * reference, GAIN_SMOOTHING_PX), 1e-300))
    return np.where(valid, high_pass(moved - gain * reference, sigma_px), 0.0), gain


def without_contrast_and_sharpness(residual: np.ndarray, reference: np.ndarray, valid: np.ndarray,
                                   sigma_px: float) -> np.ndarray:
    """The residual less its local least-squares fit on the reference's texture and on its Laplacian (Gaussian
    weights of GAIN_SMOOTHING_PX). A change of the texture's contrast or sharpness between the sessions (another
    slice profile or partial volume, a filter) is even about each feature and does not move a match, where a
    stationary error of the same variance would."""
    reference = np.where(valid, reference, 0.0)
    regressors = [np.where(valid, high_pass(reference, sigma_px), 0.0),
                  np.where(valid, high_pass(ndimage.gaussian_laplace(reference, 1.0), sigma_px), 0.0)]
    smooth = lambda image: ndimage.gaussian_filter(image, GAIN_SMOOTHING_PX)   # noqa: E731
    gram = np.array([[smooth(a * b) for b in regressors] for a in regressors])        # (2, 2, H, W)
    right = np.array([smooth(a * residual) for a in regressors])                     # (2, H, W)
    gram = np.moveaxis(gram, (0, 1), (-2, -1)) + 1e-12 * np.eye(2) * np.abs(gram).max()
    coefficients = np.linalg.solve(gram, np.moveaxis(right, 0, -1)[..., None])[..., 0]
    fitted = sum(coefficients[..., k] * regressors[k] for k in range(2))
    return np.where(valid, residual - fitted, 0.0)


def autocovariance(values: np.ndarray, mask: np.ndarray, lag: int = LAG_PX) -> np.ndarray:
    """(2 lag + 1, 2 lag + 1) mean of values(x) values(x + s) over the pixel pairs both in mask."""
    masked = np.where(mask, values, 0.0)
    weight = mask.astype(float)
    products = signal.fftconvolve(masked, masked[::-1, ::-1], mode="full")
    pairs = signal.fftconvolve(weight, weight[::-1, ::-1], mode="full")
    r, c = np.array(products.shape) // 2
    cut = (slice(r - lag, r + lag + 1), slice(c - lag, c + lag + 1))
    return products[cut] / np.maximum(np.round(pairs[cut]), 1.0)


def root_kernel(values: np.ndarray) -> np.ndarray:
    """k, the zero-phase square root of the autocovariance's spectrum (its negative part cut), kept to half the lags:
    white noise convolved with k has the autocovariance k * k, near `values`."""
    size = values.shape[0]
    lag = size // 2
    symmetric = 0.5 * (values + values[::-1, ::-1])
    grid = 4 * size
    padded = np.zeros((grid, grid))
    padded[:size, :size] = symmetric
    padded = np.roll(padded, (-lag, -lag), axis=(0, 1))   # lag 0 at index 0: a real, even spectrum
    root = np.real(np.fft.ifft2(np.sqrt(np.maximum(np.real(np.fft.fft2(padded)), 0.0))))
    half = lag // 2
    kernel = np.roll(root, (half, half), axis=(0, 1))[:2 * half + 1, :2 * half + 1]
    return kernel


def valid_autocovariance(values: np.ndarray) -> np.ndarray:
    """An autocovariance near `values` that makes a positive semi-definite covariance on any set of pixels: k * k
    (`root_kernel`: a kernel correlated with itself, whose spectrum |K|^2 cannot be negative)."""
    lag = values.shape[0] // 2
    kernel = root_kernel(values)
    made = signal.correlate(kernel, kernel, mode="full")
    out = np.zeros_like(values, dtype=float)
    reach = made.shape[0] // 2
    out[lag - reach:lag + reach + 1, lag - reach:lag + reach + 1] = made
    return out


def measure_change(unloaded: np.ndarray, loaded: np.ndarray, labels: np.ndarray, where: np.ndarray,
                   warped: np.ndarray, noise_sigma, window_px: int,
                   edge_variance_px2: float = 0.0) -> tuple[dict[str, "Change"], list[TissueChange]]:
    """The change's autocovariance per tissue (intensity^2 by lag; only the significant ones) and what was measured.
    where, warped: the loaded image's (2, H W) indices of I0's pixels and I1 sampled there, NaN outside it
    (`measurements.kept_field_warp`); noise_sigma: the raw noise sigma of I0 and of I1; edge_variance_px2: the
    windows' calibrated variance of the edges' position, whose intensity error s_edge^2 |grad I0|^2 the error model
    already holds and the simulation sends through too."""
    unloaded = np.asarray(unloaded, float)
    shape = unloaded.shape
    valid = np.isfinite(warped)
    # the window's own second moment: ZNCC and the affine warp take out what varies over more than a window
    sigma_px = window_px / np.sqrt(12.0)
    residual, gain = _residual(unloaded, warped, valid, sigma_px)
    residual = without_contrast_and_sharpness(residual, unloaded, valid, sigma_px)
    rng = np.random.default_rng(NOISE_SEED)
    edges = np.sqrt(edge_variance_px2 * edge_strength(unloaded)) if edge_variance_px2 > 0 else 0.0
    noise_residuals = []
    for _ in range(NOISE_DRAWS):
        reference_noise = rng.normal(0.0, noise_sigma[0], shape) + edges * rng.normal(size=shape)
        loaded_noise = rng.normal(0.0, noise_sigma[1], np.shape(loaded))
        warped_noise = ndimage.map_coordinates(loaded_noise, where, order=3, mode="constant", cval=0.0).reshape(shape)
        noisy = np.where(valid, high_pass(np.where(valid, warped_noise - gain * reference_noise, 0.0), sigma_px), 0.0)
        noise_residuals.append(without_contrast_and_sharpness(noisy, unloaded, valid, sigma_px))
    changes, found = {}, []
    for tissue, label in TISSUES.items():
        mask = ndimage.binary_erosion(labels == label, iterations=3) & valid
        count = int(mask.sum())
        if count < (2 * LAG_PX + 1) ** 2:
            continue
        observed = autocovariance(residual, mask)
        noise = np.mean([autocovariance(n, mask) for n in noise_residuals], axis=0)
        centre = LAG_PX
        rho = noise / max(noise[centre, centre], 1e-300)
        # the scatter of a variance estimated from `count` correlated pixels: var^2 2 sum rho^2 / N, for the observed
        # residual's estimate and the simulated noise's (averaged over the draws)
        standard_error = noise[centre, centre] * np.sqrt(2.0 * np.sum(rho ** 2) / count * (1.0 + 1.0 / NOISE_DRAWS))
        excess = observed - noise
        significant = bool(excess[centre, centre] > SIGNIFICANCE * standard_error)
        share, patches = 0.0, 0
        if significant:
            change = Change(valid_autocovariance(excess),
                            _amplitude(residual, noise_residuals, mask, excess[centre, centre], window_px))
            share, patches, moves = _displacement_share(residual, noise_residuals, change, excess, unloaded, mask,
                                                        window_px, rng)
            significant = moves
            if moves:
                changes[tissue] = Change(share * change.autocovariance, change.amplitude)
        found.append(TissueChange(tissue, count, float(observed[centre, centre]), float(noise[centre, centre]),
                                  float(excess[centre, centre]) if significant else 0.0, float(standard_error),
                                  significant, float(share), patches))
    return changes, found


def patch_displacements(residual: np.ndarray, gradients: tuple[np.ndarray, np.ndarray], mask: np.ndarray,
                        patch_px: int) -> np.ndarray:
    """(n, 2) px: the displacement (Lucas-Kanade, d = -(sum g g^T)^-1 sum g D) that the residual shows in each
    patch of patch_px x patch_px wholly inside mask whose gradients fix both directions (PATCH_CONDITION)."""
    smooth = ndimage.gaussian_filter(residual, PREFILTER_SIGMA_PX)
    grad_rows, grad_cols = gradients
    found = []
    for r in range(0, mask.shape[0] - patch_px + 1, patch_px):
        for c in range(0, mask.shape[1] - patch_px + 1, patch_px):
            cut = (slice(r, r + patch_px), slice(c, c + patch_px))
            if not mask[cut].all():
                continue
            g = np.stack([grad_cols[cut].ravel(), grad_rows[cut].ravel()], axis=1)
            normal = g.T @ g
            if np.linalg.cond(normal) > PATCH_CONDITION:
                continue
            found.append(-np.linalg.solve(normal, g.T @ smooth[cut].ravel()))
    return np.array(found).reshape(-1, 2)


def _displacement_share(residual, noise_residuals, change: Change, excess: np.ndarray, unloaded: np.ndarray,
                        mask: np.ndarray, window_px: int, rng) -> tuple[float, int, bool]:
    """How much of the change moves the texture: the excess of the patches' displacements in the residual over the
    noise's, over what a change of this autocovariance and amplitude would make of them if it were as likely to move
    a feature as to change it (a random field drawn from it: white noise convolved with `root_kernel`). A change of
    shape that keeps each feature's centroid (a box-averaged thin septum moved by a fraction of a pixel) makes none;
    structures seen at another height through a thick slice make theirs. Returns (share, patches, significant)."""
    patch_px = max(PATCH_MIN_PX, window_px // 4)
    gradients = spline_gradient(ndimage.gaussian_filter(unloaded, PREFILTER_SIGMA_PX))
    moved = patch_displacements(residual, gradients, mask, patch_px)
    if len(moved) < PATCH_MIN_COUNT:
        return 0.0, len(moved), False
    power = lambda values: float(np.mean(values ** 2))   # noqa: E731
    noise = np.mean([power(patch_displacements(n, gradients, mask, patch_px)) for n in noise_residuals])
    kernel = root_kernel(excess)
    modelled = np.mean([power(patch_displacements(
        np.where(mask, change.amplitude * signal.fftconvolve(rng.normal(size=mask.shape), kernel, mode="same"), 0.0),
        gradients, mask, patch_px)) for _ in range(NOISE_DRAWS)])
    # the mean square of 2n values: relative scatter sqrt(2 / 2n), for the observed and the simulated noise's
    spread = noise * np.sqrt(1.0 / len(moved) * (1.0 + 1.0 / NOISE_DRAWS))
    excess_power = power(moved) - noise
    return max(excess_power, 0.0) / max(modelled, 1e-300), len(moved), bool(excess_power > SIGNIFICANCE * spread)


@dataclass
class Change:
    """The change in one tissue: its autocovariance (intensity^2 by lag) and its amplitude over the image (the
    local standard deviation over the tissue's, 1 on average)."""

    autocovariance: np.ndarray
    amplitude: np.ndarray


def _amplitude(residual: np.ndarray, noise_residuals: list[np.ndarray], mask: np.ndarray, excess: float,
               window_px: int) -> np.ndarray:
    """sqrt(local excess variance / the tissue's), the local variances over a Gaussian of half a window within the
    tissue: the change is larger where the tissue slid further through the slice (under the skin, where the garment
    pushes) and the texture runs more obliquely."""
    weight = ndimage.gaussian_filter(mask.astype(float), window_px / 2.0)
    local = lambda image: ndimage.gaussian_filter(np.where(mask, image ** 2, 0.0), window_px / 2.0) / np.maximum(
        weight, 1e-6)   # noqa: E731
    variance = local(residual) - np.mean([local(n) for n in noise_residuals], axis=0)
    return np.where(mask | (weight > 0.05), np.sqrt(np.maximum(variance, 0.0) / excess), 1.0)


def window_covariance(operators, labels: np.ndarray, changes: dict[str, Change]) -> np.ndarray:
    """(2K, 2K) mm^2: Cov(p_i, p_j) of the module text for the K windows of `operators`."""
    count = len(operators.centres)
    covariance = np.zeros((2 * count, 2 * count))
    if not changes:
        return covariance
    width = labels.shape[1]
    to_mm = np.diag(operators.to_mm)
    flat_labels = np.asarray(labels).ravel()
    reach = operators.window_px + 2 * operators.prefilter.radius + 2 * LAG_PX + 2
    neighbours = cKDTree(operators.centres).query_ball_point(operators.centres, reach * np.sqrt(2.0))
    for tissue, change in changes.items():
        footprints = []
        for pixels, weights in zip(operators.noise_pixels, operators.B):
            inside = flat_labels[pixels] == TISSUES[tissue]
            r, c = np.divmod(pixels, width)
            r0, c0 = r.min(), c.min()
            image = np.zeros((2, r.max() - r0 + 1, c.max() - c0 + 1))
            image[:, r - r0, c - c0] = np.where(inside, weights * change.amplitude.ravel()[pixels], 0.0)
            footprints.append((r0, c0, image))
        for i, (ri, ci, bi) in enumerate(footprints):
            spread = np.stack([signal.fftconvolve(bi[a], change.autocovariance, mode="full") for a in range(2)])
            top, left = ri - LAG_PX, ci - LAG_PX
            for j in neighbours[i]:
                rj, cj, bj = footprints[j]
                r0, c0 = max(top, rj), max(left, cj)
                r1 = min(top + spread.shape[1], rj + bj.shape[1])
                c1 = min(left + spread.shape[2], cj + bj.shape[2])
                if r1 <= r0 or c1 <= c0:
                    continue
                a = spread[:, r0 - top:r1 - top, c0 - left:c1 - left].reshape(2, -1)
                b = bj[:, r0 - rj:r1 - rj, c0 - cj:c1 - cj].reshape(2, -1)
                covariance[2 * j:2 * j + 2, 2 * i:2 * i + 2] += to_mm @ (b @ a.T) @ to_mm
    return 0.5 * (covariance + covariance.T)


def covariance_factor(covariance: np.ndarray) -> np.ndarray | None:
    """F with F F^T = covariance (its eigenvectors above round-off), None for a zero covariance."""
    values, vectors = np.linalg.eigh(covariance)
    if values.size == 0 or values[-1] <= 0.0:
        return None
    keep = values > EIGEN_FLOOR * values[-1]
    return vectors[:, keep] * np.sqrt(values[keep])
