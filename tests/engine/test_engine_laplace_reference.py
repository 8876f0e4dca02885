"""The garment's reference-curvature law: *LAPLACE PRESSURE, ..., REFERENCE=alpha in calfit-fe.

The load is (1 - alpha) f_deformed + alpha f_reference (solver_cpp/README.md, Project keywords): f_deformed the
membrane load T/r of the deformed contour (test_engine_laplace.py), f_reference a follower pressure whose nodal
values p0 the REFERENCE contour fixes. p0 is computed here by hand (`reference_pressures`, an independent
implementation): the membrane load F0 of the tension on the reference contour, its kink forces T (t+ - t-)
included, summed at each face corner with half of each T6 face's mid-side share, over the consistent length
L0 along the unit normal n0, p0 = -(F0 . n0) / L0; a mid-side node takes the mean of its face's corners.

1. Circle of radius R0 cut into equal chords (CPE3, and CPE6 with straight skin faces as calfit's leg meshes
   have): p0 = T / R0 at every node, so REFERENCE=1 is *DLOAD T / R0 on every skin face, to round-off. An
   ellipse under a FOURIER tension profile: the applied pressure is p0 of the nodal tensions by hand, and at
   alpha = 0.4 (CPE3) 0.6 T/r of the deformed contour + 0.4 p0, to round-off.
2. The leg-like slice (orchestrator.meshing, CPE6 and CPE3, non-circular skin): the engine's laplace_pressure
   at alpha = 1 is p0 by hand to round-off; the displacements are those of *DLOAD with each face's mean p0
   (one constant pressure per face, where the engine interpolates p0 along it) to the discretisation (below
   1 % of max |u|, less on the finer mesh); the unsymmetric tangent of the follower pressure is solved as such
   (not the plain Cholesky of a symmetric one) and Newton converges quadratically (a tangent without the
   pressure's load stiffness took 25 iterations an increment and did not finish in 100 increments).
3. The same *DLOAD deck in CalculiX (`ccx`-marked): within 0.5 % of max |u|. CalculiX needs 10 increments:
   in one, its iterations stop on a zero residual with a 2 % displacement correction still pending (0.9 % of
   max |u| from calfit-fe's *DLOAD; 10 increments: 0.035 %).
4. *SENSITIVITY REFERENCE, SKIN against central differences of two engine runs (at alpha = 0.5, and at 0 by the
   one-sided second-order difference), TENSION and the profile's A1 with alpha = 0.5.
5. A change of alpha between steps ramps both shares: two steps (alpha 0 then 1) end where one step with
   alpha = 1 does.
6. Deck errors: REFERENCE outside [0, 1] or not a number; a REFERENCE sensitivity without its load.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from engine_closed_forms import Law
from engine_run import ccx_displacement_array, run_ccx, run_engine
from fe_cases import deck, face_nodes, fmt, ring

from orchestrator.engine.results import EngineResults
from orchestrator.meshing import leg_slice_deck, leg_slice_mesh

LAW = Law("AVRIL", (1.0, 10.0))
TENSION = 0.16  # N/mm on the leg (p about 3 kPa)
RING_STATIC = (0.5, 1.0, 1e-4, 0.5)

# ----------------------------------------------------------------------------------------
# p0 by hand
# ----------------------------------------------------------------------------------------

_GAUSS = [(0.5 - 0.5 * np.sqrt(0.6), 5.0 / 18.0), (0.5, 8.0 / 18.0), (0.5 + 0.5 * np.sqrt(0.6), 5.0 / 18.0)]


def _edge_shape(n: int, s: float) -> tuple[np.ndarray, np.ndarray]:
    if n == 2:
        return np.array([1.0 - s, s]), np.array([-1.0, 1.0])
    return (np.array([(1 - s) * (1 - 2 * s), 4 * s * (1 - s), s * (2 * s - 1)]),
            np.array([4 * s - 3, 4 - 8 * s, 4 * s - 1]))


def _face_node_ids(elements: np.ndarray, element: int, face: int) -> list[int]:
    """Corner, (mid-side), corner of face 1..3 (corner k to corner k + 1)."""
    e = elements[element]
    a, b = face - 1, face % 3
    return [int(e[a]), int(e[b])] if elements.shape[1] == 3 else [int(e[a]), int(e[3 + face - 1]), int(e[b])]


def reference_pressures(nodes: np.ndarray, elements: np.ndarray, faces, tension) -> np.ndarray:
    """p0 at every node of the faces (0 elsewhere); tension: one value, or one per node."""
    tension = np.broadcast_to(np.asarray(tension, dtype=float), (len(nodes),))
    force, normal, length = np.zeros((len(nodes), 2)), np.zeros((len(nodes), 2)), np.zeros(len(nodes))
    for element, face in faces:
        ids = _face_node_ids(elements, element, face)
        X, n = nodes[ids], len(ids)
        f, nw, w = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)
        for s, weight in _GAUSS:
            N, dN = _edge_shape(n, s)
            dx = dN @ X
            t = dx / np.hypot(*dx)
            T, dT = N @ tension[ids], dN @ tension[ids]
            f -= weight * np.outer(dT * N + T * dN, t)  # -integral (T N_a)' t
            w += weight * N * np.hypot(*dx)
            nw += weight * np.outer(N, [dx[1], -dx[0]])
        for corner in (0, n - 1):
            node, share = ids[corner], [corner] + ([1] if n == 3 else [])
            weights = [1.0] + [0.5] * (n == 3)
            force[node] += sum(c * f[k] for c, k in zip(weights, share))
            normal[node] += sum(c * nw[k] for c, k in zip(weights, share))
            length[node] += sum(c * w[k] for c, k in zip(weights, share))
    p = np.zeros(len(nodes))
    on = length > 0
    p[on] = -np.sum(force[on] * normal[on] / np.linalg.norm(normal[on], axis=1)[:, None], axis=1) / length[on]
    for element, face in faces:
        ids = _face_node_ids(elements, element, face)
        if len(ids) == 3:
            p[ids[1]] = 0.5 * (p[ids[0]] + p[ids[2]])
    return p


def face_mean(p: np.ndarray, ids: list[int]) -> float:
    """integral p(xi) dxi over a face of nodal values p (linear or quadratic interpolation)."""
    values = p[ids]
    return float(values.mean() if len(ids) == 2 else (values[0] + 4.0 * values[1] + values[2]) / 6.0)


def with_reference(text: str, alpha: float | str) -> str:
    """The deck with REFERENCE=alpha on its *LAPLACE PRESSURE line."""
    out, count = re.subn(r"(\*LAPLACE PRESSURE,[^\n]*)", rf"\1, REFERENCE={alpha}", text)
    assert count == 1
    return out


def converged(run) -> None:
    assert run.returncode == 0, run.stderr
    assert run.summary["status"] == "converged"


# ----------------------------------------------------------------------------------------
# 1. Circle: REFERENCE=1 is the follower pressure T / R0
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6-straight-skin"])
def test_circle_reference_is_follower_pressure_t_over_r0(tmp_path, order):
    mesh = ring(4, 48 if order == 1 else 24, order, outer=(2.0, 2.0))
    if order == 2:  # the skin's mid-side nodes to the middle of their chords, as on calfit's leg meshes
        for element, face in mesh.surfaces["OUTER"]:
            a, mid, b = face_nodes(mesh, element, face)
            mesh.nodes[mid] = 0.5 * (mesh.nodes[a] + mesh.nodes[b])
    T, R0 = 1.0, 2.0
    common = dict(fixed=[("INNER", 1, 2)], static=RING_STATIC)
    reference = run_engine(with_reference(deck(mesh, LAW, laplace=[("OUTER", T)], **common), 1), tmp_path, "reference")
    follower = run_engine(deck(mesh, LAW, pressure=[("OUTER", T / R0)], **common), tmp_path, "dload")
    converged(reference)
    converged(follower)
    u, u_dload = reference.u(), follower.u()
    assert np.abs(u - u_dload).max() < 1e-10 * np.abs(u_dload).max()
    pressure = np.asarray(reference.vtu(1).point_data["laplace_pressure"]).ravel()
    outer = mesh.nsets["OUTER"]
    assert np.abs(pressure[outer] - T / R0).max() < 1e-12 * T / R0
    assert np.all(pressure[np.setdiff1d(np.arange(len(mesh.nodes)), outer)] == 0.0)


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
def test_ellipse_reference_pressure_with_profile_is_hand_computed(tmp_path, order):
    """A FOURIER tension profile about the origin on an ellipse (quadratic arcs with CPE6): the applied pressure at
    alpha = 1 is p0 of the nodal tensions T (1 + a1 cos theta + b2 sin 2 theta), by hand; at alpha = 0.4 (CPE3) it
    is 0.6 T/r + 0.4 p0, T/r the deformed-contour law's -(F . n) / L at the run's own deformed positions (on
    straight faces the same sum as p0's, F_a = T_a (t+ - t-))."""
    mesh = ring(3, 48 if order == 1 else 24, order, outer=(2.4, 1.6))
    T, a1, b2 = 1.0, 0.3, -0.2
    text = deck(mesh, LAW, fixed=[("INNER", 1, 2)], laplace=[("OUTER", T)], static=RING_STATIC)
    text = text.replace(f"TENSION={fmt(T)}", f"TENSION={fmt(T)}, PROFILE=GARMENT")
    text = text.replace("*STEP", f"*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER, CX=0, CY=0\n1, {a1}, 0\n2, 0, {b2}\n*STEP", 1)
    theta = np.arctan2(mesh.nodes[:, 1], mesh.nodes[:, 0])
    tension = T * (1 + a1 * np.cos(theta) + b2 * np.sin(2 * theta))
    p0 = reference_pressures(deck_positions(text, len(mesh.nodes)), mesh.elems, mesh.surfaces["OUTER"], tension)
    outer = mesh.nsets["OUTER"]
    reference = run_engine(with_reference(text, 1), tmp_path, "reference")
    converged(reference)
    applied = EngineResults(reference.outdir).point_field("laplace_pressure")[outer]
    assert np.abs(applied - p0[outer]).max() < 1e-12 * p0[outer].max()
    assert p0[outer].max() > 1.5 * p0[outer].min()  # the profile and the ellipse both show
    if order == 1:
        mixed = run_engine(with_reference(text, 0.4), tmp_path, "mixed")
        converged(mixed)
        x = deck_positions(text, len(mesh.nodes)) + mixed.u()
        deformed = reference_pressures(x, mesh.elems, mesh.surfaces["OUTER"], tension)
        applied = EngineResults(mixed.outdir).point_field("laplace_pressure")[outer]
        expected = 0.6 * deformed[outer] + 0.4 * p0[outer]
        assert np.abs(applied - expected).max() < 1e-12 * expected.max()
        assert np.abs(deformed[outer] - p0[outer]).max() > 1e-3 * p0[outer].max()


# ----------------------------------------------------------------------------------------
# 2. and 3. The leg-like slice against *DLOAD with each face's mean p0, and CalculiX
# ----------------------------------------------------------------------------------------

_LEG_MESHES: dict[tuple[int, int], object] = {}


def leg_mesh(n_elements: int, order: int):
    if (n_elements, order) not in _LEG_MESHES:
        _LEG_MESHES[n_elements, order] = leg_slice_mesh(n_elements, order=order)
    return _LEG_MESHES[n_elements, order]


def deck_positions(text: str, n_nodes: int) -> np.ndarray:
    """The node positions as written in the deck's *NODE block (ids 1..n in order)."""
    block = text[text.index("\n", text.index("*NODE")) + 1:]
    rows = [line.split(",") for line in block[: block.index("*")].splitlines()]
    assert [int(row[0]) for row in rows] == list(range(1, n_nodes + 1))
    return np.array([[float(row[1]), float(row[2])] for row in rows])


def leg_decks(folder: Path, mesh, dload_static=(1.0, 1.0, 1e-4, 1.0)):
    """(the Laplace deck without REFERENCE, the *DLOAD deck of each face's mean p0, p0 at every node); p0 by hand
    on the node positions the engine reads from the deck (10 significant digits)."""
    folder.mkdir(parents=True, exist_ok=True)
    leg_slice_deck(folder / "laplace.inp", mesh=mesh, laplace_tension=TENSION, include_mesh=False)
    leg_slice_deck(folder / "dload.inp", mesh=mesh, pressure=1.0, include_mesh=False, static=dload_static)
    dload = (folder / "dload.inp").read_text()
    faces = [tuple(face) for face in mesh.skin_faces.tolist()]
    p0 = reference_pressures(deck_positions(dload, len(mesh.nodes)), mesh.elements, faces, TENSION)
    per_face = {f"{e + 1}, P{k}, 1": f"{e + 1}, P{k}, {fmt(face_mean(p0, _face_node_ids(mesh.elements, e, k)))}"
                for e, k in faces}
    dload, count = re.subn(r"^\d+, P\d, 1$", lambda m: per_face[m.group(0)], dload, flags=re.M)
    assert count == len(faces)
    return (folder / "laplace.inp").read_text(), dload, p0


@pytest.mark.parametrize("order, sizes", [(2, (450, 1200)), (1, (900, 2400))], ids=["CPE6", "CPE3"])
def test_leg_reference_matches_dload_of_face_mean_p0(tmp_path, order, sizes):
    differences = []
    for n_elements in sizes:
        mesh = leg_mesh(n_elements, order)
        folder = tmp_path / str(n_elements)
        laplace, dload, p0 = leg_decks(folder, mesh)
        reference = run_engine(with_reference(laplace, 1), folder, "reference")
        follower = run_engine(dload, folder, "dload")
        converged(reference)
        converged(follower)
        skin = mesh.node_sets["SKIN_NODES"]
        applied = EngineResults(reference.outdir).point_field("laplace_pressure")
        assert np.abs(applied[skin] - p0[skin]).max() < 1e-12 * p0[skin].max()
        assert p0[skin].min() > 0.5 * p0[skin].max()  # a convex, leg-like outline: p0 varies, and stays > 0
        # The follower pressure's tangent is unsymmetric: not the plain Cholesky of a symmetric one (the uniform
        # garment's deformed-contour law is symmetric). Newton in one increment, quadratically.
        assert reference.summary["linear_solver"] in ("cholmod-split", "umfpack")
        history = reference.residual_histories()
        assert len(history) == 1 and len(history[0]) <= 6 and history[0][-1] < 1e-12, history
        deformed = run_engine(laplace, folder, "deformed")
        converged(deformed)
        assert deformed.summary["linear_solver"] == "cholmod"
        u, u_dload = reference.u(), follower.u()
        differences.append(np.abs(u - u_dload).max() / np.abs(u_dload).max())
        # the laws differ: the deformed contour's curvature is not the reference one's
        assert np.abs(deformed.u() - u).max() > 5 * np.abs(u - u_dload).max()
    print(f"REFERENCE=1 vs *DLOAD of the faces' mean p0, {sizes} elements: {differences} of max |u|")
    assert differences[0] < 1e-2
    assert differences[1] < 0.7 * differences[0]


@pytest.mark.ccx
@pytest.mark.skipif(shutil.which("ccx") is None, reason="ccx (CalculiX) not installed")
def test_leg_reference_against_calculix(tmp_path):
    mesh = leg_mesh(450, 2)
    laplace, dload, _ = leg_decks(tmp_path, mesh, dload_static=(0.1, 1.0, 1e-5, 0.1))
    reference = run_engine(with_reference(laplace, 1), tmp_path, "reference")
    converged(reference)
    rc, displacements, out = run_ccx(dload, tmp_path / "ccx", "dload")
    assert rc == 0, out[-2000:]
    u_ccx = ccx_displacement_array(displacements, reference.table[:, 0])
    difference = np.abs(reference.u() - u_ccx).max() / np.abs(u_ccx).max()
    print(f"REFERENCE=1 vs CalculiX *DLOAD of the faces' mean p0: {difference:.2e} of max |u|")
    assert difference < 5e-3


# ----------------------------------------------------------------------------------------
# 4. Sensitivities
# ----------------------------------------------------------------------------------------

FD_STEP = 1e-3


def _sensitivity_deck(laplace: str, alpha: float, tension: float = TENSION, a1: float = 0.1,
                      parameters: tuple[str, ...] = ()) -> str:
    text = laplace.replace(f"TENSION={TENSION:.10g}", f"TENSION={tension!r}, PROFILE=GARMENT")
    text = text.replace("*STEP,", f"*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER\n1, {a1!r}, 0.05\n*STEP,", 1)
    text = with_reference(text, repr(alpha)) if alpha else text
    if parameters:
        text += "*SENSITIVITY, PRESSURE=YES\n" + "\n".join(parameters) + "\n"
    return text


def test_reference_sensitivity_matches_finite_differences(tmp_path):
    laplace, _, _ = leg_decks(tmp_path, leg_mesh(450, 2))
    counter = iter(range(100))

    def solve(**values):
        run = run_engine(_sensitivity_deck(laplace, **values), tmp_path, f"run{next(counter)}")
        converged(run)
        assert run.residual_histories()[-1][-1] < 1e-10
        return run.u(), EngineResults(run.outdir).cell_field("pressure")

    report = []
    for alpha in (0.5, 0.0):
        base = run_engine(_sensitivity_deck(laplace, alpha, parameters=("REFERENCE, SKIN", "TENSION, SKIN",
                                                                        "PROFILE, GARMENT, A1")), tmp_path, f"base{alpha}")
        converged(base)
        results = EngineResults(base.outdir)
        du, dp = results.sensitivities(), results.pressure_sensitivities()
        assert {e["name"]: e["value"] for e in results.sensitivity_parameters}["REFERENCE:SKIN"] == alpha
        steps = {"REFERENCE:SKIN": ("alpha", alpha, FD_STEP), "TENSION:SKIN": ("tension", TENSION, FD_STEP * TENSION),
                 "PROFILE:GARMENT:A1": ("a1", 0.1, FD_STEP * 0.1)}
        for name, (keyword, value, h) in steps.items():
            if alpha == 0.0 and name != "REFERENCE:SKIN":
                continue
            others = {"alpha": alpha}
            if value == 0.0:  # alpha < 0 is no deck: the one-sided difference of second order
                (u0, p0), (u1, p1), (u2, p2) = (solve(**{**others, keyword: v}) for v in (0.0, h, 2 * h))
                du_fd, dp_fd = (-3 * u0 + 4 * u1 - u2) / (2 * h), (-3 * p0 + 4 * p1 - p2) / (2 * h)
            else:
                (u_minus, p_minus), (u_plus, p_plus) = (solve(**{**others, keyword: value + s * h}) for s in (-1, 1))
                du_fd, dp_fd = (u_plus - u_minus) / (2 * h), (p_plus - p_minus) / (2 * h)
            error = np.abs(du[name] - du_fd).max() / np.abs(du_fd).max()
            dp_error = np.abs(dp[name] - dp_fd).max() / np.abs(dp_fd).max()
            report.append((alpha, name, float(np.abs(du_fd).max()), float(error), float(dp_error)))
    print("\nalpha, parameter, max |du/dtheta|, relative error of du, of dp")
    for row in report:
        print("  %.1f %-20s %.4e  %.2e  %.2e" % row)
    assert max(row[3] for row in report) < 1e-5, report
    assert max(row[4] for row in report) < 1e-4, report


# ----------------------------------------------------------------------------------------
# 5. Steps, 6. deck errors
# ----------------------------------------------------------------------------------------


def _ellipse_deck(step_loads: list[str]) -> str:
    mesh = ring(3, 32, 2, outer=(2.4, 1.6))
    text = deck(mesh, LAW, fixed=[("INNER", 1, 2)], laplace=[("OUTER", 1.0)], static=RING_STATIC)
    step = text[text.index("*STEP"):]
    steps = "".join(re.sub(r"\*LAPLACE PRESSURE[^\n]*", load, step) for load in step_loads)
    return text[: text.index("*STEP")] + steps


def test_reference_changed_between_steps_ends_at_the_one_step_state(tmp_path):
    line = "*LAPLACE PRESSURE, SURFACE=OUTER, TENSION=1.0"
    two = run_engine(_ellipse_deck([line, line + ", REFERENCE=1"]), tmp_path, "two")
    one = run_engine(_ellipse_deck([line + ", REFERENCE=1"]), tmp_path, "one")
    deformed = run_engine(_ellipse_deck([line]), tmp_path, "deformed")
    for run in (two, one, deformed):
        converged(run)
    u_two, u_one = two.u(), one.u()
    assert np.abs(u_two - u_one).max() < 1e-9 * np.abs(u_one).max()
    assert np.abs(u_one - deformed.u()).max() > 1e-2 * np.abs(u_one).max()


def _error(tmp_path: Path, text: str) -> tuple[int, int, str]:
    run = run_engine(text, tmp_path, "bad")
    found = re.findall(r"bad\.inp:(\d+):", run.stderr)
    return run.returncode, int(found[0]) if found else -1, run.stderr


@pytest.mark.parametrize("value, fragment", [("1.5", "outside [0, 1]"), ("-0.2", "outside [0, 1]"),
                                             ("most", "REFERENCE is not a number: 'most'")])
def test_reference_out_of_range_is_deck_error(tmp_path, value, fragment):
    text = _ellipse_deck([f"*LAPLACE PRESSURE, SURFACE=OUTER, TENSION=1.0, REFERENCE={value}"])
    returncode, line, stderr = _error(tmp_path, text)
    assert returncode == 2, stderr
    assert line == text.splitlines().index(f"*LAPLACE PRESSURE, SURFACE=OUTER, TENSION=1.0, REFERENCE={value}") + 1
    assert fragment in stderr


@pytest.mark.parametrize("data_line, fragment", [("REFERENCE, BACK", "surface BACK is not defined"),
                                                 ("REFERENCE", "expected REFERENCE, surface"),
                                                 ("REFERENCE, INNER_FACES", "no *LAPLACE PRESSURE on surface")])
def test_malformed_reference_sensitivity(tmp_path, data_line, fragment):
    text = _ellipse_deck(["*LAPLACE PRESSURE, SURFACE=OUTER, TENSION=1.0, REFERENCE=0.5"])
    text = text.replace("*MATERIAL", "*SURFACE, NAME=INNER_FACES, TYPE=ELEMENT\n1, S1\n*MATERIAL", 1)
    text += f"*SENSITIVITY\n{data_line}\n"
    returncode, line, stderr = _error(tmp_path, text)
    assert returncode == 2, stderr
    assert line == len(text.splitlines())
    assert fragment in stderr
