"""The k-space phantom's acquisition: a 2D slice as an MR scanner makes it, and the leg's motion between sessions.

An MR image is not a drawing of pixels. For each image of `Scanner.acquire`:

1. slice profile: the slice at height z0 is `slice_thickness_mm` thick, its profile a rect of that width blurred by
   a Gaussian of `profile_sigma_mm` (the excitation's transition bands); it is sampled by sub-planes 1 mm apart
   within +-(thickness / 2 + 2 sigma), each weighted by the profile, w(o) = [erf((o + T/2) / (sigma sqrt 2)) -
   erf((o - T/2) / (sigma sqrt 2))] / 2, normalised to a sum of 1;
2. on a grid `oversampling` times finer than the final pixels, the water and the fat signals of every sub-plane
   (`appearance3d`, each edge drawn with its coverage of a fine sample) summed with those weights;
3. both multiplied by the receive coil's complex sensitivity, a smooth function of the SCANNER position
   (magnitude 1 +- `coil_amplitude` over the leg, a smooth phase), the same in both sessions;
4. the fat displaced along the readout (x or y) by the chemical shift, (3.5 ppm x Larmor frequency) / (readout
   bandwidth per pixel): `chemical_shift_px` pixels, fixed to the scanner (the same in both sessions), applied as
   the phase ramp exp(-2 pi i k delta) on the fat's Fourier transform (an exact shift of the band-limited fat);
5. FFT; only the central rows x cols of k-space are kept (the acquired matrix: band limit, Gibbs ringing at every
   edge), with the phase ramp that puts each final sample on its pixel centre ((j + 1/2) dx);
6. an optional vendor filter (k-space apodization, off by default: "hamming" or "fermi");
7. complex Gaussian noise in k-space, scaled so that the image's noise per channel is `noise_sigma` times the fat
   signal (after the filter: correlated between pixels where one is applied);
8. inverse FFT and the magnitude (Rician noise). The stored 16-bit value is `intensity_scale` per unit of fat.

Sessions (`LegMotion`): session 0 sees the leg in its reference pose. Between the sessions the leg moves rigidly
in 3D BEFORE the garment deforms it: a bone-fixed point p0 (scanner frame x, y, z mm) is at p1 = c + R (p0 - c) + t
in session 1, R = Rz(turn) Raxis(tilt), t = (shift, slide). The loaded material point X shows at
y = c + R (X + u(X) - c) + t. For a scanner point y of session 1 the material point solves X + u(X) = c + R^T
(y - c - t), found by the fixed point X <- x - u(X) (`render.undeform`'s, in 3D), u interpolated trilinearly on a
grid of the 3D truth (`DisplacementGrid`, half a pixel in the plane, 1.5 mm along the leg, exact C3D15
interpolation at its nodes). The scanner's slice stays where it is: after an axial slide the loaded slice shows
tissue from another height of a tapering leg.

Angles: `turn_deg` is a rotation about +z in the image frame's numbers (x right, y down): a positive turn turns
the picture clockwise on screen, as `imaging.frame.RigidMotion` does.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage
from scipy.special import erf

SUBPLANE_SPACING_MM = 1.0
FIXED_POINT_TOLERANCE_MM = 1e-5
FIXED_POINT_MAX_ITERATIONS = 200
FIXED_POINT_ACCEPTED_MM = 1e-3           # a point still moving this little after the last iteration is kept
GRID_HEIGHT_STEP_MM = 1.5
VENDOR_FILTERS = (None, "hamming", "fermi")
READOUTS = ("x", "y")

Signals = Callable[[np.ndarray, np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Scanner:
    """The acquisition's settings (module text), defaults near a 1.5 T T1 TSE of the calf."""

    image_shape: tuple[int, int] = (384, 384)           # rows, columns: the acquired matrix
    pixel_size_mm: tuple[float, float] = (0.4, 0.4)      # row, column
    oversampling: int = 3
    slice_thickness_mm: float = 4.0
    profile_sigma_mm: float = 0.6
    chemical_shift_px: float = 1.4
    readout: str = "x"
    noise_sigma: float = 0.026                           # per channel, relative to the fat signal
    vendor_filter: str | None = None
    coil_amplitude: float = 0.10
    coil_seed: int = 0
    intensity_scale: float = 20000.0                     # stored value of a fat signal of 1

    def __post_init__(self):
        if self.readout not in READOUTS:
            raise ValueError(f"readout must be 'x' or 'y', not {self.readout!r}")
        if self.vendor_filter not in VENDOR_FILTERS:
            raise ValueError(f"vendor_filter must be None, 'hamming' or 'fermi', not {self.vendor_filter!r}")
        if int(self.oversampling) != self.oversampling or self.oversampling < 1:
            raise ValueError(f"oversampling must be a positive whole number, got {self.oversampling}")
        if self.slice_thickness_mm <= 0 or self.profile_sigma_mm < 0:
            raise ValueError("the slice thickness must be positive and its profile's blur not negative")
        if any(n < 8 for n in self.image_shape):
            raise ValueError(f"the matrix {self.image_shape} is too small; give at least 8 x 8")

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width along x, height along y) of the field of view."""
        return self.image_shape[1] * self.pixel_size_mm[1], self.image_shape[0] * self.pixel_size_mm[0]

    @property
    def fine_shape(self) -> tuple[int, int]:
        return self.image_shape[0] * self.oversampling, self.image_shape[1] * self.oversampling

    def subplanes(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets mm, weights) of the slice profile's sub-planes (module text, step 1)."""
        half = self.slice_thickness_mm / 2.0 + 2.0 * self.profile_sigma_mm
        count = max(1, int(math.floor(half / SUBPLANE_SPACING_MM + 1e-9)))
        offsets = SUBPLANE_SPACING_MM * np.arange(-count, count + 1)
        if self.profile_sigma_mm == 0.0:
            weights = (np.abs(offsets) <= self.slice_thickness_mm / 2.0).astype(float)
        else:
            scale = self.profile_sigma_mm * math.sqrt(2.0)
            weights = 0.5 * (erf((offsets + self.slice_thickness_mm / 2.0) / scale)
                             - erf((offsets - self.slice_thickness_mm / 2.0) / scale))
        keep = weights > 1e-4 * weights.max()
        return offsets[keep], weights[keep] / weights[keep].sum()

    def coil(self, x, y, z=0.0) -> np.ndarray:
        """The receive coil's complex sensitivity at scanner points (mm): a low-order smooth field of magnitude
        1 +- coil_amplitude over the central disc where the leg lies, and a smooth phase (module text, step 3)."""
        width, height = self.extent_mm
        rng = np.random.default_rng([self.coil_seed, 50])
        u = (np.asarray(x, float) - width / 2.0) / (width / 2.0)
        v = (np.asarray(y, float) - height / 2.0) / (height / 2.0)
        w = (np.asarray(z, float) - 0.0) / 500.0            # a slow fall-off along the bore
        terms = [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
        coefficients = rng.normal(0.0, 1.0, len(terms))
        shape = sum(c * u ** a * v ** b for c, (a, b) in zip(coefficients, terms)) + 0.3 * w
        # normalised so that its largest |value| over the disc of radius 0.8 (the leg's region) is 1
        grid_u, grid_v = np.meshgrid(np.linspace(-0.8, 0.8, 81), np.linspace(-0.8, 0.8, 81))
        disc = np.hypot(grid_u, grid_v) <= 0.8
        reference = sum(c * grid_u ** a * grid_v ** b for c, (a, b) in zip(coefficients, terms))[disc]
        spread = np.max(np.abs(reference - reference.mean()))
        magnitude = 1.0 + self.coil_amplitude * (shape - reference.mean()) / spread
        phase = rng.uniform(-0.6, 0.6) * u + rng.uniform(-0.6, 0.6) * v + rng.uniform(-0.4, 0.4) * u * v
        return magnitude * np.exp(1j * phase)

    def vendor_window(self) -> np.ndarray:
        """The k-space apodization (rows, cols) over the acquired matrix, centred (ones when none)."""
        rows, cols = self.image_shape
        ky = (np.arange(rows) - rows // 2) / (rows / 2.0)
        kx = (np.arange(cols) - cols // 2) / (cols / 2.0)
        if self.vendor_filter is None:
            return np.ones(self.image_shape)
        if self.vendor_filter == "hamming":
            return np.outer(0.54 + 0.46 * np.cos(np.pi * ky), 0.54 + 0.46 * np.cos(np.pi * kx))
        radius = np.hypot(*np.meshgrid(kx, ky, indexing="xy"))
        return 1.0 / (1.0 + np.exp((radius - 0.9) / 0.03))

    def acquire(self, signals: Signals, slice_height_mm: float, noise_seed: int | None) -> "AcquiredImage":
        """The image of the slice at that height: signals(x, y, z, sample_mm) -> (water, fat) at scanner points of
        this session (module text). noise_seed None: the noise-free image."""
        dy, dx = self.pixel_size_mm
        n = self.oversampling
        fine_rows, fine_cols = self.fine_shape
        xf = (np.arange(fine_cols) + 0.5) * dx / n
        yf = (np.arange(fine_rows) + 0.5) * dy / n
        X, Y = np.meshgrid(xf, yf)
        water, fat = np.zeros(X.shape), np.zeros(X.shape)
        offsets, weights = self.subplanes()
        for offset, weight in zip(offsets, weights):
            w, f = signals(X, Y, np.full(X.shape, slice_height_mm + offset), min(dx, dy) / n)
            water += weight * w
            fat += weight * f
        coil = self.coil(X, Y, slice_height_mm)
        spectrum_water = np.fft.fft2(coil * water)
        spectrum_fat = np.fft.fft2(coil * fat)
        ky = np.fft.fftfreq(fine_rows, d=dy / n)[:, None]     # cycles per mm
        kx = np.fft.fftfreq(fine_cols, d=dx / n)[None, :]
        shift_mm = self.chemical_shift_px * (dx if self.readout == "x" else dy)
        spectrum_fat *= np.exp(-2j * np.pi * (kx if self.readout == "x" else ky) * shift_mm)
        # each final sample on its pixel centre: the band-limited signal at x + (n - 1) / (2 n) dx
        centring = np.exp(2j * np.pi * (kx * (n - 1) / (2 * n) * dx + ky * (n - 1) / (2 * n) * dy))
        acquired = _central_block((spectrum_water + spectrum_fat) * centring, self.image_shape)
        window = self.vendor_window()
        clean_k = acquired * window
        scale = self.image_shape[0] * self.image_shape[1] / (fine_rows * fine_cols)
        clean = np.fft.ifft2(np.fft.ifftshift(clean_k)) * scale
        if noise_seed is None:
            noisy_k = clean_k
        else:
            rng = np.random.default_rng(noise_seed)
            count = self.image_shape[0] * self.image_shape[1]
            # image noise per channel = sigma_k sqrt(mean w^2) sqrt(count) scale / count = noise_sigma
            sigma_k = self.noise_sigma * math.sqrt(count) / (scale * math.sqrt(float(np.mean(window ** 2))))
            noise = sigma_k * (rng.standard_normal(self.image_shape) + 1j * rng.standard_normal(self.image_shape))
            noisy_k = clean_k + noise * window
        image = np.fft.ifft2(np.fft.ifftshift(noisy_k)) * scale
        return AcquiredImage(np.abs(image), clean, noisy_k, offsets, weights)

    def stored(self, magnitude: np.ndarray) -> np.ndarray:
        """The 16-bit image a scanner stores: intensity_scale per unit of fat, clipped to 0..65535."""
        return np.clip(np.round(magnitude * self.intensity_scale), 0, 65535).astype(np.uint16)

    def description(self) -> dict:
        offsets, weights = self.subplanes()
        return {**dataclasses.asdict(self), "subplanes_mm": offsets.tolist(), "subplane_weights": weights.tolist(),
                "fine_shape": list(self.fine_shape)}


@dataclass(frozen=True)
class AcquiredImage:
    """magnitude (rows, cols), fat ~ 1; clean: the noise-free complex image; kspace: the acquired (filtered,
    noisy) samples, centred; the slice profile's sub-planes and weights."""

    magnitude: np.ndarray
    clean: np.ndarray
    kspace: np.ndarray
    subplanes_mm: np.ndarray
    subplane_weights: np.ndarray


def _central_block(spectrum: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The central rows x cols of a spectrum (frequencies -n/2 .. n/2 - 1), centred (fftshift order)."""
    shifted = np.fft.fftshift(spectrum)
    centre = [size // 2 for size in spectrum.shape]
    return shifted[tuple(slice(c - s // 2, c - s // 2 + s) for c, s in zip(centre, shape))]


# --- the leg's motion between the sessions --------------------------------------------------------------------

@dataclass(frozen=True)
class LegMotion:
    """The rigid motion of the leg from session 0 to session 1 (module text): turn about z (deg, image frame's
    numbers), tilt (deg) about the in-plane axis at tilt_axis_deg (from +x, same convention), in-plane shift (mm),
    axial slide along +z (mm), about centre_mm (x, y, z; the leg centre at the slice's height by default)."""

    turn_deg: float = 0.0
    tilt_deg: float = 0.0
    tilt_axis_deg: float = 0.0
    shift_mm: tuple[float, float] = (0.0, 0.0)
    slide_mm: float = 0.0
    centre_mm: tuple[float, float, float] | None = None

    @property
    def rotation(self) -> np.ndarray:
        a = np.deg2rad(self.turn_deg)
        turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        b, t = np.deg2rad(self.tilt_axis_deg), np.deg2rad(self.tilt_deg)
        axis = np.array([np.cos(b), np.sin(b), 0.0])
        K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
        return turn @ (np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * K @ K)

    @property
    def translation(self) -> np.ndarray:
        return np.array([self.shift_mm[0], self.shift_mm[1], self.slide_mm], float)

    def about(self, centre_mm) -> "LegMotion":
        return dataclasses.replace(self, centre_mm=tuple(float(v) for v in centre_mm))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """p1 = c + R (p0 - c) + t of points (3, ...)."""
        c = np.asarray(self.centre_mm, float).reshape((3,) + (1,) * (np.ndim(points) - 1))
        return np.tensordot(self.rotation, np.asarray(points, float) - c, axes=1) + c + \
            self.translation.reshape(c.shape)

    def undo(self, points: np.ndarray) -> np.ndarray:
        """p0 = c + R^T (p1 - c - t) of points (3, ...)."""
        c = np.asarray(self.centre_mm, float).reshape((3,) + (1,) * (np.ndim(points) - 1))
        return np.tensordot(self.rotation.T, np.asarray(points, float) - c - self.translation.reshape(c.shape),
                            axes=1) + c

    def as_dict(self) -> dict:
        from scipy.spatial.transform import Rotation

        return {**{k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()},
                "R": self.rotation.tolist(), "t_mm": self.translation.tolist(),
                "rotation_vector_deg": np.rad2deg(Rotation.from_matrix(self.rotation).as_rotvec()).tolist()}

    def patient_motion(self, pixel_size_mm: tuple[float, float]):
        """The same motion as an `imaging.volume.RigidMotion3D` of patient points (a volume's affine puts the
        pixel centres at the image frame's less half a pixel, `phantom.volume`)."""
        from scipy.spatial.transform import Rotation

        from ...case.volume import RigidMotion3D

        dy, dx = pixel_size_mm
        centre = np.asarray(self.centre_mm, float) - np.array([0.5 * dx, 0.5 * dy, 0.0])
        vector = np.rad2deg(Rotation.from_matrix(self.rotation).as_rotvec())
        return RigidMotion3D(tuple(map(float, vector)), tuple(map(float, self.translation)), tuple(map(float, centre)))


@dataclass
class DisplacementGrid:
    """The 3D truth u(X) sampled on a regular grid of the unloaded leg (module text) for the loaded image's fixed
    point: values (3, heights, rows, cols) at x = x0 + j step, y = y0 + i step, z = z0 + k dz."""

    values: np.ndarray
    origin_mm: tuple[float, float, float]
    step_mm: tuple[float, float, float]

    @classmethod
    def sample(cls, displacement_at, extent_mm: tuple[float, float], heights_mm: tuple[float, float],
               step_mm: float, height_step_mm: float = GRID_HEIGHT_STEP_MM) -> "DisplacementGrid":
        """displacement_at(x, y, z) -> (3, ...) sampled over the field of view and heights [low, high]."""
        low, high = heights_mm
        count = max(2, int(math.ceil((high - low) / height_step_mm)) + 1)
        heights = np.linspace(low, high, count)
        xs = np.arange(0.0, extent_mm[0] + step_mm, step_mm)
        ys = np.arange(0.0, extent_mm[1] + step_mm, step_mm)
        X, Y = np.meshgrid(xs, ys)
        values = np.stack([displacement_at(X, Y, np.full(X.shape, z)) for z in heights], axis=1)
        return cls(values, (0.0, 0.0, float(low)), (step_mm, step_mm, float(heights[1] - heights[0])))

    def __call__(self, x, y, z) -> np.ndarray:
        coordinates = np.stack([(np.ravel(z) - self.origin_mm[2]) / self.step_mm[2],
                                (np.ravel(y) - self.origin_mm[1]) / self.step_mm[1],
                                (np.ravel(x) - self.origin_mm[0]) / self.step_mm[0]])
        return np.stack([ndimage.map_coordinates(component, coordinates, order=1, mode="nearest")
                         for component in self.values]).reshape((3,) + np.shape(x))


def material_points(y: np.ndarray, motion: LegMotion, displacement, in_air=None) -> np.ndarray:
    """The material points X (3, ...) shown at session-1 scanner points y (3, ...): X + u(X) = motion.undo(y) by
    the fixed point X <- x - u(X), only the points not yet converged iterated (damped after a hundred steps, as
    `render.undeform` does, for the points where the plain iteration oscillates). in_air(x, y, z) -> bool: points
    that show nothing wherever they land nearby (away from the skin), where the truth's field, continued beyond the
    mesh by its nearest element, may jump between two elements' continuations and the fixed point hop for ever:
    they are kept as they are."""
    target = motion.undo(y).reshape(3, -1)
    X = target.copy()
    index = np.arange(target.shape[1])
    for iteration in range(FIXED_POINT_MAX_ITERATIONS):
        damping = 1.0 if iteration < 100 else 0.5
        u = displacement(*X[:, index])
        step = target[:, index] - u - X[:, index]
        X[:, index] += damping * step
        stepped, index = index, index[np.max(np.abs(step), axis=0) >= FIXED_POINT_TOLERANCE_MM]
        if index.size == 0:
            return X.reshape(np.shape(y))
    # judged on the last step of the points it was taken for
    moving = np.max(np.abs(step), axis=0) >= FIXED_POINT_ACCEPTED_MM
    if in_air is not None:
        moving &= ~np.asarray(in_air(*X[:, stepped]), bool)
    if not moving.any():
        return X.reshape(np.shape(y))
    raise ValueError("x = X + u(X) could not be inverted for the loaded image (the fixed point did not converge); "
                     "the 3D truth folds the tissue: lower the tension or stiffen the tissues")


def grid_heights(scanner: Scanner, slice_heights_mm, motion: LegMotion, margin_mm: float = 3.0) -> tuple[float, float]:
    """The heights of the unloaded leg that a session-1 slab at these heights sees (its corners taken back by the
    motion), widened by margin_mm for the displacement's own axial part."""
    offsets, _ = scanner.subplanes()
    width, height = scanner.extent_mm
    corners = np.array([[x, y, z + o] for x in (0.0, width) for y in (0.0, height)
                        for z in np.atleast_1d(slice_heights_mm) for o in (offsets[0], offsets[-1])]).T
    seen = motion.undo(corners)[2]
    return float(seen.min() - margin_mm), float(seen.max() + margin_mm)
