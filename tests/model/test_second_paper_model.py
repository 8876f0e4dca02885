"""The second paper's model identified back: Bouten and Drapier's Mooney-Rivlin tissues
(Table 1: adipose C10 1.4, C01 1.0, C20 -0.04 kPa; gastrocnemius C10 0.9, C01 0.6 kPa; bulk moduli of 1e8, i.e.
incompressible), on u/p elements (CPE6H), under the explicit garment band with Coulomb friction (mu = 0.3).

The phantom is made on its own 8,000-element mesh of the phantom's true shapes, with scanner motion and points of
0.05 mm noise (a DIC window's); the fit runs from case.toml alone ([model] and [model.<tissue>] tables) on the mesh
that a case with friction gets by default (2,000 elements, made from the images), from the default start (C10 =
C01 = half of Avril et al.'s Table 2 C10, 2 to 6 times the truth), by Levenberg-Marquardt on the engine's
sensitivities (carried along the put-on's path through friction), then the noise Monte-Carlo. The muscle's C01 is
fixed at its Table 1 value, the fat's C20 too. Measured: the muscle's C10 0.883 (-1.9 %) in [0.869, 0.898]; the
fat's sum 2.47 (+2.9 %) in [2.15, 2.87]; C10 and C01 of the fat undetermined; 0.99 x the noise floor; 6 LM
iterations and 7 runs (with differenced runs and the release's adaptive increments: 7 iterations, 41 runs, 0.895).
The muscle's C10 is 2.4 of its noise standard deviations low, a bias that the noise interval does not hold (its
95 % bound misses 0.9 by 0.3 %); the fit's 2,000 elements against the truth's 8,000 are its likely cause (not
measured apart). The truth's mesh matters: made on 2,000 elements, the phantom is itself 1.16 x the floor away from
the 2,000-element fit at the truth (0.98 x from the 8,000), and the muscle's C10 came out 2.9 % low.

What can be identified: in plane strain an incompressible tissue has I1bar = I2bar, so the fat's C10 and C01 act
only through their sum. The run must say so before the fit (setup line) and after it (neither identifiable), the
sum's interval must hold the truth (and the sum be within 10 % where that interval is narrow enough to call it
identified: the Monte-Carlo reports it, `sums`); the muscle's C10 (its C01 fixed) is identifiable and within 10 %,
its error one of the Monte-Carlo's draws (within 3.29 of their standard deviations: tests/support/intervals.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from intervals import assert_each_error_within_its_spread

from orchestrator.core.frame import RigidMotion
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.truths import (
    SECOND_PAPER_FIT_TABLES,
    SECOND_PAPER_KPA,
    SECOND_PAPER_TISSUES,
)
from orchestrator.run.stages import run_identify, run_montecarlo


@pytest.mark.slow
def test_second_paper_model_is_identified_back(tmp_path):
    case, _ = make_phantom_case(tmp_path / "case", tmp_path / "truth", theta_kPa=list(SECOND_PAPER_KPA.values()),
                                rigid=RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0)), points_sigma_mm=0.05,
                                garment="explicit", friction_mu=0.3, tissues=SECOND_PAPER_TISSUES, hybrid=True)
    with open(case / "case.toml", "a") as toml:
        toml.write(SECOND_PAPER_FIT_TABLES)
    run = tmp_path / "run"
    result = run_identify(case, run, data="points", workers=2, progress=False)
    names, theta = result["parameters"], np.array(result["best"]["theta"])
    assert names == ["C10_fat", "C10_muscle", "C01_fat"]
    assert any("C10_fat and C01_fat act only through their sum" in line for line in result["setup_lines"])
    assert any("friction 0.3" in line and "along the loading path" in line for line in result["setup_lines"])

    intervals = run_montecarlo(run, draws=30, workers=2, progress=False)
    truth = np.array([SECOND_PAPER_KPA[name] for name in names])
    lower, upper = np.array(intervals["lower"]), np.array(intervals["upper"])
    fat = intervals["sums"][0]
    print(f"fit {dict(zip(names, theta.round(4)))}, misfit {result['misfit_over_floor']:.3f} x floor, "
          f"{result['best']['iterations']} iterations, {result['best']['engine_runs']} runs; intervals "
          f"{np.column_stack([lower, upper]).round(4).tolist()}, undetermined {intervals['undetermined']}; fat C10 + C01 "
          f"{fat['value']:.3f} in [{fat['lower']:.3f}, {fat['upper']:.3f}] (truth 2.4)")
    assert result["misfit_over_floor"] < 1.2
    identifiable = [name for name, ok in zip(names, intervals["identifiable"]) if ok]
    assert_each_error_within_its_spread(theta, truth, intervals, names, only=identifiable)
    assert intervals["identifiable"] == [False, True, False]          # the fat's C10 and C01 are not, alone
    assert intervals["undetermined"] == ["C10_fat", "C01_fat"]         # whatever the differenced Jacobian says
    assert abs(theta[1] / truth[1] - 1) <= 0.10                       # C10 of muscle
    assert fat["names"] == ["C10_fat", "C01_fat"] and fat["lower"] <= 2.4 <= fat["upper"]   # the sum, in its interval
    if fat["identifiable"]:                                            # and within 10 % where it is identified
        assert abs(fat["value"] / 2.4 - 1) <= 0.10
