"""Fine structure of the second phantom leg, attached to material points: texture, fat septa, fat streaks.

What digital image correlation tracks in a real calf is not a smooth random texture but anatomy: the thin
fibrous septa that cross the subcutaneous fat between the skin and the deep fascia (retinacula cutis), and
the streaks of fat between the fascicles of the muscles. Both are drawn here as level lines of smooth random
functions of the material point, so that they are continuous curves, random but reproducible from a seed,
cheap to evaluate on millions of points (no loop over features), and their distance is known for drawing
them with partial volume:

- `GradientNoise`: Perlin's gradient noise (random unit gradients on a square lattice, hashed through a
  permutation table, blended with the quintic fade 6t^5 - 15t^4 + 10t^3), scaled to unit standard deviation,
  with its exact gradient. The tissues' own texture is a sum of such noises.
- `FatSepta`: in the fat, with phi the angle about the leg centre and s the depth from the skin (0) to the
  fascia (1), the radial septa are the lines where N phi / 2 pi + b s + A n(X) is an integer (N septa around
  the leg, tilted by b and bent by the noise n, so they run obliquely and curve between skin and fascia); a
  second, sparser family crosses them, and a few tangential septa are the lines where M s + A' n'(X) is an
  integer. Each line is 0.3-0.6 mm wide (a noise chooses) and present only where another noise is high, so
  septa start, stop and branch.
- `MuscleStreaks`: in each muscle compartment (two families in the superficial posterior one, the heads
  of the gastrocnemius), fat streaks are lines across a direction of their own (level lines of
  X.n / spacing + A n(X)) shown only along stretches where an elongated noise is high.

The distance to a level line of f is |f - round(f)| / |grad f| (first order), and a line of width w is drawn
with the coverage clip(1/2 + (w/2 - distance) / h, 0, 1) of a sample of size h (partial volume).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .anatomy import LegGeometry

TABLE_SIZE = 4096     # lattice period 4096 cells: no visible repetition at any cell size used here


def line_coverage(distance: np.ndarray, width_mm, sample_mm: float) -> np.ndarray:
    """Share of a sample of size sample_mm covered by a line of width_mm at `distance` from the sample."""
    return np.clip(0.5 + (0.5 * width_mm - distance) / sample_mm, 0.0, 1.0)


def smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


class GradientNoise:
    """Perlin gradient noise of unit standard deviation with features of about `cell_mm` (module text)."""

    def __init__(self, seed, cell_mm: float):
        rng = np.random.default_rng(seed)
        angle = rng.uniform(0.0, 2.0 * np.pi, TABLE_SIZE)
        self._gradient_x, self._gradient_y = np.cos(angle), np.sin(angle)
        self._permutation = rng.permutation(TABLE_SIZE)
        self.cell_mm = float(cell_mm)
        self._scale = 1.0
        probe = np.random.default_rng(12345).uniform(0.0, 500.0 * cell_mm, (2, 40000))
        self._scale = 1.0 / float(np.std(self(*probe)))

    def _corner(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        mask = TABLE_SIZE - 1
        return self._permutation[(self._permutation[i & mask] + j) & mask]

    def __call__(self, x, y, gradient: bool = False):
        """Noise at points (mm); with gradient, also (d/dx, d/dy) per mm."""
        u, v = np.asarray(x, float) / self.cell_mm, np.asarray(y, float) / self.cell_mm
        i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - i, v - j
        corners = {}
        for di in (0, 1):
            for dj in (0, 1):
                index = self._corner(i + di, j + dj)
                gx, gy = self._gradient_x[index], self._gradient_y[index]
                corners[di, dj] = (gx, gy, gx * (fu - di) + gy * (fv - dj))
        sx, sy = _fade(fu), _fade(fv)
        (gx00, gy00, n00), (gx10, gy10, n10) = corners[0, 0], corners[1, 0]
        (gx01, gy01, n01), (gx11, gy11, n11) = corners[0, 1], corners[1, 1]
        twist = n00 - n10 - n01 + n11
        value = (n00 + sx * (n10 - n00) + sy * (n01 - n00) + sx * sy * twist) * self._scale
        if not gradient:
            return value
        du = (gx00 + sx * (gx10 - gx00) + sy * (gx01 - gx00) + sx * sy * (gx00 - gx10 - gx01 + gx11)
              + _fade_slope(fu) * (n10 - n00 + sy * twist))
        dv = (gy00 + sx * (gy10 - gy00) + sy * (gy01 - gy00) + sx * sy * (gy00 - gy10 - gy01 + gy11)
              + _fade_slope(fv) * (n01 - n00 + sx * twist))
        per_mm = self._scale / self.cell_mm
        return value, du * per_mm, dv * per_mm


def _fade(t):
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


def _fade_slope(t):
    return 30.0 * t * t * (t - 1.0) ** 2


@dataclass(frozen=True)
class SeptumFamily:
    """Fat septa along the level lines of count * coordinate + tilt * depth + warp * noise(X), shown where
    presence(X) + presence_bias is high (coordinate: phi / 2 pi for septa across the fat, the depth for septa
    along it)."""

    count: int               # lines around the leg, or across the fat's depth
    tilt: float              # lines crossed between the skin and the fascia: obliquity
    warp: float              # amplitude of the noise, in lines: bends
    noise: GradientNoise
    presence: GradientNoise
    presence_bias: float     # higher: more of each line shown

    def coverage(self, coordinate, coordinate_gradient, depth, depth_gradient, w, width, sample_mm):
        n, nx, ny = self.noise(w.real, w.imag, gradient=True)
        level = self.count * coordinate + self.tilt * depth + self.warp * n
        gradient = self.count * coordinate_gradient + self.tilt * depth_gradient + self.warp * (nx + 1j * ny)
        distance = np.abs(level - np.round(level)) / np.maximum(np.abs(gradient), 1e-9)
        shown = smoothstep(0.5 + 1.2 * (self.presence(w.real, w.imag) + self.presence_bias))
        return line_coverage(distance, width, sample_mm) * shown, level


class FatSepta:
    """The fibrous septa of the subcutaneous fat (module text): `coverage(w, sample_mm)` at leg-frame fat points."""

    def __init__(self, geometry: LegGeometry, seed: int, radial_septa: int = 44, crossing_septa: int = 31,
                 tangential_septa: int = 2, width_mm: tuple[float, float] = (0.3, 0.6)):
        self.geometry = geometry
        rng = np.random.default_rng([seed, 3])
        # across the fat: the radial septa, mostly shown, and a sparse family crossing them obliquely (branches)
        self.across = (
            SeptumFamily(radial_septa, rng.uniform(-0.6, 0.6), 0.2, GradientNoise([seed, 4], 12.0),
                         GradientNoise([seed, 5], 4.0), 0.5),
            SeptumFamily(crossing_septa, rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.5), 0.2,
                         GradientNoise([seed, 6], 12.0), GradientNoise([seed, 7], 3.0), -0.8))
        # along the fat: a few stretches of septa parallel to the skin, at 1/3 and 2/3 of its depth
        self.along = SeptumFamily(tangential_septa + 1, 0.0, 0.15, GradientNoise([seed, 8], 15.0),
                                  GradientNoise([seed, 9], 5.0), -0.4)
        self.width_mm = width_mm
        self.width_noise = GradientNoise([seed, 10], 3.0)

    def coverage(self, w: np.ndarray, sample_mm: float) -> np.ndarray:
        """Share (0-1) of each sample of size sample_mm at leg-frame points w covered by a septum."""
        rho, z = self.geometry.skin_inner.polar(w)
        rho = np.maximum(rho, 1e-6)
        outer, outer_slope = self.geometry.skin_inner.radius.evaluate(z)
        inner, inner_slope = self.geometry.fascia.radius.evaluate(z)
        thickness, thickness_slope = outer - inner, outer_slope - inner_slope
        depth = (outer - rho) / thickness
        # gradients as complex numbers (x + i y of the leg frame), from their radial (z) and tangential (i z) parts
        depth_gradient = z * (-1.0 / thickness) + 1j * z * ((outer_slope * thickness - (outer - rho) * thickness_slope)
                                                           / (thickness ** 2 * rho))
        turn, turn_gradient = np.angle(z) / (2.0 * np.pi), 1j * z / (2.0 * np.pi * rho)
        low, high = self.width_mm
        width = low + (high - low) * smoothstep(0.5 + 0.35 * self.width_noise(w.real, w.imag))
        covered = np.zeros(w.shape)
        for family in self.across:
            covered = np.maximum(covered, family.coverage(turn, turn_gradient, depth, depth_gradient, w, width,
                                                          sample_mm)[0])
        along, level = self.along.coverage(depth, depth_gradient, depth, depth_gradient, w, width, sample_mm)
        beneath = (level > 0.5) & (level < self.along.count - 0.5)     # not the skin or the fascia themselves
        return np.maximum(covered, along * beneath)


class MuscleStreaks:
    """Streaks of intramuscular fat (module text): `coverage(w, family, sample_mm)` at leg-frame muscle points.

    Family: the compartment index (COMPARTMENTS order), or `MEDIAL_HEAD` for the medial half of the superficial
    posterior compartment."""

    MEDIAL_HEAD = 4

    def __init__(self, seed: int, spacing_mm: float = 4.5, width_mm: tuple[float, float] = (0.25, 0.6),
                 length_mm: float = 14.0, threshold: float = 0.9):
        rng = np.random.default_rng([seed, 11])
        self.directions = np.exp(1j * rng.uniform(0.0, np.pi, self.MEDIAL_HEAD + 1))   # across each family's streaks
        self.spacing_mm, self.width_mm = spacing_mm, width_mm
        self.warp = GradientNoise([seed, 12], 15.0)
        self.width_noise = GradientNoise([seed, 13], 2.0)
        # presence: noise on a lattice of 1.5 mm across the streaks, stretched to `length_mm` along them
        self.presence = GradientNoise([seed, 14], 1.5)
        self.stretch = 1.5 / length_mm
        self.threshold = threshold     # streaks show where the unit-variance presence noise exceeds it

    def coverage(self, w: np.ndarray, family: np.ndarray, sample_mm: float) -> np.ndarray:
        covered = np.zeros(w.shape)
        n, nx, ny = self.warp(w.real, w.imag, gradient=True)
        low, high = self.width_mm
        width = low + (high - low) * smoothstep(0.5 + 0.35 * self.width_noise(w.real, w.imag))
        for index, direction in enumerate(self.directions):
            members = family == index
            if not members.any():
                continue
            local = w[members] / direction            # real: across the streaks, imaginary: along them
            level = local.real / self.spacing_mm + 0.12 * n[members]
            gradient = direction / self.spacing_mm + 0.12 * (nx[members] + 1j * ny[members])
            distance = np.abs(level - np.round(level)) / np.abs(gradient)
            # each streak (index k) reads the presence noise along a row of its own (5.3 mm apart, over three
            # lattice cells, and shifted by 37 mm), stretched along it: it shows over stretches of about length_mm
            streak = np.round(level)
            present = smoothstep(0.5 + 1.5 * (self.presence(local.imag * self.stretch + 37.0 * streak, 5.3 * streak)
                                              - self.threshold))
            covered[members] = line_coverage(distance, width[members], sample_mm) * present
        return covered
