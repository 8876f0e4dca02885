"""What the explicit garment band does on the leg, read from one solved deck: its contact pressure, shear, status
and slip around the skin, where it bridges, and its hoop force (the second paper's band, Bouten and Drapier
sec. 2.5).

The engine writes at every skin node (the contact's slave nodes, `decks.leg_garment_deck`): the contact pressure
p_N and shear t_T (MPa), the contact status as Abaqus's CSTATUS (0 open, 1 sticking, 2 slipping; frictionless
contact slips) and the slip, the skin's tangential motion over the band since it first touched it (mm; tracked
with friction, 0 without). The band's hoop force per unit length is its elements' hoop stress times their
thickness (`GarmentBand.hoop_tension`).

An arc of open skin nodes between two in contact is where the band bridges a hollow of the skin (beside the tibial
crest, a flat or concave calf): the band runs straight over it and presses nothing there. Each bridge is reported
with its angles, its length along the skin and how far the band stands off the skin (each open node's distance to
the deformed inner surface of the band).

The check that ties the two outputs together is the band's equilibrium: frictionless, the hoop force T is the same
all around and the band turns by 2 pi in total, through its contact only (it runs straight over a bridge), so the
line integral of the contact pressure around the skin is 2 pi T (Laplace's law p = T / r summed over the contact,
Avril et al. eq. 1). With friction, T varies along the band by the shear it passes to the skin (dT/ds = -t_T), and
the same integral holds with T's mean weighted by the band's turning.

Angles are the display angles of `regions.LegFrame` (counter-clockwise from the image's +x axis about the leg's
centre, 90 deg at the top of the picture), of the skin nodes' positions in I0.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..core.units import KPA_PER_MPA
from .regions import LegFrame

OPEN, STICKING, SLIPPING = 0, 1, 2   # Abaqus's CSTATUS, as the engine writes it (contact_status)
STATUS_NAMES = {OPEN: "open", STICKING: "sticking", SLIPPING: "slipping"}


@dataclass(frozen=True)
class Bridge:
    """An arc of skin that the band spans without touching it."""

    start_deg: float      # display angles of the touching nodes on either side, in the skin loop's order
    end_deg: float
    length_mm: float      # deformed skin length between them
    max_gap_mm: float     # the farthest the band stands off the skin on it
    direction: str        # anatomical direction of its middle (`LegFrame.direction`)


@dataclass
class BandState:
    """The band on the leg at one solved state, skin nodes in the skin loop's order (module text)."""

    angle_deg: np.ndarray            # display angle of each skin node in I0
    perimeter_mm: float              # deformed skin perimeter
    pressure_kPa: np.ndarray         # p_N >= 0
    shear_kPa: np.ndarray            # t_T on the skin, signed along the band's tangent (the engine's)
    status: np.ndarray               # OPEN, STICKING or SLIPPING
    slip_mm: np.ndarray              # tangential motion over the band since the first touch (friction only)
    gap_mm: np.ndarray               # distance to the band's inner surface where open, 0 in contact
    station_angle_deg: np.ndarray    # the band's stations (between consecutive inner corners)
    hoop_tension_N_per_mm: np.ndarray
    friction_mu: float
    bridges: list[Bridge]
    weight_mm: np.ndarray            # each node's weight in a line integral along the deformed skin
    order: int                       # of the skin's faces: 1 (corner nodes) or 2 (corner, mid-side, corner)

    @property
    def contact_force_N_per_mm(self) -> float:
        """The line integral of the contact pressure around the skin (N per mm of slice)."""
        return float(np.sum(self.weight_mm * self.pressure_kPa) / KPA_PER_MPA)

    def face_means(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(display angle of each skin face's middle, the face's mean of a nodal field): Simpson's mean on quadratic
        faces, whose corner and mid-side nodal tractions zigzag around it (`_skin_weights`), the two nodes' mean on
        linear ones."""
        if self.order == 1:
            direction = np.exp(1j * np.radians(self.angle_deg))
            return (np.degrees(np.angle(direction + np.roll(direction, -1))) % 360.0,
                    0.5 * (values + np.roll(values, -1)))
        return self.angle_deg[1::2], (values[0::2] + 4.0 * values[1::2] + np.roll(values[0::2], -1)) / 6.0

    def share(self, status: int) -> float:
        """The share of the skin's length in this contact status."""
        return float(np.sum(self.weight_mm[self.status == status]) / self.perimeter_mm)

    def as_dict(self) -> dict:
        """The band's summary and its profiles around the leg (pressures.json "band")."""
        in_contact = self.status != OPEN
        face_angle, face_pressure = self.face_means(self.pressure_kPa)
        return {
            "friction_mu": self.friction_mu,
            "contact_pressure_kPa": {"mean": self.contact_force_N_per_mm * KPA_PER_MPA / self.perimeter_mm,
                                     "max": float(self.pressure_kPa.max()),
                                     "min_in_contact": float(self.pressure_kPa[in_contact].min())
                                     if in_contact.any() else 0.0},
            "hoop_tension_N_per_mm": {"mean": float(self.hoop_tension_N_per_mm.mean()),
                                      "min": float(self.hoop_tension_N_per_mm.min()),
                                      "max": float(self.hoop_tension_N_per_mm.max())},
            "contact_force_N_per_mm": self.contact_force_N_per_mm,
            "skin_share": {name: self.share(status) for status, name in STATUS_NAMES.items()},
            "max_slip_mm": float(np.abs(self.slip_mm).max()),
            "bridges": [asdict(bridge) for bridge in self.bridges],
            "profile": {"angle_deg": self.angle_deg.tolist(), "pressure_kPa": self.pressure_kPa.tolist(),
                        "shear_kPa": self.shear_kPa.tolist(), "status": self.status.astype(int).tolist(),
                        "slip_mm": self.slip_mm.tolist(), "gap_mm": self.gap_mm.tolist()},
            "faces": {"angle_deg": face_angle.tolist(), "pressure_kPa": face_pressure.tolist(),
                      "shear_kPa": self.face_means(self.shear_kPa)[1].tolist()},
            "stations": {"angle_deg": self.station_angle_deg.tolist(),
                         "hoop_tension_N_per_mm": self.hoop_tension_N_per_mm.tolist()},
        }


def band_state(results, mesh, band, frame: LegFrame, friction_mu: float, step: int | None = None) -> BandState:
    """The band's state at the end of `step` (default the last) of an engine run of the explicit garment's deck
    (`results` an EngineResults; mesh the leg, whose nodes and elements come first in the deck, band its
    `GarmentBand`)."""
    n_leg, m_leg = len(mesh.nodes), len(mesh.elements)
    reference = np.vstack([mesh.nodes, band.nodes])
    deformed = reference + np.asarray(results.point_field("displacement", step), float)[:, :2]
    skin = np.asarray(mesh.skin_loop)
    fields = {name: np.asarray(results.point_field(name, step), float)[skin]
              for name in ("contact_pressure", "contact_shear", "contact_status", "contact_slip")}
    status = np.rint(fields["contact_status"]).astype(int)
    skin_deformed = deformed[skin]
    segment = np.linalg.norm(np.roll(skin_deformed, -1, axis=0) - skin_deformed, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(segment)[:-1]])
    perimeter = float(segment.sum())
    inner = deformed[n_leg + np.asarray(band.inner_corners)]
    gap = np.where(status == OPEN, _distance_to_loop(skin_deformed, inner), 0.0)
    angles = frame.angles_deg(mesh.nodes[skin])
    cell_stress = np.asarray(results.cell_field("cauchy_stress", step), float)[m_leg:]
    tension = band.hoop_tension(deformed[n_leg:], cell_stress)
    stations = 0.5 * (inner + np.roll(inner, -1, axis=0))
    # the stations' angles about the same centre, from where they stand on the leg (the band has no I0 position)
    station_angles = frame.angles_deg(stations)
    return BandState(angles, perimeter, fields["contact_pressure"] * KPA_PER_MPA,
                     fields["contact_shear"] * KPA_PER_MPA, status, fields["contact_slip"], gap, station_angles,
                     tension, float(friction_mu), _bridges(status, angles, arc, perimeter, gap, frame),
                     _skin_weights(segment, mesh.order), int(mesh.order))


def _skin_weights(segment: np.ndarray, order: int) -> np.ndarray:
    """Each skin node's weight in a line integral around the loop (segment i joins nodes i and i + 1): the
    trapezoid rule on linear faces; Simpson's rule on quadratic ones (corner, mid-side, corner: the loop's nodes
    alternate, a corner first), whose corner and mid-side contact pressures the penalty makes err in opposite
    senses (tests/model/test_garment.py), so that only a rule exact for the quadratic face sums them right."""
    if order == 1:
        return 0.5 * (segment + np.roll(segment, 1))
    face = segment[0::2] + segment[1::2]
    weights = np.zeros(len(segment))
    weights[1::2] = 4.0 * face / 6.0
    weights[0::2] = face / 6.0 + np.roll(face, 1) / 6.0
    return weights


def _distance_to_loop(points: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Distance of each point to the closed polyline `loop`."""
    start, end = loop, np.roll(loop, -1, axis=0)
    along = end - start
    relative = points[:, None, :] - start[None, :, :]
    share = np.clip(np.einsum("psk,sk->ps", relative, along) / np.einsum("sk,sk->s", along, along), 0.0, 1.0)
    nearest = start[None] + share[..., None] * along[None]
    return np.linalg.norm(points[:, None, :] - nearest, axis=2).min(axis=1)


def _bridges(status: np.ndarray, angles: np.ndarray, arc: np.ndarray, perimeter: float, gap: np.ndarray,
             frame: LegFrame) -> list[Bridge]:
    """The runs of open skin nodes between touching ones, around the closed skin loop."""
    touching = np.flatnonzero(status != OPEN)
    if touching.size == 0:
        return []
    bridges = []
    n = len(status)
    for before, after in zip(touching, np.roll(touching, -1)):
        span = (after - before) % n if touching.size > 1 else n
        if span <= 1:
            continue
        inside = (before + np.arange(1, span)) % n
        length = (arc[after] - arc[before]) % perimeter if span < n else perimeter
        middle = float(angles[inside[len(inside) // 2]])
        bridges.append(Bridge(float(angles[before]), float(angles[after]), float(length), float(gap[inside].max()),
                              frame.direction(middle)))
    return bridges
