"""calfit design on a stack of phantom slices with known truth, laid out as a volume study (slices.json naming B,
B1, C and D, one identified run folder per height): the leg narrow at B, widest at C, narrower again at D, the truth
stiffer towards the knee. The garment designed for RAL-GZ 387/1 class II at B with the standard's graduation,
applied to the truth's model, gives class II at B and a pressure falling from B through B1 and C to D, D at most
70 % of B (slow: about 2 minutes).

The slices are cut from no 3D volume here: each is a `CalfPhantom` whose outline is the leg's at that height, so
that the design is tested apart from the volume's slicing (tests/study covers that)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from orchestrator.core.files import write_json
from orchestrator.design.slices import evaluate, read_slices
from orchestrator.design.stage import run_design
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.geometry import CalfGeometry, CalfShape
from orchestrator.run.stages import run_identify, run_montecarlo

pytestmark = pytest.mark.slow

# height (mm), name, the outline's scale against the standard calf, the truth (kPa)
LEVELS = ((210.0, "B", 0.80, (3.2, 11.0, 92.0, 74.0)), (240.0, "B1", 0.88, (3.4, 11.8, 92.0, 74.0)),
          (290.0, "C", 1.00, (3.6, 12.4, 92.0, 74.0)), (330.0, "D", 0.93, (3.9, 13.2, 92.0, 74.0)))
NAMES = ("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle")


def phantom_volume_study(root, levels=LEVELS, draws: int = 20):
    """A study folder as `calfit study` leaves a volume: slices.json and DIR/cases/<slice>/ identified run folders;
    returns (folder, {slice name: truth theta})."""
    study, truths = root / "study", {}
    entries = []
    for height, name, scale, theta in levels:
        shape = dataclasses.replace(CalfShape(), half_width_mm=58.0 * scale, half_depth_mm=52.0 * scale)
        phantom = CalfPhantom(geometry=CalfGeometry(shape))
        folder = f"slice-{height:g}mm"
        case, _ = make_phantom_case(root / folder, root / f"{folder}.truth", theta_kPa=theta, n_elements=2000,
                                    phantom=phantom)
        run = study / "cases" / folder
        run_identify(case, run, method="lm", objective="displacement", n_elements=400, order=2, progress=False)
        run_montecarlo(run, draws=draws, workers=2, progress=False)
        entries.append({"folder": str(study / "slices" / folder), "height_mm": height})
        truths[folder] = dict(zip(NAMES, theta))
    write_json(study / "slices.json", {"slices": entries,
                                       "compression_heights_mm": {name: h for h, name, _, _ in levels}})
    return study, truths


@pytest.fixture(scope="module")
def volume(tmp_path_factory):
    return phantom_volume_study(tmp_path_factory.mktemp("design-volume"))


def test_a_graduated_class_ii_design_meets_the_profile_on_the_truth(volume, tmp_path):
    study, truths = volume
    target = tmp_path / "TARGET.toml"
    target.write_text('[design]\ntension_range_N_per_mm = [0.05, 0.6]\n\n[[target]]\nheight = "B"\n'
                      'class = "RAL II"\n')
    result = run_design(study, target, tmp_path / "out", workers=2, report=True)
    assert result["status"] == "designed" and result["graduated"]
    table = result["tension_N_per_mm"]
    assert table["height_names"] == ["B", "B1", "C", "D"] and len(table["tension_N_per_mm"]) == 4
    on_truth = {}
    for piece, tension in zip(read_slices(study), table["tension_N_per_mm"]):
        theta = [truths[piece.name].get(name, 0.0) for name in piece.model.space.names]
        on_truth[piece.height_name] = evaluate(piece, tension, [], theta).skin_mean
    klass = result["targets"][0]
    assert 23.0 - 2 * klass["std_mmHg"] <= on_truth["B"] <= 32.0 + 2 * klass["std_mmHg"]
    assert on_truth["B"] >= on_truth["B1"] - 0.1 >= on_truth["C"] - 0.2 >= on_truth["D"] - 0.3
    assert on_truth["D"] <= 0.7 * on_truth["B"] + 0.3
    assert result["graduation_probability"] > 0.5
    # the garment's own profile along the leg: each height's tension within the fabric's range, lower towards
    # the knee (the widening calf alone would lower the pressure at C; the narrower leg at D needs less still)
    tension = np.array(table["tension_N_per_mm"])
    assert np.all((tension >= 0.05 - 1e-12) & (tension <= 0.6 + 1e-12)) and np.all(np.diff(tension) < 0)
    assert (tmp_path / "out" / "report" / "design-tension.png").is_file()
