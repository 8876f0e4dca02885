"""The engine's regression gold standards, kept as FEBio keeps them: one file per verification deck.

For each deck of CASES, tests/engine/gold/<deck>.json holds what calfit-fe gave when the file was last accepted:
its status and exit code, the number of converged increments and the total of Newton iterations over all steps,
and one key value of the result (max |u|, the largest contact or Laplace pressure, a sensitivity), with the
relative tolerance it is held to. The test runs each deck and compares: status, exit code, increments and
iterations exactly, the value to its tolerance (1e-8: far above the round-off between two builds of the same
code, which give the same bytes, and far below any change of the method). A change of the engine that moves one
of them is either a regression or a reviewed change; the second is taken with

    make accept-gold        (.venv/bin/python tests/engine/test_engine_gold.py --accept)

which runs every deck with the installed engine and writes the gold files again, for the diff to show.

The decks: tests/engine/gold/decks/ (written once by gold/write_decks.py from the engine tests' own writers, so
that a change of a writer changes no gold deck) and the decks the CalculiX cross-checks store
(tests/support/ccx_reference/). Together they cover homogeneous states, follower pressures (one varying around
the leg, with an unsymmetric tangent), mixed u/p elements, the Laplace garment law (on the deformed and on the
reference contour, with a tension profile), penalty contact (a shrink fit; the garment band put on in four steps
with *MODEL CHANGE), Coulomb friction (stick and slip) and parameter sensitivities with the effect keywords.
All of them run in about 20 s.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
GOLD = HERE / "gold"
GOLD_DECKS = GOLD / "decks"
CCX_DECKS = ROOT / "tests" / "support" / "ccx_reference"
RELATIVE_TOLERANCE = 1e-8


@dataclass(frozen=True)
class Case:
    deck: Path
    covers: str
    quantity: str  # the key value: see key_value


CASES = {
    "square_neohooke_follower_cpe6": Case(GOLD_DECKS / "square_neohooke_follower_cpe6.inp",
                                          "homogeneous state, NEO HOOKE, follower pressure", "max |u|"),
    "square_elastic_general_f_cpe3": Case(GOLD_DECKS / "square_elastic_general_f_cpe3.inp",
                                          "homogeneous state, ELASTIC, a general F prescribed", "max |u|"),
    "square_mooney_rivlin_cpe6": Case(CCX_DECKS / "square_mooney_rivlin_cpe6.inp",
                                      "homogeneous state, MOONEY-RIVLIN (CalculiX's deck)", "max |u|"),
    "annulus_neohooke_cpe3": Case(CCX_DECKS / "annulus_neohooke_cpe3.inp",
                                  "quarter annulus under a follower pressure, CPE3 (CalculiX's deck)", "max |u|"),
    "leg_slice_cpe6": Case(CCX_DECKS / "leg_slice_cpe6.inp",
                           "the leg slice, two tissues, follower pressure (CalculiX's deck)", "max |u|"),
    "leg_follower_cpe6": Case(CCX_DECKS / "leg_follower_cpe6.inp",
                              "the leg slice under a pressure varying around it, unsymmetric tangent", "max |u|"),
    "cook_nearly_incompressible_cpe6h": Case(GOLD_DECKS / "cook_nearly_incompressible_cpe6h.inp",
                                             "Cook's membrane, mixed u/p, nu = 0.4999", "max |u|"),
    "ring_laplace_circle_cpe6": Case(GOLD_DECKS / "ring_laplace_circle_cpe6.inp",
                                     "Laplace garment law on a circle", "max laplace_pressure"),
    "ring_laplace_ellipse_reference_cpe3": Case(GOLD_DECKS / "ring_laplace_ellipse_reference_cpe3.inp",
                                                "Laplace law on an ellipse, tension profile, REFERENCE=0.4",
                                                "max laplace_pressure"),
    "leg_laplace_reference_cpe3": Case(GOLD_DECKS / "leg_laplace_reference_cpe3.inp",
                                       "the leg slice under the reference-contour garment law", "max |u|"),
    "shrink_fit_contact_cpe6": Case(GOLD_DECKS / "shrink_fit_contact_cpe6.inp",
                                    "penalty contact, shrink fit", "max contact_pressure"),
    "leg_garment_cpe6": Case(CCX_DECKS / "leg_garment_cpe6.inp",
                             "the leg under the garment band, put on in four steps (*MODEL CHANGE)",
                             "max contact_pressure"),
    "slider_friction_cpe6": Case(GOLD_DECKS / "slider_friction_cpe6.inp",
                                 "Coulomb friction, a slider pressed and slipping", "max |contact_shear|"),
    "capstan_friction_cpe6": Case(GOLD_DECKS / "capstan_friction_cpe6.inp",
                                  "Coulomb friction, a band pulled over a cylinder until it slides", "max |u|"),
    "leg_sensitivity_effects_cpe6h": Case(GOLD_DECKS / "leg_sensitivity_effects_cpe6h.inp",
                                          "sensitivities, mixed u/p leg slice with volume change, axial stretch "
                                          "and a rigid motion", "max |du/d VOLUME CHANGE:MUSCLE|"),
}


def key_value(run, quantity: str) -> float:
    """The quantity of the run's last step: max |u| (mm) over the nodes; the largest nodal value of a VTU point
    field (MPa); or the max |du/dtheta| that summary.json gives a sensitivity parameter."""
    last = len(run.summary["steps"])
    if quantity == "max |u|":
        return float(np.linalg.norm(run.u(), axis=1).max())
    if quantity.startswith("max |du/d "):
        name = quantity.removeprefix("max |du/d ").removesuffix("|")
        return float(next(s["max_abs_du"] for s in run.summary["sensitivities"] if s["name"] == name))
    field = quantity.removeprefix("max ").strip("|")
    values = np.asarray(run.vtu(last).point_data[field], dtype=float)
    return float((np.abs(values) if quantity.startswith("max |") else values).max())


def measure(name: str, workdir: Path) -> dict:
    """What the gold file of deck `name` records, from a run of the installed engine."""
    from engine_run import run_engine

    case = CASES[name]
    run = run_engine(None, workdir, name, deck_path=case.deck)
    assert run.summary is not None, f"{name}: no summary.json (exit {run.returncode}): {run.stderr}"
    steps = run.summary["steps"]
    return {
        "deck": case.deck.relative_to(ROOT).as_posix(),
        "covers": case.covers,
        "status": run.summary["status"],
        "exit_code": run.returncode,
        "increments": sum(s["n_increments"] for s in steps),
        "newton_iterations": sum(s["newton_iterations"] for s in steps),
        "value": {"quantity": case.quantity, "value": key_value(run, case.quantity),
                  "relative_tolerance": RELATIVE_TOLERANCE},
    }


@pytest.mark.parametrize("name", sorted(CASES))
def test_engine_matches_its_gold_standard(tmp_path, name):
    gold = json.loads((GOLD / f"{name}.json").read_text())
    now = measure(name, tmp_path)
    assert now["deck"] == gold["deck"]
    for key in ("status", "exit_code", "increments", "newton_iterations"):
        assert now[key] == gold[key], f"{name}: {key} {now[key]}, gold {gold[key]} (a reviewed change: make accept-gold)"
    assert now["value"]["quantity"] == gold["value"]["quantity"]
    value, expected = now["value"]["value"], gold["value"]["value"]
    assert value == pytest.approx(expected, rel=gold["value"]["relative_tolerance"]), (
        f"{name}: {gold['value']['quantity']} = {value!r}, gold {expected!r} (a reviewed change: make accept-gold)")


def test_every_gold_file_has_its_deck():
    assert {p.stem for p in GOLD.glob("*.json")} == set(CASES)
    assert {p.stem for p in GOLD_DECKS.glob("*.inp")} <= set(CASES)
    assert len(CASES) >= 10


def accept() -> None:
    """Write every gold file from the installed engine's runs (make accept-gold)."""
    import tempfile

    GOLD.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        for name in sorted(CASES):
            record = measure(name, Path(folder) / name)
            (GOLD / f"{name}.json").write_text(json.dumps(record, indent=2) + "\n")
            print(f"{name}: {record['status']}, {record['increments']} increments, {record['newton_iterations']} "
                  f"Newton iterations, {record['value']['quantity']} = {record['value']['value']:.10g}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--accept"]:
        sys.exit("usage: test_engine_gold.py --accept   (writes tests/engine/gold/*.json from the installed engine)")
    sys.path.insert(0, str(ROOT / "tests" / "support"))
    accept()
