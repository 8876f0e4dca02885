"""The images as the DIC sees them: a Gaussian prefilter, and the error model of a prefiltered pixel.

Why a prefilter. Gauss-Newton DIC interpolates the deformed image between its pixels (cubic splines here) and
differentiates the reference. Both are exact only for a band-limited image. An MR scanner band-limits its image
(the k-space it acquires), but other images are not: a slice rendered or acquired with partial volume (each pixel
the mean of the tissue over its area) has sharp, aliased edges, a staircase along the skin whose fine structure
does not move with the tissue. On such images the spline blurs a moving edge by several times the noise, and
windows on the skin or the fascia were wrong by 5-20 times their predicted error. Smoothing both images with a
Gaussian of about one pixel before the correlation makes them nearly band-limited, which removes most of this
bias at a small cost in noise (Pan, "Bias error reduction of digital image correlation using Gaussian
pre-filtering", Opt. Lasers Eng. 51, 2013: a 5 x 5 Gaussian; sigma = 1 pixel here, kernel to 4 sigma).

The error of a prefiltered pixel. Each raw pixel y carries white noise of variance s^2 rho(y) (s^2 both images'
noise in the tissue, the window's `intensity_variance`; rho the Rician share, `rician_variance_ratio`: a magnitude
image is Rician, its noise variance falls to 0.43 s^2 where there is no signal, the air beside the skin) and, on a sharp edge, an error of where the edge was drawn: the staircase of
partial volume, aliasing or ringing, an error of position delta of variance s_edge^2 (px^2) along the gradient,
i.e. an intensity error of variance s_edge^2 |grad I(y)|^2. A window's IC-GN is linear in the prefiltered error
G * e, so its parameters' error is sum_y B~(y) e(y), B~ = G * B the window's map (`dic`, `windows`) spread by
the prefilter, and

    Cov(p_i, p_j) = sum_y B~_i(y) [s_i s_j rho(y) + s_edge^2 |grad I(y)|^2] B~_j(y)^T.

s^2 comes from each image's own noise (`dic.estimate_noise_sigma`, on the raw images); s_edge^2 is calibrated on
the user's images: the residual of every converged window has the expectation
E[r(x)^2] = s^2 (1 - a_n) (G^2 * rho)(x) + s_edge^2 (1 - a_e) (G^2 * |grad I|^2)(x),
and `EdgeResiduals` pools the windows' residuals into its least-squares estimate (zero on a band-limited image, where
the spline is exact). a_e and a_n are the shares of the edges' error and of the noise that the window's own match takes
into its parameters (`dic._absorbed_share`): an edge's error lies where the steepest-descent images are largest, so the
match takes more of it than of the noise. Windows whose residual the model does not predict are left out of the estimate
(`fit_error_model`), by a bound that counts an edge's few independent values (`residual_bound`). On images carrying
exactly the modelled error (tests/measure/test_edge_error_model.py) the estimate is 13 % low on average (34 % before a_e and
that bound): the match takes the most on the edge's own pixels, and the line is fitted pixel by pixel. The kept part
computed per pixel, diag((I - P) C (I - P)), recovers it within a few per cent, but then the windows of the second
phantom were over-predicted (its control at 0.81 x the floor): the error left is in how the pixels' errors add up in a
window, not in this line. The same line's intercept says how much noise the residuals hold: s^2 was estimated from each
image's own pixels, where a texture as fine as a pixel passes partly for noise (1.4 times the variance on the second
phantom's muscle), so the windows' noise is rescaled to what their residuals show (a_n is 5-7 % of a 32-pixel window's
noise).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy import ndimage, special, stats

PREFILTER_SIGMA_PX = 1.0
TRUNCATE = 4.0   # the kernel's half-width in standard deviations (scipy's default)


def _spline_derivative_response(frequencies: np.ndarray) -> np.ndarray:
    """Frequency response of the derivative of the cubic-spline interpolant at the pixels (the spline prefilter
    6 / (4 + 2 cos w) times the central difference of the B-spline coefficients, i sin w)."""
    return 6.0 * np.sin(frequencies) / (4.0 + 2.0 * np.cos(frequencies))


@dataclass(frozen=True)
class Prefilter:
    """A Gaussian of `sigma_px` pixels applied to both images before correlation (0: none); module text."""

    sigma_px: float = PREFILTER_SIGMA_PX
    _kernel: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        if not (self.sigma_px >= 0.0 and np.isfinite(self.sigma_px)):
            raise ValueError(f"the DIC prefilter's sigma is a non-negative number of pixels, not {self.sigma_px}")
        if self.sigma_px == 0.0:
            kernel = np.ones(1)
        else:
            offsets = np.arange(-self.radius, self.radius + 1, dtype=float)
            kernel = np.exp(-0.5 * (offsets / self.sigma_px) ** 2)
            kernel /= kernel.sum()
        object.__setattr__(self, "_kernel", kernel)

    @property
    def kernel(self) -> np.ndarray:
        """The kernel's 2 radius + 1 taps along one axis (read-only; [1] without a prefilter)."""
        view = self._kernel.view()
        view.flags.writeable = False
        return view

    @property
    def radius(self) -> int:
        """Half-width (pixels) of the kernel: how far a window's error reaches beyond its own pixels."""
        return int(TRUNCATE * self.sigma_px + 0.5) if self.sigma_px > 0 else 0

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The image smoothed (float), with the edges of the image reflected."""
        image = np.asarray(image, float)
        if self.sigma_px == 0.0:
            return image.copy()
        return ndimage.gaussian_filter(image, self.sigma_px, mode="reflect", truncate=TRUNCATE)

    def spread(self, maps: np.ndarray) -> np.ndarray:
        """G * maps for maps (..., s, s) that are zero outside their s x s window: (..., s + 2r, s + 2r), the
        window grown by the kernel's radius r on each side (G is symmetric: spreading is the adjoint of filtering)."""
        maps = np.asarray(maps, float)
        if self.sigma_px == 0.0:
            return maps.copy()
        r = self.radius
        padded = np.pad(maps, [(0, 0)] * (maps.ndim - 2) + [(r, r), (r, r)])
        for axis in (-2, -1):
            padded = ndimage.correlate1d(padded, self._kernel, axis=axis, mode="constant")
        return padded

    @cached_property
    def noise_gain(self) -> float:
        """sum G^2: the variance of a prefiltered pixel of unit white noise (1 / the pixels one independent value
        of a prefiltered image spreads over, as an area)."""
        return float(np.sum(self._kernel ** 2) ** 2)

    @cached_property
    def derivative_noise_gain(self) -> float:
        """Variance of the cubic-spline derivative, along one axis, of prefiltered unit white noise: the gradient
        noise that the reference's Gauss-Newton matrix mistakes for texture (`dic.denoised_hessian`)."""
        w = np.linspace(-np.pi, np.pi, 4096, endpoint=False)
        response = np.abs(np.fft.fft(self._kernel, 4096)) ** 2
        along = float(np.mean(_spline_derivative_response(w) ** 2 * np.fft.fftshift(response)))
        return along * float(np.sum(self._kernel ** 2))

    @cached_property
    def correlated_pixels(self) -> float:
        """sum over lags of the squared correlation of prefiltered white noise: how many pixels one independent
        value of a prefiltered image spreads over (1 without a prefilter)."""
        autocorrelation = np.convolve(self._kernel, self._kernel)
        return float(np.sum((autocorrelation / autocorrelation.max()) ** 2) ** 2)

    def squared_kernel_response(self, image: np.ndarray) -> np.ndarray:
        """G^2 * image: what a map of raw-pixel variances becomes in the variance of prefiltered pixels."""
        image = np.asarray(image, float)
        if self.sigma_px == 0.0:
            return image.copy()
        out = image
        for axis in (0, 1):
            out = ndimage.correlate1d(out, self._kernel ** 2, axis=axis, mode="reflect")
        return out


def _rician_moments(amplitude_over_sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) of |A + n_r + i n_i| over sigma, sigma^2 for channel noise of unit sigma (Rice): mean =
    sqrt(pi/2) L_1/2(-A^2/2), variance = 2 + A^2 - mean^2, L_1/2(x) = e^(x/2) [(1 - x) I0(-x/2) - x I1(-x/2)]."""
    half = 0.25 * np.asarray(amplitude_over_sigma, float) ** 2   # -x/2 with x = -A^2/2
    laguerre = (1.0 + 2.0 * half) * special.i0e(half) + 2.0 * half * special.i1e(half)
    mean = np.sqrt(np.pi / 2.0) * laguerre
    return mean, 2.0 + np.asarray(amplitude_over_sigma, float) ** 2 - mean ** 2


_AMPLITUDES = np.concatenate([np.linspace(0.0, 10.0, 401), np.linspace(10.5, 60.0, 100)])
_RICIAN_MEAN, _RICIAN_VARIANCE = _rician_moments(_AMPLITUDES)


def rician_variance_ratio(image: np.ndarray, noise_sigma: float, smoothing_px: float = 2.0) -> np.ndarray:
    """rho(y): the noise variance of each pixel of a magnitude image over the channel variance sigma^2 (0.43 with no
    signal, 1 where the signal is strong), from the image's local mean (a Gaussian of smoothing_px) read as the mean
    of a Rician of channel noise sigma. A mean below the Rayleigh mean of no signal reads as no signal."""
    if noise_sigma <= 0:
        return np.ones(np.shape(image))
    local_mean = ndimage.gaussian_filter(np.asarray(image, float), smoothing_px, mode="reflect") / noise_sigma
    return np.interp(local_mean, _RICIAN_MEAN, _RICIAN_VARIANCE, right=1.0)


@dataclass
class EdgeResiduals:
    """Sufficient statistics, pooled over converged windows, of the least-squares line through their residuals,
    r(x)^2 / v = kappa + s_edge^2 q(x) / v, with v = s^2 sum G^2 the variance of a prefiltered pixel of noise and
    q = G^2 * |grad I|^2 (module text). kappa, the share of the noise left in the residual, is a little below 1:
    each window's fit absorbs its parameters' share of the noise, more so when the prefilter correlates the pixels
    of a small window."""

    count: int = 0
    z: float = 0.0     # sum q / v
    zz: float = 0.0    # sum (q / v)^2
    y: float = 0.0     # sum r^2 / v
    yz: float = 0.0    # sum r^2 q / v^2

    def add(self, residual: np.ndarray, q: np.ndarray, pixel_variance: np.ndarray) -> None:
        """One window's residuals r, q and v = s^2 (G^2 * rho) at its pixels."""
        y = np.asarray(residual, float) ** 2 / pixel_variance
        z = np.asarray(q, float) / pixel_variance
        self.count += y.size
        self.z += float(z.sum())
        self.zz += float(z @ z)
        self.y += float(y.sum())
        self.yz += float(y @ z)

    def __iadd__(self, other: "EdgeResiduals") -> "EdgeResiduals":
        for name in ("count", "z", "zz", "y", "yz"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        return self

    @property
    def _spread(self) -> float:
        return self.count * self.zz - self.z ** 2

    @property
    def edge_variance_px2(self) -> float:
        """s_edge^2 (px^2), the variance of the position of the images' edges; 0 when the residuals show none."""
        if self.count < 2 or self._spread <= 0:
            return 0.0
        return max(0.0, (self.count * self.yz - self.y * self.z) / self._spread)

    def residual_ratio(self, edge_variance_px2: float, kappa: float) -> float:
        """One window's squared residual over what the pooled error model predicts for it (1 when it holds)."""
        if self.count == 0:
            return float("nan")
        return (self.y - edge_variance_px2 * self.z) / (kappa * self.count)

    @property
    def residual_over_noise(self) -> float:
        """kappa: the windows' squared residual where there is no edge, over what the images' noise predicts."""
        if self.count == 0:
            return float("nan")
        return (self.y - self.edge_variance_px2 * self.z) / self.count


    def expected(self, edge_variance_px2: float, kappa: float) -> float:
        """sum mu: the squared residual (over v) the error model predicts for the window, noise and edges together."""
        return kappa * self.count + edge_variance_px2 * self.z

    def unpredicted(self, edge_variance_px2: float, kappa: float, prefilter: Prefilter, alpha: float) -> bool:
        """Whether the window's squared residual exceeds what the error model predicts for it, noise and edges
        together, beyond the 1 - alpha quantile of its independent values (`residual_bound`)."""
        if self.count == 0:
            return False
        return self.y / self.expected(edge_variance_px2, kappa) > residual_bound(self, prefilter, alpha,
                                                                                edge_variance_px2, kappa)


def residual_bound(window: EdgeResiduals, prefilter: Prefilter, alpha: float, edge_variance_px2: float,
                   kappa: float) -> float:
    """The largest squared residual, over what the error model predicts, that a window's independent values reach
    with probability 1 - alpha under the model (chi^2). A pixel's expected share is mu = kappa + s_edge^2 q / v: on
    an edge it is far above the noise's, and a few such pixels carry the window's sum, so the independent values
    are Satterthwaite's (sum mu)^2 / sum mu^2 over the pixels one prefiltered value spreads over (the window's pixels
    over them without edges). Counting every pixel alike instead set the bound too low for windows across an edge:
    the calibration then dropped the windows whose edge error happened to be large, and s_edge^2 came out 30 % low on
    images carrying exactly the modelled error (tests/measure/test_edge_error_model.py)."""
    total = window.expected(edge_variance_px2, kappa)
    squares = (kappa ** 2 * window.count + 2.0 * kappa * edge_variance_px2 * window.z
               + edge_variance_px2 ** 2 * window.zz)
    independent = total ** 2 / squares / prefilter.correlated_pixels
    return float(stats.chi2.ppf(1.0 - alpha, independent) / independent)


def fit_error_model(windows, prefilter: Prefilter, alpha: float, rounds: int = 2) -> tuple[float, float]:
    """(s_edge^2 px^2, kappa): the pooled line through the windows' residuals (`EdgeResiduals`), fitted again without
    the windows whose own residual the line does not predict (chi^2 at alpha): those whose motion the affine shape
    does not follow (a sliding interface, a period shorter than the window) would otherwise raise everyone's
    noise."""
    windows = [window for window in windows if window.count > 0]
    trusted = windows
    for _ in range(rounds + 1):
        pooled = EdgeResiduals()
        for window in trusted:
            pooled += window
        edge_variance, kappa = pooled.edge_variance_px2, pooled.residual_over_noise
        if not (np.isfinite(kappa) and kappa > 0):
            break
        fitting = [w for w in windows if not w.unpredicted(edge_variance, kappa, prefilter, alpha)]
        if len(fitting) == len(trusted) or len(fitting) < 10:
            break
        trusted = fitting
    return edge_variance, kappa
