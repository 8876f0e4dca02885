"""An analytic leg-like slice for engine verification and benchmarks, and its deck.

Independent of the imaging phantom: a smooth egg-shaped skin contour 110 mm wide and
95 mm deep (wider at the back), a fat layer whose thickness varies from about 1.9 mm
anteriorly to about 10 mm posteriorly, muscle inside, and two bone holes placed as in
a right calf seen from below in radiological convention (anterior up, y downwards in
the image frame): the tibia (ellipse 24 x 21 mm) anteromedial, the fibula (circle
13 mm) posterolateral. Bones are clamped; the skin carries a follower pressure.

`leg_slice_deck` writes a complete deck with standard keywords only (unless a
Laplace tension is asked for), so it runs in calfit-fe and in CalculiX ccx.
Units: N, mm, MPa. Default materials: Table 2 central values of the first paper
(Avril et al.): fat C10 = 4.5 kPa, Kv = 106 kPa; muscle C10 = 11.2 kPa,
Kv = 69.5 kPa, written as CalculiX NEO HOOKE with D1 = 1 / Kv. The Avril volumetric
energy Kv[(J^2 - 1)/2 - ln J] and the CalculiX one (J - 1)^2 / D1 have the same
second derivative at J = 1 when D1 = 1/Kv, i.e. the same initial bulk modulus
2 Kv (212 kPa fat, 139 kPa muscle). Default load: 20 mmHg = 2.6664e-3 MPa.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from skimage.measure import points_in_poly

from ..engine.decks import render
from .curves import Curve, SpacingRules
from .mesh import Mesh
from .triangulate import BONE_KEY_OFFSET, mesh_curves

MMHG_IN_MPA = 133.322387415e-6
DEFAULT_PRESSURE_MPA = 20.0 * MMHG_IN_MPA
# initial dt, period, min dt, max dt: the garment's strains stay below about 5% (Avril et
# al. sec. 2.2.4), so one increment converges; cut-back handles harder cases.
DEFAULT_STATIC = (1.0, 1.0, 1e-4, 1.0)

# elset -> (CalculiX *HYPERELASTIC option, data line constants), units MPa and 1/MPa
DEFAULT_MATERIALS: dict[str, tuple[str, tuple[float, ...]]] = {
    "FAT": ("NEO HOOKE", (0.0045, 1.0 / 0.106)),
    "MUSCLE": ("NEO HOOKE", (0.0112, 1.0 / 0.0695)),
}


@dataclass
class LegSliceGeometry:
    """Dense closed contours (mm, image frame) of the analytic slice."""

    skin: np.ndarray
    fascia: np.ndarray  # fat / muscle interface
    bones: list[np.ndarray]  # tibia first, then fibula

    def classify(self, points: np.ndarray) -> np.ndarray:
        """Region key of each point: 0 outside, 1 fat, 2 muscle, BONE_KEY_OFFSET + k in bone k."""
        points = np.asarray(points, dtype=float)
        keys = np.zeros(len(points), dtype=np.int64)
        inside_skin = points_in_poly(points, self.skin)
        keys[inside_skin] = 1
        keys[inside_skin & points_in_poly(points, self.fascia)] = 2
        for number, bone in enumerate(self.bones, start=1):
            keys[points_in_poly(points, bone)] = BONE_KEY_OFFSET + number
        return keys

    def curves(self) -> list[Curve]:
        curves = [Curve(self.skin, True, (0, 1)), Curve(self.fascia, True, (1, 2))]
        curves += [Curve(b, True, (2, BONE_KEY_OFFSET + k)) for k, b in enumerate(self.bones, start=1)]
        return curves

    def label_image(self, pixel_size_mm: float = 0.36) -> np.ndarray:
        """Rasterised labels (0 background, 1 fat, 2 muscle, 3 bone) on square pixels whose
        centres are ((j + 0.5) d, (i + 0.5) d); the image covers the slice with a margin."""
        top_right = np.max(np.vstack([self.skin]), axis=0) + 5.0
        shape = (int(np.ceil(top_right[1] / pixel_size_mm)), int(np.ceil(top_right[0] / pixel_size_mm)))
        rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
        centres = np.column_stack([(cols.ravel() + 0.5) * pixel_size_mm, (rows.ravel() + 0.5) * pixel_size_mm])
        keys = self.classify(centres)
        labels = np.where(keys >= BONE_KEY_OFFSET, 3, keys)
        return labels.reshape(shape).astype(np.uint8)


def leg_slice_geometry(seed: int = 0, spacing_mm: float = 0.1) -> LegSliceGeometry:
    """The analytic slice; seed 0 is the reference shape, other seeds perturb it slightly
    (skin harmonics up to 2%, fat thickness +-15%, bone positions +-1.5 mm)."""
    rng = np.random.default_rng(seed)
    centre = np.array([75.0, 70.0])
    half_width, half_depth, egg = 55.0, 47.5, 0.08
    harmonics = rng.uniform(-0.02, 0.02, size=(3, 2)) if seed else np.zeros((3, 2))
    fat_scale = rng.uniform(0.85, 1.15) if seed else 1.0
    bone_shift = rng.uniform(-1.5, 1.5, size=(2, 2)) if seed else np.zeros((2, 2))

    n = int(np.ceil(2 * np.pi * half_width / spacing_mm))
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    radial = 1.0 + egg * np.sin(t)  # sin t > 0 posteriorly (y down): wider at the back
    for k, (a, b) in enumerate(harmonics, start=2):
        radial += a * np.cos(k * t) + b * np.sin(k * t)
    skin = centre + np.column_stack([half_width * np.cos(t), half_depth * np.sin(t)]) * radial[:, None]

    tangent = np.gradient(skin, axis=0)
    normal = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    normal *= np.sign(np.einsum("ij,ij->i", normal, skin - centre))[:, None]  # outward
    fat_thickness = fat_scale * (6.0 + 4.0 * np.sin(t) + 1.0 * np.cos(t))  # 1.9 mm front, 10 mm back
    fascia = skin - fat_thickness[:, None] * normal

    def ellipse(middle, a, b, angle_deg):
        m = int(np.ceil(2 * np.pi * max(a, b) / spacing_mm))
        s = np.linspace(0.0, 2 * np.pi, m, endpoint=False)
        c, d = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        local = np.column_stack([a * np.cos(s), b * np.sin(s)])
        return middle + local @ np.array([[c, d], [-d, c]])

    tibia = ellipse(centre + np.array([12.0, -22.0]) + bone_shift[0], 12.0, 10.5, 20.0)
    fibula = ellipse(centre + np.array([-24.0, -2.0]) + bone_shift[1], 6.5, 6.5, 0.0)
    return LegSliceGeometry(skin, fascia, [tibia, fibula])


def leg_slice_mesh(n_elements: int = 5500, order: int = 2, seed: int = 0, accept_closest: bool = False) -> Mesh:
    """Mesh of the analytic slice with about n_elements CPE3 (order 1) or CPE6 (order 2)
    elements (within 2% usually, 10% at worst; the thin anterior fat and the bones need
    about 240 elements at least). Element sets FAT, MUSCLE; node sets BONE1 (tibia),
    BONE2 (fibula), BONES, SKIN_NODES, FAT_MUSCLE; surface SKIN."""
    area_per_element = 8000.0 / n_elements
    edge = np.sqrt(4.0 * area_per_element / np.sqrt(3.0))
    geometry = leg_slice_geometry(seed, spacing_mm=float(np.clip(edge / 6.0, 0.02, 0.5)))
    rules = SpacingRules(min_spacing=0.05)
    return mesh_curves(
        geometry.curves(), geometry.classify, n_elements, order=order, rules=rules, accept_closest=accept_closest
    )


def elements_for_dof(n_dof: int, order: int) -> int:
    """Element count that gives about n_dof degrees of freedom on the leg slice.

    Euler's relation for a domain with two holes, V - E + F = -1, with E = (3F + b)/2
    (b boundary edges, about 436 mm of skin and bone perimeter over the edge length):
    T3 nodes = F/2 + b/2 - 1, T6 nodes = V + E = 2F + b - 1.
    """
    nodes = n_dof / 2.0
    elements = nodes * (2.0 if order == 1 else 0.5)
    for _ in range(20):
        edge = np.sqrt(4.0 * (7400.0 / elements) / np.sqrt(3.0))
        boundary = 436.0 / edge
        elements = 2.0 * (nodes - boundary / 2.0 + 1.0) if order == 1 else (nodes - boundary + 1.0) / 2.0
    return max(10, int(round(elements)))


def leg_slice_mesh_for_dof(n_dof: int, order: int = 2, seed: int = 0) -> Mesh:
    """Leg slice mesh with about n_dof degrees of freedom (one corrective re-mesh); below
    the coarsest mesh the geometry allows (about 1,100 DOF for T6) that mesh is returned."""
    n_elements = elements_for_dof(n_dof, order)
    mesh = leg_slice_mesh(n_elements, order, seed, accept_closest=True)
    if abs(mesh.n_dof - n_dof) > 0.03 * n_dof:
        n_elements = max(10, int(round(len(mesh.elements) * n_dof / mesh.n_dof)))
        mesh = leg_slice_mesh(n_elements, order, seed, accept_closest=True)
    return mesh


def leg_slice_deck(
    path: str | Path,
    n_elements: int = 5500,
    order: int = 2,
    materials: Mapping[str, tuple[str, Sequence[float]]] | None = None,
    pressure: float = DEFAULT_PRESSURE_MPA,
    laplace_tension: float | None = None,
    seed: int = 0,
    mesh: Mesh | None = None,
    include_mesh: bool = True,
    static: Sequence[float] = DEFAULT_STATIC,
) -> Mesh:
    """Write a complete deck for the leg slice at `path` and return its mesh.

    materials: elset -> (*HYPERELASTIC option, constants), e.g. {"FAT": ("NEO HOOKE",
    (C10, D1))}, MPa; every tissue element set of the mesh needs one. pressure: follower
    pressure on the skin in MPa, written as one `*DLOAD` line `element, Pk, value` per
    skin face. laplace_tension (N/mm): if given, the project keyword `*LAPLACE PRESSURE,
    SURFACE=SKIN` replaces the *DLOAD (the deck then runs in calfit-fe only).
    include_mesh: write the mesh to `<stem>_mesh.inp` beside the deck and *INCLUDE it
    (otherwise inline). mesh: use this mesh instead of generating one.
    """
    path = Path(path)
    mesh = mesh if mesh is not None else leg_slice_mesh(n_elements, order, seed)
    materials = dict(DEFAULT_MATERIALS if materials is None else materials)
    elsets = set(mesh.element_sets())
    missing = sorted(elsets - set(materials))
    if missing:
        raise ValueError(f"no material given for element set(s) {', '.join(missing)}; add them to `materials`")
    if "BONES" not in mesh.node_sets:
        raise ValueError("the mesh has no BONES node set to clamp")
    if laplace_tension is None and not len(mesh.skin_faces):
        raise ValueError("the mesh has no SKIN faces to load")
    material_rows = [
        {
            "name": elset,
            "elset": elset,
            "law": law,
            "constants": ", ".join(f"{value:.10g}" for value in constants),
        }
        for elset, (law, constants) in materials.items()
        if elset in elsets
    ]
    include_name = None
    if include_mesh:
        include_name = f"{path.stem}_mesh.inp"
        mesh.write_include(path.parent / include_name)
    load = (
        f"Laplace pressure, garment tension {laplace_tension:g} N/mm"
        if laplace_tension is not None
        else f"follower pressure {pressure:.6g} MPa on the skin"
    )
    text = render(
        "leg_slice.inp.j2",
        seed=seed,
        n_elements=len(mesh.elements),
        element_type=mesh.element_type,
        n_nodes=len(mesh.nodes),
        n_dof=mesh.n_dof,
        load_description=load,
        mesh_include=include_name,
        mesh_text=None if include_mesh else mesh.include_text(),
        materials=material_rows,
        static=", ".join(f"{value:.10g}" for value in static),
        laplace_tension=None if laplace_tension is None else f"{laplace_tension:.10g}",
        skin_faces=[(e + 1, k) for e, k in mesh.skin_faces.tolist()],
        pressure=f"{pressure:.10g}",
    )
    path.write_text(text)
    return mesh
