"""Geometry of a parametric calf slice at its largest perimeter.

The anatomy follows the slice of the first paper (Avril et al., section 2.1.1
and Fig. 1: tibia, fibula, fat with skin, muscle; the five positions of
section 3.2) and the compartments of the second (section 3.2, Table 1):
an egg-shaped skin contour about 116 mm wide; a fat layer (skin included)
that is thin over the anteromedial face of the tibia and thick at the back;
the deep fascia as the fat/muscle interface; four muscle compartments
(anterior, lateral, deep posterior, superficial posterior) separated by
septa and the interosseous membrane; tibia and fibula with a cortex and
marrow; the great and small saphenous veins in the fat and paired deep veins
in the muscle.

Every closed boundary is a star-shaped curve r(theta) about its own centre,
so that the same geometry is available analytically (inside tests on any
point, used to render images at material points), as polygons (for meshing)
and as a label image. Positions are in mm in the image frame (x right,
y down); anterior is up (-y), posterior down (+y), medial to the left (-x).
Angles are measured in that frame: theta = atan2(y - cy, x - cx), so the
back of the leg is at +90 degrees and the front at -90 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Callable

import numpy as np

from ..model.landmarks import LANDMARK_NAMES

RadiusFn = Callable[[np.ndarray], np.ndarray]


class Tissue(IntEnum):
    """Fine tissue classes of the phantom (what the image shows); `LABEL_OF` maps them to case labels."""

    BACKGROUND = 0
    SKIN = 1
    FAT = 2
    FASCIA = 3
    MUSCLE = 4
    CORTEX = 5
    MARROW = 6
    SUPERFICIAL_VEIN = 7
    DEEP_VEIN = 8


# Case labels (docs/design.md, "The case folder"): veins count as the tissue they sit in (first paper, section 2.2.4).
LABEL_OF = {Tissue.BACKGROUND: 0, Tissue.SKIN: 1, Tissue.FAT: 1, Tissue.SUPERFICIAL_VEIN: 1,
            Tissue.FASCIA: 2, Tissue.MUSCLE: 2, Tissue.DEEP_VEIN: 2, Tissue.CORTEX: 3, Tissue.MARROW: 3}
COMPARTMENTS = ("anterior", "lateral", "deep_posterior", "superficial_posterior")
FIRST_COMPARTMENT_LABEL = 4


@dataclass(frozen=True)
class CalfShape:
    """Parameters of the calf geometry, all lengths in mm and angles in degrees (image frame)."""

    centre_mm: tuple[float, float] = (75.6, 75.6)
    half_width_mm: float = 58.0           # 116 mm wide, as a calf at its largest perimeter
    half_depth_mm: float = 52.0
    posterior_bulge: float = 0.05         # the back (gastrocnemius) is rounder than the front
    skin_mm: float = 1.2
    fat_side_mm: float = 7.0
    fat_back_mm: float = 12.0
    fat_over_tibia_mm: float = 3.0
    tibia_angle_deg: float = -120.0       # anteromedial
    tibia_radius_mm: float = 10.5
    tibia_lobes: float = 0.12             # triangular section, crest anterior
    tibia_clearance_mm: float = 1.5       # muscle/periosteum between tibia and fascia
    tibia_cortex_mm: float = 3.0
    fibula_offset_mm: tuple[float, float] = (28.0, -2.0)   # from the leg centre
    fibula_radius_mm: float = 6.5
    fibula_cortex_mm: float = 1.8
    fascia_mm: float = 0.5
    great_saphenous_angle_deg: float = 165.0
    small_saphenous_angle_deg: float = 95.0
    saphenous_radius_mm: float = 1.6
    deep_vein_radius_mm: float = 1.6
    # a groove in the skin (between the heads of the gastrocnemius, or a crease): skin and fascia pulled towards the
    # centre by the factor 1 - dent_depth exp(-(dtheta / dent_width)^2); 0 = the convex calf. A garment bridges it
    dent_depth: float = 0.0
    dent_angle_deg: float = 90.0
    dent_width_deg: float = 20.0
    anterior_septum_deg: float = -70.0    # rays from the fibula bounding the lateral compartment
    posterior_septum_deg: float = 35.0
    deep_compartment_mm: tuple[float, float] = (24.0, 13.0)  # half-axes along / across the membrane


@dataclass(frozen=True)
class StarCurve:
    """A closed curve r(theta) about a centre; r in mm, theta in radians (image frame)."""

    centre: tuple[float, float]
    radius: RadiusFn

    def polar(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        dx, dy = np.asarray(x, float) - self.centre[0], np.asarray(y, float) - self.centre[1]
        return np.hypot(dx, dy), np.arctan2(dy, dx)

    def radial_excess(self, x, y) -> np.ndarray:
        """|P - c| - r(theta_P): negative inside, zero on the curve, about the distance for round shapes."""
        rho, theta = self.polar(x, y)
        return rho - self.radius(theta)

    def contains(self, x, y) -> np.ndarray:
        return self.radial_excess(x, y) < 0

    def point(self, theta) -> np.ndarray:
        theta = np.asarray(theta, float)
        r = self.radius(theta)
        return np.stack([self.centre[0] + r * np.cos(theta), self.centre[1] + r * np.sin(theta)], axis=-1)

    def polygon(self, vertices: int = 720) -> np.ndarray:
        """(vertices, 2) points in mm, counter-clockwise in theta, not closed (first != last)."""
        return self.point(np.linspace(-np.pi, np.pi, vertices, endpoint=False))

    def shrunk(self, by_mm: float) -> "StarCurve":
        return StarCurve(self.centre, lambda theta, outer=self.radius: outer(theta) - by_mm)


@dataclass(frozen=True)
class Vein:
    name: str
    centre: tuple[float, float]
    radius_mm: float
    superficial: bool

    def contains(self, x, y) -> np.ndarray:
        return np.hypot(np.asarray(x) - self.centre[0], np.asarray(y) - self.centre[1]) < self.radius_mm

    def polygon(self, vertices: int = 48) -> np.ndarray:
        theta = np.linspace(-np.pi, np.pi, vertices, endpoint=False)
        return np.stack([self.centre[0] + self.radius_mm * np.cos(theta), self.centre[1] + self.radius_mm * np.sin(theta)], axis=-1)


def ellipse_radius(a: float, b: float) -> RadiusFn:
    return lambda theta: a * b / np.sqrt((b * np.cos(theta)) ** 2 + (a * np.sin(theta)) ** 2)


def lobed_radius(mean: float, amplitude: float, lobes: int, phase: float) -> RadiusFn:
    return lambda theta: mean * (1.0 + amplitude * np.cos(lobes * (theta - phase)))


@dataclass
class CalfGeometry:
    """The calf slice built from a `CalfShape`; raises ValueError if the parts overlap."""

    shape: CalfShape = field(default_factory=CalfShape)

    def __post_init__(self):
        s = self.shape
        c = s.centre_mm
        self._ellipse = ellipse_radius(s.half_width_mm, s.half_depth_mm)
        self.skin, self.skin_inner, self.fascia, self.muscle_outer = (
            StarCurve(c, lambda t, k=k: self.leg_radii(t)[k]) for k in range(4))
        tibia_shape = lobed_radius(s.tibia_radius_mm, s.tibia_lobes, 3, -np.pi / 2)
        self.tibia = StarCurve(self._place_tibia(tibia_shape), tibia_shape)
        self.tibia_marrow = self.tibia.shrunk(s.tibia_cortex_mm)
        fibula_centre = (c[0] + s.fibula_offset_mm[0], c[1] + s.fibula_offset_mm[1])
        self.fibula = StarCurve(fibula_centre, lobed_radius(s.fibula_radius_mm, 0.08, 3, np.pi / 2))
        self.fibula_marrow = self.fibula.shrunk(s.fibula_cortex_mm)
        self.veins = self._place_veins()
        self._check_nesting()

    # -- construction -----------------------------------------------------

    def leg_radii(self, theta) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """r(theta) (mm) of the four curves about the leg's centre, outside in: the skin (its ellipse, the posterior
        bulge, the groove), the skin's inner face, the fascia (the fat/muscle interface: the skin less the fat and
        skin's thickness) and the muscle's outer face. One place for their shapes; `layers` takes the four at once
        on every sample of an image (the skin's radius once, not four times)."""
        s = self.shape
        skin = self._ellipse(theta) * (1.0 + s.posterior_bulge * np.sin(theta)) * self.dent(theta)
        fascia = skin - self.fat_thickness(theta)
        return skin, skin - s.skin_mm, fascia, fascia - s.fascia_mm

    def dent(self, theta) -> np.ndarray:
        """The groove's factor on the skin radius (1 away from it)."""
        s = self.shape
        if s.dent_depth == 0.0:   # the convex calf: the factor is 1 and its complex exponential the layers' main cost
            return np.ones(np.shape(theta))
        offset = np.angle(np.exp(1j * (np.asarray(theta, float) - np.deg2rad(s.dent_angle_deg))))
        return 1.0 - s.dent_depth * np.exp(-((offset / np.deg2rad(s.dent_width_deg)) ** 2))

    def fat_thickness(self, theta) -> np.ndarray:
        """Fat + skin thickness (mm) along the radius: thick at the back, thin over the anteromedial tibia."""
        s = self.shape
        back = s.fat_side_mm + (s.fat_back_mm - s.fat_side_mm) * ((1.0 + np.sin(theta)) / 2.0) ** 2
        dip = np.exp(3.0 * (np.cos(theta - np.deg2rad(s.tibia_angle_deg)) - 1.0))
        return back - (back - s.fat_over_tibia_mm) * dip

    def _place_tibia(self, tibia_shape: RadiusFn) -> tuple[float, float]:
        """Push the tibia towards the anteromedial skin until it is `tibia_clearance_mm` inside the fascia."""
        s = self.shape
        direction = np.array([np.cos(np.deg2rad(s.tibia_angle_deg)), np.sin(np.deg2rad(s.tibia_angle_deg))])
        phi = np.linspace(-np.pi, np.pi, 720, endpoint=False)
        outline = np.stack([np.cos(phi), np.sin(phi)], axis=-1) * tibia_shape(phi)[:, None]

        def gap(rho: float) -> float:
            points = np.asarray(s.centre_mm) + rho * direction + outline
            return -np.max(self.fascia.radial_excess(points[:, 0], points[:, 1]))

        low, high = 0.0, float(self.fascia.radius(np.deg2rad(s.tibia_angle_deg)))
        if gap(low) < s.tibia_clearance_mm:
            raise ValueError("the tibia does not fit inside the muscle; enlarge the leg or shrink the tibia")
        for _ in range(60):
            mid = 0.5 * (low + high)
            low, high = (mid, high) if gap(mid) > s.tibia_clearance_mm else (low, mid)
        centre = np.asarray(s.centre_mm) + low * direction
        return float(centre[0]), float(centre[1])

    def membrane_frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tibia centre T, fibula centre F, unit vector m along T->F, unit normal n pointing to the back."""
        T, F = np.asarray(self.tibia.centre), np.asarray(self.fibula.centre)
        m = (F - T) / np.linalg.norm(F - T)
        n = np.array([-m[1], m[0]])
        if n[1] < 0:
            n = -n
        return T, F, m, n

    def _place_veins(self) -> list[Vein]:
        s = self.shape
        veins = []
        for name, angle in (("great_saphenous", s.great_saphenous_angle_deg), ("small_saphenous", s.small_saphenous_angle_deg)):
            theta = np.deg2rad(angle)
            r = 0.5 * (self.skin_inner.radius(theta) + self.fascia.radius(theta))
            centre = np.asarray(s.centre_mm) + r * np.array([np.cos(theta), np.sin(theta)])
            veins.append(Vein(name, (float(centre[0]), float(centre[1])), s.saphenous_radius_mm, True))
        T, F, m, n = self.membrane_frame()
        gap = 2.2 * s.deep_vein_radius_mm
        tibial = T + n * (s.tibia_radius_mm + 5.0) + m * 5.0
        peroneal = F + n * (s.fibula_radius_mm + 3.5) - m * 4.0
        for name, centre in (("posterior_tibial_vein_1", tibial - m * gap / 2), ("posterior_tibial_vein_2", tibial + m * gap / 2),
                             ("peroneal_vein_1", peroneal - m * gap / 2), ("peroneal_vein_2", peroneal + m * gap / 2)):
            veins.append(Vein(name, (float(centre[0]), float(centre[1])), s.deep_vein_radius_mm, False))
        return veins

    def _check_nesting(self, margin_mm: float = 0.5) -> None:
        """Every part must sit strictly inside its host (so that polygons nest and meshing needs no boolean operations)."""
        for bone in (self.tibia, self.fibula):
            outline = bone.polygon()
            if np.max(self.muscle_outer.radial_excess(*outline.T)) > -margin_mm:
                raise ValueError("a bone touches the fascia; move it inwards or thicken the muscle")
        if np.min(self.fat_thickness(np.linspace(-np.pi, np.pi, 720)) - self.shape.skin_mm) < 1.0:
            raise ValueError("the fat layer under the skin is thinner than 1 mm somewhere; thicken it")
        if np.min(self.fibula.radial_excess(*self.tibia.polygon().T)) < margin_mm:
            raise ValueError("tibia and fibula overlap; move the fibula")
        for vein in self.veins:
            ring = vein.polygon()
            if vein.superficial:
                ok = np.max(self.skin_inner.radial_excess(*ring.T)) < -margin_mm and np.min(self.fascia.radial_excess(*ring.T)) > margin_mm
            else:
                ok = (np.max(self.muscle_outer.radial_excess(*ring.T)) < -margin_mm
                      and min(np.min(b.radial_excess(*ring.T)) for b in (self.tibia, self.fibula)) > margin_mm)
            if not ok:
                raise ValueError(f"the {vein.name} does not sit inside its tissue; move it or change its radius")

    # -- queries at points --------------------------------------------------

    def layers(self, x, y) -> list[tuple[Tissue, np.ndarray]]:
        """(tissue, signed distance in mm, negative inside) of each part at the points, in painting order:
        a later layer covers an earlier one. The distance is radial for star-shaped parts (close to the normal
        distance for these round shapes), so renderers can draw boundaries with sub-sample precision."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        # the leg's four curves share its centre (one polar transform) and `leg_radii` (one r(theta) of the skin)
        rho, theta = self.skin.polar(x, y)
        skin, fat, fascia, muscle = (rho - radius for radius in self.leg_radii(theta))
        layers = [(Tissue.SKIN, skin), (Tissue.FAT, fat), (Tissue.FASCIA, fascia), (Tissue.MUSCLE, muscle),
                  (Tissue.FASCIA, np.maximum(muscle, self._septum_distance(x, y) - self.shape.fascia_mm / 2))]
        for vein in self.veins:
            distance = np.hypot(x - vein.centre[0], y - vein.centre[1]) - vein.radius_mm
            layers.append((Tissue.SUPERFICIAL_VEIN if vein.superficial else Tissue.DEEP_VEIN, distance))
        for bone, marrow in ((self.tibia, self.tibia_marrow), (self.fibula, self.fibula_marrow)):
            rho, theta = bone.polar(x, y)   # a bone and its marrow share their centre
            layers += [(Tissue.CORTEX, rho - bone.radius(theta)), (Tissue.MARROW, rho - marrow.radius(theta))]
        return layers

    def tissue_at(self, x, y) -> np.ndarray:
        """Fine tissue class (`Tissue`) at material points (mm), same shape as x."""
        tissue = np.full(np.shape(x), Tissue.BACKGROUND, dtype=np.uint8)
        for kind, distance in self.layers(x, y):
            tissue[distance < 0] = kind
        return tissue

    def labels_at(self, x, y, compartments: bool = False) -> np.ndarray:
        """Case labels at points: 0 background, 1 fat, 2 muscle, 3 bone; with compartments muscle is 4 + index in COMPARTMENTS."""
        tissue = self.tissue_at(x, y)
        lookup = np.zeros(len(Tissue), dtype=np.uint8)
        for fine, label in LABEL_OF.items():
            lookup[fine] = label
        labels = lookup[tissue]
        if compartments:
            muscle = labels == 2
            labels[muscle] = FIRST_COMPARTMENT_LABEL + self.compartment_at(np.asarray(x)[muscle], np.asarray(y)[muscle])
        return labels

    def compartment_at(self, x, y) -> np.ndarray:
        """Index in COMPARTMENTS of points assumed to be in the muscle (second paper, section 3.2: one material per muscle group)."""
        s = self.shape
        T, F, m, n = self.membrane_frame()
        x, y = np.asarray(x, float), np.asarray(y, float)
        angle_from_fibula = np.degrees(np.arctan2(y - F[1], x - F[0]))
        lateral = (angle_from_fibula > s.anterior_septum_deg) & (angle_from_fibula < s.posterior_septum_deg)
        behind_membrane = (x - T[0]) * n[0] + (y - T[1]) * n[1] >= 0
        D = self._deep_compartment_centre()
        a, b = s.deep_compartment_mm
        along, across = (x - D[0]) * m[0] + (y - D[1]) * m[1], (x - D[0]) * n[0] + (y - D[1]) * n[1]
        deep = (along / a) ** 2 + (across / b) ** 2 < 1.0
        lateral_of_tibia = (x - T[0]) * m[0] + (y - T[1]) * m[1] > 0
        anterior = ~behind_membrane & lateral_of_tibia   # medial to the tibia there is no anterior muscle
        index = np.where(anterior, 0, np.where(behind_membrane & deep, 2, 3))
        return np.where(lateral, 1, index).astype(np.uint8)

    def _deep_compartment_centre(self) -> np.ndarray:
        T, F, m, n = self.membrane_frame()
        return 0.5 * (T + F) + n * (self.shape.deep_compartment_mm[1] - 1.0)

    def _septum_distance(self, x, y) -> np.ndarray:
        """Distance (mm) to the septa between compartments: interosseous membrane, the two fibular septa, the transverse septum."""
        s = self.shape
        T, F, m, n = self.membrane_frame()
        distances = [_segment_distance(x, y, T, F)]   # interosseous membrane
        for angle in (s.anterior_septum_deg, s.posterior_septum_deg):
            direction = np.array([np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))])
            distances.append(_segment_distance(x, y, F, F + 200.0 * direction))
        D = self._deep_compartment_centre()
        a, b = s.deep_compartment_mm
        along, across = (x - D[0]) * m[0] + (y - D[1]) * m[1], (x - D[0]) * n[0] + (y - D[1]) * n[1]
        ellipse = np.abs(np.sqrt((along / a) ** 2 + (across / b) ** 2) - 1.0) * b
        angle_from_fibula = np.degrees(np.arctan2(y - F[1], x - F[0]))
        behind_membrane = (x - T[0]) * n[0] + (y - T[1]) * n[1] > 0
        lateral = (angle_from_fibula > s.anterior_septum_deg) & (angle_from_fibula < s.posterior_septum_deg)
        distances.append(np.where(behind_membrane & ~lateral, ellipse, np.inf))
        return np.min(distances, axis=0)

    # -- descriptions for other rooms ----------------------------------------

    def boundaries(self, vertices: int = 720) -> dict[str, np.ndarray]:
        """Closed polygons (N, 2) in mm, not repeating the first vertex: skin, fascia (fat/muscle interface),
        tibia, fibula, their marrow, and each vein. They nest without crossing."""
        polygons = {"skin": self.skin.polygon(vertices), "fascia": self.fascia.polygon(vertices),
                    "tibia": self.tibia.polygon(vertices // 2), "fibula": self.fibula.polygon(vertices // 4),
                    "tibia_marrow": self.tibia_marrow.polygon(vertices // 2), "fibula_marrow": self.fibula_marrow.polygon(vertices // 4)}
        polygons.update({vein.name: vein.polygon() for vein in self.veins})
        return polygons

    def landmarks(self) -> dict[str, tuple[float, float]]:
        """The five positions of the first paper (section 3.2), mm in the image frame."""
        s = self.shape
        c = np.asarray(s.centre_mm)
        theta_tibia = np.deg2rad(s.tibia_angle_deg)
        r_hypodermis = 0.5 * (self.skin_inner.radius(theta_tibia) + self.fascia.radius(theta_tibia))
        hypodermis = c + r_hypodermis * np.array([np.cos(theta_tibia), np.sin(theta_tibia)])
        back = c + self.fascia.radius(np.pi / 2) * np.array([0.0, 1.0])
        veins = {vein.name: np.asarray(vein.centre) for vein in self.veins}
        deep = 0.5 * (veins["posterior_tibial_vein_1"] + veins["posterior_tibial_vein_2"])
        points = {"hypodermis_tibia": hypodermis, "deep_veins": deep, "max_pressure": back,
                  "great_saphenous": veins["great_saphenous"], "small_saphenous": veins["small_saphenous"]}
        return {name: (float(points[name][0]), float(points[name][1])) for name in LANDMARK_NAMES}


def _segment_distance(x, y, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points to the segment [a, b] (mm)."""
    ab = b - a
    t = np.clip(((x - a[0]) * ab[0] + (y - a[1]) * ab[1]) / (ab @ ab), 0.0, 1.0)
    return np.hypot(x - a[0] - t * ab[0], y - a[1] - t * ab[1])
