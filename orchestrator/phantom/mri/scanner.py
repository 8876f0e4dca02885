"""The second phantom seen by a scanner: T1 grey levels, partial volume, coil bias and Rician noise.

`MRIPhantom` renders the leg of `anatomy` with the structure of `structure` as a T1-weighted axial slice,
with an image formation of its own, unlike the first phantom's band-limited (k-space) one:

- grey levels per tissue (fat ~0.88, marrow ~0.8, skin ~0.5, muscle ~0.4, septa and fascia ~0.15-0.3,
  flowing blood and cortex near 0), each tissue modulated by its own texture, all attached to the material
  point X;
- partial volume: the slice is sampled `supersampling` x `supersampling` times per pixel (by default samples
  of at most SAMPLE_MM: 3 x 3 at 0.3-0.36 mm pixels, 4 x 4 at 0.45 mm, 5 x 5 at 0.6 mm), each sample's
  boundaries and lines drawn with the share of the sample they cover (so an edge moves continuously with the
  tissue), and every pixel is the mean of its samples (box averaging over the pixel's own area); with
  `anti_aliased` False each sample is wholly in one tissue instead, as a point-sampling renderer draws
  (`imaging.drawing`: its boundaries move in steps of 1 / supersampling^2 of a pixel's coverage);
- a receive-coil bias b(y) in the scanner frame: four surface coil elements around the field of view, each
  with the on-axis sensitivity of a loop, (1 + d^2 / a^2)^(-3/2) at distance d, combined as a root sum of
  squares, of mean 1 over the central disc where the leg lies and scaled to +- `bias_amplitude` over the field
  of view (about +-10 % over the leg: brighter towards its surface, the coil elements with higher gains);
- Rician noise: the magnitude of the signal plus complex Gaussian noise of `noise_sigma` per channel.

The loaded image is made by evaluating the appearance at the material point X of every scanner sample y
(`render(to_material, ...)`: the caller solves y = R (X + u(X) - c) + c + t for X), so that every feature
moves with the tissue while the bias and the noise stay with the scanner.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ...core.frame import pixel_centres_mm
from ..geometry import COMPARTMENTS
from .anatomy import LegGeometry
from .structure import FatSepta, GradientNoise, MuscleStreaks, line_coverage

SAMPLES_PER_CHUNK = 400_000      # scanner samples evaluated at once (memory: a few tens of arrays of this size)
SAMPLE_MM = 0.125                # default sample size: well under the septa (0.3-0.6 mm) and the finest texture
POINT_SAMPLE_MM = 1e-6           # a sample this small is wholly in one tissue (`anti_aliased` False)


@dataclass(frozen=True)
class MRIContrast:
    """Grey levels (fat ~0.88), texture amplitudes (relative standard deviation), noise and bias."""

    fat: float = 0.88
    fat_septum: float = 0.30
    skin: float = 0.50
    fascia: float = 0.15
    muscle: float = 0.40
    muscle_septum: float = 0.18
    intramuscular_fat: float = 0.80
    vessel: float = 0.06
    cortex: float = 0.03
    marrow: float = 0.80
    fat_texture: float = 0.025
    skin_texture: float = 0.04
    muscle_texture: float = 0.06            # fine, cells of 0.35 mm
    muscle_coarse_texture: float = 0.04     # fascicle bundles, cells of 2.5 mm
    marrow_texture: float = 0.05
    noise_sigma: float = 0.02               # per channel, before the magnitude
    bias_amplitude: float = 0.3             # largest relative change of the coil sensitivity over the field of view
    coil_gains: tuple[float, float, float, float] = (1.0, 0.8, 1.15, 0.9)
    coil_angle_deg: float = 20.0            # direction of the first coil element from the centre of the view


@dataclass
class MRIPhantom:
    """The second phantom leg (`LegGeometry`) as a T1 slice of `image_shape` pixels of `pixel_size_mm` (dy, dx)."""

    geometry: LegGeometry = field(default_factory=LegGeometry)
    contrast: MRIContrast = field(default_factory=MRIContrast)
    image_shape: tuple[int, int] = (420, 420)
    pixel_size_mm: tuple[float, float] = (0.36, 0.36)
    supersampling: int | None = None     # samples per pixel along each axis; None: samples of at most SAMPLE_MM
    # False: each sample wholly in one tissue (a point-sampling renderer's images, `imaging.drawing`), not a scanner's
    anti_aliased: bool = True

    def __post_init__(self):
        if self.supersampling is None:
            self.supersampling = int(np.ceil(max(self.pixel_size_mm) / SAMPLE_MM - 1e-9))
        if self.supersampling < 1:
            raise ValueError("supersampling must be a positive integer")
        seed = self.geometry.shape.seed
        self.septa = FatSepta(self.geometry, seed)
        self.streaks = MuscleStreaks(seed)
        self.texture = {"fat": GradientNoise([seed, 20], 1.5), "skin": GradientNoise([seed, 21], 0.8),
                        "muscle": GradientNoise([seed, 22], 0.35), "muscle_coarse": GradientNoise([seed, 23], 2.5),
                        "marrow": GradientNoise([seed, 24], 1.2)}

    @classmethod
    def at_resolution(cls, pixel_mm: float, field_of_view_mm: float = 150.0, **options) -> "MRIPhantom":
        """Square pixels of pixel_mm over about field_of_view_mm (the matrix rounded to whole pixels)."""
        size = int(round(field_of_view_mm / pixel_mm))
        return cls(image_shape=(size, size), pixel_size_mm=(pixel_mm, pixel_mm), **options)

    @property
    def extent_mm(self) -> tuple[float, float]:
        """(width along x, height along y) of the field of view in mm."""
        return self.image_shape[1] * self.pixel_size_mm[1], self.image_shape[0] * self.pixel_size_mm[0]

    def labels(self, compartments: bool = False) -> np.ndarray:
        """Ground-truth label map of the unloaded image (pixel centres)."""
        return self.geometry.labels_at(*pixel_centres_mm(self.image_shape, self.pixel_size_mm), compartments=compartments)

    def description(self) -> dict:
        """What truth.json records of the phantom."""
        return {"renderer": "mri", "shape": dataclasses.asdict(self.geometry.shape),
                "contrast": dataclasses.asdict(self.contrast), "supersampling": self.supersampling,
                "anti_aliased": self.anti_aliased}

    # -- appearance at material points ------------------------------------------

    def intensity_at(self, x, y, sample_mm: float) -> np.ndarray:
        """Noise- and bias-free grey level of samples of size sample_mm at the material points (x, y) (mm,
        image frame): each part painted over the previous ones with the share of the sample it covers."""
        w = self.geometry.frame.to_leg(x, y).ravel()
        rho, z = self.geometry.skin.polar(w)
        leg = rho < self.geometry.skin.reach + sample_mm
        value = np.zeros(w.shape)
        value[leg] = self._leg_intensity(w[leg], rho[leg], z[leg], sample_mm)
        return value.reshape(np.shape(x))

    def _leg_intensity(self, w: np.ndarray, rho: np.ndarray, z: np.ndarray, h: float) -> np.ndarray:
        """Grey levels of samples near or in the leg ((rho, z): their polar coordinates about the leg centre). A
        tissue's appearance is evaluated only where it is not hidden under the layers painted over it."""
        g, c, texture = self.geometry, self.contrast, self.texture
        value = np.zeros(w.shape)
        outline, under_skin, fascia = (curve.distance_polar(rho, z) for curve in (g.skin, g.skin_inner, g.fascia))
        muscle_edge = fascia + g.shape.fascia_mm
        skin = under_skin > -0.5 * h
        _paint(value, _cover(outline, h), c.skin * (1.0 + c.skin_texture * texture["skin"](w[skin].real, w[skin].imag)), skin)
        fat = (under_skin < 0.5 * h) & (fascia > -0.5 * h)
        _paint(value, _cover(under_skin, h), self._fat(w[fat], h), fat)
        _paint(value, _cover(fascia, h), c.fascia)
        muscle = muscle_edge < 0.5 * h
        _paint(value, _cover(muscle_edge, h), self._muscle(w[muscle], h), muscle)
        for vessel in g.vessels:
            _paint(value, _cover(np.abs(w - vessel.centre) - vessel.radius_mm, h), c.vessel)
        for bone, marrow in ((g.tibia, g.tibia_marrow), (g.fibula, g.fibula_marrow)):
            near = np.abs(w - bone.centre) < bone.reach + h
            bone_value = value[near]
            _paint(bone_value, _cover(bone.distance(w[near]), h), c.cortex)
            inside = marrow.distance(w[near])
            core = inside < 0.5 * h
            at_core = w[near][core]
            _paint(bone_value, _cover(inside, h),
                   c.marrow * (1.0 + c.marrow_texture * texture["marrow"](at_core.real, at_core.imag)), core)
            value[near] = bone_value
        return value

    def _fat(self, w: np.ndarray, h: float) -> np.ndarray:
        """Fat with its own faint texture, crossed by the septa."""
        c = self.contrast
        fat = c.fat * (1.0 + c.fat_texture * self.texture["fat"](w.real, w.imag))
        return fat + self.septa.coverage(w, h) * (c.fat_septum - fat)

    def _muscle(self, w: np.ndarray, h: float) -> np.ndarray:
        """Muscle with its fine and coarse texture, fat streaks, the intermuscular septa and the aponeurosis."""
        g, c = self.geometry, self.contrast
        muscle = c.muscle * (1.0 + c.muscle_texture * self.texture["muscle"](w.real, w.imag)
                             + c.muscle_coarse_texture * self.texture["muscle_coarse"](w.real, w.imag))
        family = g.compartment_at_leg(w).astype(int)
        medial_head = (family == COMPARTMENTS.index("superficial_posterior")) & (w.real < 0)
        family[medial_head] = MuscleStreaks.MEDIAL_HEAD
        muscle += self.streaks.coverage(w, family, h) * (c.intramuscular_fat - muscle)
        septum = np.min([line.distance(w) for line in g.dark_lines()], axis=0)
        return muscle + line_coverage(septum, g.shape.septum_mm, h) * (c.muscle_septum - muscle)

    # -- the image ---------------------------------------------------------------

    def render(self, to_material, noise_seed: int | None) -> np.ndarray:
        """The image whose scanner sample at y shows the material point to_material(y) (module text), box
        averaged over each pixel, times the coil bias, with Rician noise (noise_seed None: noiseless)."""
        n = self.supersampling
        height, width = self.image_shape
        dy, dx = self.pixel_size_mm
        within = (np.arange(n) + 0.5) / n                     # sample positions inside a pixel, in pixels
        x_samples = ((np.arange(width)[:, None] + within) * dx).ravel()
        rows_per_chunk = max(1, SAMPLES_PER_CHUNK // (width * n * n))
        image = np.empty((height, width))
        for first in range(0, height, rows_per_chunk):
            rows = np.arange(first, min(height, first + rows_per_chunk))
            y_samples = ((rows[:, None] + within) * dy).ravel()
            X, Y = to_material(*np.meshgrid(x_samples, y_samples))
            samples = self.intensity_at(X, Y, sample_mm=min(dx, dy) / n if self.anti_aliased else POINT_SAMPLE_MM)
            image[rows] = samples.reshape(len(rows), n, width, n).mean(axis=(1, 3))
        image *= self.coil_bias(*pixel_centres_mm(self.image_shape, self.pixel_size_mm))
        if noise_seed is None:
            return image
        rng = np.random.default_rng(noise_seed)
        sigma = self.contrast.noise_sigma
        return np.hypot(image + sigma * rng.standard_normal(image.shape), sigma * rng.standard_normal(image.shape))

    def coil_bias(self, x, y) -> np.ndarray:
        """Receive sensitivity at scanner points (mm): four loop coils on a ring around the view (module text)."""
        c = self.contrast
        width, height = self.extent_mm
        centre, ring, loop = np.array([width / 2, height / 2]), 0.75 * max(width, height), 0.45 * max(width, height)

        def combined(px, py):
            angles = np.deg2rad(c.coil_angle_deg) + np.arange(len(c.coil_gains)) * np.pi / 2
            total = np.zeros(np.shape(px))
            for gain, angle in zip(c.coil_gains, angles):
                cx, cy = centre + ring * np.array([np.cos(angle), np.sin(angle)])
                total += (gain * (1.0 + ((px - cx) ** 2 + (py - cy) ** 2) / loop ** 2) ** -1.5) ** 2
            return np.sqrt(total)

        grid_x, grid_y = np.meshgrid(np.linspace(0, width, 61), np.linspace(0, height, 61))
        on_grid = combined(grid_x, grid_y)
        # mean 1 over the central disc where the leg lies, so that the tissues keep their grey levels on average
        central = np.hypot(grid_x - centre[0], grid_y - centre[1]) < 0.4 * min(width, height)
        reference = np.mean(on_grid[central])
        peak = np.max(np.abs(on_grid / reference - 1.0))
        return 1.0 + c.bias_amplitude * (combined(np.asarray(x, float), np.asarray(y, float)) / reference - 1.0) / peak


def _cover(distance: np.ndarray, sample_mm: float) -> np.ndarray:
    """Share of a sample covered by the inside (distance < 0) of a boundary at that signed distance."""
    return np.clip(0.5 - distance / sample_mm, 0.0, 1.0)


def _paint(value: np.ndarray, cover: np.ndarray, colour, where: np.ndarray | None = None) -> None:
    """value <- value + cover (colour - value) in place; with `where`, only there, colour given at those points."""
    if where is None:
        value += cover * (colour - value)
    else:
        value[where] += cover[where] * (colour - value[where])
