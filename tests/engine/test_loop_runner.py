"""Decks, the evaluation cache and run log, failures in a sweep, and Dask distributed evaluation.

- Templates use StrictUndefined: a forgotten variable is an error naming the template.
- An evaluation is cached by deck key: asking twice launches the engine once (launches are
  counted by a wrapper put in front of calfit-fe through CALFIT_FE), and every evaluation is one
  JSON line of RUN_DIR/evaluations.jsonl, read back as the cache by a new Evaluator.
- A Monte-Carlo-like sweep with a deck the engine rejects (exit 2), a load it cannot carry (exit
  3), a run past its timeout and a deck that cannot be rendered finishes; each failure is recorded
  with its status and the engine's message, the other evaluations are scored.
- The same evaluations on a local Dask cluster (started here, shut down at the end) give the same
  costs as the local process pool.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from orchestrator.engine import decks
from orchestrator.engine.locate import find_engine
from orchestrator.engine.runner import (
    BAD_DECK,
    HANG_FACTOR,
    LOG_NAME,
    NOT_CONVERGED,
    OK,
    TIMEOUT,
    TIMEOUT_COLUMNS_PER_RUN,
    EvaluationLog,
    Evaluator,
    run_timeout,
)
from orchestrator.fit.objectives import DisplacementResidualObjective
from orchestrator.meshing import leg_slice_mesh
from orchestrator.model.forward import TABLE2_CENTRAL_KPA, LegModel

SLEEP_MARKER = "** calfit-test: sleep"


@pytest.fixture(scope="module")
def leg_model():
    return LegModel(leg_slice_mesh(400, 1), 0.16)


@pytest.fixture
def counting_engine(tmp_path, monkeypatch):
    """CALFIT_FE -> a wrapper that counts launches and sleeps on decks carrying SLEEP_MARKER."""
    counter = tmp_path / "launches.txt"
    wrapper = tmp_path / "calfit-fe-wrapper"
    wrapper.write_text(f"""#!/bin/bash
echo launch >> "{counter}"
if grep -q "{SLEEP_MARKER}" "$1"; then exec sleep 30; fi
exec "{find_engine()}" "$@"
""")
    wrapper.chmod(wrapper.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CALFIT_FE", str(wrapper))
    return lambda: len(counter.read_text().splitlines()) if counter.exists() else 0


def skin_objective(model):
    """F at a few skin nodes against zero displacement: a cheap, deterministic score."""
    points = model.mesh.nodes[model.mesh.skin_loop[::5]]
    return DisplacementResidualObjective.at_points(model.mesh, points, np.zeros_like(points))


def test_templates_are_strict():
    with pytest.raises(decks.DeckError, match="leg_laplace.inp.j2.*undefined"):
        decks.render("leg_laplace.inp.j2", materials=[], tension="0.1")
    with pytest.raises(decks.DeckError, match="garment tension must be positive"):
        decks.leg_laplace_deck({"FAT": ("AVRIL", (0.0045, 0.106))}, 0.0)


def test_leg_deck_holds_the_parameters_in_MPa(leg_model):
    text = leg_model.deck([4.5, 11.2, 106.0, 69.5])
    assert "*HYPERELASTIC, AVRIL\n0.0045, 0.106\n" in text
    assert "*HYPERELASTIC, AVRIL\n0.0112, 0.0695\n" in text
    assert "*LAPLACE PRESSURE, SURFACE=SKIN, TENSION=0.16\n" in text


def test_cache_and_log_launch_each_deck_once(leg_model, counting_engine, tmp_path):
    thetas = [TABLE2_CENTRAL_KPA, [5.0, 12.0, 100.0, 70.0], TABLE2_CENTRAL_KPA]
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "run", progress=False) as evaluator:
        first = evaluator.evaluate(thetas)
        again = evaluator(TABLE2_CENTRAL_KPA)
        assert evaluator.launched == 2
    assert counting_engine() == 2
    assert first[0] == first[2] == again and first[0]["status"] == OK and first[0]["cost"] > 0
    lines = (tmp_path / "run" / LOG_NAME).read_text().splitlines()
    assert len(lines) == 2 and {json.loads(line)["key"] for line in lines} == {first[0]["key"], first[1]["key"]}
    # a new evaluator on the same run folder replays from the log without launching
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "run", progress=False) as evaluator:
        assert evaluator.evaluate(thetas) == first and evaluator.launched == 0
    assert counting_engine() == 2


class FailingLegModel(LegModel):
    """The leg model, whose decks go wrong on purpose for some first parameters (kPa)."""

    def deck(self, theta, **options):
        text = super().deck(theta, **options)
        if theta[0] < 0.05:   # an impossible load: the engine stops with exit 3
            return text.replace("TENSION=0.16", "TENSION=1000")
        if theta[0] > 100.0:  # a keyword the engine does not know: exit 2 with FILE:LINE
            return text.replace("*BOUNDARY", "*BOUNDARIES")
        if 50.0 < theta[0] < 100.0:
            return text + SLEEP_MARKER + "\n"
        return text


def test_failures_never_stop_a_sweep_and_are_recorded(counting_engine, tmp_path):
    model = FailingLegModel(leg_slice_mesh(400, 1), 0.16)
    thetas = [[4.5, 11.2, 106, 69.5], [0.01, 0.01, 0.01, 0.01], [150.0, 11.2, 106, 69.5], [60.0, 11.2, 106, 69.5],
              [-1.0, 11.2, 106, 69.5], [5.0, 11.2, 106, 69.5]]
    with Evaluator(model, skin_objective(model), tmp_path / "run", workers=2, timeout_s=3.0, progress=False) as evaluator:
        records = evaluator.evaluate(thetas, tag="monte-carlo")
    statuses = [record["status"] for record in records]
    assert statuses == [OK, NOT_CONVERGED, BAD_DECK, TIMEOUT, BAD_DECK, OK]
    assert "exit 3" in records[1]["message"]
    assert "deck.inp:" in records[2]["message"] and "BOUNDARIES" in records[2]["message"]
    assert "timeout" in records[3]["message"]
    assert "must be positive" in records[4]["message"]
    assert all(records[k]["cost"] is None for k in (1, 2, 3, 4)) and records[5]["cost"] > 0
    assert counting_engine() == 5   # the unrenderable deck never reached the engine
    logged = [json.loads(line) for line in (tmp_path / "run" / LOG_NAME).read_text().splitlines()]
    assert sorted(r["status"] for r in logged) == sorted(statuses)
    # resumed with the same timeout, nothing is launched again; with a longer one, only the run it stopped
    with Evaluator(model, skin_objective(model), tmp_path / "run", workers=2, timeout_s=3.0, progress=False) as evaluator:
        assert [r["status"] for r in evaluator.evaluate(thetas)] == statuses and evaluator.launched == 0
    with Evaluator(model, skin_objective(model), tmp_path / "run", workers=2, timeout_s=4.0, progress=False) as evaluator:
        assert [r["status"] for r in evaluator.evaluate(thetas)] == statuses and evaluator.launched == 1


def test_dask_cluster_gives_the_same_costs_as_the_local_pool(leg_model, tmp_path):
    distributed = pytest.importorskip("distributed")
    thetas = [TABLE2_CENTRAL_KPA, [5.0, 12.0, 100.0, 70.0], [3.0, 9.0, 120.0, 60.0]]
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "local", workers=2, progress=False) as evaluator:
        local = [record["cost"] for record in evaluator.evaluate(thetas)]
    # the scheduler's HTTP server on a port the system picks: 8787 may be another cluster's on this machine
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "dask", scheduler=cluster.scheduler_address,
                       progress=False) as evaluator:
            remote = evaluator.evaluate(thetas)
            assert evaluator.launched == 3
    assert [record["status"] for record in remote] == [OK] * 3
    assert [record["cost"] for record in remote] == local
    assert os.listdir(tmp_path / "dask" / "jobs") == ["meshes"]   # job folders are removed after scoring


def test_relative_run_folder_works_from_any_working_directory(leg_model, tmp_path, monkeypatch):
    # `calfit demo` passes a run folder relative to the user's working directory; the job
    # folder's link to the shared mesh must still resolve.
    monkeypatch.chdir(tmp_path)
    with Evaluator(leg_model, skin_objective(leg_model), Path("relative-run"), progress=False) as evaluator:
        record = evaluator(TABLE2_CENTRAL_KPA)
    assert record["status"] == OK, record["message"]


def test_verbose_streams_every_engine_log_and_each_job_keeps_it(leg_model, tmp_path, capfd):
    """--verbose: the engine's own lines (increments, Newton residuals) reach stderr as each run goes, from the
    worker processes too; each job folder holds them in out/engine.log (kept here with keep_jobs)."""
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "run", workers=2, progress=False,
                   verbose=True, keep_jobs=True) as evaluator:
        records = evaluator.evaluate([TABLE2_CENTRAL_KPA, [5.0, 12.0, 100.0, 70.0]])
    assert all(record["status"] == OK for record in records)
    streamed = capfd.readouterr().err
    logs = sorted((tmp_path / "run" / "jobs").glob("*/out/engine.log"))
    assert len(logs) == 2
    for log in logs:
        text = log.read_text()
        assert "iterations, residual" in text and "converged in" in text
        assert all(line in streamed for line in text.splitlines() if line.startswith("step "))
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "quiet", progress=False) as evaluator:
        assert evaluator.evaluate([TABLE2_CENTRAL_KPA])[0]["status"] == OK
    assert "iterations, residual" not in capfd.readouterr().err     # not without --verbose


def test_the_hang_guard_grows_with_the_runs_that_finished(leg_model, tmp_path):
    """A run is taken for hung only past HANG_FACTOR times the longest run of its folder that finished: on a loaded
    machine, or on a finer mesh, every run is slower (a refit's differences under the band stopped at the 120 s
    default where the runs before them had taken up to 345 s). A run that failed or was stopped does not count."""
    log = EvaluationLog(tmp_path / LOG_NAME)
    for key, status, seconds in (("finished", OK, 100.0), ("stopped", TIMEOUT, 900.0)):
        log.append({"key": key, "theta": [1.0], "options": {}, "tag": "", "status": status, "cost": 1.0,
                    "outputs": {}, "message": "", "newton_iterations": 3, "time_s": seconds, "finished_at": 0.0})
    log.close()
    theta = list(TABLE2_CENTRAL_KPA)
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path, timeout_s=120.0, progress=False) as evaluator:
        assert evaluator.task(theta).timeout_s == pytest.approx(HANG_FACTOR * 100.0)
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path, timeout_s=600.0, progress=False) as evaluator:
        assert evaluator.task(theta).timeout_s == 600.0                  # the user's, when longer
    with Evaluator(leg_model, skin_objective(leg_model), tmp_path / "fresh", timeout_s=120.0,
                   progress=False) as evaluator:
        assert evaluator.task(theta).timeout_s == 120.0                  # nothing finished yet


def test_a_run_carrying_sensitivities_through_friction_gets_the_time_they_take(leg_model):
    """Each column carried along the put-on's path is a back-substitution at every increment: the hang guard grows
    with them, and only there (the same deck without friction, or without sensitivities, keeps the user's timeout)."""
    theta = list(TABLE2_CENTRAL_KPA)
    band = LegModel(leg_model.mesh, 0.16, garment="explicit", friction_mu=0.3, engine_sensitivities=True,
                    effects=("drainage",))
    text = band.deck(theta + [0.0])
    # five columns: the four constants and the muscle's volume change
    assert run_timeout(text, 120.0) == pytest.approx(120.0 * (1 + 5 / TIMEOUT_COLUMNS_PER_RUN))
    frictionless = LegModel(leg_model.mesh, 0.16, garment="explicit", engine_sensitivities=True)
    assert run_timeout(frictionless.deck(theta), 120.0) == 120.0
    assert run_timeout(LegModel(leg_model.mesh, 0.16, garment="explicit", friction_mu=0.3).deck(theta), 120.0) == 120.0
