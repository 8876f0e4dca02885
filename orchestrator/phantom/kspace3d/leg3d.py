"""The 3D leg of the k-space phantom: the second phantom's cross-section carried along the leg by a smooth map.

The leg is the set of points (Phi(X, z), z) for X in the reference section (`mri.LegGeometry`, the calf at its
largest girth, drawn at height `reference_height_mm`) and z the height along the leg (mm, +z towards the knee).
The pair (X, z) is the leg's material coordinate in 3D: the truth's mesh, the appearance and the labels are all
written in it, so that everything that is drawn moves with the same tissue.

Phi(X, z) at height z, in the reference section's leg frame w = l + i a (complex, mm from the leg centre,
`anatomy.LegFrame`), with (rho, phi) the polar coordinates of w:

1. the fat changes its thickness: a radial map rho -> rho' along each ray (phi kept), piecewise linear between
   four knots: the identity inside an inner muscle radius r_in(phi), the fascia r_f moved to r_f + d_f and the
   inner face of the skin r_s moved to r_s + d_s, then a shift by d_s beyond it (the skin keeps its
   thickness). The fat t = r_s - r_f becomes t g(z, phi), g = exp(dz (fat_per_100mm - fat_back_per_100mm
   sin phi) / 100) (dz = z - z_ref; thicker towards the knee, and more at the back, where the calf's fat is),
   of which the share `fat_change_inwards` is taken from the muscle (d_f = -share (t' - t)) and the rest pushes
   the skin out. r_in lies between the bones and the fascia (at most `muscle_band_mm` under the fascia), so the
   bones are never moved by this step and the map is monotone while r_f + d_f > r_in;
2. the section is scaled by s(z) = 1 + taper_per_100mm dz / 100 (the calf narrows towards the ankle: 15 %
   over 140 mm by default) and turned by tw(z) = twist_deg_per_100mm dz / 100 about the leg centre;
3. the leg centre drifts by drift_mm_per_mm dz in the image frame (the leg's axis is not the scanner's z).

Every step is invertible in closed form (the radial map is piecewise linear along the ray and keeps phi), so the
reference point of any scanner point (x, y, z) is exact: `reference_point`. Labels at any height are the reference
section's labels at the reference point (0 air, 1 fat and skin, 2 muscle, 3 bone), landmarks at a height are the
reference landmarks carried by Phi. At z = z_ref Phi is the identity.

The outline's hoop curvature at height z is exact (`skin_curvature`): the skin lies beyond r_s, so step 1 moves it
by d_s(phi) along its ray, and its outline at z is the polar curve R(phi) = r(phi) + d_s(phi, z) (r the reference
skin's trigonometric polynomial, d_s = (1 - share) (r_s - r_f) (g - 1), every factor with closed-form derivatives in
phi), scaled by s(z) and moved rigidly: kappa = (R^2 + 2 R'^2 - R R'') / (s (R^2 + R'^2)^(3/2)), the curvature of a
curve in polar form (e.g. do Carmo, Differential Geometry of Curves and Surfaces, sec. 1-5, ex. 8).

The tibia and the fibula are carried by steps 2-3 only: they scale with the leg, turn with it and drift, so that
their cross-sections and the line between them change with height (what lets a 3D alignment on the bones find an
axial slide, `imaging.align3d`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..mri.anatomy import LegGeometry, LegShape

RAY_SAMPLES = 1440              # angular table of the inner muscle radius
RAY_STEP_MM = 0.05              # radial step of the search for the bones' outer edge along a ray
SMOOTHING_DEG = 6.0             # the inner radius is smoothed over this angle (it shapes the muscle's stretch)
MONOTONE_MARGIN_MM = 0.3        # the moved fascia stays this far outside the inner muscle radius


@dataclass(frozen=True)
class LegAlongHeight:
    """How the section changes along the leg (module text); rates per 100 mm of height from `reference_height_mm`."""

    reference_height_mm: float = 70.0
    taper_per_100mm: float = 0.107             # s(z): 15 % over 140 mm
    twist_deg_per_100mm: float = 4.0
    drift_mm_per_mm: tuple[float, float] = (0.03, -0.02)    # image frame x, y per mm of height
    fat_per_100mm: float = 0.25                # ln of the fat's thickness factor per 100 mm
    fat_back_per_100mm: float = 0.20           # more at the back (phi = -90 deg)
    fat_change_inwards: float = 0.4            # share of a change of fat taken from the muscle
    muscle_band_mm: float = 8.0                # the muscle stretched by the fat's change lies this far under the fascia


@dataclass
class Leg3D:
    """The 3D leg: the reference section (`LegGeometry` of `shape`) and its map along the leg (module text)."""

    shape: LegShape = field(default_factory=LegShape)
    along: LegAlongHeight = field(default_factory=LegAlongHeight)

    def __post_init__(self):
        self.geometry = LegGeometry(self.shape)
        self.frame = self.geometry.frame
        self._phi_table = np.linspace(-np.pi, np.pi, RAY_SAMPLES, endpoint=False)
        self._band_table = self._muscle_band(self._phi_table)

    # -- construction ------------------------------------------------------------------

    def _muscle_band(self, phi: np.ndarray) -> np.ndarray:
        """Depth under the fascia of the inner muscle radius along each ray: at most muscle_band_mm and at most 60 %
        of the muscle between the bones' outer edge and the fascia, smoothed over SMOOTHING_DEG."""
        g = self.geometry
        z = np.exp(1j * phi)
        fascia = g.fascia.radius.evaluate(z)[0]
        radii = np.arange(0.0, float(fascia.max()), RAY_STEP_MM)
        points = radii[None, :] * z[:, None]
        in_bone = (g.tibia.excess(points) < 0) | (g.fibula.excess(points) < 0)
        outer_bone = np.where(in_bone.any(axis=1), radii[np.argmax(np.where(in_bone, radii[None, :], -1.0), axis=1)],
                              -np.inf)
        band = np.minimum(self.along.muscle_band_mm, 0.6 * (fascia - outer_bone))
        # the smallest band within +-SMOOTHING_DEG, then a periodic running mean over the same width
        half = max(1, int(round(SMOOTHING_DEG / 360.0 * RAY_SAMPLES)))
        padded = np.concatenate([band[-half:], band, band[:half]])
        window = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
        lowest = window.min(axis=1)
        padded = np.concatenate([lowest[-half:], lowest, lowest[:half]])
        smooth = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1).mean(axis=1)
        if np.min(smooth) < 0.5:
            raise ValueError("a bone comes within about 1 mm of the fascia; move it inwards (LegShape) so that the "
                             "muscle over it can carry the fat's change along the leg")
        return smooth

    # -- the map ---------------------------------------------------------------------------

    def _knots(self, phi: np.ndarray, z_mm: np.ndarray):
        """(r_in, r_f, r_s, d_f, d_s) along rays phi at heights z (module text, step 1)."""
        g, a = self.geometry, self.along
        unit = np.exp(1j * phi)
        r_f = g.fascia.radius.evaluate(unit)[0]
        r_s = g.skin_inner.radius.evaluate(unit)[0]
        band = np.interp(phi, self._phi_table, self._band_table, period=2.0 * np.pi)
        rise = (np.asarray(z_mm, float) - a.reference_height_mm) / 100.0
        factor = np.exp(rise * (a.fat_per_100mm - a.fat_back_per_100mm * np.sin(phi)))
        change = (r_s - r_f) * (factor - 1.0)
        return r_f - band, r_f, r_s, -a.fat_change_inwards * change, (1.0 - a.fat_change_inwards) * change

    def _radial(self, rho, phi, z_mm, inverse: bool = False):
        """The fat's radial map rho -> rho' along rays (or its inverse): piecewise linear between the knots."""
        r_in, r_f, r_s, d_f, d_s = self._knots(phi, z_mm)
        if np.any(r_f + d_f < r_in + MONOTONE_MARGIN_MM):
            raise ValueError("the fat's change along the leg takes the fascia below the inner muscle radius; reduce "
                             "LegAlongHeight.fat_change_inwards or the fat's rates, or shorten the segment")
        source = (r_in, r_f, r_s)
        target = (r_in, r_f + d_f, r_s + d_s)
        if inverse:
            source, target = target, source
        rho = np.asarray(rho, float)
        out = np.where(rho <= source[0], rho, 0.0)
        inner = (rho > source[0]) & (rho <= source[1])
        out = np.where(inner, target[0] + (rho - source[0]) * (target[1] - target[0]) / (source[1] - source[0]), out)
        middle = (rho > source[1]) & (rho <= source[2])
        out = np.where(middle, target[1] + (rho - source[1]) * (target[2] - target[1]) / (source[2] - source[1]), out)
        return np.where(rho > source[2], rho + (target[2] - source[2]), out)

    def scale(self, z_mm) -> np.ndarray:
        return 1.0 + self.along.taper_per_100mm * (np.asarray(z_mm, float) - self.along.reference_height_mm) / 100.0

    def twist_rad(self, z_mm) -> np.ndarray:
        rise = np.asarray(z_mm, float) - self.along.reference_height_mm
        return np.deg2rad(self.along.twist_deg_per_100mm * rise / 100.0)

    def centre_mm(self, z_mm) -> tuple[np.ndarray, np.ndarray]:
        """The leg centre (image frame) at heights z."""
        rise = np.asarray(z_mm, float) - self.along.reference_height_mm
        cx, cy = self.shape.centre_mm
        return cx + self.along.drift_mm_per_mm[0] * rise, cy + self.along.drift_mm_per_mm[1] * rise

    def leg_frame_at(self, x, y, z_mm) -> np.ndarray:
        """Scanner points (x, y) at heights z in the leg frame of their own section (centre removed, the reference
        frame's axes): complex, mm. Shared by `reference_point` and the appearance's polar coordinates."""
        cx, cy = self.centre_mm(z_mm)
        c0x, c0y = self.shape.centre_mm
        return self.frame.to_leg(np.asarray(x, float) - (cx - c0x), np.asarray(y, float) - (cy - c0y))

    def to_scanner(self, X, Y, z_mm) -> tuple[np.ndarray, np.ndarray]:
        """Phi: reference-section points (X, Y) (image frame at z_ref, mm) to the scanner's (x, y) at heights z."""
        X, Y, z_mm = np.broadcast_arrays(np.asarray(X, float), np.asarray(Y, float), np.asarray(z_mm, float))
        w = self.frame.to_leg(X, Y)
        rho, phi = np.abs(w), np.angle(w)
        moved = self._radial(rho, phi, z_mm) * np.exp(1j * phi) * self.scale(z_mm) * np.exp(1j * self.twist_rad(z_mm))
        x, y = self.frame.to_image(moved)
        cx, cy = self.centre_mm(z_mm)
        c0x, c0y = self.shape.centre_mm
        return x + (cx - c0x), y + (cy - c0y)

    def reference_point(self, x, y, z_mm) -> tuple[np.ndarray, np.ndarray]:
        """Phi^-1: the reference-section point (X, Y) (image frame at z_ref) of scanner points (x, y) at heights z."""
        x, y, z_mm = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z_mm, float))
        w = self.leg_frame_at(x, y, z_mm) / (self.scale(z_mm) * np.exp(1j * self.twist_rad(z_mm)))
        rho, phi = np.abs(w), np.angle(w)
        return self.frame.to_image(self._radial(rho, phi, z_mm, inverse=True) * np.exp(1j * phi))

    # -- queries ----------------------------------------------------------------------------

    def labels_at(self, x, y, z_mm, compartments: bool = False) -> np.ndarray:
        """Exact labels at scanner points (x, y, z): 0 air, 1 fat and skin, 2 muscle, 3 bone (with compartments the
        muscle is 4 + its index in COMPARTMENTS)."""
        X, Y = self.reference_point(x, y, z_mm)
        return self.geometry.labels_at(X, Y, compartments=compartments)

    def skin_curvature(self, phi, z_mm) -> np.ndarray:
        """Exact hoop curvature (1/mm, positive where convex) of the section's outline at heights z, where the
        reference section's ray phi (leg frame, about the leg centre) meets it (module text)."""
        phi, z_mm = np.broadcast_arrays(np.asarray(phi, float), np.asarray(z_mm, float))
        g, a = self.geometry, self.along
        unit = np.exp(1j * phi)
        r, r1, r2 = _profile_with_derivatives(g.skin.radius, unit)
        fat = [s - f for s, f in zip(_profile_with_derivatives(g.skin_inner.radius, unit),
                                     _profile_with_derivatives(g.fascia.radius, unit))]
        rise = (z_mm - a.reference_height_mm) / 100.0
        # g = exp(rise (a - b sin phi)): g' = -g rise b cos phi, g'' = g ((rise b cos phi)^2 + rise b sin phi)
        back = rise * a.fat_back_per_100mm
        factor = np.exp(rise * a.fat_per_100mm - back * np.sin(phi))
        factor1 = -factor * back * np.cos(phi)
        factor2 = factor * ((back * np.cos(phi)) ** 2 + back * np.sin(phi))
        share = 1.0 - a.fat_change_inwards
        R = r + share * fat[0] * (factor - 1.0)
        R1 = r1 + share * (fat[1] * (factor - 1.0) + fat[0] * factor1)
        R2 = r2 + share * (fat[2] * (factor - 1.0) + 2.0 * fat[1] * factor1 + fat[0] * factor2)
        return (R * R + 2.0 * R1 * R1 - R * R2) / ((R * R + R1 * R1) ** 1.5 * self.scale(z_mm))

    def landmarks_at(self, z_mm: float) -> dict[str, tuple[float, float]]:
        """The reference section's five landmarks carried to height z (image frame, mm)."""
        out = {}
        for name, (X, Y) in self.geometry.landmarks().items():
            x, y = self.to_scanner(X, Y, z_mm)
            out[name] = (float(x), float(y))
        return out

    def skin_polygon(self, z_mm: float, vertices: int = 720) -> np.ndarray:
        """(vertices, 2) points of the outline (outer skin) of the section at height z, image frame."""
        reference = self.geometry.skin.polygon(vertices)
        return np.stack(self.to_scanner(reference[:, 0], reference[:, 1], z_mm), axis=-1)

    def bones_clear_of_band(self) -> bool:
        """Whether no bone point lies beyond the inner muscle radius (the fat's map leaves the bones alone)."""
        g = self.geometry
        for bone in (g.tibia, g.fibula):
            w = bone.points(360)
            r_in = self._knots(np.angle(w), np.full(w.shape, self.along.reference_height_mm))[0]
            if np.any(np.abs(w) > r_in):
                return False
        return True

    def description(self) -> dict:
        return {"shape": dataclasses.asdict(self.shape), "along": dataclasses.asdict(self.along)}

    def prismatic(self) -> "Leg3D":
        """The same section with no change along the leg (the plane-strain check)."""
        along = dataclasses.replace(self.along, taper_per_100mm=0.0, twist_deg_per_100mm=0.0,
                                    drift_mm_per_mm=(0.0, 0.0), fat_per_100mm=0.0, fat_back_per_100mm=0.0)
        return Leg3D(self.shape, along)


def _profile_with_derivatives(profile, unit: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """f, df/dphi and d2f/dphi2 of a trigonometric polynomial f = Re(sum_k c_k e^{i k phi}) at unit = e^{i phi}."""
    c = profile.coefficients
    k = np.arange(len(c))
    powers = unit[..., None] ** k
    return ((powers @ c).real, (powers @ (1j * k * c)).real, (powers @ (-(k ** 2) * c)).real)
