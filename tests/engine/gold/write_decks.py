"""Write the gold-standard decks of tests/engine/test_engine_gold.py into tests/engine/gold/decks/.

    .venv/bin/python tests/engine/gold/write_decks.py

The decks are stored, not generated at test time, so that the gold standards hold the engine alone: a change of a
deck writer in tests/support or orchestrator/ changes no gold deck. Each deck is one verification case of the
engine's tests, built by the same writer with the same values (the test named in each entry below), and kept
small enough that the whole set runs in a few seconds. Run this only to change the set; then `make accept-gold`.
The decks the CalculiX cross-checks store (tests/support/ccx_reference/) are named there, not copied.
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parents[1] / "support"), str(HERE.parent)]

from engine_closed_forms import Law
from fe_cases import cook_membrane, deck, edge_loads, fmt, ring, unit_square

from orchestrator.meshing import leg_slice_deck, leg_slice_mesh

DECKS = HERE / "decks"


def homogeneous_square() -> str:
    """test_engine_homogeneous.py, test_pressure_on_top_with_rollers: NEO HOOKE, CPE6, rollers, follower p = 0.5."""
    return deck(unit_square(2, 2), Law("NEO HOOKE", (1.0, 0.1)), fixed=[("LEFT", 1, 1), ("BOTTOM", 2, 2)],
                pressure=[("TOP", 0.5)], heading="gold: homogeneous square, NEO HOOKE CPE6, follower pressure on top")


def general_deformation_square() -> str:
    """test_engine_homogeneous.py, test_prescribed_general_deformation: ELASTIC (St Venant-Kirchhoff), CPE3, every
    boundary node given the displacement of a general F."""
    import numpy as np

    mesh = unit_square(3, 1)
    ub = mesh.nodes @ (np.array([[1.25, 0.2], [-0.1, 0.85]]) - np.eye(2)).T
    prescribed = [(int(n), d + 1, float(ub[n, d])) for n in mesh.nsets["ALLB"] for d in range(2)]
    return deck(mesh, Law("ELASTIC", (10.0, 0.3)), prescribed=prescribed,
                heading="gold: homogeneous square, ELASTIC CPE3, a general F prescribed on the boundary")


def cook_nearly_incompressible() -> str:
    """test_engine_mixed.py, cook_tip: Cook's membrane, CPE6H 8 x 8, nearly incompressible (E 240.565, nu 0.4999)."""
    E, nu, load, n = 240.565, 0.4999, 100.0, 8
    mu, kappa = E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))
    mesh = cook_membrane(n, 2, hybrid=True)
    loads = [(int(node), 2, float(f)) for node, f in zip(mesh.nsets["RIGHT"], edge_loads(2, n, load))]
    return deck(mesh, Law("AVRIL", (mu / 2, kappa / 2)), fixed=[("LEFT", 1, 2)], cloads=loads,
                static=(0.25, 1.0, 1e-4, 0.5), heading="gold: Cook's membrane, mixed u/p CPE6H, nearly incompressible")


def laplace_circle() -> str:
    """test_engine_laplace.py, _run_ring: a full ring (CPE6, 6 x 48), AVRIL, *LAPLACE PRESSURE T = 1 outside."""
    mesh = ring(6, 48, 2, outer=(2.0, 2.0))
    return deck(mesh, Law("AVRIL", (1.0, 10.0)), fixed=[("INNER", 1, 2)], laplace=[("OUTER", 1.0)],
                static=(0.25, 1.0, 1e-4, 0.25), heading="gold: ring under the Laplace law on a circle, CPE6")


def laplace_ellipse_reference() -> str:
    """test_engine_laplace_reference.py, the ellipse: CPE3, a FOURIER tension profile, REFERENCE=0.4."""
    mesh = ring(3, 48, 1, outer=(2.4, 1.6))
    T, a1, b2 = 1.0, 0.3, -0.2
    text = deck(mesh, Law("AVRIL", (1.0, 10.0)), fixed=[("INNER", 1, 2)], laplace=[("OUTER", T)],
                static=(0.5, 1.0, 1e-4, 0.5), heading="gold: ellipse under the Laplace law, tension profile, REFERENCE=0.4")
    text = text.replace(f"TENSION={fmt(T)}", f"TENSION={fmt(T)}, PROFILE=GARMENT, REFERENCE=0.4")
    profile = f"*TENSION PROFILE, NAME=GARMENT, TYPE=FOURIER, CX=0, CY=0\n1, {a1}, 0\n2, 0, {b2}\n*STEP"
    return text.replace("*STEP", profile, 1)


def _two_bodies(order: int) -> str:
    from test_engine_contact import two_bodies

    return two_bodies(order)[0]


def shrink_fit() -> str:
    """test_engine_contact.py, test_shrink_fit_matches_lame: penalty contact of a core and a ring, CPE6."""
    return _two_bodies(2)


def capstan() -> str:
    """test_engine_contact.py, test_capstan_relation_at_sliding: a band pulled over a cylinder, mu = 0.2, CPE6."""
    from test_engine_contact import capstan_deck

    return capstan_deck(0.2, 0.1, pull=0.05, order=2, nt=60)[0]


def slider_friction() -> str:
    """test_engine_friction.py: the slider pressed and slid (slip: mu 0.1, shift 0.004) in 3 increments, CPE6."""
    from test_engine_friction import slider_deck

    return slider_deck(0.1, 0.004, 3)[0]


def leg_sensitivity() -> str:
    """test_engine_sensitivity.py, test_effect_sensitivities_match_finite_differences ("given", CPE6H): the leg slice
    (300 T6, mixed u/p) under a profiled Laplace garment with a drained muscle, an axial stretch and a moved bone,
    and the sensitivities of every parameter kind the effects add."""
    from test_engine_sensitivity import EFFECT_CASES, EFFECT_PARAMETERS, LAWS, PROFILE, TENSION, write_deck

    effects, c20 = EFFECT_CASES["given"]
    laws = {elset: (law, dict(constants)) for elset, (law, constants) in LAWS["avril-mooney"].items()}
    laws["FAT"][1]["C20"] = c20
    names = EFFECT_PARAMETERS + ["MATERIAL:MUSCLE:C10", "TENSION:SKIN", "PROFILE:GARMENT:A1"]
    with tempfile.TemporaryDirectory() as folder:
        path = write_deck(Path(folder), leg_slice_mesh(300, order=2), laws, "CPE6H", TENSION, PROFILE, names, effects)
        return path.read_text()


def leg_reference_laplace() -> str:
    """test_engine_laplace_reference.py, leg_decks: the leg slice (CPE3) under REFERENCE=1 of the garment law."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "leg.inp"
        leg_slice_deck(path, mesh=leg_slice_mesh(400, order=1), laplace_tension=0.16, include_mesh=False)
        text = path.read_text()
    return re.sub(r"(\*LAPLACE PRESSURE[^\n]*)", r"\1, REFERENCE=1", text)


WRITERS = {
    "square_neohooke_follower_cpe6": homogeneous_square,
    "square_elastic_general_f_cpe3": general_deformation_square,
    "cook_nearly_incompressible_cpe6h": cook_nearly_incompressible,
    "ring_laplace_circle_cpe6": laplace_circle,
    "ring_laplace_ellipse_reference_cpe3": laplace_ellipse_reference,
    "shrink_fit_contact_cpe6": shrink_fit,
    "capstan_friction_cpe6": capstan,
    "slider_friction_cpe6": slider_friction,
    "leg_sensitivity_effects_cpe6h": leg_sensitivity,
    "leg_laplace_reference_cpe3": leg_reference_laplace,
}


def main(names: list[str]) -> None:
    DECKS.mkdir(exist_ok=True)
    for name in names or WRITERS:
        (DECKS / f"{name}.inp").write_text(WRITERS[name]())
        print(f"wrote {DECKS / name}.inp")


if __name__ == "__main__":
    main(sys.argv[1:])
