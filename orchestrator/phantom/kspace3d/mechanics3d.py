"""The truth of the k-space phantom, solved in 3D by CalculiX: the leg segment under the garment.

Mesh. The reference section's exact labels (`leg3d.Leg3D`, sampled at 0.1 mm) are meshed by calfit's own mesher
(`meshing.mesh_from_labels`, quadratic triangles, bones as holes) and the triangles are extruded into quadratic
wedges C3D15 over the segment: node planes at the heights of `Layering` (fine near the imaged slices, growing
geometrically to coarse away from them), a mid plane of vertical mid-edge nodes between each pair, and every
node placed by Phi at its own height, so that the wedges follow the taper, the twist, the drift and the fat's
change of the leg. Nodes, elements and sets go to an include (mesh.inp); the step to a deck rendered from
templates/leg3d_ccx.inp.j2.

Physics, as the first paper's slice but in 3D (Avril et al. 2010 sec. 2.2): every tissue NEO HOOKE,
W = C10 (I1bar - 3) + (J - 1)^2 / D1, with D1 = 1 / Kv (the bulk modulus of `materials`: the same small-strain
response as the Avril law's Kv [(J^2 - 1)/2 - ln J]); deck units MPa = kPa / 1000, mm, N. The bones' surfaces
are clamped (ux = uy = uz = 0). The end faces are held axially (uz = 0, free in their plane): the leg continues
beyond the segment. The garment is a follower pressure (*DLOAD P, which NLGEOM makes follow the face) on every
skin face of the segment, p = T kappa: Laplace's law with kappa the hoop curvature of the skin's cross-section at
that face's height, the EXACT curvature of the leg's analytic outline (`Leg3D.skin_curvature`) averaged over the
face (FACE_POINTS Gauss points along its chord, each taken to the outline along its ray, times LAYER_POINTS across
its layer): the garment of the smooth leg, whatever polygon the mesh makes of it. (It had been the kink curvature
of the mesh's skin polygon, smoothed over 3 mm. The sections calfit's mesher makes from 0.1 mm labels have skin
faces of 1.2-14 mm and corners that Triangle put on a chord when it split a long segment, 0.37 mm inside the
outline: there the kink is 0 where the outline's curvature is 0.0115 / mm. That garment was 7.5 % RMS of the
curvature off the outline's, 46 % at worst, on the default case's section, its displacement 1.2 % RMS of max |u|
(9 % at worst) off the exact garment's, and on calfit's identification of a prismatic case it left a misfit of
2.65 x the noise floor, alpha_unloaded 0.76, C10_muscle -4.2 %; with the exact curvature the same case fits at
0.99 x, alpha 0.97, every constant within 1 %.) calfit-fe's
`*LAPLACE PRESSURE, REFERENCE=1` (solver_cpp/README.md, "Garment pressure") takes kappa from the polygon's kinks,
linear along each face: on a skin sampled at equal steps, as calfit meshes one from images, that is the exact
curvature to 0.9 % RMS (2.2 % at worst) and the displacement to 0.17 % RMS of max |u|; on this phantom's own
sections, with their long faces and chord corners, it is 1.6 % RMS (19 % at worst, next to a chord corner) from
the exact garment's displacement on the default mesh and 0.6 % (11 %) on the fine one, while the exact garment's
own discretization error is 0.24 % (0.16 %) RMS against an 8,000-triangle section.

- garment_law "unloaded": kappa of the undeformed section (a garment designer's p = T kappa0); one solve.
- garment_law "deformed": Avril et al.'s p = T / r with r of the DEFORMED contour, by a fixed point of solves: the
  exact curvature moved by the change of the mid-plane skin polygons' kink curvature from the undeformed to the
  deformed positions (the polygon's own kinks cancel in the change), until no face's pressure changes by more than
  0.5 % of the largest. As an explicit iteration it is unstable at short wavelengths (a bump of wavenumber k changes the
  pressure by T k^2 times its height and the tissue answers by about 1 / (mu k): a gain of T k / mu, over 1 below
  wavelengths of a few tens of mm); so the curvature's CHANGE is averaged along the skin over CHANGE_SMOOTHING_MM
  (the garment's flattening of the leg is of long wavelength) and each solve moves the pressures
  PRESSURE_RELAXATION of the way: 3-5 solves.

Hidden effects (`HiddenEffects3D`), off by default: drainage, an isotropic eigenstrain of the muscle
(*EXPANSION of the muscle's materials with a temperature step 0 -> 1, the linear strain as the coefficient: ccx
applies it as a thermal stretch of the stress-free state, the engine's *VOLUME CHANGE with dv = (1 + e)^3 - 1);
a tension profile T(theta) = T (1 + a cos(theta - theta0)), theta = atan2(y - cy, x - cx) in the image frame
about the leg centre at the face's height (calfit-fe's angle convention, so that a1 = a cos theta0, b1 =
a sin theta0 of the catalog's `tension_profile`); a stiffer muscle compartment or sector (C10 and Kv times a
factor); and bone_motion, the second bone (the fibula) displaced rigidly instead of clamped.

Interpolation (`LegSolution3D.at`): a scanner point (x, y, z) is taken back to its reference point X = Phi^-1
(exact), its triangle and barycentric coordinates found in the reference mesh, its layer and zeta in [-1, 1] from
z (every node of a plane has the plane's height, so z is linear in zeta), and the C3D15 shape functions applied:
the element's own interpolation, up to the difference between Phi and its quadratic interpolation on the wedge.

`plane_strain_difference` solves the reference section with calfit's plane-strain engine (`forward.LegModel`,
neo_hooke tissues, the same triangles) and compares the in-plane nodal displacement of the 3D solution's node
plane at the reference height: under the same face pressures (`*DLOAD`) and under the engine's own Laplace law.
For a prismatic leg with its end faces held axially, 3D is plane strain: the same-load difference is the
discretization's and the solver's: 0.04-0.08 % RMS of max |u| on the default mesh (1,049 triangles x 8 layers,
25,388 nodes, ccx 30-40 s on two cores) and on the fine one (2,083 x 14, 83,620 nodes, 290 s). The tapering leg
departs from plane strain at mid-segment by 0.32 % RMS (0.62 % at most) on both meshes: physics, not mesh.
"""

from __future__ import annotations

import dataclasses
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ...core.frame import pixel_centres_mm
from ...core.units import KPA_PER_MPA
from ...engine.decks import numbers, render
from ...meshing import Mesh, MeshingError, mesh_from_labels
from ...meshing.mesh import ITEMS_PER_SET_LINE
from ..geometry import COMPARTMENTS, FIRST_COMPARTMENT_LABEL
from .ccx import DEFAULT_TIMEOUT_S, CcxError, CcxRun, run_ccx
from .leg3d import Leg3D

LEG_PARAMETERS = ("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle")
GARMENT_LAWS = ("unloaded", "deformed")
LABEL_SAMPLE_MM = 0.1                 # the reference labels are meshed from this grid
DEFAULT_SECTION_ELEMENTS = 1000       # triangles of the default section (fast: one solve well under 90 s)
FINE_SECTION_ELEMENTS = 2000
SECTION_MESH_ATTEMPTS = 3
PRESSURE_TOLERANCE = 0.005            # the deformed law's fixed point: largest change / largest pressure
MAX_PRESSURE_UPDATES = 8
PRESSURE_RELAXATION = 0.6             # the deformed law's fixed point moves this share of the way per solve
CHANGE_SMOOTHING_MM = 8.0             # the deformed law's change of curvature averaged along the skin over this
FACE_POINTS = 4                       # Gauss points along a skin face for its mean pressure
LAYER_POINTS = 3                      # and across a layer
CANDIDATES = 8                         # nearest triangle centroids searched for the triangle of a point
CHUNK = 200_000                        # points interpolated at once
STATIC = (0.5, 1.0, 1e-3, 0.5)         # two increments at least: ccx's single increment may stop short (README)
# Wedge faces of the extruded triangle's faces 1..3 (corner k to k + 1): ccx's C3D15 faces 3, 4, 5
WEDGE_FACE_OF_TRIANGLE_FACE = 2


@dataclass(frozen=True)
class Layering:
    """The node planes along the segment: layers of `fine_mm` over the band around the imaged heights, then
    growing by `growth` per layer up to `coarse_mm` towards the ends (the displacement varies over tens of mm
    along the leg, and the wedges are quadratic in z)."""

    bottom_mm: float = 0.0
    top_mm: float = 140.0
    fine_mm: float = 8.0
    coarse_mm: float = 30.0
    growth: float = 1.6

    def heights(self, focus_mm: Sequence[float], band_mm: float, anchor_mm: float | None = None) -> np.ndarray:
        """Node-plane heights: the fine band [min(focus) - band, max(focus) + band] (clipped to the segment), its
        planes on a grid through anchor_mm (e.g. the reference height, so that one plane is the reference
        section), and the graded layers beyond."""
        if not self.bottom_mm < self.top_mm:
            raise ValueError(f"the segment's bottom {self.bottom_mm} mm must lie below its top {self.top_mm} mm")
        focus = np.asarray(focus_mm, float)
        low = max(self.bottom_mm, float(focus.min()) - band_mm)
        high = min(self.top_mm, float(focus.max()) + band_mm)
        anchor = float(np.clip(anchor_mm if anchor_mm is not None else low, low, high))
        below = anchor - self.fine_mm * np.arange(int(np.ceil((anchor - low) / self.fine_mm - 1e-9)) + 1)
        above = anchor + self.fine_mm * np.arange(1, int(np.ceil((high - anchor) / self.fine_mm - 1e-9)) + 1)
        band = np.unique(np.clip(np.concatenate([below, above]), self.bottom_mm, self.top_mm))
        lower = band[0] - np.cumsum(self._graded(band[0] - self.bottom_mm))
        upper = band[-1] + np.cumsum(self._graded(self.top_mm - band[-1]))
        heights = np.unique(np.round(np.concatenate([lower, band, upper]), 9))
        keep = np.concatenate([[True], np.diff(heights) > 0.25 * self.fine_mm])
        return heights[keep]

    def _graded(self, length: float) -> np.ndarray:
        if length <= 0.25 * self.fine_mm:
            return np.zeros(0)
        sizes, size = [], self.fine_mm * self.growth
        while sum(sizes) < length:
            sizes.append(min(size, self.coarse_mm))
            size *= self.growth
        if len(sizes) > 1 and sum(sizes) - length > 0.5 * sizes[-1]:
            sizes.pop()
        return np.asarray(sizes) * length / sum(sizes)


@dataclass(frozen=True)
class HiddenEffects3D:
    """Physics of the truth that the baseline model has not (module text)."""

    muscle_linear_strain: float = 0.0                  # drainage: e of the stretch 1 + e of the stress-free muscle
    tension_amplitude: float = 0.0                     # a of T (1 + a cos(theta - theta0))
    tension_phase_deg: float = 0.0                     # theta0, image frame (calfit-fe's angle)
    stiffer_factor: float = 1.0                        # on C10 and Kv of the stiffer muscle
    stiffer_compartment: str | None = None             # one of geometry.COMPARTMENTS
    stiffer_sector_deg: tuple[float, float] | None = None   # or the muscle within this sector (theta, as above)
    bone_motion_mm: tuple[float, float, float] | None = None   # rigid displacement of the fibula (mm)

    def __post_init__(self):
        if not -0.2 < self.muscle_linear_strain < 0.2:
            raise ValueError(f"the muscle's linear strain {self.muscle_linear_strain} is not a drainage; give one "
                             "between -0.2 and 0.2 (e.g. -0.0116)")
        if not 0.0 <= self.tension_amplitude < 1.0:
            raise ValueError(f"a tension profile's amplitude must lie in [0, 1), got {self.tension_amplitude}")
        if self.stiffer_factor <= 0.0:
            raise ValueError(f"the stiffer muscle's factor must be positive, got {self.stiffer_factor}")
        if self.stiffer_compartment is not None and self.stiffer_compartment not in COMPARTMENTS:
            raise ValueError(f"unknown compartment {self.stiffer_compartment!r}; name one of {', '.join(COMPARTMENTS)}")
        if self.stiffer_factor != 1.0 and (self.stiffer_compartment is None) == (self.stiffer_sector_deg is None):
            raise ValueError("a stiffer muscle needs one of stiffer_compartment and stiffer_sector_deg")

    @property
    def stiffer(self) -> bool:
        return self.stiffer_factor != 1.0

    @classmethod
    def from_dict(cls, effects: dict | None) -> "HiddenEffects3D":
        """From {effect: {parameter: value}}: drainage {muscle_linear_strain}, tension_profile {amplitude,
        phase_deg}, stiffer_muscle {factor, compartment | sector_deg}, bone_motion {ux_BONE2, uy_BONE2[, uz_BONE2]}."""
        values: dict = {}
        for name, parameters in (effects or {}).items():
            p = dict(parameters)
            try:
                if name == "drainage":
                    values["muscle_linear_strain"] = float(p.pop("muscle_linear_strain"))
                elif name == "tension_profile":
                    values["tension_amplitude"] = float(p.pop("amplitude"))
                    values["tension_phase_deg"] = float(p.pop("phase_deg", 0.0))
                elif name == "stiffer_muscle":
                    values["stiffer_factor"] = float(p.pop("factor"))
                    values["stiffer_compartment"] = p.pop("compartment", None)
                    sector = p.pop("sector_deg", None)
                    values["stiffer_sector_deg"] = tuple(map(float, sector)) if sector is not None else None
                elif name == "bone_motion":
                    values["bone_motion_mm"] = (float(p.pop("ux_BONE2")), float(p.pop("uy_BONE2")),
                                                float(p.pop("uz_BONE2", 0.0)))
                else:
                    raise ValueError(f"unknown hidden effect {name!r}; write drainage, tension_profile, stiffer_muscle "
                                     "or bone_motion")
            except KeyError as missing:
                raise ValueError(f"the hidden effect {name!r} needs its parameter {missing}") from None
            if p:
                raise ValueError(f"the hidden effect {name!r} has no parameter {sorted(p)[0]!r}")
        return cls(**values)

    def catalog_form(self) -> dict[str, dict[str, float]]:
        """The effects in the terms of calfit's catalog (`orchestrator.model.effects`) where it has them."""
        out: dict[str, dict] = {}
        if self.muscle_linear_strain:
            out["drainage"] = {"dv_muscle": (1.0 + self.muscle_linear_strain) ** 3 - 1.0}
        if self.tension_amplitude:
            phase = np.deg2rad(self.tension_phase_deg)
            out["tension_profile"] = {"a1": self.tension_amplitude * float(np.cos(phase)),
                                      "b1": self.tension_amplitude * float(np.sin(phase))}
        if self.stiffer:
            out["stiffer_muscle"] = {"factor": self.stiffer_factor, "compartment": self.stiffer_compartment,
                                     "sector_deg": list(self.stiffer_sector_deg) if self.stiffer_sector_deg else None}
        if self.bone_motion_mm is not None:
            out["bone_motion"] = {"ux_BONE2": self.bone_motion_mm[0], "uy_BONE2": self.bone_motion_mm[1]}
        return out


# --- the mesh ----------------------------------------------------------------------------------------------

def section_mesh(leg: Leg3D, field_of_view_mm: tuple[float, float], n_elements: int = DEFAULT_SECTION_ELEMENTS,
                 compartments: bool = False) -> Mesh:
    """The reference section's T6 mesh from its exact labels sampled every LABEL_SAMPLE_MM over the field of view
    (width, height in mm)."""
    shape = (int(np.ceil(field_of_view_mm[1] / LABEL_SAMPLE_MM)), int(np.ceil(field_of_view_mm[0] / LABEL_SAMPLE_MM)))
    x, y = pixel_centres_mm(shape, (LABEL_SAMPLE_MM, LABEL_SAMPLE_MM))
    labels = leg.geometry.labels_at(x, y, compartments=compartments)
    # calfit's mesher places the curves' points for the size asked; where the thin muscle over the tibia makes two
    # curves cross at a coarse size, a somewhat finer one is tried (at most three times)
    for attempt in range(SECTION_MESH_ATTEMPTS):
        try:
            return mesh_from_labels(labels, (LABEL_SAMPLE_MM, LABEL_SAMPLE_MM),
                                    n_elements=int(round(n_elements * 1.25 ** attempt)), order=2)
        except MeshingError as error:
            failure = error
    raise ValueError(f"the reference section could not be meshed with about {n_elements} triangles ({failure}); "
                     "ask for more elements") from failure


@dataclass
class LegMesh3D:
    """The extruded mesh (module text). nodes (n, 3) mm; elements (m, 15) 0-based in ccx's C3D15 order (bottom
    corners, top corners, bottom mid-sides 1-2 2-3 3-1, top mid-sides, vertical mid-edges); element m = layer *
    len(section.elements) + triangle."""

    leg: Leg3D
    section: Mesh
    heights_mm: np.ndarray
    nodes: np.ndarray = field(init=False)
    elements: np.ndarray = field(init=False)

    def __post_init__(self):
        s = self.section
        if s.order != 2:
            raise ValueError("the section mesh must be quadratic (T6) to be extruded into C3D15 wedges")
        self.heights_mm = np.asarray(self.heights_mm, float)
        if len(self.heights_mm) < 2 or np.any(np.diff(self.heights_mm) <= 0):
            raise ValueError("the node planes' heights must be at least two and increasing")
        n2, layers = len(s.nodes), len(self.heights_mm) - 1
        self.corner_nodes = np.unique(s.elements[:, :3])
        corner_rank = np.full(n2, -1)
        corner_rank[self.corner_nodes] = np.arange(len(self.corner_nodes))
        per_layer = n2 + len(self.corner_nodes)
        # plane k's copy of section node a; mid plane k's copy of section corner a
        self.full_index = np.arange(layers + 1)[:, None] * per_layer + np.arange(n2)[None, :]
        self.mid_index = np.full((layers, n2), -1)
        self.mid_index[:, self.corner_nodes] = (np.arange(layers)[:, None] * per_layer + n2
                                                + corner_rank[self.corner_nodes][None, :])
        self.mid_heights_mm = 0.5 * (self.heights_mm[1:] + self.heights_mm[:-1])
        total = (layers + 1) * n2 + layers * len(self.corner_nodes)
        nodes = np.empty((total, 3))
        for k, z in enumerate(self.heights_mm):
            x, y = self.leg.to_scanner(s.nodes[:, 0], s.nodes[:, 1], z)
            nodes[self.full_index[k]] = np.column_stack([x, y, np.full(n2, z)])
        corners = s.nodes[self.corner_nodes]
        for k, z in enumerate(self.mid_heights_mm):
            x, y = self.leg.to_scanner(corners[:, 0], corners[:, 1], z)
            nodes[self.mid_index[k, self.corner_nodes]] = np.column_stack([x, y, np.full(len(corners), z)])
        self.nodes = nodes
        t = s.elements
        blocks = []
        for k in range(layers):
            bottom, top, mid = self.full_index[k], self.full_index[k + 1], self.mid_index[k]
            blocks.append(np.column_stack([bottom[t[:, :3]], top[t[:, :3]], bottom[t[:, 3:]], top[t[:, 3:]],
                                           mid[t[:, :3]]]))
        self.elements = np.vstack(blocks)
        self.element_triangle = np.tile(np.arange(len(t)), layers)
        self.element_layer = np.repeat(np.arange(layers), len(t))
        self.element_regions = np.tile(s.element_regions, layers)

    @property
    def layers(self) -> int:
        return len(self.heights_mm) - 1

    def copies(self, section_nodes: np.ndarray) -> np.ndarray:
        """Every 3D node of the given section nodes: their copy in every plane and, for corners, every mid plane."""
        section_nodes = np.asarray(section_nodes, int)
        mids = self.mid_index[:, section_nodes].ravel()
        return np.unique(np.concatenate([self.full_index[:, section_nodes].ravel(), mids[mids >= 0]]))

    def end_nodes(self) -> np.ndarray:
        return np.concatenate([self.full_index[0], self.full_index[-1]])

    def skin_faces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(3D element, ccx face number, layer) of every skin face, layer by layer in the section's face order."""
        faces = self.section.skin_faces
        layer = np.repeat(np.arange(self.layers), len(faces))
        element = layer * len(self.section.elements) + np.tile(faces[:, 0], self.layers)
        return element, np.tile(faces[:, 1], self.layers) + WEDGE_FACE_OF_TRIANGLE_FACE, layer

    def include_text(self, element_sets: dict[str, np.ndarray], node_sets: dict[str, np.ndarray]) -> str:
        lines = [f"** calfit 3D leg: {len(self.nodes)} nodes, {len(self.elements)} C3D15 elements, "
                 f"{self.layers} layers, mm", "*NODE, NSET=NALL"]
        ids = np.arange(1, len(self.nodes) + 1)
        lines += ["%d, %.10g, %.10g, %.10g" % (i, x, y, z) for i, (x, y, z) in zip(ids, self.nodes.tolist())]
        lines.append("*ELEMENT, TYPE=C3D15, ELSET=EALL")
        numbered = np.hstack([np.arange(1, len(self.elements) + 1)[:, None], self.elements + 1])
        row = "%d" + ", %d" * 15
        lines += [row % tuple(r) for r in numbered.tolist()]
        for keyword, sets in (("ELSET", element_sets), ("NSET", node_sets)):
            for name, members in sets.items():
                lines.append(f"*{keyword}, {keyword}={name}")
                members = np.asarray(members, int) + 1
                lines += [", ".join(map(str, members[i:i + ITEMS_PER_SET_LINE].tolist()))
                          for i in range(0, len(members), ITEMS_PER_SET_LINE)]
        return "\n".join(lines) + "\n"


# --- the garment --------------------------------------------------------------------------------------------

def polygon_corner_curvature(points: np.ndarray, smoothing_mm: float = 0.0) -> np.ndarray:
    """Curvature (1/mm) at the corners of a closed polygon (k, 2) whose tissue lies on its left (positive signed
    area in the image frame's numbers): the normal part of the kink t_i - t_{i-1} of the unit tangents over the
    tributary length (module text), positive where the polygon is convex. With smoothing_mm, averaged along the
    outline by a periodic Gaussian of that standard deviation in arc length, weighted by the tributary lengths
    (the total turning, hence the garment's load, is kept to the smoothing's accuracy)."""
    following = np.roll(points, -1, axis=0) - points
    length = np.linalg.norm(following, axis=1)
    tangent = following / length[:, None]
    outward = np.column_stack([tangent[:, 1], -tangent[:, 0]])       # the face's outward normal (ty, -tx)
    normal = outward + np.roll(outward, 1, axis=0)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    kink = tangent - np.roll(tangent, 1, axis=0)
    tributary = 0.5 * (length + np.roll(length, 1))
    curvature = -np.einsum("ij,ij->i", kink, normal) / tributary
    return smooth_along(points, curvature, smoothing_mm) if smoothing_mm > 0.0 else curvature


def smooth_along(points: np.ndarray, values: np.ndarray, sigma_mm: float) -> np.ndarray:
    """Corner values of a closed polygon averaged along it by a periodic Gaussian of sigma_mm in arc length,
    weighted by the corners' tributary lengths."""
    length = np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)
    tributary = 0.5 * (length + np.roll(length, 1))
    arc = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    gap = np.abs(arc[:, None] - arc[None, :])
    gap = np.minimum(gap, float(length.sum()) - gap)
    weight = np.exp(-0.5 * (gap / sigma_mm) ** 2) * tributary[None, :]
    return weight @ values / weight.sum(axis=1)


@dataclass
class GarmentLoad:
    """The skin faces of the 3D mesh and their pressures (module text)."""

    mesh: LegMesh3D
    tension_N_per_mm: float
    effects: HiddenEffects3D = field(default_factory=HiddenEffects3D)

    def __post_init__(self):
        s = self.mesh.section
        self.elements, self.faces, self.layers = self.mesh.skin_faces()
        corners = s.elements[s.skin_faces[:, 0][:, None], FACE_CORNERS[s.skin_faces[:, 1] - 1]]   # (f, 2)
        # the skin polygon's corners in face order: face j runs from corner j to corner j + 1
        start = corners[:, 0]
        order = {int(a): j for j, a in enumerate(start)}
        if len(order) != len(start) or any(int(b) not in order for b in corners[:, 1]):
            raise ValueError("the section's skin is not one closed loop of faces; mesh the section again")
        self.ring = start                                  # ring[j]: the first corner of face j
        self.next_face = np.array([order[int(b)] for b in corners[:, 1]])
        self.loop = [0]
        while len(self.loop) < len(start):
            self.loop.append(int(self.next_face[self.loop[-1]]))
        self.loop = np.asarray(self.loop)
        # the faces' sample points in the reference section: FACE_POINTS along each face's chord
        t = 0.5 * (1.0 + _FACE_GAUSS[0])
        ends = s.nodes[corners]                            # (f, 2 corners, 2)
        self._samples = ends[:, :1] * (1.0 - t)[None, :, None] + ends[:, 1:] * t[None, :, None]   # (f, q, 2)
        self._phi = np.angle(self.mesh.leg.frame.to_leg(self._samples[..., 0], self._samples[..., 1]))

    def pressures(self, deformed_nodes: np.ndarray | None = None) -> np.ndarray:
        """MPa on every skin face (in `mesh.skin_faces` order): T(theta) kappa of the exact outline averaged over
        the face (layer by layer), plus for the deformed law the curvature's change to the deformed mid-plane skin
        polygons of `deformed_nodes` (n, 3)."""
        faces_per_layer = len(self.ring)
        out = np.empty(self.mesh.layers * faces_per_layer)
        heights = self.mesh.heights_mm
        for layer in range(self.mesh.layers):
            low, high = heights[layer], heights[layer + 1]
            z, weights = 0.5 * (low + high) + 0.5 * (high - low) * _LAYER_GAUSS[0], _LAYER_GAUSS[1]
            part = sum(w * self._face_pressures(h, self.effects.tension_amplitude)
                       for h, w in zip(z, weights)) / weights.sum()
            if deformed_nodes is not None:
                corner_ids = self.mesh.mid_index[layer, self.ring[self.loop]]
                part = part + self._change(self.mesh.nodes[corner_ids, :2], deformed_nodes[corner_ids, :2],
                                           self.mesh.mid_heights_mm[layer], self.effects.tension_amplitude)
            out[layer * faces_per_layer:(layer + 1) * faces_per_layer] = part
        return out

    def plane_pressures(self, plane_nodes: np.ndarray, deformed: np.ndarray | None = None) -> np.ndarray:
        """MPa on the section's skin faces (section face order) of one node plane whose section nodes are at
        plane_nodes (n2, 3), deformed to `deformed` (n2, 2) for the deformed law (no tension profile: the
        plane-strain check's): T kappa of the exact outline at the plane's height, averaged along each face."""
        pressures = self._face_pressures(float(plane_nodes[0, 2]), 0.0)
        if deformed is None:
            return pressures
        corners = self.ring[self.loop]
        return pressures + self._change(plane_nodes[corners, :2], deformed[corners], float(plane_nodes[0, 2]), 0.0)

    def exact_curvature(self, z_mm: float) -> np.ndarray:
        """(faces,) the outline's exact hoop curvature (1/mm) at height z averaged along each skin face."""
        kappa = self.mesh.leg.skin_curvature(self._phi, z_mm)
        return kappa @ _FACE_GAUSS[1] / _FACE_GAUSS[1].sum()

    def _face_pressures(self, z: float, amplitude: float) -> np.ndarray:
        """T(theta) kappa at height z averaged along each face, kappa the exact curvature of the outline."""
        kappa = self.mesh.leg.skin_curvature(self._phi, z)
        if amplitude:
            x, y = self.mesh.leg.to_scanner(self._samples[..., 0], self._samples[..., 1], z)
            kappa = kappa * self._tension_factor(x, y, z, amplitude)
        return self.tension_N_per_mm * (kappa @ _FACE_GAUSS[1]) / _FACE_GAUSS[1].sum()

    def _change(self, undeformed: np.ndarray, deformed: np.ndarray, z: float, amplitude: float) -> np.ndarray:
        """The deformed law's T(theta) times the change of the skin polygon's kink curvature from `undeformed` to
        `deformed` (corners in loop order (k, 2), at height z), averaged along the skin over CHANGE_SMOOTHING_MM
        (module text: the fixed point's stability), a face taking the mean of its two corners. The polygon's own
        kinks, which are not the outline's curvature, cancel in the change."""
        change = polygon_corner_curvature(deformed) - polygon_corner_curvature(undeformed)
        change = smooth_along(undeformed, change, CHANGE_SMOOTHING_MM)
        if amplitude:
            change = change * self._tension_factor(undeformed[:, 0], undeformed[:, 1], z, amplitude)
        at_start = np.empty(len(self.ring))
        at_start[self.loop] = self.tension_N_per_mm * change      # face loop[i] starts at polygon corner i
        return 0.5 * (at_start + at_start[self.next_face])

    def _tension_factor(self, x, y, z: float, amplitude: float) -> np.ndarray:
        """1 + a cos(theta - theta0), theta the image-frame angle of (x, y) about the leg centre at height z."""
        cx, cy = self.mesh.leg.centre_mm(z)
        theta = np.arctan2(np.asarray(y) - cy, np.asarray(x) - cx)
        return 1.0 + amplitude * np.cos(theta - np.deg2rad(self.effects.tension_phase_deg))

    def include_text(self, pressures: np.ndarray) -> str:
        return "".join("%d, P%d, %.10g\n" % (e + 1, f, p)
                       for e, f, p in zip(self.elements.tolist(), self.faces.tolist(), np.asarray(pressures).tolist()))


_FACE_GAUSS = np.polynomial.legendre.leggauss(FACE_POINTS)
_LAYER_GAUSS = np.polynomial.legendre.leggauss(LAYER_POINTS)
FACE_CORNERS = np.array([[0, 1], [1, 2], [2, 0]])   # section corners of a triangle's faces 1..3


# --- the solution -----------------------------------------------------------------------------------------

@dataclass
class LegSolution3D:
    """The 3D truth: nodal displacements (n, 3) mm on `mesh`, the last pressures, the runs of ccx."""

    mesh: LegMesh3D
    displacement_mm: np.ndarray
    pressures_MPa: np.ndarray
    runs: list[CcxRun]
    theta_kPa: tuple[float, ...]
    tension_N_per_mm: float
    garment_law: str
    effects: HiddenEffects3D

    def __post_init__(self):
        s = self.mesh.section
        self._tree = cKDTree(s.nodes[s.elements[:, :3]].mean(axis=1))

    @property
    def wall_s(self) -> float:
        return float(sum(run.wall_s for run in self.runs))

    def _locate(self, X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(triangle, barycentric (n, 3)) of reference points; outside the mesh, its nearest element's nearest point."""
        s = self.mesh.section
        points = np.column_stack([X, Y])
        k = min(CANDIDATES, len(s.elements))
        _, candidates = self._tree.query(points, k=k)
        candidates = candidates.reshape(len(points), k)
        corners = s.nodes[s.elements[candidates][..., :3]]                      # (n, k, 3, 2)
        v1, v2 = corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]
        d = points[:, None, :] - corners[..., 0, :]
        det = v1[..., 0] * v2[..., 1] - v1[..., 1] * v2[..., 0]
        l2 = (d[..., 0] * v2[..., 1] - d[..., 1] * v2[..., 0]) / det
        l3 = (v1[..., 0] * d[..., 1] - v1[..., 1] * d[..., 0]) / det
        bary = np.stack([1.0 - l2 - l3, l2, l3], axis=-1)
        worst = bary.min(axis=2)
        inside = worst >= -1e-9
        choice = np.where(inside.any(axis=1), inside.argmax(axis=1), worst.argmax(axis=1))
        rows = np.arange(len(points))
        chosen = np.clip(bary[rows, choice], 0.0, None)
        return candidates[rows, choice], chosen / chosen.sum(axis=1, keepdims=True)

    def at(self, x, y, z) -> np.ndarray:
        """(3, ...) displacement (ux, uy, uz) mm of the material at scanner points (x, y, z) of the unloaded leg."""
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
        shape = x.shape
        x, y, z = x.ravel(), y.ravel(), z.ravel()
        out = np.empty((3, x.size))
        for first in range(0, x.size, CHUNK):
            part = slice(first, first + CHUNK)
            out[:, part] = self._at(x[part], y[part], z[part])
        return out.reshape((3,) + shape)

    def _at(self, x, y, z) -> np.ndarray:
        m = self.mesh
        X, Y = m.leg.reference_point(x, y, z)
        triangle, L = self._locate(X, Y)
        heights = m.heights_mm
        layer = np.clip(np.searchsorted(heights, z, side="right") - 1, 0, m.layers - 1)
        zeta = np.clip(2.0 * (z - heights[layer]) / (heights[layer + 1] - heights[layer]) - 1.0, -1.0, 1.0)
        nodes = m.elements[layer * len(m.section.elements) + triangle]        # (n, 15)
        u = np.einsum("nk,nkc->cn", wedge_shape_functions(L, zeta), self.displacement_mm[nodes])
        # inside a bone the material moves with it: clamped, or (bone_motion) the fibula's rigid displacement
        g = m.leg.geometry
        w = g.frame.to_leg(X, Y)
        u[:, g.tibia.excess(w) < 0] = 0.0
        u[:, g.fibula.excess(w) < 0] = (np.asarray(self.effects.bone_motion_mm, float)[:, None]
                                        if self.effects.bone_motion_mm is not None else 0.0)
        return u

    def slice_field(self, z_mm: float, image_shape: tuple[int, int], pixel_size_mm: tuple[float, float]) -> np.ndarray:
        """(3, H, W): the displacement of the material under each pixel centre of a slice at height z (ux, uy in
        the image frame, uz along the leg), relative to the bones (they are clamped)."""
        x, y = pixel_centres_mm(image_shape, pixel_size_mm)
        return self.at(x, y, np.full(x.shape, float(z_mm)))

    def plane_nodal(self, z_mm: float) -> np.ndarray:
        """(section nodes, 3) displacement of the node plane at height z (ValueError when no plane is there)."""
        k = int(np.argmin(np.abs(self.mesh.heights_mm - z_mm)))
        if abs(self.mesh.heights_mm[k] - z_mm) > 1e-6:
            raise ValueError(f"no node plane at {z_mm} mm (planes at {list(np.round(self.mesh.heights_mm, 3))})")
        return self.displacement_mm[self.mesh.full_index[k]]

    def description(self) -> dict:
        return {"element": "C3D15", "n_nodes": int(len(self.mesh.nodes)), "n_elements": int(len(self.mesh.elements)),
                "section_elements": int(len(self.mesh.section.elements)), "layers": int(self.mesh.layers),
                "node_planes_mm": [float(h) for h in self.mesh.heights_mm],
                "parameters_kPa": dict(zip(LEG_PARAMETERS, map(float, self.theta_kPa))),
                "tension_N_per_mm": float(self.tension_N_per_mm), "garment_law": self.garment_law,
                "effects": dataclasses.asdict(self.effects), "max_u_mm": float(np.abs(self.displacement_mm).max()),
                "pressure_MPa": {"min": float(self.pressures_MPa.min()), "max": float(self.pressures_MPa.max())},
                "ccx": [{"wall_s": round(r.wall_s, 2), "increments": r.increments, "iterations": r.iterations}
                        for r in self.runs]}


def wedge_shape_functions(L: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    """(n, 15) C3D15 shape functions at barycentric coordinates L (n, 3) and zeta (n,) in [-1, 1] (bottom -1)."""
    below, above, bubble = 1.0 - zeta, 1.0 + zeta, 1.0 - zeta ** 2
    l1, l2, l3 = L[:, 0], L[:, 1], L[:, 2]
    out = np.empty((len(L), 15))
    for i, li in enumerate((l1, l2, l3)):
        out[:, i] = 0.5 * li * ((2.0 * li - 1.0) * below - bubble)
        out[:, 3 + i] = 0.5 * li * ((2.0 * li - 1.0) * above - bubble)
        out[:, 12 + i] = li * bubble
    for j, (a, b) in enumerate(((l1, l2), (l2, l3), (l3, l1))):
        out[:, 6 + j] = 2.0 * a * b * below
        out[:, 9 + j] = 2.0 * a * b * above
    return out


# --- solving -------------------------------------------------------------------------------------------------

def leg_mesh_3d(leg: Leg3D, field_of_view_mm: tuple[float, float], *, focus_mm: Sequence[float], band_mm: float,
                layering: Layering = Layering(), n_elements: int = DEFAULT_SECTION_ELEMENTS,
                compartments: bool = False) -> LegMesh3D:
    """The extruded mesh of the segment, its fine band around the heights `focus_mm` (+- band_mm), a node plane at
    the reference height when it lies in the segment."""
    section = section_mesh(leg, field_of_view_mm, n_elements, compartments)
    z_ref = leg.along.reference_height_mm
    heights = layering.heights(focus_mm, band_mm, anchor_mm=z_ref)
    if layering.bottom_mm <= z_ref <= layering.top_mm and not np.isclose(heights, z_ref).any():
        heights = np.sort(np.append(heights, z_ref))
    return LegMesh3D(leg, section, heights)


def solve_leg3d(mesh: LegMesh3D, theta_kPa: Sequence[float], tension_N_per_mm: float, *,
                garment_law: str = "unloaded", effects: HiddenEffects3D | None = None, folder: Path | None = None,
                timeout_s: float = DEFAULT_TIMEOUT_S, threads: int | None = None) -> LegSolution3D:
    """Solve the segment at theta_kPa = (C10_fat, C10_muscle, Kv_fat, Kv_muscle) under the garment (module text).
    folder: where ccx runs (default a temporary folder, removed)."""
    theta = tuple(float(v) for v in theta_kPa)
    if len(theta) != 4 or min(theta) <= 0.0:
        raise ValueError(f"theta_kPa must be four positive values {LEG_PARAMETERS}, got {list(theta_kPa)}")
    if garment_law not in GARMENT_LAWS:
        raise ValueError(f"garment_law must be one of {GARMENT_LAWS}, not {garment_law!r}")
    if tension_N_per_mm <= 0.0:
        raise ValueError(f"the garment tension must be positive, got {tension_N_per_mm} N/mm")
    effects = effects or HiddenEffects3D()
    load = GarmentLoad(mesh, tension_N_per_mm, effects)
    deck = _deck(mesh, theta, effects, garment_law, tension_N_per_mm)
    mesh_text = mesh.include_text(*_sets(mesh, effects))
    with tempfile.TemporaryDirectory(prefix="calfit-leg3d-") as scratch:
        work = Path(folder) if folder is not None else Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        (work / "mesh.inp").write_text(mesh_text, encoding="utf-8")
        pressures = load.pressures()
        runs: list[CcxRun] = []
        for update in range(MAX_PRESSURE_UPDATES if garment_law == "deformed" else 1):
            (work / "pressure.inp").write_text(load.include_text(pressures), encoding="utf-8")
            runs.append(_run_in(work, deck, len(mesh.nodes), update, timeout_s, threads))
            displacement = runs[-1].displacement_mm
            if garment_law == "unloaded":
                break
            updated = load.pressures(mesh.nodes + displacement)
            change = float(np.max(np.abs(updated - pressures)) / np.max(np.abs(updated)))
            if change < PRESSURE_TOLERANCE:
                pressures = updated
                break
            pressures = pressures + PRESSURE_RELAXATION * (updated - pressures)
        else:
            raise CcxError(f"the deformed garment law's pressures still changed by {100 * change:.2f} % after "
                           f"{MAX_PRESSURE_UPDATES} solves; lower the tension or use garment_law='unloaded'")
    return LegSolution3D(mesh, displacement, pressures, runs, theta, float(tension_N_per_mm), garment_law, effects)


def _run_in(work: Path, deck: str, n_nodes: int, update: int, timeout_s: float, threads: int | None) -> CcxRun:
    """One ccx run in `work` (the mesh and pressure includes beside the deck), its job named by the update."""
    return run_ccx(deck, work, n_nodes, job=f"leg3d-{update}", timeout_s=timeout_s, threads=threads)


def _sets(mesh: LegMesh3D, effects: HiddenEffects3D) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Element sets (FAT, MUSCLE, STIFF) and node sets (BONES, FIBULA, ENDS) of the 3D mesh."""
    regions = mesh.element_regions
    muscle = (regions == 2) | (regions >= FIRST_COMPARTMENT_LABEL)
    stiff = np.zeros(len(regions), bool)
    if effects.stiffer:
        if effects.stiffer_compartment is not None:
            label = FIRST_COMPARTMENT_LABEL + COMPARTMENTS.index(effects.stiffer_compartment)
            if not np.any(regions == label):
                raise ValueError(f"the mesh has no {effects.stiffer_compartment} compartment; mesh the section with "
                                 "compartments (compartments=True)")
            stiff = regions == label
        else:
            centroid = mesh.nodes[mesh.elements[:, :6]].mean(axis=1)
            cx, cy = mesh.leg.centre_mm(centroid[:, 2])
            theta = np.rad2deg(np.arctan2(centroid[:, 1] - cy, centroid[:, 0] - cx))
            low, high = effects.stiffer_sector_deg
            stiff = muscle & (((theta - low) % 360.0) <= ((high - low) % 360.0))
            if not stiff.any():
                raise ValueError(f"no muscle lies in the sector {effects.stiffer_sector_deg} deg; widen it")
    element_sets = {"FAT": np.flatnonzero(regions == 1), "MUSCLE": np.flatnonzero(muscle & ~stiff)}
    if stiff.any():
        element_sets["STIFF"] = np.flatnonzero(stiff)
    s = mesh.section
    node_sets = {"BONES": mesh.copies(s.node_sets["BONES"]), "ENDS": mesh.end_nodes()}
    if effects.bone_motion_mm is not None:
        node_sets["FIBULA"] = mesh.copies(fibula_nodes(mesh))
    return element_sets, node_sets


def fibula_nodes(mesh: LegMesh3D) -> np.ndarray:
    """The section's nodes on the fibula's surface: the bone node set (BONE1, BONE2, ...) nearest its centre."""
    s, g = mesh.section, mesh.leg.geometry
    bones = {name: nodes for name, nodes in s.node_sets.items() if name.startswith("BONE") and name != "BONES"}
    if len(bones) < 2:
        raise ValueError("bone_motion moves the fibula, and the section has one bone only")
    centre = np.array(g.frame.to_image(g.fibula.centre), float)
    return min(bones.values(), key=lambda nodes: float(np.linalg.norm(s.nodes[nodes].mean(axis=0) - centre)))


def _deck(mesh: LegMesh3D, theta: tuple[float, ...], effects: HiddenEffects3D, garment_law: str,
          tension: float) -> str:
    c10_fat, c10_muscle, kv_fat, kv_muscle = (v / KPA_PER_MPA for v in theta)
    expansion = f"{effects.muscle_linear_strain:.10g}" if effects.muscle_linear_strain else None
    materials = [{"name": "FAT", "elset": "FAT", "constants": numbers((c10_fat, 1.0 / kv_fat)), "expansion": None},
                 {"name": "MUSCLE", "elset": "MUSCLE", "constants": numbers((c10_muscle, 1.0 / kv_muscle)),
                  "expansion": expansion}]
    if effects.stiffer:
        f = effects.stiffer_factor
        materials.append({"name": "STIFF", "elset": "STIFF", "expansion": expansion,
                          "constants": numbers((f * c10_muscle, 1.0 / (f * kv_muscle)))})
    moved = []
    if effects.bone_motion_mm is not None:
        moved = [f"FIBULA, {dof}, {dof}, {value:.10g}" for dof, value in zip((1, 2, 3), effects.bone_motion_mm)]
    return render("leg3d_ccx.inp.j2", description=(f"theta = {list(theta)} kPa, T = {tension:g} N/mm, garment law "
                                                   f"{garment_law}, effects {effects.catalog_form()}"),
                  mesh_include="mesh.inp", materials=materials, clamped_set="BONES", eigenstrain=expansion is not None,
                  max_increments=100, static=numbers(STATIC), moved_bone=moved, pressure_include="pressure.inp")


# --- the plane-strain check ------------------------------------------------------------------------------------

def plane_strain_difference(solution: LegSolution3D) -> dict:
    """The 3D solution's node plane at the reference height against calfit's plane-strain engine on the same
    section's triangles (module text), RMS and largest in-plane difference over the section's nodes relative to
    max |u|, twice: `same_load`, the plane-strain model under the very face pressures of the 3D garment at that
    plane (`*DLOAD`: what remains is the 3D solution's departure from plane strain and the discretization), and
    `engine_laplace`, the engine's own Laplace law (REFERENCE=1 for the unloaded law, the deformed membrane for
    the deformed one), whose pressure is distributed along the skin its own way (solver_cpp/README.md)."""
    from ...core.materials import TissueLaw
    from ...engine.runner import solve_once
    from ...fit.objectives import leg_rows
    from ...model.forward import LegModel

    if solution.effects != HiddenEffects3D():
        raise ValueError("the plane-strain check compares the baseline physics; solve without hidden effects")
    mesh, section = solution.mesh, solution.mesh.section
    law = TissueLaw("neo_hooke")
    z_ref = mesh.leg.along.reference_height_mm
    spatial = solution.plane_nodal(z_ref)
    largest_3d = float(np.linalg.norm(spatial[:, :2], axis=1).max())
    out = {"max_u_mm": largest_3d, "max_uz_mm_in_plane": float(np.abs(spatial[:, 2]).max())}
    fixed = {"unloaded_curvature": {"alpha_unloaded": 1.0}} if solution.garment_law == "unloaded" else {}
    model = LegModel(section, solution.tension_N_per_mm, fixed_effects=fixed, tissues={"fat": law, "muscle": law})
    laplace_deck = model.deck(list(solution.theta_kPa))
    plane = int(np.argmin(np.abs(mesh.heights_mm - z_ref)))
    load = GarmentLoad(mesh, solution.tension_N_per_mm)
    ids = mesh.full_index[plane]
    deformed = (mesh.nodes[ids] + solution.displacement_mm[ids])[:, :2] if solution.garment_law == "deformed" else None
    pressures = load.plane_pressures(mesh.nodes[ids], deformed)
    dload = "*DLOAD\n" + "".join("%d, P%d, %.10g\n" % (e + 1, k, p)
                                  for (e, k), p in zip(section.skin_faces.tolist(), pressures.tolist()))
    same_load_deck = re.sub(r"^\*LAPLACE PRESSURE[^\n]*\n", lambda _: dload, laplace_deck, count=1, flags=re.M)
    if same_load_deck == laplace_deck:
        raise RuntimeError("the plane-strain deck has no *LAPLACE PRESSURE line to replace by the 3D garment's faces")
    for name, deck in (("same_load", same_load_deck), ("engine_laplace", laplace_deck)):
        start = time.perf_counter()
        planar = leg_rows(solve_once(model, deck, "calfit-fe did not converge on the reference section; lower the "
                                                  "tension"), len(section.nodes))[:, :2]
        difference = np.linalg.norm(spatial[:, :2] - planar, axis=1)
        largest = float(np.linalg.norm(planar, axis=1).max())
        out[name] = {"rms_over_max_u": float(np.sqrt(np.mean(difference ** 2)) / largest),
                     "max_over_max_u": float(difference.max() / largest), "max_u_mm": largest,
                     "engine_s": time.perf_counter() - start}
    return out
