"""A Monte-Carlo and a diagnosis killed at random points and started again: every evaluation the
killed run finished is read back from the run folder's log (with its engine sensitivities), the engine is
launched exactly for the evaluations still missing, none is evaluated twice, and the result is the one an
uninterrupted run gives, number for number.

The case is the phantom with a hidden fluid loss of the muscle of conftest.py (so that the diagnosis ranks
it and refits with it); its identified run folder is copied for the uninterrupted run and for each killed
one, so they start from the same log.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import subprocess

import pytest
from killing import calfit_command, counting_wrapper, kill_after, log_lines

# Timings and counts of engine launches say how a run went, not what it found.
RUN_BOOKKEEPING = {"wall_time_s", "engine_runs", "from_log", "launched"}


@pytest.fixture(scope="module")
def identified(drainage_identified):
    return drainage_identified


COMMANDS = {
    "montecarlo": lambda run: calfit_command("montecarlo", run, "--method", "noise", "--draws", "24",
                                             "--workers", "1", "--json"),
    "diagnose": lambda run: calfit_command("diagnose", run, "--workers", "1", "--json"),
}


def _without_bookkeeping(value):
    if isinstance(value, dict):
        return {k: _without_bookkeeping(v) for k, v in value.items() if k not in RUN_BOOKKEEPING}
    if isinstance(value, list):
        return [_without_bookkeeping(v) for v in value]
    return value


def _run(command, environment=None) -> dict:
    finished = subprocess.run(command, env=environment, capture_output=True, text=True, timeout=900)
    assert finished.returncode == 0, finished.stderr
    return json.loads(finished.stdout)


@pytest.fixture(scope="module")
def uninterrupted(identified, tmp_path_factory):
    """Each stage run once without interruption: its result and the length of its log."""
    runs = {}

    def result_of(stage):
        if stage not in runs:
            fresh = tmp_path_factory.mktemp(f"{stage}-uninterrupted") / "run"
            shutil.copytree(identified, fresh)
            runs[stage] = _run(COMMANDS[stage](fresh)), len(log_lines(fresh))
        return runs[stage]
    return result_of


# The diagnosis runs tens of evaluations (the ranking, the drainage refit from two starts, the local change's refit
# when it could rival drainage's): slow; a second draw of the Monte-Carlo's kill point too.
@pytest.mark.parametrize("stage, seed", [("montecarlo", 1), pytest.param("montecarlo", 2, marks=pytest.mark.slow),
                                         pytest.param("diagnose", 1, marks=pytest.mark.slow),
                                         pytest.param("diagnose", 2, marks=pytest.mark.slow)])
def test_killed_stage_resumes_reusing_every_finished_evaluation(identified, uninterrupted, tmp_path, stage, seed):
    before = len(log_lines(identified))
    expected, total = uninterrupted(stage)
    assert total - before >= 4, f"the {stage} ran only {total - before} new evaluations: too few to interrupt"

    run = tmp_path / "run"
    shutil.copytree(identified, run)
    wrapper, launches = counting_wrapper(tmp_path)
    environment = dict(os.environ, CALFIT_FE=str(wrapper))
    kill_at = before + random.Random(seed).randint(1, total - before - 2)
    kill_after(COMMANDS[stage](run), environment, run, kill_at)
    logged, launched = len(log_lines(run)), launches()
    assert logged >= kill_at and launched - (logged - before) <= 1     # at most the run in flight is lost

    resumed = _run(COMMANDS[stage](run), environment)
    records = log_lines(run)
    print(f"{stage}: killed after {logged - before} of {total - before} evaluations, resumed with "
          f"{launches() - launched} launches")
    assert len({record["key"] for record in records}) == len(records) == total    # the same evaluations, once each
    assert launches() - launched == total - logged                                 # only the missing ones launched
    assert _without_bookkeeping(resumed) == _without_bookkeeping(expected)
