"""Coulomb friction in calfit-fe's penalty contact: answers that depend neither on the increments nor on the
slave nodes' spacing.

A stiff slider (E = 1e6) above a stiff clamped base, an open gap g0 between them; the slider's top is moved
down by g0 + d and sideways by s, linearly over one step (both dofs prescribed). The bodies barely deform
(the contact tractions are of order 1), so the slider's bottom follows its top: it touches the base at the
fraction alpha = g0 / (g0 + d) of the step and then slides by s (1 - alpha) over the base under the normal
overclosure d. With penalty K, stick slope lambda and friction mu, per unit contact length L:

    normal force      N = K d L,
    tangential force  F = min(lambda s (1 - alpha), mu K d) L      (stick, or sliding at mu N).

1. Increments: the same answer whether the step is taken in 1, 3 or 12 increments. Before the first touch was
   located within its increment (solver_cpp/src/contact/node_to_segment.hpp), the increment in which a node
   touched was frictionless: one increment gave F = 0, three gave F too small; the leg under the explicit
   garment band, whose band wraps onto the skin within two of its five release increments, moved by 48 um RMS
   between 5 and 80 increments (10 times the 5 um left now).
2. Slave spacing: N and F do not depend on how many T3/T6 elements the slider's bottom has (the tangential
   force is weighted by each slave node's tributary length as the normal one is).
3. Reference state: a slave node touching the master in the very first increment of the analysis is anchored
   like any other (the contact history of the reference state is recorded before the first increment).
4. CalculiX (live, when installed), on the same deck: its node-to-surface penalty friction gives calfit-fe's forces
   (the closed form) once its increments put the first touch on an increment's boundary; its face-to-face penalty
   friction depends on its increments, which is why the garment with friction is compared with it in
   benchmarks/engine.py but not held to 0.5 %.
"""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
from engine_run import CCX, node_to_surface, run_ccx, run_engine
from fe_cases import _grid_triangles, _ids, boundary_faces, fmt

K, STICK, E_BODY = 100.0, 100.0, 1e6
GAP, OVERCLOSURE, LENGTH = 0.01, 0.01, 1.0


def slider_deck(mu: float, shift: float, increments: int, nx: int = 4, order: int = 2, base_nx: int = 7,
                gap: float = GAP, overclosure: float = OVERCLOSURE) -> tuple[str, np.ndarray]:
    """The slider on the base (module text); returns the deck and the slider's top node indices (0-based)."""
    base_nodes, base_elems, _ = _grid_triangles(base_nx, 2, order, lambda s, t: (-0.5 + 2.0 * s, -0.5 + 0.5 * t))
    top_nodes, top_elems, grid = _grid_triangles(nx, 2, order, lambda s, t: (LENGTH * s, gap + 0.5 * t))
    off, n_base = len(base_nodes), len(base_elems)
    etype = "CPE3" if order == 1 else "CPE6"
    lines = ["*HEADING", "stiff slider pressed and slid on a stiff base", "*NODE, NSET=NALL"]
    lines += [f"{i + 1}, {fmt(x)}, {fmt(y)}" for i, (x, y) in enumerate(np.vstack([base_nodes, top_nodes]))]
    lines.append(f"*ELEMENT, TYPE={etype}, ELSET=BASE")
    lines += [f"{i + 1}, " + ", ".join(str(n + 1) for n in e) for i, e in enumerate(base_elems)]
    lines.append(f"*ELEMENT, TYPE={etype}, ELSET=SLIDER")
    lines += [f"{n_base + i + 1}, " + ", ".join(str(n + 1 + off) for n in e) for i, e in enumerate(top_elems)]
    bottom = np.flatnonzero(np.isclose(base_nodes[:, 1], -0.5))
    top = np.flatnonzero(grid[:, 1] == grid[:, 1].max())
    lines += ["*NSET, NSET=BASE_BOTTOM", _ids(bottom), "*NSET, NSET=SLIDER_TOP", _ids(top + off)]
    lines.append("*SURFACE, NAME=BASE_TOP, TYPE=ELEMENT")
    lines += [f"{ie + 1}, S{f}" for ie, f in boundary_faces(base_elems, np.isclose(base_nodes[:, 1], 0.0))]
    lines.append("*SURFACE, NAME=SLIDER_BOTTOM, TYPE=ELEMENT")
    lines += [f"{n_base + ie + 1}, S{f}" for ie, f in boundary_faces(top_elems, grid[:, 1] == 0)]
    lines += ["*MATERIAL, NAME=STIFF", "*ELASTIC", f"{fmt(E_BODY)}, 0.3",
              "*SOLID SECTION, ELSET=BASE, MATERIAL=STIFF", "*SOLID SECTION, ELSET=SLIDER, MATERIAL=STIFF",
              "*SURFACE INTERACTION, NAME=SI", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", fmt(K)]
    if mu > 0.0:
        lines += ["*FRICTION", f"{fmt(mu)}, {fmt(STICK)}"]
    dt = 1.0 / increments
    lines += ["*CONTACT PAIR, INTERACTION=SI, TYPE=SURFACE TO SURFACE", "SLIDER_BOTTOM, BASE_TOP",
              "*BOUNDARY", "BASE_BOTTOM, 1, 2",
              "*STEP, NLGEOM, INC=100", "*STATIC", f"{fmt(dt)}, 1, {fmt(dt)}, {fmt(dt)}",
              "*BOUNDARY", f"SLIDER_TOP, 1, 1, {fmt(shift)}", f"SLIDER_TOP, 2, 2, {fmt(-(gap + overclosure))}",
              "*END STEP"]
    return "\n".join(lines) + "\n", top + off


def slider_forces(tmp_path, name: str, **kwargs) -> tuple[float, float, dict]:
    """(normal force N, tangential force F) on the slider, from the reactions at its top; the run's summary."""
    text, top = slider_deck(**kwargs)
    run = run_engine(text, tmp_path / name)
    assert run.returncode == 0, run.stderr
    reaction = np.asarray(run.vtu(1).point_data["reaction"])[top, :2].sum(axis=0)
    return float(-reaction[1]), float(reaction[0]), run.summary


def expected_forces(mu: float, shift: float, gap: float = GAP, overclosure: float = OVERCLOSURE) -> tuple[float, float]:
    alpha = gap / (gap + overclosure)
    normal = K * overclosure * LENGTH
    return normal, min(STICK * shift * (1.0 - alpha), mu * K * overclosure) * LENGTH


@pytest.mark.parametrize("mu, shift", [(0.3, 0.004), (0.1, 0.004)], ids=["stick", "slip"])
def test_friction_force_does_not_depend_on_the_increments(tmp_path, mu, shift):
    normal, tangential = expected_forces(mu, shift)
    assert (STICK * shift * 0.5 < mu * K * OVERCLOSURE) == (mu == 0.3)  # the two cases are what they say
    for increments in (1, 3, 12):
        N, F, summary = slider_forces(tmp_path, f"inc{increments}", mu=mu, shift=shift, increments=increments)
        assert summary["steps"][0]["n_increments"] == increments
        assert N == pytest.approx(normal, rel=2e-3), increments
        assert F == pytest.approx(tangential, rel=2e-3), increments


@pytest.mark.parametrize("order", [1, 2], ids=["CPE3", "CPE6"])
@pytest.mark.parametrize("mu", [0.3, 0.1], ids=["stick", "slip"])
def test_friction_force_does_not_depend_on_the_slave_spacing(tmp_path, order, mu):
    normal, tangential = expected_forces(mu, 0.004)
    for nx in (2, 5, 11):
        N, F, _ = slider_forces(tmp_path, f"nx{nx}", mu=mu, shift=0.004, increments=3, nx=nx, order=order)
        assert N == pytest.approx(normal, rel=2e-3), nx
        assert F == pytest.approx(tangential, rel=2e-3), nx


def test_contact_from_the_reference_state_is_anchored(tmp_path):
    """No gap: the slider rests on the base from the start, pressed by d and slid by s in one increment. The
    whole slide is under contact, F = min(lambda s, mu K d) L."""
    N, F, _ = slider_forces(tmp_path, "closed", mu=0.3, shift=0.002, increments=1, gap=0.0)
    assert N == pytest.approx(K * OVERCLOSURE * LENGTH, rel=2e-3)
    assert F == pytest.approx(STICK * 0.002 * LENGTH, rel=2e-3)


def calculix_slider_forces(deck: str, folder) -> tuple[float, float]:
    """(N, F) of CalculiX on the slider's deck, from the total reaction at the slider's top that it prints."""
    deck = deck.replace("*END STEP", "*NODE PRINT, NSET=SLIDER_TOP\nU\n"
                        "*NODE PRINT, NSET=SLIDER_TOP, TOTALS=ONLY\nRF\n*END STEP")
    rc, _, out = run_ccx(deck, folder, "slider")
    assert rc == 0, out[-2000:]
    totals = [line.split() for line in (folder / "slider.dat").read_text().splitlines() if re.match(r"^\s*-?\d", line)]
    return -float(totals[-1][1]), float(totals[-1][0])


@pytest.mark.ccx
@pytest.mark.skipif(shutil.which(CCX) is None, reason="ccx (CalculiX) not installed")
def test_calculix_friction_on_the_slider_depends_on_its_increments(tmp_path):
    """CalculiX 2.20 on the slider sticking (closed form F = 0.2, which calfit-fe gives with 1, 3 and 12
    increments above): 0.30 with 1 increment, 0.22 with 5, 0.12 with 25, 0.065 with 100, falling as its increments
    shrink (measured; with mu = 0.1 it even slides at 0.065 < mu N with 25). Its garment with friction differs from
    calfit-fe's by 4.2 % of max |u| (2,000 elements): not a reference. When a CalculiX release converges here,
    this test fails: then hold the garment with friction to the 0.5 % of the others."""
    forces = {}
    for increments in (5, 100):
        text, _ = slider_deck(mu=0.3, shift=0.004, increments=increments)
        forces[increments] = calculix_slider_forces(text, tmp_path / f"inc{increments}")[1]
    normal, tangential = expected_forces(0.3, 0.004)
    assert forces[5] > 1.05 * tangential and forces[100] < 0.5 * tangential, forces


@pytest.mark.ccx
@pytest.mark.skipif(shutil.which(CCX) is None, reason="ccx (CalculiX) not installed")
@pytest.mark.parametrize("mu", [0.3, 0.1], ids=["stick", "slip"])
def test_calculix_node_to_surface_friction_gives_the_same_forces(tmp_path, mu):
    """calfit-fe against CalculiX 2.20 on the same deck with friction. CalculiX counts an increment's slip from its
    start, also when a node touches within it: with the touch (alpha = 0.5) inside an increment its stick force is
    too large (0.30, 0.23, 0.22 with 1, 3, 5 increments, measured); with 10 increments the touch is an increment's
    boundary, and from there on it gives 0.19994 (10, 30, 100 increments; calfit-fe 0.19994). calfit-fe locates the
    touch within the increment and gives the same with any count (test above)."""
    text, top = slider_deck(mu=mu, shift=0.004, increments=10)
    text = node_to_surface(text)   # tests/support/engine_run.py
    fe = run_engine(text, tmp_path / "fe")
    assert fe.returncode == 0, fe.stderr
    reaction = np.asarray(fe.vtu(1).point_data["reaction"])[top, :2].sum(axis=0)
    ccx_normal, ccx_tangential = calculix_slider_forces(text, tmp_path / "ccx")
    normal, tangential = expected_forces(mu, 0.004)
    assert ccx_normal == pytest.approx(normal, rel=2e-4) and ccx_tangential == pytest.approx(tangential, rel=1e-3)
    assert -reaction[1] == pytest.approx(ccx_normal, rel=2e-4)
    assert reaction[0] == pytest.approx(ccx_tangential, rel=1e-3)

