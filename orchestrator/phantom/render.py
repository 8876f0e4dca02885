"""Render the unloaded and loaded images of the phantom calf.

The unloaded image samples the material intensity i(X) (see `appearance`) at
the pixels. The loaded image is made by inverse warping, the converse of the
warping of the first paper (section 2.1.2): a material point X moves to
x = X + u(X) and then, with an optional rigid scanner motion, to
y = R (x - c) + c + t. The loaded grey level at a scanner pixel y is the
material intensity at X(y), found by undoing the rigid motion and solving
X + u(X) = x by the fixed-point iteration X <- x - u(X), which converges
while |grad u| < 1 (any physical compression). The texture therefore moves
with the tissue, while the bias field and the noise stay with the scanner.

The scanner is modelled as MR acquisition is: the material intensity is
sampled on a grid `supersampling` times finer than the pixels and only the
k-space of the pixel grid is kept (with a Tukey apodisation against Gibbs
ringing), which band-limits the image like a real reconstruction. Boundaries
are therefore blurred over about a pixel, not aligned with the pixel grid,
and the images are not made by the interpolation the identification uses
(no inverse crime).

`render_unloaded`, `make_loaded_image` and `loaded_labels` take any `Phantom` (a `render(to_material,
noise_seed)` method and exact labels): `orchestrator.phantom.mri.MRIPhantom` is a second one, drawn and
rendered independently of `CalfPhantom` (box-averaged partial volume instead of the k-space band limit).

`displacement` is a callable u(x_mm, y_mm) -> (ux_mm, uy_mm) on arrays in the
image frame of the unloaded image, or a (2, H, W) field on its pixel grid
(interpolated bilinearly, held constant beyond the edge). The engine that
computes u from material parameters is not called here: callers pass its
interpolated nodal field as such a callable.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy import ndimage

from ..core.frame import DisplacementFn, RigidMotion, mm_to_index, pixel_centres_mm
from .appearance import T1Contrast, TextureField, add_rician_noise, bias_field
from .geometry import CalfGeometry

FIXED_POINT_TOLERANCE_MM = 1e-6
FIXED_POINT_MAX_ITERATIONS = 1000
FIXED_POINT_PLAIN_ITERATIONS = 100
FIXED_POINT_DIVERGED_MM = 1e4


@dataclass
class CalfPhantom:
    """A calf slice (geometry + T1 appearance) seen by a scanner with the given matrix and pixel size."""

    geometry: CalfGeometry = field(default_factory=CalfGeometry)
    contrast: T1Contrast = field(default_factory=T1Contrast)
    image_shape: tuple[int, int] = (420, 420)
    pixel_size_mm: tuple[float, float] = (0.36, 0.36)
    supersampling: int = 3

    def __post_init__(self):
        self.texture = TextureField(self.extent_mm, self.contrast.texture_correlation_mm, self.contrast.texture_seed)
        self._base, self._amplitude = self.contrast.tables()

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width along x, height along y) of the field of view in mm."""
        return self.image_shape[1] * self.pixel_size_mm[1], self.image_shape[0] * self.pixel_size_mm[0]

    def intensity_at(self, x, y, edge_mm: float = 0.0) -> np.ndarray:
        """Noise- and bias-free grey level of the material points X = (x, y) (mm), texture included.

        With edge_mm > 0 each part is painted over the previous ones with a coverage rising linearly from 0 to 1
        across edge_mm of its boundary (anti-aliasing: a boundary moves continuously, not by whole samples)."""
        texture = self.texture(x, y)
        value = np.zeros(np.shape(x))
        for tissue, distance in self.geometry.layers(x, y):
            coverage = np.clip(0.5 - distance / edge_mm, 0.0, 1.0) if edge_mm > 0 else (distance < 0).astype(float)
            tissue_value = self._base[tissue] * (1.0 + self._amplitude[tissue] * texture)
            value += coverage * (tissue_value - value)
        return value

    def labels(self, compartments: bool = False) -> np.ndarray:
        """Ground-truth label map of the unloaded image (pixel centres)."""
        return self.geometry.labels_at(*pixel_centres_mm(self.image_shape, self.pixel_size_mm), compartments=compartments)

    def description(self) -> dict:
        """What truth.json records of the phantom."""
        return {"shape": dataclasses.asdict(self.geometry.shape), "contrast": dataclasses.asdict(self.contrast),
                "supersampling": self.supersampling}

    def render(self, to_material, noise_seed: int | None) -> np.ndarray:
        """Sample the material intensity at the material points to_material(x, y) of a grid `supersampling` times
        finer than the pixels, keep the k-space of the pixel grid (what an MR scanner acquires; Tukey-apodised
        against Gibbs ringing), then bias and noise (noise_seed None: noiseless)."""
        n = self.supersampling
        if n < 1 or n % 2 == 0:
            raise ValueError("supersampling must be an odd positive integer (so that a fine sample sits at each pixel centre)")
        height, width = self.image_shape
        dy, dx = self.pixel_size_mm
        fine_rows, fine_cols = np.indices((height * n, width * n), dtype=float)
        X, Y = to_material((fine_cols + 0.5) * dx / n, (fine_rows + 0.5) * dy / n)
        fine = self.intensity_at(X, Y, edge_mm=min(dx, dy) / n)
        signal = _keep_pixel_bandwidth(np.roll(fine, (-(n // 2), -(n // 2)), axis=(0, 1)), (height, width))
        x_centre, y_centre = pixel_centres_mm(self.image_shape, self.pixel_size_mm)
        signal *= bias_field(x_centre, y_centre, self.extent_mm, self.contrast.bias_amplitude)
        if noise_seed is None:
            return signal
        return add_rician_noise(signal, self.contrast.noise_sigma, np.random.default_rng(noise_seed))


class Phantom(Protocol):
    """What the case machinery (`render_unloaded`, `make_loaded_image`, `write_case`, `study.make_phantom_case`)
    needs of a phantom: `CalfPhantom` and `orchestrator.phantom.mri.MRIPhantom` are two.

    geometry.labels_at(x, y, compartments) gives the exact labels at material points (mm), geometry.landmarks()
    the five LANDMARK_NAMES; bone_clamped_compression also reads geometry.shape.centre_mm and
    geometry.tibia / geometry.fibula .radial_excess(x, y). render(to_material, noise_seed) makes the image whose
    pixel at the scanner point y shows the material point to_material(y)."""

    geometry: Any
    image_shape: tuple[int, int]
    pixel_size_mm: tuple[float, float]

    @property
    def extent_mm(self) -> tuple[float, float]: ...

    def labels(self, compartments: bool = False) -> np.ndarray: ...

    def description(self) -> dict: ...

    def render(self, to_material, noise_seed: int | None) -> np.ndarray: ...


def render_unloaded(phantom: Phantom, noise_seed: int | None = 0) -> np.ndarray:
    """The unloaded image I0 (float, fat ~ 1). noise_seed=None gives the noiseless image."""
    return phantom.render(lambda x, y: (x, y), noise_seed)


def make_loaded_image(phantom: Phantom, displacement, rigid: RigidMotion | None = None,
                      noise_seed: int | None = 1) -> np.ndarray:
    """The loaded image I1 of the phantom deformed by `displacement` (mm) and moved by `rigid`, by inverse warping."""
    displacement_fn = as_displacement_fn(displacement, phantom.pixel_size_mm)
    return phantom.render(lambda x, y: material_points(x, y, displacement_fn, rigid), noise_seed)


def loaded_labels(phantom: Phantom, displacement, rigid: RigidMotion | None = None,
                  compartments: bool = False) -> np.ndarray:
    """Ground-truth label map of the loaded image (pixel centres)."""
    displacement_fn = as_displacement_fn(displacement, phantom.pixel_size_mm)
    X, Y = material_points(*pixel_centres_mm(phantom.image_shape, phantom.pixel_size_mm), displacement_fn, rigid)
    return phantom.geometry.labels_at(X, Y, compartments=compartments)


def material_points(x_scanner, y_scanner, displacement_fn: DisplacementFn, rigid: RigidMotion | None = None):
    """Material points X whose deformed and moved position is the scanner point y: solve X + u(X) = rigid^-1(y)."""
    x, y = (x_scanner, y_scanner) if rigid is None else rigid.inverse().apply(x_scanner, y_scanner)
    return undeform(x, y, lambda X, Y, index: displacement_fn(X, Y))


def undeform(x, y, displacement):
    """The material points X with X + u(X) = x (mm), by fixed point. displacement(X, Y, index) gives u at the points
    still iterating, `index` their positions in x.ravel() (for a field that also depends on per-point data, such as
    the height of `phantom.volume`)."""
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    shape = x.shape
    x, y = x.ravel(), y.ravel()
    X, Y = x.copy(), y.copy()
    # iterate only the points not yet converged, held by index: a few slow points near a bone's hole take hundreds
    # of iterations, and a mask over every sample each time cost 2 s of a phantom's 10
    index = np.arange(x.size)
    for iteration in range(FIXED_POINT_MAX_ITERATIONS):
        # X <- X + w (x - u(X) - X): plain (w = 1) first; then damped, which also converges where a
        # compressive gradient (grad u < -1, e.g. across a bone hole's interpolated field) makes it oscillate
        damping = 1.0 if iteration < FIXED_POINT_PLAIN_ITERATIONS else 0.5
        X_now, Y_now = X[index], Y[index]
        ux, uy = displacement(X_now, Y_now, index)
        step_x, step_y = x[index] - ux - X_now, y[index] - uy - Y_now
        change = np.maximum(np.abs(step_x), np.abs(step_y))
        if not np.all(change < FIXED_POINT_DIVERGED_MM):
            break
        X[index] = X_now + damping * step_x
        Y[index] = Y_now + damping * step_y
        index = index[change >= FIXED_POINT_TOLERANCE_MM]
        if index.size == 0:
            return X.reshape(shape), Y.reshape(shape)
    raise ValueError("x = X + u(X) could not be inverted (the fixed point did not converge); "
                     "the displacement field folds the tissue or varies too fast (|grad u| must stay below 1)")


def as_displacement_fn(displacement, pixel_size_mm: tuple[float, float]) -> DisplacementFn:
    """A callable u(x, y) from a callable or from a (2, H, W) field on the pixel grid (bilinear, constant beyond the edge)."""
    if callable(displacement):
        return displacement
    field_mm = np.asarray(displacement, dtype=float)
    if field_mm.ndim != 3 or field_mm.shape[0] != 2:
        raise ValueError(f"a displacement field must have shape (2, H, W), got {field_mm.shape}")

    def interpolated(x, y):
        rows, cols = mm_to_index(x, y, pixel_size_mm)
        coordinates = np.stack([np.ravel(rows), np.ravel(cols)])
        return tuple(ndimage.map_coordinates(component, coordinates, order=1, mode="nearest").reshape(np.shape(x))
                     for component in field_mm)

    return interpolated


def _keep_pixel_bandwidth(fine: np.ndarray, shape: tuple[int, int], taper: float = 0.5) -> np.ndarray:
    """Down-sample a finely sampled image (whose sample 0 of each block is the pixel centre) by truncating its
    spectrum to the frequencies of the coarse grid, with a Tukey window of the given taper fraction."""
    spectrum = np.fft.fftshift(np.fft.fft2(fine))
    centre = [size // 2 for size in fine.shape]
    crop = tuple(slice(c - s // 2, c - s // 2 + s) for c, s in zip(centre, shape))
    window = np.outer(_tukey(shape[0], taper), _tukey(shape[1], taper))
    coarse = np.fft.ifft2(np.fft.ifftshift(spectrum[crop] * window)).real
    return coarse * (shape[0] * shape[1]) / fine.size


def _tukey(size: int, taper: float) -> np.ndarray:
    """Tukey window over the centred frequencies: flat in the middle, cosine tapers over `taper` of the band."""
    position = np.abs(np.arange(size) - size // 2) / (size / 2)
    edge = 1.0 - taper
    return np.where(position <= edge, 1.0, 0.5 * (1.0 + np.cos(np.pi * (position - edge) / taper)))


def bone_clamped_compression(geometry, strain: float = 0.025, ramp_mm: float = 8.0) -> DisplacementFn:
    """An analytic stand-in for the engine: a radial shrink towards the leg centre, u = -strain (X - c) w(X),
    with w rising smoothly (C1) from 0 on the bones to 1 at `ramp_mm` from them, so the bones stay clamped
    as in the first paper's boundary conditions (section 2.2.2). |grad u| < 1 for strain < 0.05.
    geometry: a `CalfGeometry` or an `mri.LegGeometry` (it reads shape.centre_mm and tibia / fibula .radial_excess)."""
    cx, cy = geometry.shape.centre_mm

    def displacement(x, y):
        distance = np.minimum(geometry.tibia.radial_excess(x, y), geometry.fibula.radial_excess(x, y))
        t = np.clip(distance / ramp_mm, 0.0, 1.0)
        weight = t * t * (3.0 - 2.0 * t)
        return -strain * (x - cx) * weight, -strain * (y - cy) * weight

    return displacement
