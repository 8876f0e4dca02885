"""How the phantom looks in a T1-weighted spin-echo slice.

Grey levels follow the T1 contrast the first paper relies on for segmentation
(section 2.1.1: fat bright, muscle intermediate; cortical bone dark, fatty
marrow bright; flowing blood dark). Three effects make the images realistic
and keep tests honest (no inverse crime):

- tissue texture: a smooth random field g(X) of unit variance, attached to
  the material point X, modulates each tissue, i(X) = i_tissue (1 + a_tissue g(X));
  it moves with the tissue, which is what digital image correlation tracks
  (second paper, section 2.2);
- a smooth multiplicative bias field b(y) fixed in the scanner frame y (coil
  sensitivity), the same for both acquisitions;
- Rician noise, the magnitude of a complex signal with Gaussian noise of
  standard deviation sigma on each channel: |s + n_r + i n_i|.

Intensities are in units of the fat signal (fat = 1).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .geometry import Tissue


def _default_intensity() -> dict[str, float]:
    return {"BACKGROUND": 0.0, "SKIN": 0.55, "FAT": 1.0, "FASCIA": 0.18, "MUSCLE": 0.40,
            "CORTEX": 0.04, "MARROW": 0.92, "SUPERFICIAL_VEIN": 0.12, "DEEP_VEIN": 0.10}


def _default_texture() -> dict[str, float]:
    return {"SKIN": 0.05, "FAT": 0.08, "FASCIA": 0.05, "MUSCLE": 0.18, "MARROW": 0.08}


@dataclass(frozen=True)
class T1Contrast:
    """Grey levels per tissue (fat = 1), texture amplitudes, noise and bias."""

    intensity: dict[str, float] = field(default_factory=_default_intensity)
    texture_amplitude: dict[str, float] = field(default_factory=_default_texture)
    texture_correlation_mm: float = 0.5   # Gaussian smoothing length of the texture field
    texture_seed: int = 7
    noise_sigma: float = 0.015            # per channel, before the magnitude (Rician)
    bias_amplitude: float = 0.12          # peak relative change of the bias field over the field of view

    def tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Look-up arrays indexed by `Tissue`: base intensity and texture amplitude."""
        base = np.array([self.intensity[t.name] for t in Tissue])
        amplitude = np.array([self.texture_amplitude.get(t.name, 0.0) for t in Tissue])
        return base, amplitude


class TextureField:
    """A smooth random field of unit standard deviation over a square region, evaluated by cubic splines at any point (mm)."""

    def __init__(self, extent_mm: tuple[float, float], correlation_mm: float, seed: int,
                 spacing_mm: float = 0.18, margin_mm: float = 15.0):
        self.origin = -margin_mm
        self.spacing = spacing_mm
        shape = tuple(int(np.ceil((e + 2 * margin_mm) / spacing_mm)) + 1 for e in (extent_mm[1], extent_mm[0]))
        white = np.random.default_rng(seed).standard_normal(shape)
        smooth = ndimage.gaussian_filter(white, correlation_mm / spacing_mm, mode="wrap")
        smooth /= smooth.std()
        self._coefficients = ndimage.spline_filter(smooth, order=3, mode="nearest")

    def __call__(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        coordinates = np.stack([(y - self.origin) / self.spacing, (x - self.origin) / self.spacing])
        return ndimage.map_coordinates(self._coefficients, coordinates.reshape(2, -1), order=3,
                                       prefilter=False, mode="nearest").reshape(x.shape)


def _bias_shape(xi, eta):
    return 0.5 * xi - 0.35 * eta + 0.25 * xi * eta - 0.3 * (xi ** 2 + eta ** 2) + 0.2


_BIAS_PEAK = float(np.max(np.abs(_bias_shape(*np.meshgrid(np.linspace(-1, 1, 101), np.linspace(-1, 1, 101))))))


def bias_field(x_mm, y_mm, extent_mm: tuple[float, float], amplitude: float) -> np.ndarray:
    """Smooth coil sensitivity b(y) in the scanner frame: a fixed low-order polynomial, 1 +- amplitude over the field of view."""
    xi = 2.0 * np.asarray(x_mm) / extent_mm[0] - 1.0
    eta = 2.0 * np.asarray(y_mm) / extent_mm[1] - 1.0
    return 1.0 + amplitude * _bias_shape(xi, eta) / _BIAS_PEAK


def add_rician_noise(signal: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Magnitude of the signal plus complex Gaussian noise (standard deviation sigma per channel)."""
    if sigma <= 0:
        return signal.copy()
    real = signal + sigma * rng.standard_normal(signal.shape)
    imaginary = sigma * rng.standard_normal(signal.shape)
    return np.hypot(real, imaginary)
