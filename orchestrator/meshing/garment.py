"""The compression garment as an explicit hyperelastic band around a leg mesh (Bouten and Drapier sec. 2.5, Fig. 2).

The band is a thin ring of CPE3/CPE6 elements (the order of the leg mesh), `n_through` elements
through its thickness t, whose NATURAL (stress-free) inner contour is the skin contour scaled down
about the skin's area centroid c by 1/stretch: X_in = c + (X_skin - c) / stretch, the outer contour
offset by t along the outward normal. Where the skin is concave the natural contour bridges the
pocket instead, on a shallow outward arc over the skin's convex-hull chord: a band dented inwards is an arch under
external pressure once wrapped and snaps through; a real garment, a tube, does not follow the pockets either.
Stretched back over the undeformed skin, its hoop stretch is `stretch`, and band station I lies on skin node I
(outside the pockets).
The deck (templates/leg_garment.inp.j2) puts it on as the second paper does (Fig. 2): inflated clear of the
skin with the contact pair removed, then the contact pair added (penalty, optional Coulomb friction) and the
inflation pressure released, so that the band closes onto the leg with no initial overclosure.

Band material: CalculiX NEO HOOKE, W = C10 (I1bar - 3) + (J - 1)^2 / D1, Cauchy stress
    sigma = (2 C10 / J) dev(bbar) + (2 / D1) (J - 1) I,  bbar = J^(-2/3) b,
with D1 from a chosen Poisson ratio nu (mu = 2 C10, K = 2 mu (1 + nu) / (3 (1 - 2 nu)), D1 = 2 / K).
In the band (plane strain, free faces), the hoop stretch l1, the thickness stretch l2 (solved from
sigma_22 = 0), l3 = 1; the hoop force per unit length along the leg is
    T = sigma_11 t l2,
linear in C10 at fixed nu. In the incompressible limit l2 = 1 / l1 and T = 2 C10 t (l1 - l1^-3).
C10 is chosen so that T(stretch) equals the requested tension (0.16 N/mm by default, the first
paper's garment; with stretch 1.15, t = 0.5 mm and nu = 0.4: C10 = 0.35 MPa, E = 6 C10 (1 + nu) / 3
= 1.9 MPa). Once on the leg the tissue yields, the band shortens a little and its tension falls
below the design value; the contact pressure then follows Laplace's law p = T / r (Avril et al.
eq. 1) where the band touches convex skin and the band bridges concave stretches.

Inflation. A membrane under internal pressure p rounds out to a circle: the inflated band is a circle of
inner radius R = max |X_skin - c| + clearance about c, hoop stretch l = 2 pi R / P_natural (P_natural the
natural inner perimeter), held by p = T(l) / R (the ring's Laplace law: half the ring carries 2 T against
2 p R). dp/dl must stay positive (the neo-Hookean ring has a pressure limit 2 C10 t / R_natural in the
incompressible case); `garment_band` refuses a clearance past it. The deck does not reach that circle by
ramping p: the natural ring, not round and without tension, has near-zero stiffness against inextensional
bending (the five smallest tangent eigenvalues of the dented leg's band are 1e-8..1e-6 against moduli of
order 1), so under pressure alone Newton has no stiffness to work with and stalls (dented leg: no
convergence down to dt = 2.4e-4). Step 1 prescribes every band node instead (`inflated_ring`: uniform hoop
stretch, station I at the arc-length fraction s_I of the circle; rows through the thickness at the thickness
stretch of a free band) while p is ramped up as a mere reaction; step 2 lets the band go, and p alone holds
it round: a ring in tension is stiff against inextensional bending (geometric stiffness (n^2 - 1) T / R^2
per unit length for the n-lobed mode), and the only imbalance is
what uniform stretch leaves out (bending, the hoop stretch varying through the thickness): 3 Newton
iterations.

Rigid-body pins. While the band is free (steps 2 and 3, until it touches) it is held by three statically
determinate constraints at their inflated displacements: u_x at its top-most and bottom-most inner nodes
(GARMENT_PIN_X) and u_y at its right-most inner node (GARMENT_PIN_Y) (a pin pair u_x at the top and u_y at
the right alone would leave a rotation free). The loads on the free band (follower pressure on a closed
contour) are self-equilibrated, so their reactions are zero. Once the band is wrapped on the clamped leg,
the contact holds its translations and only its sliding around the leg is free: the three pins are then
statically indeterminate and carry tangential forces, each a jump in the hoop force (measured: 7e-3 and
9.5e-3 N/mm, jumps of up to 6.5% of T at the GARMENT_PIN_X nodes). Step 4 therefore releases GARMENT_PIN_X
and keeps GARMENT_PIN_Y alone against sliding, whose reaction is then 2e-6 N/mm.
The pins hold their tangential components (u_x at the top and bottom, u_y at the right) from the inflated circle
on, so the circle is turned and shifted rigidly (`_place_on_design_wrap`) until those components are the ones of
the design wrap, band station I on skin node I: the pins then impose no slide. Without it they held the band
0.2-0.5 mm round from where it wraps, by an amount that depends on which nodes of a mesh are extremal; without
friction the band slid back once released, but friction locked the offset in as a twist, and the tissue's
displacement under the band with mu = 0.3 differed by 33 um RMS between a 1,100- and an 8,000-element leg (16 um
once placed; 13 um without friction; benchmarks/friction_convergence.py).

Positions are in mm in the image frame; elements are counter-clockwise in deck coordinates (see
mesh.py); GARMENT_IN are the band's inner faces, ordinary outward faces of the band, as calfit-fe
requires of a master surface.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import brentq, least_squares
from scipy.spatial import ConvexHull

from .mesh import Mesh, _id_lines, signed_areas

DEFAULT_TENSION_N_PER_MM = 0.16
DEFAULT_THICKNESS_MM = 0.5
DEFAULT_STRETCH = 1.15
DEFAULT_POISSON = 0.4
DEFAULT_N_THROUGH = 1  # one T6 element through the thickness bends quadratically; more only slow Newton down
DEFAULT_CLEARANCE_FRACTION = 0.05
BAND_SECTORS = 24   # 15-degree sectors of the band for a prestretch that varies around the leg (`sector_sets`)


def neo_hooke_D1(C10: float, poisson: float) -> float:
    """CalculiX D1 of a neo-Hookean solid with shear modulus 2 C10 and small-strain Poisson ratio nu."""
    mu = 2.0 * C10
    bulk = 2.0 * mu * (1.0 + poisson) / (3.0 * (1.0 - 2.0 * poisson))
    return 2.0 / bulk


def _plane_strain_stress(C10: float, D1: float, l1: float, l2: float) -> tuple[float, float]:
    """Cauchy sigma_11, sigma_22 of the CalculiX neo-Hookean solid at stretches (l1, l2, 1)."""
    J = l1 * l2
    b_bar = np.array([l1**2, l2**2, 1.0]) * J ** (-2.0 / 3.0)
    deviator = b_bar - b_bar.sum() / 3.0
    volumetric = 2.0 / D1 * (J - 1.0)
    sigma = 2.0 * C10 / J * deviator + volumetric
    return float(sigma[0]), float(sigma[1])


def band_thickness_stretch(C10: float, D1: float, hoop_stretch: float) -> float:
    """Thickness stretch l2 of a plane-strain band at hoop stretch l1, free through its thickness
    (sigma_22 = 0)."""
    return brentq(lambda l2: _plane_strain_stress(C10, D1, hoop_stretch, l2)[1], 0.05, 2.0, xtol=1e-14)


def band_hoop_tension(C10: float, D1: float, hoop_stretch: float, thickness_mm: float) -> float:
    """Hoop force per unit length T = sigma_11 t l2 (N/mm) of a plane-strain band at hoop stretch l1,
    free through its thickness (sigma_22 = 0 fixes the thickness stretch l2)."""
    l2 = band_thickness_stretch(C10, D1, hoop_stretch)
    return _plane_strain_stress(C10, D1, hoop_stretch, l2)[0] * thickness_mm * l2


def band_constants_for_tension(tension_N_per_mm: float, hoop_stretch: float, thickness_mm: float,
                               poisson: float = DEFAULT_POISSON) -> tuple[float, float]:
    """(C10, D1) in MPa, 1/MPa of the band that carries `tension_N_per_mm` at `hoop_stretch` (T is
    linear in C10 when nu is fixed: C10 = T / T(C10 = 1))."""
    if not hoop_stretch > 1.0:
        raise ValueError(f"the garment's design stretch must exceed 1, got {hoop_stretch}")
    unit = band_hoop_tension(1.0, neo_hooke_D1(1.0, poisson), hoop_stretch, thickness_mm)
    C10 = tension_N_per_mm / unit
    return C10, neo_hooke_D1(C10, poisson)


@dataclass
class GarmentBand:
    """The band around one leg mesh. Indices are 0-based and local to the band; in the deck, band
    nodes and elements follow the leg's (offsets `len(leg.nodes)`, `len(leg.elements)`).

    nodes            (n, 2) natural positions, mm
    elements         (m, 3|6) counter-clockwise
    inner_faces      (k, 2) (element, face 1..3) of the inner surface GARMENT_IN
    station_elements (n_around, 2 n_through) the elements between corner stations i and i+1
    inner_corners, outer_corners  (n_around,) corner nodes on the inner / outer contour
    node_sets        GARMENT_PIN_X, GARMENT_PIN_Y, GARMENT_INNER (every node of the inner contour)
    inflated_nodes   (n, 2) positions on the inflated circle (deck step 1, `inflated_ring`)
    """

    nodes: np.ndarray
    elements: np.ndarray
    inner_faces: np.ndarray
    station_elements: np.ndarray
    inner_corners: np.ndarray
    outer_corners: np.ndarray
    node_sets: dict[str, np.ndarray]
    C10: float
    D1: float
    thickness_mm: float
    design_stretch: float
    design_tension_N_per_mm: float
    inflation_pressure_MPa: float
    inflated_radius_mm: float
    inflated_nodes: np.ndarray
    centroid: np.ndarray

    @property
    def element_type(self) -> str:
        return "CPE3" if self.elements.shape[1] == 3 else "CPE6"

    def at_tension(self, tension_N_per_mm: float) -> "GarmentBand":
        """The same band (natural shape, mesh, design stretch) made of a fabric that carries `tension_N_per_mm` at
        the design stretch: C10 scaled by the ratio of tensions (T is linear in C10 at a fixed Poisson ratio,
        `band_hoop_tension`, D1 going as 1 / C10; the inflated ring's holding pressure with it, its shape not).
        How a garment tension known to +-10 % (Avril et al. Table 4), or a second sock, is put on the band: the
        fabric's stiffness is what differs, not the size it was knitted to."""
        if not tension_N_per_mm > 0.0:
            raise ValueError(f"a garment tension must be > 0 N/mm, not {tension_N_per_mm}")
        ratio = tension_N_per_mm / self.design_tension_N_per_mm
        return replace(self, C10=self.C10 * ratio, D1=self.D1 / ratio, design_tension_N_per_mm=tension_N_per_mm,
                       inflation_pressure_MPa=self.inflation_pressure_MPa * ratio)

    def sector_sets(self, count: int = BAND_SECTORS) -> dict[str, tuple[np.ndarray, float]]:
        """The band's elements in `count` equal sectors around its centroid: name GARMENT_Skk -> (0-based local
        elements, the sector's middle angle in radians, counter-clockwise on the image from its +x axis, y up),
        by each element's natural centroid. A prestretch that varies around the leg (`effects`, band_profile)
        is a volume change per sector."""
        centres = self.nodes[self.elements[:, :3]].mean(axis=1) - self.centroid
        angle = np.mod(np.arctan2(-centres[:, 1], centres[:, 0]), 2.0 * np.pi)
        index = np.minimum((angle / (2.0 * np.pi) * count).astype(int), count - 1)
        return {f"GARMENT_S{k:02d}": (np.flatnonzero(index == k), (k + 0.5) * 2.0 * np.pi / count)
                for k in range(count) if np.any(index == k)}

    def sector_elsets_text(self, leg: Mesh, count: int = BAND_SECTORS) -> str:
        """*ELSET GARMENT_Skk of `sector_sets` with the deck's element ids (after the leg's)."""
        return "".join(f"*ELSET, ELSET={name}\n" + _id_lines(members + 1 + len(leg.elements))
                       for name, (members, _) in self.sector_sets(count).items())

    def include_text(self, leg: Mesh) -> str:
        """The leg's mesh include followed by the band: *NODE (NSET=GARMENT_NODES), *ELEMENT
        (ELSET=GARMENT), the pin node sets and *SURFACE GARMENT_IN; 1-based ids after the leg's."""
        node_offset, element_offset = len(leg.nodes), len(leg.elements)
        out = [leg.include_text(), "** garment band: %d nodes, %d %s elements, natural shape\n"
               % (len(self.nodes), len(self.elements), self.element_type), "*NODE, NSET=GARMENT_NODES\n"]
        ids = np.arange(1, len(self.nodes) + 1) + node_offset
        out.append("".join("%d, %.10g, %.10g\n" % (i, x, y) for i, (x, y) in zip(ids, self.nodes.tolist())))
        out.append(f"*ELEMENT, TYPE={self.element_type}, ELSET=GARMENT\n")
        row_format = "%d" + ", %d" * self.elements.shape[1] + "\n"
        numbered = np.hstack([np.arange(1, len(self.elements) + 1)[:, None] + element_offset,
                              self.elements + 1 + node_offset])
        out.append("".join(row_format % tuple(row) for row in numbered.tolist()))
        for name, members in self.node_sets.items():
            out.append(f"*NSET, NSET={name}\n")
            out.append(_id_lines(np.asarray(members) + 1 + node_offset))
        out.append("*SURFACE, NAME=GARMENT_IN, TYPE=ELEMENT\n")
        out.append("".join("%d, S%d\n" % (e + 1 + element_offset, k) for e, k in self.inner_faces.tolist()))
        return "".join(out)

    def deck_inflation_displacements(self, leg: Mesh) -> list[tuple[int, float, float]]:
        """(1-based deck node id, u_x, u_y) that draw every band node onto the inflated circle (step 1)."""
        u = self.inflated_nodes - self.nodes
        ids = np.arange(1, len(self.nodes) + 1) + len(leg.nodes)
        return [(int(i), float(ux), float(uy)) for i, (ux, uy) in zip(ids, u.tolist())]

    def deck_pins(self, leg: Mesh, names: tuple[str, ...] = ("GARMENT_PIN_X", "GARMENT_PIN_Y")) -> list[tuple[int, int, float]]:
        """(1-based deck node id, dof 1|2, value) of the rigid-body pins GARMENT_PIN_X (dof 1) and
        GARMENT_PIN_Y (dof 2), held at their inflated displacement once the band is let go."""
        u = self.inflated_nodes - self.nodes
        return [(int(n) + 1 + len(leg.nodes), dof, float(u[n, dof - 1]))
                for name, dof in (("GARMENT_PIN_X", 1), ("GARMENT_PIN_Y", 2)) if name in names
                for n in self.node_sets[name]]

    def deck_inner_faces(self, leg: Mesh) -> list[tuple[int, int]]:
        """(1-based deck element id, face number) of GARMENT_IN, for the inflation *DLOAD."""
        return [(int(e) + 1 + len(leg.elements), int(k)) for e, k in self.inner_faces]

    def hoop_tension(self, deformed_nodes: np.ndarray, cell_stress: np.ndarray) -> np.ndarray:
        """Hoop force per unit length at each corner station i (N/mm): the hoop Cauchy stress
        sigma_tt averaged over the elements between stations i and i+1, times the deformed band
        thickness there. deformed_nodes (n, 2) band nodes; cell_stress (m, >=4) band elements,
        components xx, yy, zz, xy."""
        inner, outer = deformed_nodes[self.inner_corners], deformed_nodes[self.outer_corners]
        tangent = np.roll(inner, -1, axis=0) - inner
        tangent /= np.linalg.norm(tangent, axis=1)[:, None]
        mid_inner = 0.5 * (inner + np.roll(inner, -1, axis=0))
        mid_outer = 0.5 * (outer + np.roll(outer, -1, axis=0))
        normal = np.column_stack([tangent[:, 1], -tangent[:, 0]])
        thickness = np.abs(np.einsum("ij,ij->i", mid_outer - mid_inner, normal))
        s = cell_stress[self.station_elements]  # (n_around, 2 n_through, 6)
        tx, ty = tangent[:, 0][:, None], tangent[:, 1][:, None]
        s_tt = s[..., 0] * tx**2 + s[..., 1] * ty**2 + 2.0 * s[..., 3] * tx * ty
        return s_tt.mean(axis=1) * thickness


def polygon_centroid(points: np.ndarray) -> np.ndarray:
    """Area centroid of a closed polygon."""
    x, y = points[:, 0], points[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2.0
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)


def convex_hull_contour(loop: np.ndarray) -> np.ndarray:
    """The counter-clockwise closed loop with each concave pocket bridged: the points between two
    consecutive convex-hull vertices move onto a shallow outward arc (parabola of sagitta s) over
    the hull chord, spaced as along the pocket. s starts at L^2 / (8 R) (a circle of the loop's
    mean radius R over the chord L) and is halved until the contour turns left at every point.
    A flat chord would carry no tension under the inflation pressure (a membrane resists transverse
    load through its curvature only), which Newton cannot start from. Convex loops come back unchanged."""
    hull = np.sort(ConvexHull(loop).vertices)
    centre = polygon_centroid(loop)
    mean_radius = float(np.linalg.norm(loop - centre, axis=1).mean())
    out = loop.copy()
    for start, stop in zip(hull, np.roll(hull, -1)):
        pocket = np.arange(start, stop + (len(loop) if stop <= start else 0) + 1) % len(loop)
        if len(pocket) <= 2:
            continue
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop[pocket], axis=0), axis=1))])
        share = (arc / arc[-1])[:, None]
        chord = loop[stop] - loop[start]
        length = float(np.linalg.norm(chord))
        outward = np.array([chord[1], -chord[0]]) / length
        sagitta = length**2 / (8.0 * mean_radius)
        for _ in range(12):
            out[pocket] = loop[start] + share * chord + 4.0 * sagitta * share * (1.0 - share) * outward
            if _turns_left(out, pocket):
                break
            sagitta *= 0.5
    return out


def _turns_left(loop: np.ndarray, pocket: np.ndarray) -> bool:
    """Whether the loop turns left (cross product >= 0) at the pocket's points and their neighbours."""
    around = np.unique(np.concatenate([pocket - 1, pocket, pocket + 1]) % len(loop))
    before, after = loop[around] - loop[around - 1], loop[(around + 1) % len(loop)] - loop[around]
    return bool(np.all(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0] >= 0.0))


def garment_band(leg: Mesh, tension_N_per_mm: float = DEFAULT_TENSION_N_PER_MM,
                 thickness_mm: float = DEFAULT_THICKNESS_MM, stretch: float = DEFAULT_STRETCH,
                 n_through: int = DEFAULT_N_THROUGH, poisson: float = DEFAULT_POISSON,
                 clearance_mm: float | None = None) -> GarmentBand:
    """The band around `leg`'s skin, one corner station per skin corner node, its constants chosen to
    carry `tension_N_per_mm` at hoop stretch `stretch` (module docstring), and the inflation
    pressure that rounds it out to a circle clearing the skin by `clearance_mm` (default: 5% of
    the largest skin radius) about the skin centroid, and every node's position on that circle."""
    if len(leg.skin_loop) == 0:
        raise ValueError("the leg mesh has no skin loop to wrap the garment around")
    if n_through < 1 or thickness_mm <= 0.0:
        raise ValueError("the band needs n_through >= 1 elements through a positive thickness")
    order = leg.order
    skin = leg.nodes[leg.skin_loop]  # counter-clockwise in deck coordinates, corner first
    corners = skin[::order]
    centroid = polygon_centroid(corners)
    n_around = len(corners)

    # Natural inner contour (corners, and T6 mid-side stations on the straight natural edges).
    inner = centroid + (convex_hull_contour(corners) - centroid) / stretch
    if order == 2:
        stations = np.empty((2 * n_around, 2))
        stations[0::2] = inner
        stations[1::2] = 0.5 * (inner + np.roll(inner, -1, axis=0))
    else:
        stations = inner
    n_stations = len(stations)
    # Outward normal at each station: counter-clockwise loop, so the normal of direction (tx, ty)
    # is (ty, -tx); average of the two adjacent segments.
    segment = np.roll(stations, -1, axis=0) - stations
    segment /= np.linalg.norm(segment, axis=1)[:, None]
    seg_normal = np.column_stack([segment[:, 1], -segment[:, 0]])
    normal = seg_normal + np.roll(seg_normal, 1, axis=0)
    normal /= np.linalg.norm(normal, axis=1)[:, None]

    n_layers = order * n_through + 1  # node rows through the thickness
    depth = np.linspace(0.0, thickness_mm, n_layers)
    nodes = (stations[None, :, :] + depth[:, None, None] * normal[None, :, :]).reshape(-1, 2)

    def node(I, J):  # station I (wrapping), row J
        return J * n_stations + I % n_stations

    elements, inner_faces, station_elements = [], [], [[] for _ in range(n_around)]
    for i in range(n_around):
        for j in range(n_through):
            I, J = order * i, order * j
            a, b, c, d = node(I, J), node(I + order, J), node(I + order, J + order), node(I, J + order)
            if order == 1:
                first, second = [a, c, b], [a, d, c]
            else:
                first = [a, c, b, node(I + 1, J + 1), node(I + 2, J + 1), node(I + 1, J)]
                second = [a, d, c, node(I, J + 1), node(I + 1, J + 2), node(I + 1, J + 1)]
            if j == 0:
                inner_faces.append((len(elements), 3))  # face 3 of (a, c, b) runs b -> a on the inner contour
            station_elements[i] += [len(elements), len(elements) + 1]
            elements += [first, second]
    elements = np.asarray(elements, dtype=np.int64)
    if np.any(signed_areas(nodes, elements) <= 0.0):
        raise ValueError("the natural band has inverted elements: the skin contour folds within one band thickness")

    inner_corners = np.array([node(order * i, 0) for i in range(n_around)])
    outer_corners = np.array([node(order * i, n_layers - 1) for i in range(n_around)])
    inner_xy = nodes[inner_corners]
    pins_x = np.unique([inner_corners[np.argmin(inner_xy[:, 1])], inner_corners[np.argmax(inner_xy[:, 1])]])
    pin_y = np.array([inner_corners[np.argmax(inner_xy[:, 0])]])

    C10, D1 = band_constants_for_tension(tension_N_per_mm, stretch, thickness_mm, poisson)
    radius_max = float(np.linalg.norm(corners - centroid, axis=1).max())
    clearance = DEFAULT_CLEARANCE_FRACTION * radius_max if clearance_mm is None else clearance_mm
    inflated_radius = radius_max + clearance
    natural_perimeter = float(np.linalg.norm(np.roll(inner, -1, axis=0) - inner, axis=1).sum())
    inflated_stretch = 2.0 * np.pi * inflated_radius / natural_perimeter

    def ring_pressure(hoop_stretch):
        return band_hoop_tension(C10, D1, hoop_stretch, thickness_mm) / (hoop_stretch * natural_perimeter / (2 * np.pi))

    if ring_pressure(1.02 * inflated_stretch) <= ring_pressure(inflated_stretch):
        raise ValueError(f"inflating the band to radius {inflated_radius:.1f} mm passes its pressure limit; "
                         "ask for a smaller clearance or a larger design stretch")
    inflated_nodes = inflated_ring(stations, depth, centroid, inflated_radius,
                                   band_thickness_stretch(C10, D1, inflated_stretch)).reshape(-1, 2)
    design = {k: corners[i] for i, k in enumerate(inner_corners)}   # band station I on skin corner I
    inflated_nodes = _place_on_design_wrap(inflated_nodes, centroid, [(k, 0, design[k][0]) for k in pins_x]
                                           + [(k, 1, design[k][1]) for k in pin_y])
    return GarmentBand(
        nodes=nodes, elements=elements, inner_faces=np.asarray(inner_faces, dtype=np.int64),
        station_elements=np.asarray(station_elements, dtype=np.int64), inner_corners=inner_corners,
        outer_corners=outer_corners,
        node_sets={"GARMENT_PIN_X": pins_x, "GARMENT_PIN_Y": pin_y, "GARMENT_INNER": np.arange(n_stations)},
        C10=C10, D1=D1, thickness_mm=thickness_mm, design_stretch=stretch, design_tension_N_per_mm=tension_N_per_mm,
        inflation_pressure_MPa=float(ring_pressure(inflated_stretch)), inflated_radius_mm=inflated_radius,
        inflated_nodes=inflated_nodes, centroid=centroid)


def _place_on_design_wrap(positions: np.ndarray, centre: np.ndarray,
                          pinned: list[tuple[int, int, float]]) -> np.ndarray:
    """positions turned about centre by phi and shifted by t, (phi, t) such that each pinned (node, component,
    value) holds value (module text: the pins' tangential components at the design wrap). Least squares from no
    motion: with one x pin (top and bottom the same node) the placement is not unique, and a small one is taken."""
    def moved(p):
        rotation = np.array([[np.cos(p[0]), -np.sin(p[0])], [np.sin(p[0]), np.cos(p[0])]])
        return centre + (positions - centre) @ rotation.T + p[1:]

    def mismatch(p):
        placed = moved(p)
        return [placed[node, component] - value for node, component, value in pinned]

    solution = least_squares(mismatch, np.zeros(3), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return moved(solution.x)


def inflated_ring(stations: np.ndarray, depth: np.ndarray, centre: np.ndarray, radius: float,
                  thickness_stretch: float) -> np.ndarray:
    """Positions (n_rows, n_stations, 2) of the band's nodes drawn onto a circle: the inner contour on
    the circle of `radius` about `centre`, station I at the polar angle theta_0 + 2 pi s_I, s_I its
    arc-length fraction along the natural inner contour (a uniform hoop stretch, the state of an
    inflated frictionless ring, Laplace's law with one T and one r); row J at radius
    radius + depth_J thickness_stretch along the radial direction. theta_0 is the circular mean of
    (polar angle of station I) - 2 pi s_I, so that the stations move about radially and the ring is
    not turned as a whole."""
    closed = np.vstack([stations, stations[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    share = arc[:-1] / arc[-1]
    polar = np.arctan2(stations[:, 1] - centre[1], stations[:, 0] - centre[0])
    theta_0 = np.angle(np.exp(1j * (polar - 2.0 * np.pi * share)).sum())
    theta = theta_0 + 2.0 * np.pi * share
    radial = np.column_stack([np.cos(theta), np.sin(theta)])
    return centre + (radius + thickness_stretch * depth)[:, None, None] * radial[None, :, :]
