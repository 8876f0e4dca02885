"""The engine side of the effect catalog: the project keywords *VOLUME CHANGE (drainage),
*AXIAL STRETCH (out_of_plane), *RIGID MOTION (bone_motion) and AVRIL's C20 (stiffening),
against closed forms (engine_closed_forms.py) and against equivalent standard decks.

1. *VOLUME CHANGE dv on a free body (one node pinned, one dof of another: statically
   determinate): homogeneous F = diag(l, l, 1), sigma_11 = sigma_22 = 0 and sigma_33 the
   plane-strain reaction; l is NOT the growth factor g = (1 + dv)^(1/3) (plane strain keeps
   F33 = 1 while the stress-free state would need g). On a clamped square: the hydrostatic
   stress U'(1 / g^3). With D1 = 0 (CPE6H) the area follows the grown volume: l^2 = g^3.
2. *AXIAL STRETCH lambda_z on a free square: F = diag(l, l, lambda_z) with
   sigma_11 = sigma_22 = 0 (neo-Hooke and Avril, with and without C20).
3. *RIGID MOTION of a body by 30 degrees (an edge moved, the rest free; or every node):
   exact rigid displacements and zero stress; two steps with a moved centre; an annulus
   whose inner ring is moved rigidly equals the deck with those displacements written as
   *BOUNDARY values.
4. The hybrid elements: CPE6H and CPE3H match the closed forms above as CPE6 and CPE3 do,
   and CPE6H == CPE6 for a compressible law to 1e-8 with each keyword on homogeneous states;
   CPE3H == CPE3 on an inhomogeneous annulus with all three keywords (constant pressure per
   element, one-point rule: the pressure is condensable). CPE6H's continuous linear
   pressure is another discretization of an inhomogeneous field: there the two converge
   to each other with the mesh.
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_closed_forms import (
    Law,
    clamped_growth_pressure,
    elastic_gradient,
    free_inplane_stretch,
    growth_factor,
)
from engine_run import run_engine
from fe_cases import deck, fmt, ring, unit_square

AVRIL = Law("AVRIL", (1.0, 10.0))
AVRIL_C20 = Law("AVRIL", (1.0, 10.0, 0.6))  # the `stiffening` effect
NEO_HOOKE = Law("NEO HOOKE", (1.0, 0.1))
NEO_HOOKE_INCOMPRESSIBLE = Law("NEO HOOKE", (1.0, 0.0))

ELEMENTS = {"CPE3": (1, False), "CPE6": (2, False), "CPE3H": (1, True), "CPE6H": (2, True)}


def square(etype: str, n: int = 2):
    order, hybrid = ELEMENTS[etype]
    mesh = unit_square(n, order)
    mesh.hybrid = hybrid
    return mesh


def node_index(nodes: np.ndarray, X: np.ndarray) -> int:
    return int(np.argmin(np.hypot(nodes[:, 0] - X[0], nodes[:, 1] - X[1])))


def node_at(mesh, x: float, y: float) -> int:
    return int(np.flatnonzero(np.hypot(mesh.nodes[:, 0] - x, mesh.nodes[:, 1] - y) < 1e-12)[0])


def statically_determinate(mesh) -> list[tuple[int, int, int]]:
    """Pin (0, 0) and hold u_y of (1, 0): no rigid motion left, no constraint on a homogeneous state."""
    return [(node_at(mesh, 0.0, 0.0), 1, 2), (node_at(mesh, 1.0, 0.0), 2, 2)]


def cell_stress(run, step: int = 1) -> np.ndarray:
    """(n_cells, 6) Cauchy stress xx yy zz xy yz xz."""
    return np.concatenate(run.vtu(step).cell_data["cauchy_stress"])


def relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def solve(tmp_path, text: str, name: str = "job"):
    run = run_engine(text, tmp_path, name)
    assert run.returncode == 0, run.stderr
    return run


# ----------------------------------------------------------------------------------------
# Closed forms: self-checks in Python
# ----------------------------------------------------------------------------------------


def test_closed_form_free_growth_is_not_g_but_small_strain_poisson():
    """Plane strain: l - 1 -> (1 + nu)(g - 1) as dv -> 0, nu = (3K - 2mu) / (2 (3K + mu))."""
    mu, K = 2 * AVRIL.params[0], 2 * AVRIL.params[1]
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    for dv in (1e-5, -1e-5):
        g, l = growth_factor(dv), free_inplane_stretch(AVRIL, dv)
        assert (l - 1) / (g - 1) == pytest.approx(1 + nu, rel=1e-3)
    l, g = free_inplane_stretch(AVRIL, -0.1), growth_factor(-0.1)
    assert abs(l - g) > 1e-2  # at dv = -10 % the free stretch is far from g
    sigma = AVRIL.cauchy(elastic_gradient(l, l, -0.1))
    assert sigma[2, 2] > 0.1  # the body is not stress free: the constrained axis pulls


def test_closed_form_clamped_growth_is_hydrostatic():
    g = growth_factor(-0.1)
    sigma = AVRIL.cauchy(np.eye(3) / g)
    assert np.allclose(sigma, clamped_growth_pressure(AVRIL, -0.1) * np.eye(3), rtol=1e-13, atol=1e-14)


def test_closed_form_avril_c20_enters_w1():
    F = np.diag([1.3, 0.8, 1.0])
    assert not np.allclose(AVRIL_C20.cauchy(F), AVRIL.cauchy(F))
    assert np.allclose(AVRIL_C20.cauchy(np.eye(3)), 0.0, atol=1e-14)


# ----------------------------------------------------------------------------------------
# 1. *VOLUME CHANGE
# ----------------------------------------------------------------------------------------

DV = -0.1


@pytest.mark.parametrize("law", [AVRIL, AVRIL_C20, NEO_HOOKE], ids=["Avril", "Avril C20", "neo-Hooke"])
@pytest.mark.parametrize("etype", list(ELEMENTS))
def test_volume_change_free_body(tmp_path, etype, law):
    mesh = square(etype)
    text = deck(mesh, law, fixed=statically_determinate(mesh), step_extra=f"*VOLUME CHANGE, ELSET=EALL\n{fmt(DV)}\n")
    run = solve(tmp_path, text)
    l = free_inplane_stretch(law, DV)
    exact = (l - 1.0) * mesh.nodes
    error = relative(run.u(), exact)
    print(f"\n{etype} {law.kind}{law.params}: dv {DV}: l = {l:.12f} (g = {growth_factor(DV):.12f}), "
          f"|u - u_exact| / |u| = {error:.2e}")
    assert error < 1e-8
    s = cell_stress(run)
    sigma = law.cauchy(elastic_gradient(l, l, DV))
    scale = abs(sigma[2, 2])
    assert np.abs(s[:, [0, 1, 3, 4, 5]]).max() < 1e-8 * scale  # in-plane stress free ...
    assert np.abs(s[:, 2] - sigma[2, 2]).max() < 1e-8 * scale  # ... the plane-strain axis carries sigma_33
    J = np.concatenate(run.vtu(1).cell_data["J"])
    assert np.allclose(J, l * l, rtol=1e-9)


def test_volume_change_incompressible_follows_the_grown_volume(tmp_path):
    """D1 = 0 (CPE6H): J_e = 1, so the free area grows by g^3: l = g^(3/2)."""
    mesh = square("CPE6H")
    text = deck(mesh, NEO_HOOKE_INCOMPRESSIBLE, fixed=statically_determinate(mesh),
                step_extra=f"*VOLUME CHANGE, ELSET=EALL\n{fmt(DV)}\n")
    run = solve(tmp_path, text)
    l = growth_factor(DV) ** 1.5
    assert relative(run.u(), (l - 1.0) * mesh.nodes) < 1e-8


@pytest.mark.parametrize("etype", list(ELEMENTS))
def test_volume_change_clamped_square(tmp_path, etype):
    mesh = square(etype, n=3)
    text = deck(mesh, AVRIL, fixed=[("ALLB", 1, 2)], step_extra=f"*VOLUME CHANGE, ELSET=EALL\n{fmt(DV)}\n")
    run = solve(tmp_path, text)
    assert np.abs(run.u()).max() < 1e-12
    p = clamped_growth_pressure(AVRIL, DV)
    expected = np.array([p, p, p, 0.0, 0.0, 0.0])
    error = float(np.abs(cell_stress(run) - expected).max() / abs(p))
    print(f"\n{etype}: clamped, dv {DV}: sigma = {p:.12f} I, relative error {error:.2e}")
    # Displacement elements evaluate U'(J_e) at the exact J_e = 1/g^3; the hybrid elements'
    # pressure is an unknown, converged to Newton's tolerance (relative residual 1e-9).
    assert error < (1e-7 if ELEMENTS[etype][1] else 1e-12)


def test_volume_change_ramps_from_the_previous_step_and_op_new(tmp_path):
    """Step 1 dv = -0.1; step 2 dv = -0.2 on one half (OP=NEW drops the other half back to 0);
    step 3 back to dv = -0.1 everywhere: steps 1 and 3 match the closed form, step 2 differs."""
    mesh = square("CPE6")
    half = np.flatnonzero(mesh.nodes[mesh.elems[:, :3]].mean(axis=1)[:, 0] < 0.5)
    mesh.elsets = {"HALF": half}
    text = deck(mesh, AVRIL, fixed=statically_determinate(mesh), step_extra="*VOLUME CHANGE, ELSET=EALL\n-0.1\n")
    static = "*STATIC\n0.1, 1.0, 1e-5, 0.1\n"
    text += f"*STEP, NLGEOM, INC=1000\n{static}*VOLUME CHANGE, ELSET=HALF, OP=NEW\n-0.2\n*END STEP\n"
    text += f"*STEP, NLGEOM, INC=1000\n{static}*VOLUME CHANGE, ELSET=EALL\n-0.1\n*END STEP\n"
    run = solve(tmp_path, text)
    exact = (free_inplane_stretch(AVRIL, -0.1) - 1.0) * mesh.nodes
    u = [run.vtu(k).point_data["displacement"][:, :2] for k in (1, 2, 3)]
    assert relative(u[0], exact) < 1e-8
    assert relative(u[2], exact) < 1e-8
    assert relative(u[1], exact) > 0.1


# ----------------------------------------------------------------------------------------
# 2. *AXIAL STRETCH
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("stretch", [0.9, 1.1])
@pytest.mark.parametrize("law", [NEO_HOOKE, AVRIL, AVRIL_C20], ids=["neo-Hooke", "Avril", "Avril C20"])
@pytest.mark.parametrize("etype", list(ELEMENTS))
def test_axial_stretch_free_square(tmp_path, etype, law, stretch):
    mesh = square(etype)
    text = deck(mesh, law, fixed=statically_determinate(mesh), step_extra=f"*AXIAL STRETCH\n{fmt(stretch)}\n")
    run = solve(tmp_path, text)
    l = free_inplane_stretch(law, 0.0, stretch)
    error = relative(run.u(), (l - 1.0) * mesh.nodes)
    print(f"\n{etype} {law.kind}{law.params}: lambda_z {stretch}: l = {l:.12f}, relative error {error:.2e}")
    assert error < 1e-8
    sigma = law.cauchy(np.diag([l, l, stretch]))
    s = cell_stress(run)
    assert np.abs(s[:, [0, 1, 3, 4, 5]]).max() < 1e-8 * abs(sigma[2, 2])
    assert np.abs(s[:, 2] - sigma[2, 2]).max() < 1e-8 * abs(sigma[2, 2])
    J = np.concatenate(run.vtu(1).cell_data["J"])
    assert np.allclose(J, stretch * l * l, rtol=1e-9)  # J includes lambda_z


def test_axial_stretch_with_volume_change_is_stress_free_at_lambda_z_equal_g(tmp_path):
    """lambda_z = g with the same dv: the stress-free grown state F = g I, no stress at all."""
    mesh = square("CPE6H")
    g = growth_factor(DV)
    text = deck(mesh, AVRIL, fixed=statically_determinate(mesh),
                step_extra=f"*VOLUME CHANGE, ELSET=EALL\n{fmt(DV)}\n*AXIAL STRETCH\n{fmt(g)}\n")
    run = solve(tmp_path, text)
    assert relative(run.u(), (g - 1.0) * mesh.nodes) < 1e-10
    assert np.abs(cell_stress(run)).max() < 1e-10


# ----------------------------------------------------------------------------------------
# 3. *RIGID MOTION
# ----------------------------------------------------------------------------------------


def rigid(X: np.ndarray, t, angle_deg: float, c) -> np.ndarray:
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.asarray(t) + (X - np.asarray(c)) @ (R - np.eye(2)).T


@pytest.mark.parametrize("nset", ["LEFT", "NALL"], ids=["edge moved, body free", "every node moved"])
@pytest.mark.parametrize("etype", list(ELEMENTS))
def test_rigid_motion_of_a_body_by_30_degrees(tmp_path, etype, nset):
    mesh = square(etype, n=3)
    text = deck(mesh, AVRIL, step_extra=f"*RIGID MOTION, NSET={nset}\n0.3, -0.2, 30\n")
    run = solve(tmp_path, text)
    ids = mesh.nsets[nset] if nset in mesh.nsets else np.arange(len(mesh.nodes))
    centre = mesh.nodes[ids].mean(axis=0)  # the default centre: the set's centroid
    exact = rigid(mesh.nodes, (0.3, -0.2), 30.0, centre)
    error = relative(run.u(), exact)
    stress = float(np.abs(cell_stress(run)).max() / AVRIL.params[0])
    print(f"\n{etype} {nset}: 30 degrees: |u - u_rigid| / |u| = {error:.2e}, max |sigma| / C10 = {stress:.2e}")
    # Every node moved: the rigid kinematics and the elements' objectivity alone, exact to
    # round-off. An edge moved and the body free: the free nodes lag behind the edge in each
    # increment and are brought back by Newton to its tolerance (relative residual 1e-9).
    tolerance = 1e-12 if nset == "NALL" else 1e-9
    assert error < tolerance
    assert stress < tolerance


def test_rigid_motion_two_steps_with_a_moved_centre(tmp_path):
    """Step 1: 30 degrees about the centroid; step 2: 100 degrees and a new translation about
    (2, -1): the body stays rigid at the end of each step (the previous motion is re-expressed
    about the new centre, so nothing jumps)."""
    mesh = square("CPE6", n=3)
    text = deck(mesh, AVRIL, step_extra="*RIGID MOTION, NSET=LEFT\n0.3, -0.2, 30\n")
    text += "*STEP, NLGEOM, INC=1000\n*STATIC\n0.1, 1.0, 1e-5, 0.1\n*RIGID MOTION, NSET=LEFT, CX=2, CY=-1\n1.0, 0.5, 100\n*END STEP\n"
    run = solve(tmp_path, text)
    centre = mesh.nodes[mesh.nsets["LEFT"]].mean(axis=0)
    u1 = run.vtu(1).point_data["displacement"][:, :2]
    u2 = run.vtu(2).point_data["displacement"][:, :2]
    assert relative(u1, rigid(mesh.nodes, (0.3, -0.2), 30.0, centre)) < 1e-9  # Newton's tolerance, as above
    assert relative(u2, rigid(mesh.nodes, (1.0, 0.5), 100.0, (2.0, -1.0))) < 1e-9
    assert np.abs(cell_stress(run, 2)).max() < 1e-9 * AVRIL.params[0]


def test_rigid_motion_starts_from_where_its_nodes_stood(tmp_path):
    """Step 1: a free body drains (its nodes move); step 2: a new *RIGID MOTION of the left
    edge (taking over the pin of the model data). The edge starts from its drained place
    and ends exactly on the rigid motion of its reference positions."""
    mesh = square("CPE6", n=3)
    text = deck(mesh, AVRIL, fixed=statically_determinate(mesh), step_extra="*VOLUME CHANGE, ELSET=EALL\n-0.1\n")
    text += "*STEP, NLGEOM, INC=1000\n*STATIC\n0.1, 1.0, 1e-5, 0.1\n*RIGID MOTION, NSET=LEFT\n0.05, 0.1, 20\n*END STEP\n"
    run = solve(tmp_path, text)
    left = mesh.nsets["LEFT"]
    u1 = run.vtu(1).point_data["displacement"][:, :2]
    u2 = run.vtu(2).point_data["displacement"][:, :2]
    assert relative(u1, (free_inplane_stretch(AVRIL, -0.1) - 1.0) * mesh.nodes) < 1e-8
    exact = rigid(mesh.nodes[left], (0.05, 0.1), 20.0, mesh.nodes[left].mean(axis=0))
    assert np.abs(u2[left] - exact).max() < 1e-14
    assert np.abs(u1[left] - exact).max() > 1e-2  # the edge did move in step 2


def leg_slice(order: int, hybrid: bool = False):
    mesh = ring(3, 24, order, A=1.0, outer=(2.4, 1.9))
    mesh.hybrid = hybrid
    return mesh


MOTION = (0.08, -0.05, 12.0)  # ux, uy, angle in degrees
TENSION = 0.4


def test_rigid_motion_equals_the_boundary_values(tmp_path):
    """Annulus (a leg slice: bone ring inside, garment tension on the elliptic skin): the
    inner ring given a *RIGID MOTION equals the same deck with *BOUNDARY values from Python."""
    mesh = leg_slice(2)
    inner = mesh.nsets["INNER"]
    ux, uy, angle = MOTION
    u_inner = rigid(mesh.nodes[inner], (ux, uy), angle, mesh.nodes[inner].mean(axis=0))
    static = (0.25, 1.0, 1e-4, 0.25)
    moved = solve(tmp_path, deck(mesh, AVRIL, laplace=[("OUTER", TENSION)], static=static,
                                 step_extra=f"*RIGID MOTION, NSET=INNER\n{ux}, {uy}, {angle}\n"), "rigid")
    prescribed = [(int(n), d + 1, float(u_inner[k, d])) for k, n in enumerate(inner) for d in (0, 1)]
    written = solve(tmp_path, deck(mesh, AVRIL, laplace=[("OUTER", TENSION)], static=static, prescribed=prescribed),
                    "boundary")
    error = relative(moved.u(), written.u())
    print(f"\nannulus, inner ring moved by {MOTION}: |u_rigid - u_boundary| / |u| = {error:.2e}")
    assert np.abs(moved.u()[inner] - u_inner).max() < 1e-14
    assert error < 1e-8
    # Not trivially rigid: the garment tension deforms the tissue.
    free = rigid(mesh.nodes, (ux, uy), angle, mesh.nodes[inner].mean(axis=0))
    assert np.abs(moved.u() - free).max() > 1e-2


# ----------------------------------------------------------------------------------------
# 4. Hybrid elements
# ----------------------------------------------------------------------------------------

KEYWORD_CASES = {
    "VOLUME CHANGE": f"*VOLUME CHANGE, ELSET=EALL\n{fmt(DV)}\n",
    "AXIAL STRETCH": "*AXIAL STRETCH\n0.93\n",
    "RIGID MOTION": "*RIGID MOTION, NSET=LEFT\n0.1, 0.05, 25\n",
}


@pytest.mark.parametrize("keyword", list(KEYWORD_CASES))
def test_cpe6h_equals_cpe6_for_a_compressible_law(tmp_path, keyword):
    """Homogeneous states, where CPE6H's linear pressure holds U'(J_e) exactly: rollers on
    the left and bottom edges and a follower pressure on the top face with the volume change
    or the axial stretch; the rigid motion of the left edge of a free body."""
    runs = {}
    for etype in ("CPE6", "CPE6H"):
        mesh = square(etype, n=3)
        if keyword == "RIGID MOTION":
            text = deck(mesh, AVRIL, step_extra=KEYWORD_CASES[keyword])
        else:
            text = deck(mesh, AVRIL, fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", 0.2)],
                        step_extra=KEYWORD_CASES[keyword])
        runs[etype] = solve(tmp_path, text, etype)
    error = relative(runs["CPE6H"].u(), runs["CPE6"].u())
    print(f"\n{keyword}: |u_CPE6H - u_CPE6| / |u| = {error:.2e}")
    assert error < 1e-8


def annulus_with_every_keyword(order: int, hybrid: bool, muscle_only: bool = True, nr: int = 3, nt: int = 24):
    mesh = ring(nr, nt, order, A=1.0, outer=(2.4, 1.9))
    mesh.hybrid = hybrid
    centroids = mesh.nodes[mesh.elems[:, :3]].mean(axis=1)
    drained = np.flatnonzero(centroids[:, 0] > 0.3) if muscle_only else np.arange(len(mesh.elems))
    mesh.elsets = {"MUSCLE": drained}
    ux, uy, angle = MOTION
    extra = (f"*VOLUME CHANGE, ELSET=MUSCLE\n-0.08\n*AXIAL STRETCH\n0.97\n"
             f"*RIGID MOTION, NSET=INNER\n{ux}, {uy}, {angle}\n")
    return mesh, deck(mesh, AVRIL, laplace=[("OUTER", TENSION)], static=(0.25, 1.0, 1e-4, 0.25), step_extra=extra)


def test_cpe3h_equals_cpe3_on_an_inhomogeneous_annulus_with_every_keyword(tmp_path):
    """Part of the ring drains (a jump of dv across element edges), the axial stretch and the
    rigid motion of the inner ring act together: CPE3H's constant pressure per element with
    the one-point rule solves U'(J_e) = p exactly in each element, so it equals CPE3."""
    u = {}
    for etype in ("CPE3", "CPE3H"):
        _, text = annulus_with_every_keyword(*ELEMENTS[etype])
        u[etype] = solve(tmp_path, text, etype).u()
    error = relative(u["CPE3H"], u["CPE3"])
    print(f"\nannulus, every keyword: |u_CPE3H - u_CPE3| / |u| = {error:.2e}")
    assert error < 1e-8


def test_cpe6h_converges_to_cpe6_on_an_annulus_with_every_keyword(tmp_path):
    """CPE6H's pressure is continuous and linear, so on an inhomogeneous field it is another
    discretization than CPE6's pointwise U'(J_e): the two agree as the mesh is refined (here
    with the whole ring drained; a jump of dv across an interface makes the continuous
    pressure smear the pressure jump, and the agreement comes only at a rate h^(1/2))."""
    differences = []
    for nr, nt in ((3, 24), (6, 48)):
        u = {}
        for etype in ("CPE6", "CPE6H"):
            _, text = annulus_with_every_keyword(*ELEMENTS[etype], muscle_only=False, nr=nr, nt=nt)
            u[etype] = solve(tmp_path, text, f"{etype}_{nr}").u()
        differences.append(relative(u["CPE6H"], u["CPE6"]))
    print(f"\nannulus, every keyword: |u_CPE6H - u_CPE6| / |u| = {differences[0]:.2e} (3 x 24), "
          f"{differences[1]:.2e} (6 x 48)")
    assert differences[0] < 1e-3
    assert differences[1] < 0.3 * differences[0]  # at least second order in h
