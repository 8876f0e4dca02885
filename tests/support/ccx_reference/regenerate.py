"""Regenerate the CalculiX reference results used by tests/test_engine_ccx.py.

    cd /work/main && PYTHONPATH=. .venv/bin/python tests/support/ccx_reference/regenerate.py [CASE ...]

Each case is one standard-keyword deck (written here as `<case>.inp`) that CalculiX
(`ccx -i`, version 2.20, plane-strain elements expanded to 3D internally) solves; the
nodal displacements it prints with *NODE PRINT, NSET=NALL / U (last time, 7 significant
digits) are kept as `<case>.u.txt` (node id, u_x, u_y). calfit-fe runs either the same
deck, or, for the Avril law, the same mesh and load with `*HYPERELASTIC, AVRIL` (C10, Kv)
where CalculiX runs ARRUDA-BOYCE with mu = 2 C10, lambda_m = 1e4, D = 1/Kv (same energy
up to terms of order 1/lambda_m^2). The leg-like slice deck comes from
orchestrator.meshing.leg_slice_deck (two tissues, clamped bones, follower pressure on the
skin; Table 2 values of Avril et al.); the same slice under a pressure varying around the
leg, and under the explicit garment band (penalty contact, frictionless, and with friction through CalculiX's
node-to-surface contact), come from tests/support/leg_decks.py.
"""

from __future__ import annotations

import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parents[2]))

from engine_closed_forms import Law  # noqa: E402
from engine_run import run_ccx  # noqa: E402
from fe_cases import deck, ring, unit_square  # noqa: E402

SYM = [("INNER", 1, 2), ("XSYM", 1, 1), ("YSYM", 2, 2)]
# The garment's leg: with 1,000 elements calfit-fe and CalculiX differ by 0.62 % of max |u| (the skin's sliding in
# one sector, 3.4 % of the leg's own max |u|), with 2,000 by 0.31 % (1.2 %): the two contact discretizations
# (node-to-segment on straight sub-segments here, CalculiX's face-to-face on quadratic faces) converge together.
GARMENT_ELEMENTS = 2000
# With friction, the release converged in its increments (tests/support/leg_decks.py garment_friction_text says by how much):
# calfit-fe takes it in 50 increments where CalculiX took 200, which keeps the fast test fast.
GARMENT_FRICTION_ENGINE_RELEASE = (0.02, 1.0, 1e-5, 0.02)


@dataclass
class CcxCase:
    name: str
    description: str
    ccx_deck: str  # what CalculiX runs
    engine_deck: str  # what calfit-fe runs (identical unless a project keyword is needed)
    meta: dict


def _annulus(name, order, nr, law, p, engine_law=None, description=""):
    mesh = ring(nr, 2 * nr, order, quarter=True)
    kw = dict(fixed=SYM, pressure=[("OUTER", p)], static=(0.25, 1.0, 1e-4, 0.25))
    ccx_deck = deck(mesh, law, heading=f"ccx cross-check {name}", **kw)
    engine_deck = ccx_deck if engine_law is None else deck(mesh, engine_law, heading=f"ccx cross-check {name}", **kw)
    return CcxCase(name, description, ccx_deck, engine_deck, {"p": p, "kind": "annulus"})


def _square(name, law, p):
    mesh = unit_square(2, 2)
    text = deck(mesh, law, fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)], pressure=[("TOP", p)], heading=f"ccx cross-check {name}")
    return CcxCase(name, f"homogeneous square, {law.kind}, follower pressure {p}", text, text, {"p": p, "kind": "square"})


def _leg(name, n_elements, order):
    from orchestrator.meshing import leg_slice_deck

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{name}.inp"
        leg_slice_deck(path, n_elements=n_elements, order=order, include_mesh=False)
        text = path.read_text()
    return CcxCase(name, f"leg-like slice, {n_elements} elements order {order}", text, text, {"kind": "leg"})


def _leg_follower(name, n_elements, increments):
    from leg_decks import nonuniform_follower_text

    from orchestrator.meshing import leg_slice_mesh

    text = nonuniform_follower_text(leg_slice_mesh(n_elements, order=2), increments)
    return CcxCase(name, f"leg-like slice, {n_elements} elements order 2, pressure 1 + 0.5 cos t + 0.2 sin 2t, "
                   f"{increments} increments", text, text, {"kind": "leg"})


def _leg_garment(name, n_elements):
    from leg_decks import garment_text

    from orchestrator.meshing import garment_band, leg_slice_mesh

    leg = leg_slice_mesh(n_elements, order=2)
    text = garment_text(leg, garment_band(leg), friction_mu=0.0)
    return CcxCase(name, f"leg-like slice, {n_elements} elements order 2, under the explicit garment band "
                   "(frictionless penalty contact; inflate, let go, release, settle)", text, text, {"kind": "leg"})


def _leg_garment_friction(name, n_elements):
    from leg_decks import (
        GARMENT_FRICTION,
        GARMENT_FRICTION_RELEASE,
        garment_friction_text,
    )

    from orchestrator.meshing import garment_band, leg_slice_mesh

    leg = leg_slice_mesh(n_elements, order=2)
    text = garment_friction_text(leg, garment_band(leg))
    return CcxCase(name, f"leg-like slice, {n_elements} elements order 2, under the explicit garment band "
                   f"(node-to-surface penalty contact, Coulomb friction mu = {GARMENT_FRICTION}, the release in "
                   f"increments of {GARMENT_FRICTION_RELEASE[0]}; inflate, let go, release, settle)", text, text,
                   {"kind": "leg", "engine_release": GARMENT_FRICTION_ENGINE_RELEASE})


def engine_release(deck_text: str, release_static: tuple[float, ...]) -> str:
    """The deck with the release step (the one that adds the contact pair) in increments of release_static
    (initial, period, min, max)."""
    head, sep, tail = deck_text.partition("*MODEL CHANGE, TYPE=CONTACT PAIR, ADD")
    static_line = head.rstrip("\n").rsplit("\n", 1)[-1]
    assert sep and head.rstrip("\n").rsplit("\n", 2)[-2] == "*STATIC", "no *STATIC right before the contact's ADD"
    line = ", ".join(f"{v:g}" for v in release_static)
    return head.rstrip("\n")[: -len(static_line)] + line + "\n" + sep + tail


def cases() -> dict[str, CcxCase]:
    """Every reference case by name (decks are regenerated deterministically)."""
    out = [
        _annulus("annulus_neohooke_cpe6", 2, 4, Law("NEO HOOKE", (1.0, 0.1)), 0.5, description="quarter annulus CPE6 NEO HOOKE p=0.5"),
        _annulus("annulus_neohooke_cpe3", 1, 8, Law("NEO HOOKE", (1.0, 0.1)), 0.5, description="quarter annulus CPE3 NEO HOOKE p=0.5"),
        _annulus(
            "annulus_avril_cpe6", 2, 4, Law("ARRUDA-BOYCE", (2.0, 1.0e4, 0.1)), 2.0,
            engine_law=Law("AVRIL", (1.0, 10.0)),
            description="quarter annulus CPE6, Avril C10=1 Kv=10 (ccx: ARRUDA-BOYCE mu=2, lm=1e4, D=0.1), p=2",
        ),
        _square("square_mooney_rivlin_cpe6", Law("MOONEY-RIVLIN", (0.8, 0.3, 0.1)), 0.5),
        _square("square_reduced_polynomial3_cpe6", Law("REDUCED POLYNOMIAL", (1.0, 0.4, 0.2, 0.1, 0.5, 1.0), n=3), 0.5),
        _square("square_arruda_boyce_cpe6", Law("ARRUDA-BOYCE", (2.0, 1.5, 0.1)), 0.5),
        _square("square_elastic_cpe6", Law("ELASTIC", (10.0, 0.3)), 0.5),
    ]
    try:
        out.append(_leg("leg_slice_cpe6", 600, 2))
        out.append(_leg("leg_slice_cpe3", 1200, 1))
        out.append(_leg_follower("leg_follower_cpe6", 600, 6))
        out.append(_leg_garment("leg_garment_cpe6", GARMENT_ELEMENTS))
        out.append(_leg_garment_friction("leg_garment_friction_cpe6", GARMENT_ELEMENTS))
    except ImportError:
        pass
    return {c.name: c for c in out}


def node_ids(deck_text: str) -> np.ndarray:
    """Node ids of the *NODE blocks of a deck (in order)."""
    ids, active = [], False
    for line in deck_text.splitlines():
        s = line.strip()
        if s.startswith("**") or not s:
            continue
        if s.startswith("*"):
            active = bool(re.match(r"\*NODE\s*(,|$)", s, re.I))
            continue
        if active:
            ids.append(int(s.split(",")[0]))
    return np.array(ids, dtype=np.int64)


def load_reference(name: str) -> np.ndarray:
    """(n, 3): node id, u_x, u_y as CalculiX printed them."""
    return np.loadtxt(HERE / f"{name}.u.txt", ndmin=2)


def regenerate(name: str, case: CcxCase) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        rc, disp, out = run_ccx(case.ccx_deck, Path(tmp), name)
        if rc != 0 or not disp:
            raise SystemExit(f"ccx failed on {name} (exit {rc}):\n{out[-3000:]}")
    ids = node_ids(case.ccx_deck)
    table = np.column_stack([ids, [disp[int(i)][0] for i in ids], [disp[int(i)][1] for i in ids]])
    (HERE / f"{name}.inp").write_text(case.ccx_deck)
    header = f"{case.description}\nCalculiX {ccx_version()} displacements (*NODE PRINT U, last time): node id, u_x, u_y"
    np.savetxt(HERE / f"{name}.u.txt", table, fmt=["%d", "%.7e", "%.7e"], header=header)
    print(f"{name}: {len(ids)} nodes, max |u| = {np.abs(table[:, 1:]).max():.6e}")


def ccx_version() -> str:
    import subprocess

    proc = subprocess.run(["ccx", "-v"], capture_output=True, text=True, timeout=30)
    m = re.search(r"Version\s+(\S+)", proc.stdout)
    return m.group(1) if m else "unknown"


def main(argv: list[str]) -> None:
    all_cases = cases()
    for name in argv or list(all_cases):
        regenerate(name, all_cases[name])


if __name__ == "__main__":
    main(sys.argv[1:])
