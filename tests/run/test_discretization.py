"""The fit's mesh against its measurements (orchestrator/run/discretization.py): the identification solves its fit again
on a mesh of twice the elements and says whether the misfit depends on the mesh more than the noise lets one see.

A phantom calf made on its own 8,000-element mesh, measured at points (0.02 mm noise), identified from a start that
is not the truth: on a mesh of 400 linear triangles (CPE3) the discretization error is many times the noise and the
run says the mesh is too coarse, with the number of elements to ask for; on the default mesh (2,000 CPE6) it is
fine. A default mesh that the check finds too coarse is meshed again with twice the elements, once."""

from __future__ import annotations

import pytest

from orchestrator.core.frame import RigidMotion
from orchestrator.engine.runner import LOG_NAME, EvaluationLog
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import random_truth
from orchestrator.run import stages as pipeline
from orchestrator.run.setup import load_run
from orchestrator.run.stages import run_identify


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("discretization")
    case, _ = make_phantom_case(folder / "case", theta_kPa=random_truth(5), rigid=RigidMotion(0.5, (0.3, -0.2), (75.0, 75.0)),
                                points_spacing_mm=6.0, points_sigma_mm=0.02)
    return case


@pytest.mark.parametrize("elements, order, adequate", [(400, 1, False), (None, None, True)])
def test_the_identification_says_whether_its_mesh_is_fine_enough(case, tmp_path, elements, order, adequate):
    result = run_identify(case, tmp_path / "run", data="points", n_elements=elements, order=order, progress=False)
    check = result["discretization"]
    print(check)
    assert check["checked"] and check["adequate"] == adequate
    assert check["finer_elements"] >= 1.9 * check["elements"]
    line = result["setup_lines"][-1]
    if adequate:
        assert line.startswith("mesh fine enough") and check["chi2_disc"] <= check["limit"]
    else:
        assert line.startswith("MESH TOO COARSE") and f"--elements {check['finer_elements']}" in line
        assert check["chi2_disc"] > check["limit"] and check["drop"] > check["limit"]


def test_a_default_mesh_too_coarse_is_meshed_again_and_the_fit_carried_to_it(case, tmp_path, monkeypatch):
    """The default mesh here made coarse (400 CPE3): the run meshes again with the check's finer mesh, fits from where
    the coarse fit ended, says so, and keeps what the coarse mesh gave."""
    monkeypatch.setitem(pipeline.DEFAULT_MESH, "displacement", (400, 1))
    result = run_identify(case, tmp_path / "run", data="points", progress=False)
    coarse = result["coarser_mesh"]
    assert not coarse["discretization"]["adequate"]
    elements = len(load_run(tmp_path / "run").mesh.elements)
    assert elements == result["discretization"]["elements"]
    assert abs(elements / coarse["discretization"]["finer_elements"] - 1) < 0.05   # the mesher's count is approximate
    assert result["misfit_over_floor"] < coarse["misfit_over_floor"]
    assert any(line.startswith("meshed again with") for line in result["setup_lines"])
    assert result["best"]["start"] == coarse["best"]["theta"]
    # run again (as after an interruption): the same finer mesh from the same start, every evaluation replayed
    runs = len(EvaluationLog(tmp_path / "run" / LOG_NAME))
    again = run_identify(case, tmp_path / "run", data="points", progress=False)
    assert len(EvaluationLog(tmp_path / "run" / LOG_NAME)) == runs
    assert again["best"]["theta"] == result["best"]["theta"] and again["coarser_mesh"] == coarse
