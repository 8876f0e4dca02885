"""Fixtures shared by the test modules that need a whole phantom run: made once per session, since each costs
an engine-made phantom and an identification. They are read-only; a test that adds to a run copies it first
(`copy_run`)."""

from __future__ import annotations

import shutil

import pytest

from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.stages import run_identify

HIDDEN_DRAINAGE = {"drainage": {"dv_muscle": -0.05}}


@pytest.fixture(scope="session")
def drainage_case(tmp_path_factory):
    """(case, truth folder): the phantom calf with a hidden fluid loss of the muscle (5 %), truth on 2,000 CPE6,
    points.csv every 6 mm with 0.02 mm noise."""
    folder = tmp_path_factory.mktemp("drainage")
    return make_phantom_case(folder / "case", folder / "case.truth", n_elements=2000, effects=HIDDEN_DRAINAGE)


@pytest.fixture(scope="session")
def drainage_identified(drainage_case, tmp_path_factory):
    """The drainage case identified with the baseline model (Levenberg-Marquardt from the default start, not the
    truth; 400 CPE6): a run folder to copy."""
    run = tmp_path_factory.mktemp("drainage-identified") / "run"
    run_identify(drainage_case[0], run, method="lm", objective="displacement", n_elements=400, order=2,
                 progress=False)
    return run


def copy_run(run, target):
    """A copy of a run folder to add to (the evaluation log and sensitivities come along)."""
    shutil.copytree(run, target)
    return target
