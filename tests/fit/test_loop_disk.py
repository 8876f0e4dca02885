"""The disk test of Bouten and Drapier (sec. 3.4): synthetic displacements of a disk under radial
load (an annulus clamped inside, pressed outside) made by the engine at known parameters, then
identified back with Nelder-Mead and with Levenberg-Marquardt (finite-difference Jacobian, its
columns evaluated in parallel) from a wrong start: Young's modulus E of a linear elastic disk
(*ELASTIC) and C10, C01 of a Mooney-Rivlin disk. Both methods must recover the truth; the numbers
of iterations and engine runs are printed (the paper: NM 202 iterations, LM 49). In plane strain
the Mooney-Rivlin energy depends on C10 and C01 separately only through finite strain and volume
change (I1bar = I2bar when J = 1), so this is a stiff test of both optimizers."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.engine.results import OK
from orchestrator.engine.runner import Evaluator
from orchestrator.fit.identify import levenberg_marquardt, nelder_mead
from orchestrator.fit.objectives import DisplacementResidualObjective
from orchestrator.model.forward import DiskModel


class NodalDisplacement:
    """Records the nodal displacement itself: the 'experiment' of the synthetic test."""

    fingerprint = "nodal-u"

    def outputs(self, nodal_u, outdir):
        return {"cost": 0.0, "u": np.asarray(nodal_u).tolist()}


def synthetic_objective(model: DiskModel, truth, folder) -> DisplacementResidualObjective:
    with Evaluator(model, NodalDisplacement(), folder, progress=False) as evaluator:
        record = evaluator(truth)
    assert record["status"] == OK
    u = np.array(record["outputs"]["u"])
    # measurement points: every other node off the clamped circle (F of eq. 2 at those points)
    free = np.setdiff1d(np.arange(len(model.mesh.nodes)), model.mesh.node_sets["BONES"])[::2]
    return DisplacementResidualObjective.at_points(model.mesh, model.mesh.nodes[free], u[free])


@pytest.mark.parametrize("law, truth, start", [("ELASTIC", (60.0,), (30.0,)),
                                               ("MOONEY-RIVLIN", (12.0, 6.0), (8.0, 9.0))])
def test_disk_identification_nm_and_lm_recover_the_truth(law, truth, start, tmp_path):
    model = DiskModel(law)
    objective = synthetic_objective(model, truth, tmp_path / "truth")
    with Evaluator(model, objective, tmp_path / "nm", workers=2, progress=False) as evaluator:
        nm = nelder_mead(evaluator, start, xatol=1e-6, fatol=1e-14, max_evaluations=1000)
    with Evaluator(model, objective, tmp_path / "lm", workers=2, progress=False) as evaluator:
        lm = levenberg_marquardt(evaluator, start)
    for fit in (nm, lm):
        print(f"disk {law:<13} {fit.method:<20} theta = {np.round(fit.theta, 5)} (truth {truth}), "
              f"{fit.iterations} iterations, {fit.engine_runs} engine runs, {fit.wall_time_s:.2f} s")
        assert fit.converged
        np.testing.assert_allclose(fit.theta, truth, rtol=1e-3)
    # Levenberg-Marquardt needs fewer iterations than Nelder-Mead (the paper: 49 against 202)
    assert lm.iterations < nm.iterations
