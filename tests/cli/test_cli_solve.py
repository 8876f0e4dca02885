"""The `calfit` command line and the engine runner: exit codes become typed outcomes,
the engine's FILE:LINE message reaches the user, a timeout stops the engine, and the
built-in demo runs end to end with garment pressures of the order of Avril et al.'s
Table 3 (2.7-4.4 kPa at the five landmarks for a garment of about 20 mmHg)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from orchestrator.cli import main
from orchestrator.core.errors import DeckRejected, EngineFailed
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import ENGINE_LOG, run_engine
from orchestrator.meshing import leg_slice_deck


@pytest.fixture(scope="module")
def leg_deck(tmp_path_factory):
    folder = tmp_path_factory.mktemp("leg")
    deck = folder / "leg.inp"
    leg_slice_deck(deck, n_elements=400, order=1)
    return deck


def test_runner_returns_converged_outcome_and_results(leg_deck, tmp_path):
    outcome = run_engine(leg_deck, tmp_path / "out")
    assert outcome.converged and outcome.returncode == 0
    assert (tmp_path / "out" / ENGINE_LOG).read_text() == outcome.stdout and "converged in" in outcome.stdout
    results = EngineResults(outcome.outdir)
    assert results.summary["status"] == "converged"
    u = results.displacement()
    table = results.table()
    assert u.shape == (results.summary["n_nodes"], 2)
    # every skin point moves inward under the garment: u . (X - centroid) < 0 on average
    X = table[:, 1:3]
    assert np.mean(np.sum(u * (X - X.mean(axis=0)), axis=1)) < 0.0


def test_runner_raises_deck_rejected_with_engine_message(tmp_path):
    deck = tmp_path / "bad.inp"
    deck.write_text("*NODE\n1, 0, 0\n*ELEMENT, TYPE=CPE3\n1, 1, 2, 3\n")
    with pytest.raises(DeckRejected, match=r"bad\.inp:4: node 2 is not defined"):
        run_engine(deck)


def test_runner_timeout_stops_the_engine(leg_deck, tmp_path):
    # The leg deck's pressure in a million increments: minutes of work, so that the engine is still running when the
    # watchdog fires whatever the load of the machine (the deck itself converges in some 10 ms, which a 1 ms timeout
    # on a busy machine could miss: the watchdog's thread woke after the engine had finished).
    text = leg_deck.read_text().replace("*STEP, NLGEOM, INC=100\n*STATIC\n1, 1, 0.0001, 1\n",
                                        "*STEP, NLGEOM, INC=1000000\n*STATIC\n1e-6, 1, 1e-6, 1e-6\n")
    assert "INC=1000000" in text
    deck = leg_deck.with_name("slow.inp")   # beside the mesh that the deck includes
    deck.write_text(text)
    with pytest.raises(EngineFailed, match="timeout"):
        run_engine(deck, tmp_path / "out", timeout_s=0.5)
    # the engine's log of the stopped run is kept, as far as it went
    assert "iterations, residual" in (tmp_path / "out" / ENGINE_LOG).read_text()


def test_calfit_solve_json_prints_one_object(leg_deck, tmp_path, capsys):
    code = main(["solve", str(leg_deck), "-o", str(tmp_path / "out"), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["status"] == "converged" and summary["exit_code"] == 0


def test_calfit_solve_bad_deck_exits_2(tmp_path, capsys):
    deck = tmp_path / "bad.inp"
    deck.write_text("*NODE\n1, 0, zero\n")
    assert main(["solve", str(deck)]) == 2
    assert "bad.inp:2: y coordinate is not a number" in capsys.readouterr().err


def test_calfit_help_lists_commands():
    out = subprocess.run([sys.executable, "-m", "orchestrator.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    for command in ("demo", "solve"):
        assert command in out.stdout


def test_demo_pressures_are_of_the_order_of_table_3(tmp_path, capsys):
    code = main(["demo", "--leg-slice", "--out", str(tmp_path), "--elements", "600", "--order", "1"])
    assert code == 0
    results = EngineResults(tmp_path / "results")
    mesh = results.mesh()
    pressure_kpa = np.asarray(mesh.cell_data["pressure"][0]).ravel() * 1e3
    # Table 3 of Avril et al.: 2.74 to 4.42 kPa at the landmarks; the whole field spans
    # a little more (0.9 to 5.3 kPa in their Fig. 5).
    assert 0.5 < np.percentile(pressure_kpa, 5) and np.percentile(pressure_kpa, 95) < 6.0
    assert 2.0 < np.median(pressure_kpa) < 4.5
    assert "hydrostatic pressure" in capsys.readouterr().out
