"""Deck writers for the calfit-fe verification cases.

Plain functions that build small structured meshes (unit square, the MacNeal-Harder
patch, polar annuli with refinement levels, rings with a circular or elliptical outer
boundary for the Laplace law) and render them as standard-keyword decks that both
calfit-fe and CalculiX read (see solver_cpp/README.md). Node and element ids are the
0-based array indices plus one; T6 mid-side nodes are ordered 4: 1-2, 5: 2-3, 6: 3-1,
face k of an element joins corner k to corner k+1 (S1..S3 / P1..P3).

The MacNeal-Harder patch geometry is the one of MacNeal & Harder, "A proposed standard
set of problems to test finite element accuracy", Finite Elem. Anal. Des. 1 (1985) 3-20.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from engine_closed_forms import Law


@dataclass
class Mesh:
    nodes: np.ndarray  # (n_nodes, 2) reference coordinates
    elems: np.ndarray  # (n_elems, 3 | 6) 0-based node indices, counter-clockwise
    nsets: dict[str, np.ndarray] = field(default_factory=dict)  # name -> 0-based node indices
    surfaces: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # name -> (elem idx, face 1..3)
    elsets: dict[str, np.ndarray] = field(default_factory=dict)  # name -> 0-based element indices
    hybrid: bool = False  # mixed u/p elements CPE3H / CPE6H

    @property
    def order(self) -> int:
        return 1 if self.elems.shape[1] == 3 else 2

    @property
    def etype(self) -> str:
        return ("CPE3" if self.order == 1 else "CPE6") + ("H" if self.hybrid else "")

    @property
    def n_dof(self) -> int:
        return 2 * len(self.nodes)


# ----------------------------------------------------------------------------------------
# Mesh building blocks
# ----------------------------------------------------------------------------------------

_FACE_CORNERS = {1: (0, 1), 2: (1, 2), 3: (2, 0)}


def _grid_triangles(nx: int, ny: int, order: int, coords) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Structured triangulation of the parameter square [0,1]^2 mapped by coords(s, t).

    Returns nodes, elems and the (i, j) grid index of every node on the refined grid
    (step 1/(order nx), 1/(order ny)). Each cell is split along alternating diagonals.
    """
    mx, my = order * nx, order * ny
    s = np.linspace(0.0, 1.0, mx + 1)
    t = np.linspace(0.0, 1.0, my + 1)
    S, T = np.meshgrid(s, t, indexing="ij")
    x, y = coords(S.ravel(), T.ravel())
    nodes = np.column_stack([x, y])
    idx = lambda i, j: i * (my + 1) + j  # noqa: E731
    elems = []
    for i in range(nx):
        for j in range(ny):
            a, b = order * i, order * j
            p00, p10, p11, p01 = (a, b), (a + order, b), (a + order, b + order), (a, b + order)
            if (i + j) % 2 == 0:
                tris = [(p00, p10, p11), (p00, p11, p01)]
            else:
                tris = [(p00, p10, p01), (p10, p11, p01)]
            for c in tris:
                corners = [idx(*q) for q in c]
                if order == 2:
                    mids = [
                        idx((c[k][0] + c[(k + 1) % 3][0]) // 2, (c[k][1] + c[(k + 1) % 3][1]) // 2) for k in range(3)
                    ]
                    corners += mids
                elems.append(corners)
    grid = np.column_stack([np.repeat(np.arange(mx + 1), my + 1), np.tile(np.arange(my + 1), mx + 1)])
    return nodes, np.array(elems, dtype=np.int64), grid


def boundary_faces(elems: np.ndarray, node_mask: np.ndarray) -> list[tuple[int, int]]:
    """(element, face 1..3) whose two corner nodes are both in node_mask and that lie on the boundary."""
    count: dict[tuple[int, int], int] = {}
    for e in elems:
        for f, (a, b) in _FACE_CORNERS.items():
            key = tuple(sorted((int(e[a]), int(e[b]))))
            count[key] = count.get(key, 0) + 1
    out = []
    for ie, e in enumerate(elems):
        for f, (a, b) in _FACE_CORNERS.items():
            key = tuple(sorted((int(e[a]), int(e[b]))))
            if count[key] == 1 and node_mask[e[a]] and node_mask[e[b]]:
                out.append((ie, f))
    return out


def face_nodes(mesh: Mesh, ie: int, f: int) -> list[int]:
    """Nodes of face f of element ie, in order corner, (mid), corner."""
    e = mesh.elems[ie]
    a, b = _FACE_CORNERS[f]
    if mesh.order == 1:
        return [int(e[a]), int(e[b])]
    return [int(e[a]), int(e[3 + f - 1]), int(e[b])]


# ----------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------


def unit_square(n: int, order: int, L: float = 1.0) -> Mesh:
    """n x n cells on [0, L]^2; nsets LEFT, RIGHT, BOTTOM, TOP, ALLB, CORNER (L, L); surfaces TOP, RIGHT."""
    nodes, elems, _ = _grid_triangles(n, n, order, lambda s, t: (L * s, L * t))
    x, y = nodes[:, 0], nodes[:, 1]
    tol = 1e-12 * L
    m = Mesh(nodes, elems)
    m.nsets = {
        "LEFT": np.flatnonzero(np.abs(x) < tol),
        "RIGHT": np.flatnonzero(np.abs(x - L) < tol),
        "BOTTOM": np.flatnonzero(np.abs(y) < tol),
        "TOP": np.flatnonzero(np.abs(y - L) < tol),
        "CORNER": np.flatnonzero((np.abs(x - L) < tol) & (np.abs(y - L) < tol)),
    }
    m.nsets["ALLB"] = np.unique(np.concatenate([m.nsets[k] for k in ("LEFT", "RIGHT", "BOTTOM", "TOP")]))
    m.surfaces = {
        "TOP": boundary_faces(elems, np.abs(y - L) < tol),
        "RIGHT": boundary_faces(elems, np.abs(x - L) < tol),
    }
    return m


MH_CORNERS = [(0.0, 0.0), (0.24, 0.0), (0.24, 0.12), (0.0, 0.12)]
MH_INTERIOR = [(0.04, 0.02), (0.18, 0.03), (0.16, 0.08), (0.08, 0.08)]


def macneal_harder_patch(order: int) -> Mesh:
    """The MacNeal-Harder patch (0.24 x 0.12, four interior nodes), each quad cut in two triangles.

    nset BOUNDARY holds every node on the rectangle's edges (with T6, the mid-side nodes
    there too); nset INTERIOR the others.
    """
    corners = np.array(MH_CORNERS + MH_INTERIOR)
    quads = [(0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7), (4, 5, 6, 7)]
    tris = []
    for a, b, c, d in quads:
        tris += [(a, b, c), (a, c, d)]
    nodes = list(map(tuple, corners))
    elems = []
    mid_index: dict[tuple[int, int], int] = {}
    for t in tris:
        conn = list(t)
        if order == 2:
            for k in range(3):
                key = tuple(sorted((t[k], t[(k + 1) % 3])))
                if key not in mid_index:
                    mid_index[key] = len(nodes)
                    nodes.append(tuple(0.5 * (corners[key[0]] + corners[key[1]])))
                conn.append(mid_index[key])
        elems.append(conn)
    nodes = np.array(nodes)
    x, y = nodes[:, 0], nodes[:, 1]
    on_b = (np.abs(x) < 1e-14) | (np.abs(x - 0.24) < 1e-14) | (np.abs(y) < 1e-14) | (np.abs(y - 0.12) < 1e-14)
    return Mesh(nodes, np.array(elems), nsets={"BOUNDARY": np.flatnonzero(on_b), "INTERIOR": np.flatnonzero(~on_b)})


COOK_CORNERS = np.array([(0.0, 0.0), (48.0, 44.0), (48.0, 60.0), (0.0, 44.0)])


def cook_membrane(n: int, order: int, hybrid: bool = False) -> Mesh:
    """Cook's membrane: the quadrilateral (0,0), (48,44), (48,60), (0,44) mapped from an
    n x n grid. nsets LEFT (clamped edge), RIGHT (loaded edge, ordered bottom to top), TIP (48, 60)."""
    P = COOK_CORNERS

    def coords(s, t):
        w = [(1 - s) * (1 - t), s * (1 - t), s * t, (1 - s) * t]
        return sum(wk * P[k, 0] for k, wk in enumerate(w)), sum(wk * P[k, 1] for k, wk in enumerate(w))

    nodes, elems, grid = _grid_triangles(n, n, order, coords)
    m = order * n
    right = np.flatnonzero(grid[:, 0] == m)
    mesh = Mesh(nodes, elems, hybrid=hybrid)
    mesh.nsets = {
        "LEFT": np.flatnonzero(grid[:, 0] == 0),
        "RIGHT": right[np.argsort(grid[right, 1])],
        "TIP": np.flatnonzero((grid[:, 0] == m) & (grid[:, 1] == m)),
    }
    return mesh


def edge_loads(order: int, n_segments: int, total: float) -> np.ndarray:
    """Consistent nodal forces of a uniform traction of resultant `total` on a straight
    edge of n_segments equal element faces (nodes ordered along the edge)."""
    weights = np.array([0.5, 0.5]) if order == 1 else np.array([1.0, 4.0, 1.0]) / 6.0
    forces = np.zeros(order * n_segments + 1)
    for k in range(n_segments):
        forces[order * k : order * k + order + 1] += weights * total / n_segments
    return forces


def ring(nr: int, nt: int, order: int, A: float = 1.0, outer=(2.0, 2.0), quarter: bool = False) -> Mesh:
    """Ring between the circle of radius A and the ellipse with semi-axes outer = (a, b).

    Polar-structured: point(s, th) = (1-s) A (cos, sin) + s (a cos, b sin), s radial in
    [0, 1], th in [0, 2 pi) (full ring, periodic) or [0, pi/2] (quarter). T6 mid-side
    nodes lie on the mapped grid (curved, isoparametric). nsets INNER, OUTER (and XSYM:
    nodes on x = 0, YSYM: nodes on y = 0 for the quarter); surface OUTER.
    """
    a, b = outer
    span = 0.5 * np.pi if quarter else 2.0 * np.pi

    def coords(s, t):
        th = span * t
        return (1 - s) * A * np.cos(th) + s * a * np.cos(th), (1 - s) * A * np.sin(th) + s * b * np.sin(th)

    nodes, elems, grid = _grid_triangles(nr, nt, order, coords)
    if not quarter:  # merge the seam th = 2 pi onto th = 0
        my = order * nt
        seam = grid[:, 1] == my
        target = np.arange(len(nodes))
        target[seam] = np.flatnonzero(grid[:, 1] == 0)
        keep = ~seam
        new_index = -np.ones(len(nodes), dtype=np.int64)
        new_index[keep] = np.arange(keep.sum())
        elems = new_index[target[elems]]
        nodes, grid = nodes[keep], grid[keep]
    mr = order * nr
    m = Mesh(nodes, elems)
    inner, outer_mask = grid[:, 0] == 0, grid[:, 0] == mr
    m.nsets = {"INNER": np.flatnonzero(inner), "OUTER": np.flatnonzero(outer_mask)}
    if quarter:
        m.nsets["YSYM"] = np.flatnonzero(grid[:, 1] == 0)  # on y = 0: u_y = 0
        m.nsets["XSYM"] = np.flatnonzero(grid[:, 1] == order * nt)  # on x = 0: u_x = 0
        m.nodes[m.nsets["XSYM"], 0] = 0.0
    m.surfaces = {"OUTER": boundary_faces(elems, outer_mask)}
    return m


# ----------------------------------------------------------------------------------------
# Deck text
# ----------------------------------------------------------------------------------------


def _ids(idx) -> str:
    ids = [str(int(i) + 1) for i in idx]
    return "\n".join(", ".join(ids[k : k + 16]) for k in range(0, len(ids), 16))


def mesh_text(mesh: Mesh, elset: str = "EALL") -> str:
    out = ["*NODE"]
    out += [f"{i + 1}, {fmt(x)}, {fmt(y)}" for i, (x, y) in enumerate(mesh.nodes)]
    out.append(f"*ELEMENT, TYPE={mesh.etype}, ELSET={elset}")
    out += [f"{i + 1}, " + ", ".join(str(int(n) + 1) for n in e) for i, e in enumerate(mesh.elems)]
    for name, idx in mesh.nsets.items():
        if len(idx):
            out += [f"*NSET, NSET={name}", _ids(idx)]
    for name, idx in mesh.elsets.items():
        if len(idx):
            out += [f"*ELSET, ELSET={name}", _ids(idx)]
    return "\n".join(out) + "\n"


def surface_text(mesh: Mesh, name: str) -> str:
    lines = [f"*SURFACE, NAME={name}, TYPE=ELEMENT"]
    lines += [f"{ie + 1}, S{f}" for ie, f in mesh.surfaces[name]]
    return "\n".join(lines) + "\n"


def dload_text(mesh: Mesh, surface: str, p: float) -> str:
    lines = ["*DLOAD"] + [f"{ie + 1}, P{f}, {fmt(p)}" for ie, f in mesh.surfaces[surface]]
    return "\n".join(lines) + "\n"


def deck(
    mesh: Mesh,
    law: Law | dict[str, Law],
    *,
    fixed: list[tuple[str, int, int]] = (),
    prescribed: list[tuple[int | str, int, float]] = (),
    cloads: list[tuple[int, int, float]] = (),
    pressure: list[tuple[str, float]] = (),
    laplace: list[tuple[str, float]] = (),
    static: tuple[float, float, float, float] = (0.1, 1.0, 1e-5, 0.1),
    inc: int = 1000,
    integration: str | None = None,
    heading: str = "calfit-fe verification case",
    outputs: bool = True,
    step_extra: str = "",
) -> str:
    """A complete deck: mesh, material(s), sections, zero BCs, one NLGEOM static step.

    law: one Law for the whole mesh (elset EALL) or {elset: Law}. fixed: (nset or node
    index, first dof, last dof) fixed to zero before the step. prescribed: (node index or
    nset, dof, value) inside the step. pressure: (surface, p) follower *DLOAD. laplace:
    (surface, T) the project keyword *LAPLACE PRESSURE (not CalculiX). cloads: (node
    index, dof, force) dead loads. step_extra: keyword text put in the step after *STATIC
    (e.g. the project keywords *VOLUME CHANGE, *AXIAL STRETCH, *RIGID MOTION).
    """
    text = [f"*HEADING\n{heading}\n", mesh_text(mesh)]
    for s in sorted({s for s, _ in laplace}):  # *DLOAD lists element faces, ccx needs no surface
        text.append(surface_text(mesh, s))
    laws = law if isinstance(law, dict) else {"EALL": law}
    for k, (elset, lw) in enumerate(laws.items()):
        name = f"M{k + 1}"
        text.append(lw.deck_lines(name))
        integ = f", INTEGRATION={integration}" if integration else ""
        text.append(f"*SOLID SECTION, ELSET={elset}, MATERIAL={name}{integ}\n")
    if fixed:
        text.append("*BOUNDARY\n" + "".join(f"{_ref(n)}, {d0}, {d1}\n" for n, d0, d1 in fixed))
    text.append(f"*STEP, NLGEOM, INC={inc}\n*STATIC\n" + ", ".join(fmt(v) for v in static) + "\n")
    if step_extra:
        text.append(step_extra if step_extra.endswith("\n") else step_extra + "\n")
    if prescribed:
        text.append("*BOUNDARY\n" + "".join(f"{_ref(n)}, {d}, {d}, {fmt(v)}\n" for n, d, v in prescribed))
    if cloads:
        text.append("*CLOAD\n" + "".join(f"{n + 1}, {d}, {fmt(v)}\n" for n, d, v in cloads))
    for s, p in pressure:
        text.append(dload_text(mesh, s, p))
    for s, T in laplace:
        text.append(f"*LAPLACE PRESSURE, SURFACE={s}, TENSION={fmt(T)}\n")
    if outputs:
        text.append("*NODE PRINT, NSET=NALL\nU\n")
    text.append("*END STEP\n")
    out = "".join(text)
    if outputs:  # NALL for the ccx .dat output
        out = out.replace("*ELEMENT,", "*NSET, NSET=NALL, GENERATE\n1, %d\n*ELEMENT," % len(mesh.nodes), 1)
    return out


def fmt(v: float) -> str:
    """Shortest round-trip text of v that fits CalculiX's 20-character fields."""
    v = float(v)
    text = repr(v)
    digits = 17
    while len(text) > 20:
        digits -= 1
        text = f"{v:.{digits}g}"
    return text


def _ref(n) -> str:
    return n if isinstance(n, str) else str(int(n) + 1)


def write(path: Path, text: str) -> Path:
    path = Path(path)
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------------------
# Post-processing helpers shared by the tests
# ----------------------------------------------------------------------------------------

# Triangle quadrature, degree 6 (Dunavant, 12 points): barycentric (a, b, c), weight (area-normalised).
_D6 = [
    (0.249286745170910, 0.249286745170910, 0.501426509658179, 0.116786275726379),
    (0.063089014491502, 0.063089014491502, 0.873821971016996, 0.050844906370207),
    (0.053145049844817, 0.310352451033784, 0.636502499121399, 0.082851075618374),
]


def _quad_points():
    pts, w = [], []
    a, b, c, wt = _D6[0]
    for p in ((a, b, c), (b, c, a), (c, a, b)):
        pts.append(p)
        w.append(wt)
    a, b, c, wt = _D6[1]
    for p in ((a, b, c), (b, c, a), (c, a, b)):
        pts.append(p)
        w.append(wt)
    a, b, c, wt = _D6[2]
    for p in ((a, b, c), (b, c, a), (c, a, b), (b, a, c), (a, c, b), (c, b, a)):
        pts.append(p)
        w.append(wt)
    return np.array(pts), np.array(w)


def shape(order: int, L: np.ndarray) -> np.ndarray:
    """Shape functions at barycentric points L (q, 3) -> (q, 3|6)."""
    l1, l2, l3 = L[:, 0], L[:, 1], L[:, 2]
    if order == 1:
        return L.copy()
    return np.column_stack(
        [l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), l3 * (2 * l3 - 1), 4 * l1 * l2, 4 * l2 * l3, 4 * l3 * l1]
    )


def _shape_grad(order: int, L: np.ndarray) -> np.ndarray:
    """dN/d(xi, eta) with l1 = 1 - xi - eta, l2 = xi, l3 = eta -> (q, nn, 2)."""
    l1, l2, l3 = L[:, 0], L[:, 1], L[:, 2]
    if order == 1:
        g = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
        return np.broadcast_to(g, (len(L), 3, 2)).copy()
    d1 = np.stack([-(4 * l1 - 1), -(4 * l1 - 1)], -1)
    d2 = np.stack([4 * l2 - 1, 0 * l2], -1)
    d3 = np.stack([0 * l3, 4 * l3 - 1], -1)
    d4 = np.stack([4 * (l1 - l2), -4 * l2], -1)
    d5 = np.stack([4 * l3, 4 * l2], -1)
    d6 = np.stack([-4 * l3, 4 * (l1 - l3)], -1)
    return np.stack([d1, d2, d3, d4, d5, d6], 1)


def l2_error(mesh: Mesh, u: np.ndarray, exact) -> tuple[float, float]:
    """(||u_h - u||_L2, ||u||_L2) over the reference domain with an isoparametric map.

    u: (n_nodes, 2) nodal displacements; exact(X, Y) -> (ux, uy) at reference points.
    """
    L, w = _quad_points()
    N = shape(mesh.order, L)
    dN = _shape_grad(mesh.order, L)
    X = mesh.nodes[mesh.elems]  # (m, nn, 2)
    U = u[mesh.elems]
    xq = np.einsum("qa,mad->mqd", N, X)
    uq = np.einsum("qa,mad->mqd", N, U)
    jac = np.einsum("qak,mad->mqdk", dN, X)
    detj = np.abs(np.linalg.det(jac))  # (m, q)
    ex, ey = exact(xq[..., 0], xq[..., 1])
    err2 = ((uq[..., 0] - ex) ** 2 + (uq[..., 1] - ey) ** 2) * detj * w * 0.5
    nrm2 = (ex**2 + ey**2) * detj * w * 0.5
    return float(np.sqrt(err2.sum())), float(np.sqrt(nrm2.sum()))
