"""The k-space phantom's appearance: water and fat signals as continuous functions of the 3D material point.

A scanner sees two signals that it displaces differently (the fat by the chemical shift along the readout,
`acquisition`), so the appearance gives them apart: `Appearance3D.signals(x, y, z, sample_mm)` -> (water, fat) at
points of the unloaded leg (scanner frame of session 0, mm), each drawn with its coverage of a sample of size
sample_mm (partial volume, as `mri.scanner` draws: a boundary at signed distance d covers
clip(1/2 - d / h, 0, 1) of the sample and each part is painted over the previous ones). Every feature is written
in the leg's material coordinates (X, z) (`leg3d`: X = Phi^-1 the reference-section point, z the height), so that
it runs along the leg, tapers and twists with it, and moves with the tissue under load. Distances are measured in
the reference section and scaled to the scanner's mm by the taper s(z).

T1-like signals (fat ~1.0), after the second phantom's grey levels (`mri.scanner.MRIContrast`):
- skin: water 0.5 with a weak texture; subcutaneous fat: fat 1.0 with a faint texture, crossed by fibrous septa
  (water 0.12, no fat) that are SHEETS in 3D: a family of radial sheets, the level sets of
  N phi / 2 pi + b depth + A n(X, z) (n 3D noise whose cells along the leg are 4 mm, so that a sheet's line in a
  slice moves by about 0.5 mm per mm of height and the sheets run obliquely), a family of randomly oriented
  sheets, the zero set of an isotropic 3D noise (cells 5 mm), and a few sheets parallel to the skin; each shown
  where its own 3D presence noise is high, 0.3-0.6 mm wide;
- the deep fascia: a dark line (water 0.1) on the muscle's side of the fat;
- muscle: water 0.4 with a fine texture elongated along the leg (cells 0.4 x 0.4 x 3 mm: fibres) and a coarse
  one (fascicle bundles), crossed by streaks of intramuscular fat (fat 0.9): sheets across a direction of each
  compartment, tilted a few degrees from the leg's axis, shown over stretches about 14 mm long in the section
  and 30 mm along the leg (a 3D presence noise stretched along them); the intermuscular septa and the
  aponeurosis (water 0.18) run along the leg;
- vessels (flow voids, water 0.05) run along the leg: the reference section's circles carried by Phi;
- cortex dark (water 0.03); marrow: fat 0.85 with a texture.
The structure's 3D noises are `noise3d.GradientNoise3D` (a lattice noise, vectorised and seeded).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..geometry import COMPARTMENTS
from ..mri.structure import line_coverage, smoothstep
from .leg3d import Leg3D
from .noise3d import GradientNoise3D, tilt_rotation

STREAK_FAMILIES = len(COMPARTMENTS) + 1      # the compartments and the gastrocnemius' medial head
MEDIAL_HEAD = len(COMPARTMENTS)
AIR_MARGIN_MM = 0.5                          # beyond the skin by this much, a sample of a fine grid is all air


@dataclass(frozen=True)
class KspaceContrast:
    """Water and fat signals of the tissues (fat ~1.0) and their textures (relative standard deviation)."""

    fat: float = 1.0
    fat_septum_water: float = 0.12
    skin_water: float = 0.5
    fascia_water: float = 0.10
    muscle_water: float = 0.40
    muscle_septum_water: float = 0.18
    streak_fat: float = 0.90
    vessel_water: float = 0.05
    cortex_water: float = 0.03
    marrow_fat: float = 0.85
    fat_texture: float = 0.02
    skin_texture: float = 0.04
    muscle_texture: float = 0.05
    muscle_coarse_texture: float = 0.03
    marrow_texture: float = 0.05
    radial_septa: int = 44
    septum_width_mm: tuple[float, float] = (0.3, 0.6)
    streak_spacing_mm: float = 4.5
    streak_width_mm: tuple[float, float] = (0.25, 0.55)
    streak_tilt_deg: float = 6.0                 # the streaks' sheets lean this far from the leg's axis


@dataclass
class Appearance3D:
    """The leg's water and fat signals (module text); `seed` picks its structure."""

    leg: Leg3D = field(default_factory=Leg3D)
    contrast: KspaceContrast = field(default_factory=KspaceContrast)
    seed: int = 0

    def __post_init__(self):
        s, c = self.seed, self.contrast
        rng = np.random.default_rng([s, 30])
        self.septum_tilt = float(rng.uniform(-0.6, 0.6))
        self.radial_warp = GradientNoise3D([s, 31], (12.0, 12.0, 4.0))
        self.radial_presence = GradientNoise3D([s, 32], (4.0, 4.0, 6.0))
        self.oblique = GradientNoise3D([s, 33], 5.0)
        self.oblique_presence = GradientNoise3D([s, 34], 4.0)
        self.along_warp = GradientNoise3D([s, 35], (15.0, 15.0, 8.0))
        self.along_presence = GradientNoise3D([s, 36], (5.0, 5.0, 8.0))
        self.width = GradientNoise3D([s, 37], 3.0)
        self.texture = {"fat": GradientNoise3D([s, 40], 1.5), "skin": GradientNoise3D([s, 41], (0.8, 0.8, 2.0)),
                        "muscle": GradientNoise3D([s, 42], (0.4, 0.4, 3.0)),
                        "muscle_coarse": GradientNoise3D([s, 43], (2.5, 2.5, 12.0)),
                        "marrow": GradientNoise3D([s, 44], 1.2)}
        directions = rng.uniform(0.0, np.pi, STREAK_FAMILIES)
        self.streak_directions = np.exp(1j * directions)            # across each family's streaks (leg frame)
        self.streak_tilts = np.tan(np.deg2rad(c.streak_tilt_deg * rng.choice([-1.0, 1.0], STREAK_FAMILIES)))
        self.streak_warp = GradientNoise3D([s, 45], (15.0, 15.0, 20.0))
        self.streak_width = GradientNoise3D([s, 46], 2.0)
        # presence along each streak: a lattice of 1.5 mm read stretched to 14 mm along it and 30 mm along the leg
        self.streak_presence = GradientNoise3D([s, 47], 1.5, rotation=tilt_rotation(3.0, float(rng.uniform(0, 360))))

    def description(self) -> dict:
        return {"seed": self.seed, "contrast": dataclasses.asdict(self.contrast)}

    # -- the signals -----------------------------------------------------------------------------

    def in_air(self, x, y, z, margin_mm: float = AIR_MARGIN_MM) -> np.ndarray:
        """Points farther than margin_mm outside the skin (reference mm), where no sample shows any signal."""
        X, Y = self.leg.reference_point(x, y, z)
        return self.leg.geometry.skin.excess(self.leg.frame.to_leg(X, Y)) > margin_mm

    def signals(self, x, y, z, sample_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """(water, fat) of samples of size sample_mm at points (x, y, z) of the unloaded leg (module text)."""
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
        shape = x.shape
        x, y, z = x.ravel(), y.ravel(), z.ravel()
        X, Y = self.leg.reference_point(x, y, z)
        w = self.leg.frame.to_leg(X, Y)
        g = self.leg.geometry
        h = sample_mm / self.leg.scale(z)                      # the sample's size in the reference section's mm
        rho, unit = g.skin.polar(w)
        near = rho < g.skin.reach + h
        water, fat = np.zeros(x.size), np.zeros(x.size)
        if near.any():
            water[near], fat[near] = self._leg(w[near], z[near], rho[near], unit[near], h[near])
        return water.reshape(shape), fat.reshape(shape)

    def _leg(self, w, z, rho, unit, h):
        g, c, t = self.leg.geometry, self.contrast, self.texture
        W, F = np.zeros(w.shape), np.zeros(w.shape)
        outline, under_skin, fascia = (curve.distance_polar(rho, unit) for curve in (g.skin, g.skin_inner, g.fascia))
        muscle_edge = fascia + g.shape.fascia_mm
        skin = under_skin > -0.5 * h
        _paint((W, F), _cover(outline, h), (c.skin_water * (1.0 + c.skin_texture * t["skin"](w[skin].real, w[skin].imag,
                                                                                          z[skin])), 0.0), skin)
        in_fat = (under_skin < 0.5 * h) & (fascia > -0.5 * h)
        fat_w, fat_f = self._fat(w[in_fat], z[in_fat], rho[in_fat], unit[in_fat], h[in_fat])
        _paint((W, F), _cover(under_skin, h), (fat_w, fat_f), in_fat)
        _paint((W, F), _cover(fascia, h), (c.fascia_water, 0.0))
        in_muscle = muscle_edge < 0.5 * h
        muscle_w, muscle_f = self._muscle(w[in_muscle], z[in_muscle], h[in_muscle])
        _paint((W, F), _cover(muscle_edge, h), (muscle_w, muscle_f), in_muscle)
        for vessel in g.vessels:
            _paint((W, F), _cover(np.abs(w - vessel.centre) - vessel.radius_mm, h), (c.vessel_water, 0.0))
        for bone, marrow in ((g.tibia, g.tibia_marrow), (g.fibula, g.fibula_marrow)):
            near = np.abs(w - bone.centre) < bone.reach + h
            if not near.any():
                continue
            wn, zn, hn = w[near], z[near], h[near]
            bw, bf = W[near], F[near]
            _paint((bw, bf), _cover(bone.distance(wn), hn), (c.cortex_water, 0.0))
            inside = marrow.distance(wn)
            core = inside < 0.5 * hn
            texture = c.marrow_fat * (1.0 + c.marrow_texture * t["marrow"](wn[core].real, wn[core].imag, zn[core]))
            _paint((bw, bf), _cover(inside, hn), (0.0, texture), core)
            W[near], F[near] = bw, bf
        return W, F

    def _fat(self, w, z, rho, unit, h):
        """Fat with its faint texture, crossed by the septa (sheets in 3D, module text)."""
        c = self.contrast
        fat = c.fat * (1.0 + c.fat_texture * self.texture["fat"](w.real, w.imag, z))
        covered = self.septa_coverage(w, z, rho, unit, h)
        return covered * c.fat_septum_water, fat * (1.0 - covered)

    def septa_coverage(self, w, z, rho, unit, h):
        """Share of each sample covered by a fat septum (0-1), at leg-frame fat points w at heights z."""
        g, c = self.leg.geometry, self.contrast
        rho = np.maximum(rho, 1e-6)
        outer, outer_slope = g.skin_inner.radius.evaluate(unit)
        inner, inner_slope = g.fascia.radius.evaluate(unit)
        thickness, thickness_slope = outer - inner, outer_slope - inner_slope
        depth = (outer - rho) / thickness
        across = (outer_slope * thickness - (outer - rho) * thickness_slope) / (thickness ** 2 * rho)
        depth_gradient = unit * (-1.0 / thickness) + 1j * unit * across
        turn, turn_gradient = np.angle(unit) / (2.0 * np.pi), 1j * unit / (2.0 * np.pi * rho)
        low, high = c.septum_width_mm
        width = low + (high - low) * smoothstep(0.5 + 0.35 * self.width(w.real, w.imag, z))
        # radial sheets: level sets of N turn + b depth + A n(X, z)
        n, nx, ny, nz = self.radial_warp(w.real, w.imag, z, gradient=True)
        level = c.radial_septa * turn + self.septum_tilt * depth + 0.3 * n
        in_plane = c.radial_septa * turn_gradient + self.septum_tilt * depth_gradient + 0.3 * (nx + 1j * ny)
        slope = np.hypot(np.abs(in_plane), 0.3 * nz)
        shown = smoothstep(0.5 + 1.2 * (self.radial_presence(w.real, w.imag, z) + 0.5))
        covered = line_coverage(np.abs(level - np.round(level)) / np.maximum(slope, 1e-9), width, h) * shown
        # oblique sheets: the zero set of an isotropic noise, in every orientation
        n, nx, ny, nz = self.oblique(w.real, w.imag, z, gradient=True)
        shown = smoothstep(0.5 + 1.2 * (self.oblique_presence(w.real, w.imag, z) - 0.7))
        covered = np.maximum(covered, line_coverage(np.abs(n) / np.maximum(np.sqrt(nx ** 2 + ny ** 2 + nz ** 2), 1e-9),
                                                    width, h) * shown)
        # sheets parallel to the skin at a third and two thirds of the fat's depth
        n, nx, ny, nz = self.along_warp(w.real, w.imag, z, gradient=True)
        level = 3.0 * depth + 0.15 * n
        slope = np.hypot(np.abs(3.0 * depth_gradient + 0.15 * (nx + 1j * ny)), 0.15 * nz)
        beneath = (level > 0.5) & (level < 2.5)
        shown = smoothstep(0.5 + 1.2 * (self.along_presence(w.real, w.imag, z) - 0.4))
        along = line_coverage(np.abs(level - np.round(level)) / np.maximum(slope, 1e-9), width, h) * shown * beneath
        return np.maximum(covered, along)

    def _muscle(self, w, z, h):
        """Muscle with its textures, intramuscular fat streaks, the septa and the aponeurosis."""
        g, c, t = self.leg.geometry, self.contrast, self.texture
        water = c.muscle_water * (1.0 + c.muscle_texture * t["muscle"](w.real, w.imag, z)
                                  + c.muscle_coarse_texture * t["muscle_coarse"](w.real, w.imag, z))
        family = g.compartment_at_leg(w).astype(int)
        family[(family == COMPARTMENTS.index("superficial_posterior")) & (w.real < 0)] = MEDIAL_HEAD
        streak = self.streak_coverage(w, z, family, h)
        water = water * (1.0 - streak)
        fat = streak * c.streak_fat
        septum = np.min([line.distance(w) for line in g.dark_lines()], axis=0)
        cover = line_coverage(septum, g.shape.septum_mm, h)
        return water + cover * (c.muscle_septum_water - water), fat * (1.0 - cover)

    def streak_coverage(self, w, z, family, h):
        """Share of each sample covered by an intramuscular fat streak (module text)."""
        c = self.contrast
        covered = np.zeros(w.shape)
        n, nx, ny, nz = self.streak_warp(w.real, w.imag, z, gradient=True)
        low, high = c.streak_width_mm
        width = low + (high - low) * smoothstep(0.5 + 0.35 * self.streak_width(w.real, w.imag, z))
        for index, (direction, tilt) in enumerate(zip(self.streak_directions, self.streak_tilts)):
            members = family == index
            if not members.any():
                continue
            local = w[members] / direction           # real: across the streaks, imaginary: along them
            zm = z[members]
            level = (local.real + tilt * zm) / c.streak_spacing_mm + 0.12 * n[members]
            gradient = direction / c.streak_spacing_mm + 0.12 * (nx[members] + 1j * ny[members])
            slope = np.hypot(np.abs(gradient), tilt / c.streak_spacing_mm + 0.12 * nz[members])
            distance = np.abs(level - np.round(level)) / slope
            streak = np.round(level)
            present = smoothstep(0.5 + 1.5 * (self.streak_presence(local.imag * (1.5 / 14.0) + 37.0 * streak,
                                                                   5.3 * streak, zm * (1.5 / 30.0)) - 0.9))
            covered[members] = line_coverage(distance, width[members], h[members]) * present
        return covered


def _cover(distance: np.ndarray, sample_mm) -> np.ndarray:
    """Share of a sample covered by the inside (distance < 0) of a boundary at that signed distance."""
    return np.clip(0.5 - distance / sample_mm, 0.0, 1.0)


def _paint(channels, cover: np.ndarray, colours, where: np.ndarray | None = None) -> None:
    """Each channel <- channel + cover (colour - channel), in place; with `where`, only there (colours given
    there or scalars)."""
    for channel, colour in zip(channels, colours):
        if where is None:
            channel += cover * (colour - channel)
        else:
            channel[where] += cover[where] * (colour - channel[where])
