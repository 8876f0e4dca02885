"""calfit design on an identified phantom slice whose truth is known (orchestrator/design/): the engine's tension
sensitivity against a difference of runs; the designed garment, applied to the truth's model, meets each target
within its stated uncertainty; a target no garment in the fabric's range can meet is reported infeasible with the
closest design; Laplace's law beside it; a knitted-in profile; the command's design.json."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from orchestrator.core.files import read_json
from orchestrator.design.slices import evaluate, read_slices
from orchestrator.design.stage import run_design
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.setup import PARAMETERS_FILE
from orchestrator.run.stages import run_identify, run_montecarlo

TRUTH_KPA = (3.6, 12.4, 92.0, 74.0)     # C10_fat, C10_muscle, Kv_fat, Kv_muscle

TARGETS = """
[design]
tension_range_N_per_mm = [0.05, 0.6]
slice_height = "B"
{extra}
[[target]]
height = "B"
class = "RAL II"

[[target]]
landmark = "deep_veins"
min_mmHg = 15

[[target]]
region = "tibial_crest"
max_mmHg = 40
"""


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    """A phantom slice (truth on 2,000 CPE6, points every 6 mm with 0.02 mm noise) identified on 400 CPE6, with
    20 noise Monte-Carlo draws; and its truth's parameters."""
    root = tmp_path_factory.mktemp("design")
    case, truth = make_phantom_case(root / "case", root / "case.truth", theta_kPa=TRUTH_KPA, n_elements=2000)
    run = root / "run"
    run_identify(case, run, method="lm", objective="displacement", n_elements=400, order=2, progress=False)
    run_montecarlo(run, draws=20, workers=2, progress=False)
    return run, read_json(truth / PARAMETERS_FILE, "the phantom")["parameters_kPa"]


def _truth_theta(piece, truth: dict) -> list[float]:
    return [truth.get(name, 0.0) for name in piece.model.space.names]


def test_the_engine_differentiates_the_pressures_with_respect_to_the_tension(identified):
    run, _ = identified
    piece = read_slices(run)[0]
    base, ahead = evaluate(piece, 0.16, []), evaluate(piece, 0.1616, [])
    assert base.sensitivity == "engine"
    for name, value in base.landmarks.items():
        assert base.d_landmarks[name][0] == pytest.approx((ahead.landmarks[name] - value) / 0.0016, rel=5e-3)
    assert base.d_skin_mean[0] == pytest.approx((ahead.skin_mean - base.skin_mean) / 0.0016, rel=5e-3)
    # the mean skin pressure is 2 pi T over the deformed girth (the curvature integrates to 2 pi)
    assert base.skin_mean == pytest.approx(2 * np.pi * 0.16 / base.deformed_perimeter_mm * 1000 * 7.50062, rel=1e-9)


def test_the_designed_garment_on_the_truth_meets_each_target_within_its_uncertainty(identified, tmp_path):
    run, truth = identified
    path = tmp_path / "TARGET.toml"
    path.write_text(TARGETS.format(extra=""))
    result = run_design(run, path, tmp_path / "out", workers=2, report=False)
    assert result["status"] == "designed" and 0.05 <= result["tension_N_per_mm"] <= 0.6
    piece = read_slices(run)[0]
    on_truth = evaluate(piece, result["tension_N_per_mm"], [], _truth_theta(piece, truth))
    for row in result["targets"]:
        true = on_truth.value(row["kind"], row["where"])
        assert abs(true - row["value"]) <= 2 * row["std_mmHg"], row
        low = row["min_mmHg"] if row["min_mmHg"] is not None else -np.inf
        high = row["max_mmHg"] if row["max_mmHg"] is not None else np.inf
        assert low - 2 * row["std_mmHg"] <= true <= high + 2 * row["std_mmHg"], row
        assert 0.0 <= row["probability_met"] <= 1.0
    klass = result["targets"][0]
    assert klass["value"] == pytest.approx(27.5, abs=0.05)     # the class's middle
    assert klass["probability_met"] > 0.5
    assert result["targets"][1]["probability_met"] >= 0.9     # the margin asked (probability = 0.9)


def test_without_the_tensions_uncertainty_the_truth_lies_within_the_parameters_spread(identified, tmp_path):
    """The tension known exactly: what is left is the leg's, and the truth's pressure at the veins is within three
    of its standard deviations (plus the truth's and the model's meshes' difference, the same mesh here)."""
    run, truth = identified
    path = tmp_path / "TARGET.toml"
    path.write_text(TARGETS.format(extra="tension_rel_uncertainty = 0.0"))
    result = run_design(run, path, tmp_path / "out", workers=2, report=False)
    piece = read_slices(run)[0]
    on_truth = evaluate(piece, result["tension_N_per_mm"], [], _truth_theta(piece, truth))
    veins = result["targets"][1]
    assert abs(on_truth.landmarks["deep_veins"] - veins["value"]) <= 3 * veins["std_mmHg"] + 0.05


def test_a_target_no_garment_in_the_range_meets_is_infeasible_with_the_closest_design(identified, tmp_path):
    run, _ = identified
    path = tmp_path / "TARGET.toml"
    path.write_text('[design]\ntension_range_N_per_mm = [0.05, 0.3]\n\n[[target]]\nlandmark = "deep_veins"\n'
                    'min_mmHg = 60\n')
    result = run_design(run, path, tmp_path / "out", workers=2, report=False)
    assert result["status"] == "infeasible" and not result["feasible"]
    assert result["tension_N_per_mm"] == pytest.approx(0.3)          # the closest: the fabric's strongest
    (missed,) = result["shortfalls"]
    assert missed["name"] == "deep_veins" and missed["shortfall_mmHg"] > 10
    assert result["targets"][0]["probability_met"] == 0.0
    assert json.loads((tmp_path / "out" / "design.json").read_text())["status"] == "infeasible"


def test_laplace_law_predicts_the_skin_at_the_veins_and_its_garment_gives_less_there(identified, tmp_path):
    """Laplace's law alone chooses the garment whose skin pressure is the veins' target; through the tissues the
    veins get less than the skin."""
    run, _ = identified
    path = tmp_path / "TARGET.toml"
    path.write_text('[[target]]\nlandmark = "deep_veins"\nvalue_mmHg = 15\ntolerance_mmHg = 0.5\n')
    result = run_design(run, path, tmp_path / "out", workers=2, report=False)
    fe, law = result["slices"][0], result["laplace"]["slices"][0]
    assert fe["landmarks_mmHg"]["deep_veins"] == pytest.approx(15, abs=0.05)
    assert law["laplace_landmarks_mmHg"]["deep_veins"] == pytest.approx(15, abs=0.05)
    assert law["landmarks_mmHg"]["deep_veins"] < 15 - 0.5          # what the Laplace garment really gives
    assert result["laplace"]["tension_N_per_mm"] < result["tension_N_per_mm"]


def test_a_knitted_in_profile_lowers_the_crest_under_the_same_class(identified, tmp_path):
    run, _ = identified
    uniform, profiled = tmp_path / "uniform.toml", tmp_path / "profiled.toml"
    text = '[design]\nslice_height = "B"\n{extra}\n[[target]]\nheight = "B"\nvalue_mmHg = 27\n\n' \
           '[[target]]\nregion = "tibial_crest"\nmax_mmHg = {cap}\n'
    first = run_design(run, _written(uniform, text.format(extra="", cap=60)), tmp_path / "u", workers=2,
                       report=False)
    crest = first["slices"][0]["skin_max_mmHg"]["tibial_crest"]
    second = run_design(run, _written(profiled, text.format(extra="harmonics = 2", cap=round(crest - 3, 1))),
                        tmp_path / "p", workers=2, report=False)
    table = second["tension_N_per_mm"]
    assert set(table) >= {"angles_deg", "values", "profile"} and len(table["values"][0]) == len(table["angles_deg"])
    assert second["slices"][0]["skin_max_mmHg"]["tibial_crest"] < crest - 2
    assert second["slices"][0]["skin_mean_mmHg"] == pytest.approx(27, abs=0.3)


def _written(path, text):
    path.write_text(text)
    return path


def test_the_command_writes_design_json_and_its_page(identified, tmp_path):
    run, _ = identified
    path = tmp_path / "TARGET.toml"
    path.write_text(TARGETS.format(extra="") + "\n[fabric]\nstretch = [1.0, 1.2, 1.4, 1.6]\n"
                    "tension_N_per_mm = [0.0, 0.08, 0.17, 0.28]\n")
    done = subprocess.run([sys.executable, "-m", "orchestrator.cli", "design", str(run), "--target", str(path),
                           "--out", str(tmp_path / "out"), "--draws", "8", "-q"], capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stderr
    assert "probability met" in done.stdout and "Laplace's law alone would choose" in done.stdout
    design = json.loads((tmp_path / "out" / "design.json").read_text())
    assert isinstance(design["tension_N_per_mm"], float)
    assert all({"name", "value", "probability_met"} <= set(row) for row in design["targets"])
    (fabric,) = design["fabric"]
    assert 1.4 < fabric["stretch"] < 1.6    # about 0.2 N/mm: between the test's 0.17 and 0.28 N/mm
    assert fabric["knit_circumference_mm"] == pytest.approx(fabric["leg_circumference_mm"] / fabric["stretch"])
    assert (tmp_path / "out" / "report" / "index.html").is_file()
    assert (tmp_path / "out" / "report" / "design-maps.png").is_file()
    bad = tmp_path / "bad.toml"
    bad.write_text('[[target]]\nlandmark = "femoral"\nmin_mmHg = 15\n')
    refused = subprocess.run([sys.executable, "-m", "orchestrator.cli", "design", str(run), "--target", str(bad),
                              "--out", str(tmp_path / "out2")], capture_output=True, text=True,
                             check=False)
    assert refused.returncode == 2 and "landmark 'femoral'" in refused.stderr and "Traceback" not in refused.stderr


def test_a_height_the_run_folder_has_no_slice_for_is_refused_before_any_engine_run(identified, tmp_path):
    from orchestrator.core.errors import CaseError

    run, _ = identified
    path = tmp_path / "TARGET.toml"
    path.write_text('[[target]]\nheight = "B"\nclass = "RAL II"\n')
    with pytest.raises(CaseError, match='has no slice named B; write slice_height = "B" under \\[design\\]'):
        run_design(run, path, tmp_path / "out", report=False)
    assert not (tmp_path / "out").exists()


def test_the_design_uses_the_effects_the_identification_added(drainage_case, tmp_path):
    """A leg whose muscle lost 5 % of its fluid, identified with the drainage effect: the design's model carries it
    at its identified value, and the design on the truth (drainage included) meets the veins' target within its
    uncertainty."""
    case, truth_folder = drainage_case
    run = tmp_path / "run"
    run_identify(case, run, method="lm", objective="displacement", effects=("drainage",), n_elements=400, order=2,
                 progress=False)
    run_montecarlo(run, draws=12, workers=2, progress=False)
    piece = read_slices(run)[0]
    assert "drainage" in piece.model.effects
    dv = piece.theta[piece.model.space.names.index("dv_muscle")]
    assert dv == pytest.approx(-0.05, abs=0.01)
    path = tmp_path / "TARGET.toml"
    path.write_text('[[target]]\nlandmark = "deep_veins"\nmin_mmHg = 15\n')
    result = run_design(run, path, tmp_path / "out", workers=2, report=False)
    assert result["slices"][0]["effects"] == ["drainage"]
    truth = read_json(truth_folder / PARAMETERS_FILE, "the phantom")["parameters_kPa"]
    theta = [truth.get(name, -0.05 if name == "dv_muscle" else 0.0) for name in piece.model.space.names]
    veins = result["targets"][0]
    true = evaluate(piece, result["tension_N_per_mm"], [], theta).landmarks["deep_veins"]
    assert abs(true - veins["value"]) <= 2 * veins["std_mmHg"] and true >= 15 - 2 * veins["std_mmHg"]
