"""End to end on a phantom case whose loaded image is made by the engine (calfit phantom): known
parameters (Avril et al. Table 2 central values), image noise and noisy measured displacements
(sigma 0.02 mm), a fine T6 mesh for the truth and the 400-element mesh of the fit (no inverse
crime).

- Identification (LM on F, Bouten and Drapier eq. 2, from the starts of Avril et al. Table 1, on the
  first paper's 400 elements, CPE6: the CPE3 of the paper bias the muscle C10 by about 1 %, which
  puts the truth just outside the interval): the parameters Avril et al.'s threshold Monte-Carlo
  calls well identified are within 10 % of the truth, every interval contains the truth, and the
  fat C10 comes out poorly identified (as in the first paper).
- Landmark pressures for a 0.16 N/mm (about 20 mmHg) garment are of the order of Table 3 (2.7 to
  4.4 kPa), with a coefficient of variation; +-10 % tension moves them by about +-10 % (Table 4).
- `--json` prints one JSON object (the report is tested in test_report.py).
- Killing `calfit identify` half-way and running it again finishes with no evaluation repeated:
  the second run launches the engine exactly for the evaluations missing from the log, and ends
  where an uninterrupted run ends.
"""

from __future__ import annotations

import json
import os
import random
import subprocess

import numpy as np
import pytest
from killing import calfit_command, counting_wrapper, kill_after, log_lines

from orchestrator.cli import main
from orchestrator.core.errors import RunFolderError
from orchestrator.model.forward import LEG_PARAMETERS
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.setup import PARAMETERS_FILE, read_json
from orchestrator.run.stages import run_identify, run_montecarlo, run_pressures


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    folder = tmp_path_factory.mktemp("phantom")
    case, truth = make_phantom_case(folder / "case", folder / "case.truth")
    parameters = read_json(truth / PARAMETERS_FILE, "calfit phantom")["parameters_kPa"]
    return case, truth, np.array([parameters[name] for name in LEG_PARAMETERS])


@pytest.fixture(scope="module")
def study(phantom, tmp_path_factory):
    case, _, truth = phantom
    run = tmp_path_factory.mktemp("run")
    identification = run_identify(case, run, method="lm", objective="displacement", starts="table1", workers=2,
                                  n_elements=400, order=2, progress=False)
    montecarlo = run_montecarlo(run, method="threshold", draws=400, workers=2, progress=False)
    pressures = run_pressures(run, workers=2, progress=False)
    return run, identification, montecarlo, pressures


def test_well_identified_parameters_are_within_10_percent_and_intervals_hold_the_truth(phantom, study):
    _, _, truth = phantom
    _, identification, montecarlo, _ = study
    theta = np.array(identification["best"]["theta"])
    error = np.abs(theta - truth) / truth
    print("identified", dict(zip(LEG_PARAMETERS, np.round(theta, 3))), "relative error", np.round(error, 3))
    print("intervals", list(zip(LEG_PARAMETERS, np.round(montecarlo["lower"], 2), np.round(montecarlo["upper"], 2))),
          "poorly identified", montecarlo["poorly_identified"])
    well = [k for k, name in enumerate(LEG_PARAMETERS) if name not in montecarlo["poorly_identified"]]
    assert {"C10_muscle", "Kv_muscle"} <= {LEG_PARAMETERS[k] for k in well}
    assert np.all(error[well] < 0.10)
    assert np.all(np.array(montecarlo["lower"]) <= truth) and np.all(truth <= np.array(montecarlo["upper"]))
    assert "C10_fat" in montecarlo["poorly_identified"]
    assert montecarlo["accepted"] > 10 and montecarlo["failed"] == 0
    # Table 1: every start ends near the same misfit
    costs = [fit["cost"] for fit in identification["fits"]]
    assert len(costs) == 9 and max(costs) < 1.05 * min(costs)


def test_landmark_pressures_are_of_the_order_of_table_3(study):
    _, _, _, pressures = study
    mean, cv = np.array(pressures["mean_kPa"]), np.array(pressures["cv_percent"])
    print("landmark pressures (kPa)", dict(zip(pressures["landmarks"], np.round(mean, 2))), "CV %", np.round(cv, 2))
    assert len(mean) == 5 and np.all((1.5 < mean) & (mean < 6.0)) and 2.0 < mean.mean() < 4.5
    assert np.all((0 < cv) & (cv < 15.0)) and pressures["draws"] == 30 and pressures["failed"] == 0
    # Table 4: +-10 % tension changes the pressures by 5 to 15 % (Laplace law, geometric non-linearity)
    for deviation in (pressures["plus_deviation_percent"], pressures["minus_deviation_percent"]):
        assert np.all((5.0 < np.array(deviation)) & (np.array(deviation) < 15.0))


def test_pressures_json_prints_one_object(study, capsys):
    run, _, _, pressures = study
    assert main(["pressures", str(run), "--json", "--workers", "1"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["mean_kPa"] == pressures["mean_kPa"]


def test_unknown_effects_are_refused_with_the_catalog(phantom, tmp_path, capsys):
    case, _, _ = phantom
    assert main(["identify", str(case), "--out", str(tmp_path / "run"), "--effects", "oedema"]) == 2
    message = capsys.readouterr().err
    assert "unknown effect 'oedema'" in message and "drainage" in message


def _identify_command(case, run, method="nm"):
    extra = ["--starts", "table1"] if method == "lm" else []   # LM: the five starts of Table 1, ~25 evaluations
    # the fixture's mesh (400 CPE6): what is tested is the resume, not the mesh
    return calfit_command("identify", case, "--out", run, "--method", method, "--objective", "displacement",
                          "--elements", "400", "--workers", "1", "--json", *extra)


def test_killed_identification_resumes_without_repeating_an_evaluation(phantom, tmp_path):
    case, _, _ = phantom
    wrapper, launches = counting_wrapper(tmp_path)
    environment = dict(os.environ, CALFIT_FE=str(wrapper))
    run = tmp_path / "run"
    kill_after(_identify_command(case, run), environment, run, 40)
    logged_before, launched_before = len(log_lines(run)), launches()
    assert logged_before >= 40 and launched_before - logged_before <= 1   # at most the run in flight is lost

    finished = subprocess.run(_identify_command(case, run), env=environment, capture_output=True, text=True,
                              timeout=600)
    assert finished.returncode == 0, finished.stderr
    resumed = json.loads(finished.stdout)
    records = log_lines(run)
    assert len({record["key"] for record in records}) == len(records)        # nothing evaluated twice
    assert launches() - launched_before == len(records) - logged_before      # only the missing ones launched
    assert resumed["best"]["from_log"] >= logged_before - 1

    uninterrupted = subprocess.run(_identify_command(case, tmp_path / "fresh"), capture_output=True, text=True,
                                   timeout=600)
    assert uninterrupted.returncode == 0, uninterrupted.stderr
    fresh = json.loads(uninterrupted.stdout)
    assert resumed["best"]["theta"] == fresh["best"]["theta"] and resumed["best"]["cost"] == fresh["best"]["cost"]
    assert len(log_lines(tmp_path / "fresh")) == len(records)


@pytest.mark.parametrize("seed", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_killed_lm_identification_resumes_with_the_same_steps(phantom, tmp_path, seed):
    """Levenberg-Marquardt with the engine's sensitivities, killed after a random number of evaluations: the
    resumed run reads the Jacobians back (RUN_DIR/sensitivities), so it takes the same steps, launches only what
    was not finished and ends where an uninterrupted run ends."""
    case, _, _ = phantom
    uninterrupted = subprocess.run(_identify_command(case, tmp_path / "fresh", "lm"), capture_output=True, text=True,
                                   timeout=600)
    assert uninterrupted.returncode == 0, uninterrupted.stderr
    fresh, total = json.loads(uninterrupted.stdout), len(log_lines(tmp_path / "fresh"))
    kill_at = random.Random(seed).randint(1, total - 2)

    wrapper, launches = counting_wrapper(tmp_path)
    environment = dict(os.environ, CALFIT_FE=str(wrapper))
    run = tmp_path / "run"
    kill_after(_identify_command(case, run, "lm"), environment, run, kill_at)
    logged_before, launched_before = len(log_lines(run)), launches()

    finished = subprocess.run(_identify_command(case, run, "lm"), env=environment, capture_output=True, text=True,
                              timeout=600)
    assert finished.returncode == 0, finished.stderr
    resumed, records = json.loads(finished.stdout), log_lines(run)
    assert len({record["key"] for record in records}) == len(records) == total     # the same evaluations, once each
    assert launches() - launched_before == total - logged_before                     # only the missing ones launched
    assert resumed["best"]["theta"] == fresh["best"]["theta"] and resumed["best"]["cost"] == fresh["best"]["cost"]


def test_monte_carlo_and_pressures_run_again_replay_everything(study):
    """Every evaluation of the Monte-Carlo and of the pressures is in the log: run again, they launch nothing and
    give the same numbers."""
    run, _, montecarlo, pressures = study
    logged = len(log_lines(run))
    again = run_montecarlo(run, method="threshold", draws=400, workers=2, progress=False)
    again_pressures = run_pressures(run, workers=2, progress=False)
    assert len(log_lines(run)) == logged
    assert again["lower"] == montecarlo["lower"] and again["upper"] == montecarlo["upper"]
    assert again_pressures["mean_kPa"] == pressures["mean_kPa"]


def test_pressures_are_those_of_the_identified_model_with_its_effects(phantom, tmp_path):
    """A run identified with a catalog effect: the Monte-Carlo's intervals hold the effect's parameter, and the
    pressures are drawn from the model that has it (the model without it cannot take those parameters); a
    Monte-Carlo left from another identification is refused with a sentence that says what to run."""
    case, _, _ = phantom
    run = tmp_path / "run"
    identification = run_identify(case, run, method="lm", objective="displacement", workers=2, n_elements=400,
                                  order=2, effects=["unloaded_curvature"], skin_uncertainty=False, progress=False)
    assert identification["parameters"][-1] == "alpha_unloaded"
    montecarlo = run_montecarlo(run, method="noise", draws=10, workers=2, progress=False)
    assert len(montecarlo["central"]) == 5
    pressures = run_pressures(run, draws=4, workers=2, progress=False)
    assert pressures["failed"] == 0 and len(pressures["mean_kPa"]) == 5
    stale = dict(montecarlo, central=montecarlo["central"][:4], lower=montecarlo["lower"][:4],
                 upper=montecarlo["upper"][:4])
    (run / "montecarlo.json").write_text(json.dumps(stale))
    with pytest.raises(RunFolderError, match="run calfit montecarlo RUN_DIR again"):
        run_pressures(run, draws=4, workers=2, progress=False)


def test_the_diagnosis_reads_the_landmark_pressures_of_both_models_and_places_missing_landmarks(study):
    """`landmark_pressures`: the final model's law at alpha = 0 is the identified model's (the same pressures), at
    alpha = 1 (the garment pressing by the unloaded skin's curvature) the pressures move; a case whose case.toml
    names no landmarks gets them placed from I0's segmentation, within a vein's diameter of the phantom's."""
    import dataclasses
    from types import SimpleNamespace

    from orchestrator.run.diagnose_stage import landmark_pressures
    from orchestrator.run.setup import load_run

    run, identification, _, _ = study
    setup = load_run(run)
    theta = list(identification["best"]["theta"])

    def step(effects, values):
        return SimpleNamespace(effects=effects, fit=SimpleNamespace(parameters=list(values), theta=list(values.values())))

    identified = step([], dict(zip(LEG_PARAMETERS, theta)))
    assert landmark_pressures(setup, SimpleNamespace(steps=[identified], final=identified)) is None   # nothing added
    for alpha, moved in ((0.0, False), (1.0, True)):
        final = step(["unloaded_curvature"], {**dict(zip(LEG_PARAMETERS, theta)), "alpha_unloaded": alpha})
        found = landmark_pressures(setup, SimpleNamespace(steps=[identified, final], final=final))
        assert found["landmarks"] == list(setup.case.landmarks) and found["landmarks_from"] == "case.toml"
        change = np.abs(np.array(found["final_kPa"]) - found["baseline_kPa"]) / np.array(found["baseline_kPa"])
        assert (change.max() > 0.005) == moved, change
    given = dict(setup.case.landmarks)
    setup.case = dataclasses.replace(setup.case, landmarks=None)
    placed, source = setup.landmarks()
    assert source == "segmentation" and list(placed) == list(given)
    for name in given:
        assert np.hypot(*(np.array(placed[name]) - given[name])) < 3.2, name
