"""Levenberg-Marquardt with the engine's sensitivities: on the phantom case of the demo (4
parameters of Avril et al., displacement residual at points.csv), the Jacobian from du/dtheta
(`*SENSITIVITY`) reaches the optimum that finite differences reach, from a start 20-30 % off the
truth, in at most 15 engine runs (fitted on 600 CPE6, the phantom made on its own mesh)."""

import numpy as np
import pytest

from orchestrator.model.forward import TABLE2_CENTRAL_KPA
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.stages import run_identify

START_KPA = (np.array(TABLE2_CENTRAL_KPA) * np.array([1.3, 0.8, 0.8, 1.25])).tolist()   # off the truth


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lm-sensitivities")
    case, _ = make_phantom_case(folder / "case")
    results = {}
    for label, engine in (("engine", True), ("fd", False)):
        results[label] = run_identify(case, folder / f"run-{label}", method="lm", objective="displacement",
                                      start=START_KPA, engine_sensitivities=engine, n_elements=600,
                                      progress=False)["best"]
    return results


def test_engine_sensitivities_reach_the_finite_difference_optimum(fits):
    engine, fd = np.array(fits["engine"]["theta"]), np.array(fits["fd"]["theta"])
    assert np.max(np.abs(engine - fd) / fd) < 1e-3
    assert fits["engine"]["cost"] == pytest.approx(fits["fd"]["cost"], rel=1e-6)


def test_engine_sensitivities_need_at_most_15_runs(fits):
    assert fits["engine"]["engine_runs"] <= 15
    assert fits["fd"]["engine_runs"] > fits["engine"]["engine_runs"]
