"""The second paper's model identified back (issue 13, must-show 1): Bouten and Drapier's Mooney-Rivlin tissues
(Table 1: adipose C10 1.4, C01 1.0, C20 -0.04 kPa; gastrocnemius C10 0.9, C01 0.6 kPa; bulk moduli of 1e8, i.e.
incompressible), on u/p elements (CPE6H), under the explicit garment band with Coulomb friction (mu = 0.3).

The phantom is made on its own 2,000-element mesh of the phantom's true shapes, with scanner motion and points of
0.05 mm noise (a DIC window's); the fit runs from case.toml alone ([model] and [model.<tissue>] tables) on a mesh
of 1,000 elements made from the images, from the default start (C10 = C01 = half of Avril et al.'s Table 2 C10,
2 to 6 times the truth), by Levenberg-Marquardt with differenced runs (no sensitivities through friction), then the
noise Monte-Carlo. The muscle's C01 is fixed at its Table 1 value, the fat's C20 too.

What can be identified: in plane strain an incompressible tissue has I1bar = I2bar, so the fat's C10 and C01 act
only through their sum. The run must say so before the fit (setup line) and after it (neither identifiable), the
sum's interval must hold the truth (and the sum be within 10 % where that interval is narrow enough to call it
identified); the muscle's C10 (its C01 fixed) is identifiable and within 10 %. Every free parameter's truth lies in
its 95 % interval.
"""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.imaging.frame import RigidMotion
from orchestrator.materials import TissueLaw
from orchestrator.pipeline import run_identify, run_montecarlo
from orchestrator.study import make_phantom_case

TABLE1_KPA = {"C10_fat": 1.4, "C10_muscle": 0.9, "C01_fat": 1.0, "C01_muscle": 0.6}
FAT = TissueLaw("mooney_rivlin", terms=3, incompressible=True, fixed={"C20": -0.04})
MUSCLE = TissueLaw("mooney_rivlin", incompressible=True)
FIT_TABLES = """
[model]
element = "CPE6H"
garment = "explicit"
friction = 0.3
[model.fat]
law = "mooney_rivlin"
terms = 3
incompressible = true
fixed = { C20 = -0.04 }
[model.muscle]
law = "mooney_rivlin"
incompressible = true
fixed = { C01 = 0.6 }
"""


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not yet (issue 13): on a 1,000-element fit the muscle's C10 comes out 0.856 "
                   "(-4.9 %) with an interval [0.801, 0.868], and the fat's C10 + C01 2.83 (+18 %) with [2.77, 30.1], "
                   "at 1.24 x the floor: the friction band's difference between the truth's mesh of the true shapes "
                   "and the fit's from the images, which the noise Monte-Carlo does not count (600 elements: 0.873, "
                   "[0.857, 0.895])")
def test_second_paper_model_is_identified_back(tmp_path):
    case, _ = make_phantom_case(tmp_path / "case", tmp_path / "truth", theta_kPa=list(TABLE1_KPA.values()),
                                n_elements=2000, rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)),
                                points_sigma_mm=0.05, garment="explicit", friction_mu=0.3,
                                tissues={"fat": FAT, "muscle": MUSCLE}, hybrid=True)
    with open(case / "case.toml", "a") as toml:
        toml.write(FIT_TABLES)
    run = tmp_path / "run"
    result = run_identify(case, run, data="points", n_elements=1000, workers=2, progress=False)
    names, theta = result["parameters"], np.array(result["best"]["theta"])
    assert names == ["C10_fat", "C10_muscle", "C01_fat"]
    assert any("C10_fat and C01_fat act only through their sum" in line for line in result["setup_lines"])
    assert any("friction 0.3" in line and "differences runs" in line for line in result["setup_lines"])

    intervals = run_montecarlo(run, draws=30, workers=2, progress=False)
    truth = np.array([TABLE1_KPA[name] for name in names])
    lower, upper = np.array(intervals["lower"]), np.array(intervals["upper"])
    samples = np.array(intervals["samples"])
    fat_sum = samples[:, 0] + samples[:, 2]
    print(f"fit {dict(zip(names, theta.round(3)))}, misfit {result['misfit_over_floor']:.2f} x floor, "
          f"{result['best']['iterations']} iterations, {result['best']['engine_runs']} runs; intervals "
          f"{np.column_stack([lower, upper]).round(3).tolist()}, undetermined {intervals['undetermined']}; fat C10 + C01 "
          f"{theta[0] + theta[2]:.3f} in {np.percentile(fat_sum, [2.5, 97.5]).round(3)} (truth 2.4)")
    assert result["misfit_over_floor"] < 1.5
    assert np.all((lower <= truth) & (truth <= upper)), "a truth outside its 95 % interval"
    assert intervals["identifiable"] == [False, True, False]          # the fat's C10 and C01 are not, alone
    assert abs(theta[1] / truth[1] - 1) <= 0.10                       # C10 of muscle
    low, high = np.percentile(fat_sum, [2.5, 97.5])
    assert low <= 2.4 <= high                                          # the fat's sum, in its interval
    if (high - low) / (2 * (theta[0] + theta[2])) <= 0.10:            # and within 10 % where it is identified
        assert abs((theta[0] + theta[2]) / 2.4 - 1) <= 0.10
