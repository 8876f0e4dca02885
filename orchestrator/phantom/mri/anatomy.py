"""Anatomy of the second phantom leg: outlines, bones, compartments, vessels, labels and landmarks.

The first phantom (`orchestrator.phantom.geometry`) is an egg-shaped calf; a method checked only on it may
have learnt its shapes. This leg is drawn independently, from a cross-section of a calf at its largest
perimeter as a T1 axial slice shows it: a rounded, somewhat triangular and asymmetric outline (tibial crest
in front, the two heads of the gastrocnemius behind, the medial one larger), a subcutaneous fat layer of its
own thickness (thin over the subcutaneous face of the tibia, thick at the back), a triangular tibia and a
small fibula (about 10 mm across), each a cortex around fatty marrow, four muscle compartments bounded by
curved septa, and veins in the fat and the muscle.

Everything is built in the leg's own frame, a complex coordinate w = l + i a (l lateral, a anterior, mm from
the leg centre), and mapped to the image frame (x right, y down, mm) by the side of the leg (radiological
view from the feet: the fibula of a right leg is on the image's left) and a rotation of the leg in the coil.
Closed outlines are radius profiles r(phi) about a centre that are trigonometric polynomials, evaluated in
z = e^{i phi} by Horner's scheme (no trigonometric function per point), so that inside tests are exact and
fast on millions of points, and signed distances (to first order, (rho - r) / sqrt(1 + (r'/rho)^2)) are
available to draw edges with partial volume. Septa are parabolic arcs over a chord. The outline, the fat
thickness and the small vessels are perturbed from `seed`, so that several legs can be drawn.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..geometry import COMPARTMENTS, FIRST_COMPARTMENT_LABEL, LANDMARK_NAMES

BACKGROUND, FAT, MUSCLE, BONE = 0, 1, 2, 3
PROFILE_SAMPLES = 64           # samples of a radius profile: exact for trigonometric polynomials of degree < 32


@dataclass(frozen=True)
class LegShape:
    """Parameters of the leg, lengths in mm and angles in degrees.

    Angles `*_deg` without further note are directions from the leg centre in the leg's frame: 0 lateral,
    90 anterior, 180 medial, -90 posterior. Offsets are (lateral, anterior) in mm.
    """

    centre_mm: tuple[float, float] = (75.0, 75.0)     # image frame
    side: str = "right"                               # radiological view: a right leg's fibula is on the image's left
    rotation_deg: float = 5.0                         # the leg turned in the coil, clockwise on screen
    seed: int = 0                                     # outline and fat jitter, small vessels, septa, streaks, texture
    # outline: mean radius + (harmonic, amplitude mm, phase deg) terms r += a cos(k (phi - phase))
    mean_radius_mm: float = 54.0
    outline_terms: tuple[tuple[int, float, float], ...] = (
        (1, 2.5, -90.0),     # the back (gastrocnemius) bulges
        (2, 3.0, 0.0),       # wider from side to side than from front to back
        (3, 2.0, 90.0),      # rounded triangle: tibial crest in front, the two heads of the gastrocnemius behind
        (1, 1.5, -135.0),    # the medial head is the larger
    )
    outline_jitter_mm: float = 1.0                    # seeded harmonics 2-6, amplitude / k
    skin_mm: float = 1.5
    skin_posterior_mm: float = 0.4                    # the skin thickens towards the back by this much
    # subcutaneous fat (skin excluded): mean + front/back and medial/lateral terms + seeded jitter, thinned to
    # `fat_over_tibia_mm` in front of the tibia's subcutaneous face
    fat_mean_mm: float = 6.0
    fat_back_mm: float = 2.5                          # + at the back, - in front
    fat_medial_mm: float = 1.0                        # + medially, - laterally
    fat_jitter_mm: float = 0.6
    fat_over_tibia_mm: float = 2.5
    fascia_mm: float = 0.5                            # the deep fascia: a dark line on the muscle's side of the interface
    # bones: tibia pushed along `tibia_deg` until `tibia_clearance_mm` of muscle separates it from the fascia
    tibia_deg: float = 118.0
    tibia_radius_mm: float = 11.5
    tibia_triangularity: float = 0.14                 # cos 3 term: crest, medial and interosseous borders
    tibia_elongation: float = 0.06                    # cos 2 term: longer front to back
    tibia_clearance_mm: float = 2.0
    tibia_cortex_mm: float = 1.7                      # 1.4 to 2.0 mm: thickest at the crest
    fibula_offset_mm: tuple[float, float] = (28.0, -3.0)
    fibula_radius_mm: float = 4.9                     # about 10 mm across
    fibula_cortex_mm: float = 1.4
    # septa: anterior and posterior intermuscular septa from the fibula to the fascia at these angles; the
    # interosseous membrane and the transverse septum over the tibia -> fibula chord, bulging by these (mm,
    # + towards the front)
    anterior_septum_deg: float = 45.0
    posterior_septum_deg: float = -20.0
    membrane_bulge_mm: float = 1.5
    transverse_septum_bulge_mm: float = -13.0
    septum_mm: float = 0.6
    # the aponeurosis between the soleus and the gastrocnemius: a dark arc inside the superficial posterior
    # compartment (not a compartment boundary), between these angles, this deep under the fascia
    aponeurosis_deg: tuple[float, float] = (-140.0, -45.0)
    aponeurosis_depth_mm: float = 14.0
    # vessels: saphenous veins in the fat at these angles (mid depth), deep vessels in the compartments
    great_saphenous_deg: float = 178.0
    small_saphenous_deg: float = -95.0
    great_saphenous_radius_mm: float = 2.0
    small_saphenous_radius_mm: float = 1.5
    deep_vein_radius_mm: float = 1.6
    small_fat_vessels: int = 5                        # seeded, 0.5-1.0 mm radius
    small_muscle_veins: int = 3                       # seeded, soleal / gastrocnemial sinuses, 1.0-2.0 mm radius


@dataclass(frozen=True)
class LegFrame:
    """Maps the leg's frame w = l + i a (complex, mm from the leg centre) to the image frame and back."""

    centre_mm: tuple[float, float]
    side: str
    rotation_deg: float

    def __post_init__(self):
        if self.side not in ("right", "left"):
            raise ValueError(f"side must be 'right' or 'left', not {self.side!r}")

    @property
    def _turn(self) -> complex:
        return complex(np.exp(1j * np.deg2rad(self.rotation_deg)))

    def to_leg(self, x, y) -> np.ndarray:
        """Complex leg-frame coordinates of image points (mm)."""
        d = ((np.asarray(x, float) - self.centre_mm[0]) + 1j * (np.asarray(y, float) - self.centre_mm[1])) / self._turn
        # right leg: lateral = image left, anterior = image up; left leg: lateral = image right
        return -d if self.side == "right" else np.conj(d)

    def to_image(self, w) -> tuple[np.ndarray, np.ndarray]:
        w = np.asarray(w, complex)
        d = (-w if self.side == "right" else np.conj(w)) * self._turn
        return d.real + self.centre_mm[0], d.imag + self.centre_mm[1]


class AngularProfile:
    """A smooth periodic function of an angle, f(phi) = Re(sum_k c_k e^{i k phi}): a trigonometric polynomial."""

    def __init__(self, coefficients):
        self.coefficients = np.asarray(coefficients, complex)

    @classmethod
    def of(cls, function: Callable[[np.ndarray], np.ndarray]) -> "AngularProfile":
        """The profile of a function that is a trigonometric polynomial of degree < PROFILE_SAMPLES / 2."""
        phi = np.linspace(0.0, 2.0 * np.pi, PROFILE_SAMPLES, endpoint=False)
        coefficients = np.fft.rfft(function(phi)) / PROFILE_SAMPLES
        coefficients[1:] *= 2.0
        if np.max(np.abs(coefficients[-4:])) > 1e-9 * max(1.0, np.max(np.abs(coefficients))):
            raise ValueError("the profile is not a trigonometric polynomial of low enough degree")
        significant = np.nonzero(np.abs(coefficients) > 1e-12)[0]
        return cls(coefficients[: (significant[-1] + 1) if significant.size else 1])

    def __sub__(self, other: "AngularProfile") -> "AngularProfile":
        size = max(len(self.coefficients), len(other.coefficients))
        return AngularProfile(np.pad(self.coefficients, (0, size - len(self.coefficients)))
                              - np.pad(other.coefficients, (0, size - len(other.coefficients))))

    def evaluate(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f and df/dphi at unit complex numbers z = e^{i phi} (Horner's scheme on the polynomial and its derivative)."""
        value = np.full(np.shape(z), self.coefficients[-1], complex)
        slope = np.full(np.shape(z), (len(self.coefficients) - 1) * self.coefficients[-1], complex)
        for k in range(len(self.coefficients) - 2, -1, -1):
            value = value * z + self.coefficients[k]
            slope = slope * z + k * self.coefficients[k]
        return value.real, (1j * slope).real

    def __call__(self, phi) -> np.ndarray:
        return self.evaluate(np.exp(1j * np.asarray(phi, float)))[0]


class PolarCurve:
    """A closed curve r(phi) about a centre of the leg's frame; the image-frame queries go through `frame`."""

    def __init__(self, frame: LegFrame, centre: complex, radius: AngularProfile):
        self.frame, self.centre, self.radius = frame, complex(centre), radius

    @property
    def reach(self) -> float:
        """An upper bound of the radius (the sum of the profile's |coefficients|): no point farther is inside."""
        return float(np.sum(np.abs(self.radius.coefficients)))

    def polar(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho, e^{i phi}) of leg-frame points about the centre; at the centre itself z = 0, where the profile
        gives its mean radius."""
        offset = np.asarray(w, complex) - self.centre
        rho = np.abs(offset)
        return rho, offset / np.maximum(rho, 1e-300)

    def excess(self, w: np.ndarray) -> np.ndarray:
        """rho - r(phi) at leg-frame points: negative inside."""
        rho, z = self.polar(w)
        return rho - self.radius.evaluate(z)[0]

    def distance(self, w: np.ndarray) -> np.ndarray:
        """Signed distance (mm, negative inside) to first order: the radial excess over |grad (rho - r(phi))|."""
        return self.distance_polar(*self.polar(w))

    def distance_polar(self, rho: np.ndarray, z: np.ndarray) -> np.ndarray:
        """`distance` at points given by their `polar` coordinates about this curve's centre."""
        r, slope = self.radius.evaluate(z)
        return (rho - r) / np.sqrt(1.0 + (slope / np.maximum(rho, 1e-6)) ** 2)

    def radial_excess(self, x, y) -> np.ndarray:
        """rho - r(phi) at image points (mm): negative inside, about the distance to the curve."""
        return self.excess(self.frame.to_leg(x, y))

    def contains(self, x, y) -> np.ndarray:
        return self.radial_excess(x, y) < 0

    def points(self, vertices: int = 720) -> np.ndarray:
        """(vertices,) leg-frame points on the curve."""
        z = np.exp(1j * np.linspace(-np.pi, np.pi, vertices, endpoint=False))
        return self.centre + self.radius.evaluate(z)[0] * z

    def polygon(self, vertices: int = 720) -> np.ndarray:
        """(vertices, 2) image-frame points in mm, not closed."""
        return np.stack(self.frame.to_image(self.points(vertices)), axis=-1)

    def shrunk(self, by: AngularProfile) -> "PolarCurve":
        return PolarCurve(self.frame, self.centre, self.radius - by)


class ArcCurve:
    """A septum: the parabola q = 4 h s (1 - s) over the chord from `start` to `end` (s the fraction along it, q
    to the left of it, leg frame), continued straight along its end tangents for side tests."""

    def __init__(self, start: complex, end: complex, bulge_mm: float):
        self.start, self.end, self.bulge = complex(start), complex(end), float(bulge_mm)
        self.length = abs(self.end - self.start)
        self.direction = (self.end - self.start) / self.length

    def chord_coordinates(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(fraction s along the chord, offset q to its left in mm)."""
        local = (np.asarray(w, complex) - self.start) / self.direction
        return local.real / self.length, local.imag

    def height(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The arc's offset q(s) and its slope dq/d(chord mm), continued along the end tangents outside [0, 1]."""
        clamped = np.clip(s, 0.0, 1.0)
        slope = 4.0 * self.bulge * (1.0 - 2.0 * clamped) / self.length
        return 4.0 * self.bulge * clamped * (1.0 - clamped) + slope * (s - clamped) * self.length, slope

    def side(self, w: np.ndarray) -> np.ndarray:
        """Offset to the left of the (continued) arc, mm (first order)."""
        s, q = self.chord_coordinates(w)
        height, slope = self.height(s)
        return (q - height) / np.sqrt(1.0 + slope ** 2)

    def distance(self, w: np.ndarray) -> np.ndarray:
        """Unsigned distance to the arc between its ends (mm, first order across it)."""
        s, q = self.chord_coordinates(w)
        height, slope = self.height(s)
        across = np.abs(q - height) / np.sqrt(1.0 + slope ** 2)
        beyond = np.minimum(np.abs(w - self.start), np.abs(w - self.end))
        return np.where((s >= 0.0) & (s <= 1.0), across, beyond)

    def point(self, s: float) -> complex:
        return self.start + self.direction * (s * self.length + 1j * float(self.height(np.array(s))[0]))


@dataclass(frozen=True)
class Vessel:
    name: str
    centre: complex          # leg frame
    radius_mm: float
    tissue: int              # FAT or MUSCLE: the tissue it runs in (its label)


class LegGeometry:
    """The leg built from a `LegShape`; raises ValueError when its parts do not nest with room for a mesh."""

    def __init__(self, shape: LegShape | None = None):
        self.shape = s = shape or LegShape()
        self.frame = LegFrame(s.centre_mm, s.side, s.rotation_deg)
        rng = np.random.default_rng([s.seed, 1])
        self.skin = PolarCurve(self.frame, 0.0, AngularProfile.of(self._outline(rng)))
        skin_thickness = AngularProfile.of(lambda phi: s.skin_mm + s.skin_posterior_mm * (1.0 - np.sin(phi)) / 2.0)
        self.skin_inner = self.skin.shrunk(skin_thickness)
        self.fascia = self.skin_inner.shrunk(AngularProfile.of(self._fat_thickness(rng)))
        self.tibia = self._place_tibia()
        self.tibia_marrow = self.tibia.shrunk(AngularProfile.of(
            lambda phi: s.tibia_cortex_mm + 0.3 * np.cos(phi - np.pi / 2)))
        fibula_centre = complex(*s.fibula_offset_mm)
        self.fibula = PolarCurve(self.frame, fibula_centre, AngularProfile.of(   # a rounded triangle, a little flattened
            lambda phi: s.fibula_radius_mm * (1.0 + 0.10 * np.cos(3.0 * (phi - 0.3)) + 0.06 * np.cos(2.0 * phi))))
        self.fibula_marrow = self.fibula.shrunk(AngularProfile([s.fibula_cortex_mm]))
        T, F = self.tibia.centre, self.fibula.centre
        # bulges are given towards the front; an arc bulges to the left of its chord
        forwards = self._front_sign()
        self.membrane = ArcCurve(T, F, forwards * s.membrane_bulge_mm)
        self.transverse_septum = ArcCurve(T, F, forwards * s.transverse_septum_bulge_mm)
        self.anterior_septum = ArcCurve(F, self._through_fascia(s.anterior_septum_deg), 1.5)
        self.posterior_septum = ArcCurve(F, self._through_fascia(s.posterior_septum_deg), -1.5)
        self.crest_direction = np.exp(1j * np.deg2rad(90.0))   # the tibia's crest points forwards
        ends = [self._under_fascia(angle, s.aponeurosis_depth_mm) for angle in s.aponeurosis_deg]
        self.aponeurosis = ArcCurve(ends[0], ends[1], -0.25 * abs(ends[1] - ends[0]))   # bowed backwards
        self.vessels = self._place_vessels(np.random.default_rng([s.seed, 2]))
        self._check()

    # -- construction -------------------------------------------------------

    def _outline(self, rng: np.random.Generator):
        s = self.shape
        terms = [(k, a, np.deg2rad(p)) for k, a, p in s.outline_terms]
        terms += [(k, s.outline_jitter_mm * rng.standard_normal() / k, rng.uniform(0, 2 * np.pi)) for k in range(2, 7)]
        return lambda phi: s.mean_radius_mm + sum(a * np.cos(k * (phi - p)) for k, a, p in terms)

    def _fat_thickness(self, rng: np.random.Generator):
        """Fat thickness under the skin: front/back and medial/lateral terms, seeded jitter, and a dip of raised
        cosine power cos^16((phi - phi_t) / 2) (about 35 degrees wide) to `fat_over_tibia_mm` at the tibia."""
        s = self.shape
        jitter = [(k, s.fat_jitter_mm * rng.standard_normal() / k, rng.uniform(0, 2 * np.pi)) for k in range(1, 5)]
        tibia = np.deg2rad(s.tibia_deg)

        def base(phi):
            return (s.fat_mean_mm - s.fat_back_mm * np.sin(phi) - s.fat_medial_mm * np.cos(phi)
                    + sum(a * np.cos(k * (phi - p)) for k, a, p in jitter))

        dip = float(base(np.array(tibia))) - s.fat_over_tibia_mm
        return lambda phi: base(phi) - dip * np.cos((phi - tibia) / 2.0) ** 16

    def _place_tibia(self) -> PolarCurve:
        """Slide the tibia outwards along `tibia_deg` until `tibia_clearance_mm` of muscle is left under the fascia."""
        s = self.shape
        crest = np.pi / 2
        profile = AngularProfile.of(lambda phi: s.tibia_radius_mm * (1.0 + s.tibia_triangularity * np.cos(3.0 * (phi - crest))
                                                                     + s.tibia_elongation * np.cos(2.0 * (phi - crest))))
        direction = np.exp(1j * np.deg2rad(s.tibia_deg))

        def clearance(distance: float) -> float:
            outline = PolarCurve(self.frame, distance * direction, profile).points(720)
            return -float(np.max(self.fascia.distance(outline)))

        near, far = 0.0, float(self.fascia.radius(np.deg2rad(s.tibia_deg)))
        if clearance(near) < s.tibia_clearance_mm:
            raise ValueError("the tibia does not fit inside the muscle; enlarge the leg or shrink the tibia")
        for _ in range(50):
            middle = 0.5 * (near + far)
            near, far = (middle, far) if clearance(middle) > s.tibia_clearance_mm else (near, middle)
        return PolarCurve(self.frame, near * direction, profile)

    def _through_fascia(self, angle_deg: float, beyond_mm: float = 1.0) -> complex:
        """The point `beyond_mm` outside the fascia in the direction angle_deg from the leg centre (a septum's end)."""
        return self._under_fascia(angle_deg, -beyond_mm)

    def _under_fascia(self, angle_deg: float, depth_mm: float) -> complex:
        """The point `depth_mm` inside the fascia in the direction angle_deg from the leg centre."""
        z = np.exp(1j * np.deg2rad(angle_deg))
        return complex((float(self.fascia.radius.evaluate(np.array([z]))[0][0]) - depth_mm) * z)

    def _fat_point(self, angle_deg: float, depth: float = 0.5) -> complex:
        """The point at `depth` (0 skin, 1 fascia) of the subcutaneous fat in the direction angle_deg."""
        z = np.array([np.exp(1j * np.deg2rad(angle_deg))])
        outer, inner = self.skin_inner.radius.evaluate(z)[0][0], self.fascia.radius.evaluate(z)[0][0]
        return complex((outer + depth * (inner - outer)) * z[0])

    def _place_vessels(self, rng: np.random.Generator) -> list[Vessel]:
        s = self.shape
        vessels = [Vessel("great_saphenous", self._fat_point(s.great_saphenous_deg), s.great_saphenous_radius_mm, FAT),
                   Vessel("small_saphenous", self._fat_point(s.small_saphenous_deg), s.small_saphenous_radius_mm, FAT)]
        chord = self.membrane.direction
        across = 1j * chord
        r = s.deep_vein_radius_mm
        # paired veins along the chord with their artery just behind them, in the deep posterior compartment
        for name, fraction, depth, radius in (("posterior_tibial", 0.32, 0.55, r), ("peroneal", 0.78, 0.5, 0.85 * r)):
            middle = self.membrane.start + chord * fraction * self.membrane.length + across * depth * float(
                self.transverse_septum.height(np.array(fraction))[0])
            gap = chord * 1.15 * radius
            vessels += [Vessel(f"{name}_vein_1", middle - gap, radius, MUSCLE),
                        Vessel(f"{name}_vein_2", middle + gap, radius, MUSCLE),
                        Vessel(f"{name}_artery", middle - across * 1.9 * radius, 0.65 * radius, MUSCLE)]
        anterior = self.membrane.point(0.45) + across * 4.0
        vessels += [Vessel("anterior_tibial_vein", anterior, 1.1, MUSCLE),
                    Vessel("anterior_tibial_artery", anterior + chord * 2.4, 0.8, MUSCLE)]
        vessels += self._random_vessels(rng, vessels)
        return vessels

    def _random_vessels(self, rng: np.random.Generator, placed: list[Vessel]) -> list[Vessel]:
        """Small vessels at seeded places: in the fat (perforators, tributaries) and in the superficial posterior
        muscle (soleal and gastrocnemial venous sinuses), clear of the other vessels and of the septa."""
        s = self.shape
        found: list[Vessel] = []
        wanted = ([("fat_vessel", FAT, 0.5, 1.0, number) for number in range(1, s.small_fat_vessels + 1)]
                  + [("muscle_vein", MUSCLE, 1.0, 2.0, number) for number in range(1, s.small_muscle_veins + 1)])
        for name, tissue, smallest, largest, number in wanted:
            for _ in range(200):
                radius = rng.uniform(smallest, largest)
                if tissue == FAT:
                    centre = self._fat_point(rng.uniform(-180.0, 180.0), rng.uniform(0.3, 0.7))
                    fits = (self._fat_depth_mm(centre) > radius + 1.0)
                else:
                    centre = complex(rng.uniform(-45.0, 45.0), rng.uniform(-50.0, -5.0))
                    fits = (self.compartment_at_leg(np.array([centre]))[0] == COMPARTMENTS.index("superficial_posterior")
                            and self._muscle_clearance_mm(np.array([centre]))[0] > radius + 3.0)
                if fits and all(abs(centre - other.centre) > radius + other.radius_mm + 3.0 for other in placed + found):
                    found.append(Vessel(f"{name}_{number}", centre, radius, tissue))
                    break
        return found

    def _fat_depth_mm(self, w: complex) -> float:
        """Distance from a fat point to the nearer of the skin's inner face and the fascia."""
        point = np.array([w])
        return float(min(-self.skin_inner.distance(point)[0], self.fascia.distance(point)[0]))

    def _muscle_clearance_mm(self, w: np.ndarray) -> np.ndarray:
        """Distance from muscle points to the fascia, the bones, the septa and the aponeurosis."""
        return np.min([-self.fascia.distance(w), self.tibia.distance(w), self.fibula.distance(w),
                       *(line.distance(w) for line in self.dark_lines())], axis=0)

    def _front_sign(self) -> float:
        """+1 when the left of the tibia -> fibula chord is the front (the fibula lateral to the tibia)."""
        return float(np.sign((self.fibula.centre - self.tibia.centre).real))

    def septa(self) -> tuple[ArcCurve, ...]:
        """The intermuscular septa, which bound the compartments."""
        return self.membrane, self.transverse_septum, self.anterior_septum, self.posterior_septum

    def dark_lines(self) -> tuple[ArcCurve, ...]:
        """Every dark line drawn in the muscle: the septa and the aponeurosis."""
        return self.septa() + (self.aponeurosis,)

    def _check(self, margin_mm: float = 1.0) -> None:
        """Every part inside its host with room for a mesh: no fat or muscle thinner than about 1 mm."""
        phi = np.linspace(-np.pi, np.pi, 720, endpoint=False)
        if np.min(self.skin_inner.radius(phi) - self.fascia.radius(phi)) < 1.5:
            raise ValueError("the subcutaneous fat is thinner than 1.5 mm somewhere; thicken it")
        for name, bone in (("tibia", self.tibia), ("fibula", self.fibula)):
            if np.max(self.fascia.distance(bone.points())) > -1.5:
                raise ValueError(f"the {name} comes within 1.5 mm of the fascia; move it inwards")
        if np.min(self.fibula.distance(self.tibia.points())) < 5.0:
            raise ValueError("the tibia and the fibula are closer than 5 mm; move the fibula")
        for vessel in self.vessels:
            ring = vessel.centre + vessel.radius_mm * np.exp(1j * np.linspace(-np.pi, np.pi, 48, endpoint=False))
            if vessel.tissue == FAT:
                ok = np.max(self.skin_inner.distance(ring)) < -margin_mm and np.min(self.fascia.distance(ring)) > margin_mm
            else:
                ok = np.min(self._muscle_clearance_mm(ring)) > 0.5 * margin_mm
            if not ok:
                raise ValueError(f"the {vessel.name} does not sit inside its tissue; move it or shrink it")

    # -- queries at points ----------------------------------------------------

    def labels_at(self, x, y, compartments: bool = False) -> np.ndarray:
        """Case labels at image points (mm): 0 background, 1 fat (skin included), 2 muscle, 3 bone; with
        compartments the muscle is 4 + its index in COMPARTMENTS. Veins and septa count as their tissue."""
        w = self.frame.to_leg(x, y)
        labels = np.zeros(w.shape, np.uint8)
        leg = self.skin.excess(w) < 0
        inner = w[leg]
        muscle = self.fascia.excess(inner) < 0
        bone = (self.tibia.excess(inner) < 0) | (self.fibula.excess(inner) < 0)
        tissue = np.where(bone, BONE, np.where(muscle, MUSCLE, FAT)).astype(np.uint8)
        if compartments:
            in_muscle = tissue == MUSCLE
            tissue[in_muscle] = FIRST_COMPARTMENT_LABEL + self.compartment_at_leg(inner[in_muscle])
        labels[leg] = tissue
        return labels

    def compartment_at(self, x, y) -> np.ndarray:
        """Index in COMPARTMENTS of image points assumed to be in the muscle."""
        return self.compartment_at_leg(self.frame.to_leg(x, y))

    def compartment_at_leg(self, w: np.ndarray) -> np.ndarray:
        """Index in COMPARTMENTS of leg-frame points assumed to be in the muscle: lateral between the two
        fibular septa, deep posterior between the interosseous membrane and the transverse septum, anterior in
        front of the membrane, lateral to the tibia's crest and on the tibia's side of the anterior septum,
        superficial posterior the rest (with the thin muscle over the tibia's medial face)."""
        w = np.asarray(w, complex)
        lateral_reference = self.fibula.centre + 10.0 * np.exp(1j * np.angle(
            (self.anterior_septum.direction + self.posterior_septum.direction) / 2.0))
        lateral = ((self.anterior_septum.side(w) * self.anterior_septum.side(lateral_reference) > 0)
                   & (self.posterior_septum.side(w) * self.posterior_septum.side(lateral_reference) > 0))
        front = self._front_sign()
        s, _ = self.membrane.chord_coordinates(w)
        in_front = front * self.membrane.side(w) > 0
        deep = (s > 0) & (s < 1) & ~in_front & (front * self.transverse_septum.side(w) > 0)
        beside_crest = ((w - self.tibia.centre) / self.crest_direction).imag
        lateral_of_crest = beside_crest * ((self.fibula.centre - self.tibia.centre) / self.crest_direction).imag > 0
        tibial_side_of_septum = self.anterior_septum.side(w) * self.anterior_septum.side(self.tibia.centre) > 0
        anterior = in_front & lateral_of_crest & tibial_side_of_septum
        index = np.where(lateral, 1, np.where(anterior, 0, np.where(deep, 2, 3)))
        return index.astype(np.uint8)

    def boundaries(self, vertices: int = 720) -> dict[str, np.ndarray]:
        """Closed polygons (N, 2) in mm, image frame: skin, fascia, tibia, fibula and their marrow."""
        return {"skin": self.skin.polygon(vertices), "fascia": self.fascia.polygon(vertices),
                "tibia": self.tibia.polygon(vertices // 2), "fibula": self.fibula.polygon(vertices // 4),
                "tibia_marrow": self.tibia_marrow.polygon(vertices // 2),
                "fibula_marrow": self.fibula_marrow.polygon(vertices // 4)}

    def vessel(self, name: str) -> Vessel:
        return next(vessel for vessel in self.vessels if vessel.name == name)

    def landmarks(self) -> dict[str, tuple[float, float]]:
        """The five positions of the first paper (section 3.2), mm in the image frame: the fat in front of the
        tibia's subcutaneous face, between the posterior tibial veins, the fascia under the skin's sharpest
        bend (where Laplace's law puts the garment's highest pressure), the two saphenous veins."""
        phi = np.linspace(-np.pi, np.pi, 1440, endpoint=False)
        r, slope = self.skin.radius.evaluate(np.exp(1j * phi))
        curvature_slope = np.gradient(slope, phi)
        curvature = (r ** 2 + 2 * slope ** 2 - r * curvature_slope) / (r ** 2 + slope ** 2) ** 1.5
        sharpest = np.exp(1j * phi[np.argmax(curvature)])
        points = {"hypodermis_tibia": self._fat_point(self.shape.tibia_deg),
                  "deep_veins": (self.vessel("posterior_tibial_vein_1").centre + self.vessel("posterior_tibial_vein_2").centre) / 2,
                  "max_pressure": self.fascia.radius.evaluate(np.array([sharpest]))[0][0] * sharpest,
                  "great_saphenous": self.vessel("great_saphenous").centre,
                  "small_saphenous": self.vessel("small_saphenous").centre}
        return {name: tuple(float(v) for v in self.frame.to_image(points[name])) for name in LANDMARK_NAMES}
