"""Is the fit's mesh fine enough for its measurements?

The misfit's floor assumes that the model's displacements are exact. A mesh too coarse adds its discretization
error to every residual, and the misfit, the lack-of-fit test, the diagnosis's scores and the refits' misfit over
the floor all carry it as if it were the model's. The fit at the identified theta is solved again on a mesh of the
same labels with FINER_FACTOR times the elements (the muscle's compartments assigned as the setup did), and the two
whitened residuals are compared: chi2_disc = |r_N - r_finer|^2 is the part of the coarse mesh's error that the finer
mesh corrects, measured in the units of the noise. It does not depend on how well the model fits; the drop of the
misfit, chi2_N - chi2_finer, does (at a fit that lacks an effect, the discretization error's cross term with the
model's error has any sign and size), and is reported beside it. At the truth they were 142 and 353 on the leg below:
the coarse mesh's error and what the finer mesh keeps of it point the same way, so chi2_disc is a lower bound.

The mesh is adequate when chi2_disc is at most sqrt(2 n), one standard deviation of the floor's own chi^2 with n
degrees of freedom: then no test on the misfit can tell the discretization from the noise. Above it the run says
so, with the misfit on both meshes and the number of elements to ask for (--elements); a default mesh is meshed
again with the finer mesh's elements, once, and the fit carried to it (`pipeline.run_identify`).

Measured (the second paper's leg under the band with friction, 0.007 mm DIC windows, the model at the phantom's
truth, 620 values): 1.74 x the floor on calfit's 2,000-element mesh of its segmentation, 1.16 x on 4,000 (the skin's
geometric uncertainty in the weights; measurement weights alone: 2.08 x on 2,000, 1.25 x on 6,000, and 0.92 x on the
phantom's own 8,000-element mesh of its true shapes)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..engine.results import OK
from ..engine.runner import Evaluator
from ..fit.objectives import DisplacementResidualObjective

FINER_FACTOR = 2


def discretization_check(setup, theta: Sequence[float], measurements, run_dir, *, workers: int = 1,
                         timeout_s: float = 120.0) -> dict:
    """chi2_disc of the module text for the first garment level's measurements, at theta: the run's fitted model
    (`setup.model`, whose run at theta a case of one level has in its log already) against the same effects on a mesh
    of FINER_FACTOR times its elements meshed from the same labels. Returns what identification.json keeps."""
    from .setup import case_model

    finer = setup.mesh_again(FINER_FACTOR * len(setup.mesh.elements))
    residuals = []
    for label, model in (("mesh", setup.model), ("finer", case_model(finer, setup.case, effects=setup.model.effects))):
        objective = DisplacementResidualObjective(model.mesh, measurements)
        with Evaluator(model, objective, run_dir, workers=workers, timeout_s=FINER_FACTOR * timeout_s,
                       progress=False, label=f"discretization check ({label})") as evaluator:
            record = evaluator(list(theta))
        if record["status"] != OK:
            return {"checked": False, "reason": f"the engine failed on the {label} mesh: {record['message']}"}
        residuals.append(np.asarray(record["outputs"]["residuals"], float))
    chi2_mesh, chi2_finer = (float(r @ r) for r in residuals)
    chi2_disc = float((residuals[0] - residuals[1]) @ (residuals[0] - residuals[1]))
    n = len(residuals[0])
    dof = n - len(theta) - objective.nuisance_dof
    limit = float(np.sqrt(2.0 * n))
    return {"checked": True, "elements": len(setup.mesh.elements), "finer_elements": len(finer.elements),
            "chi2_disc": chi2_disc, "chi2_mesh": chi2_mesh, "chi2_finer": chi2_finer, "drop": chi2_mesh - chi2_finer,
            "values": n, "limit": limit, "adequate": bool(chi2_disc <= limit),
            "misfit_over_floor_mesh": chi2_mesh / dof, "misfit_over_floor_finer": chi2_finer / dof}


def discretization_line(check: dict) -> str:
    """What the run says of its mesh (identification setup lines and the report)."""
    if not check.get("checked"):
        return f"mesh not checked against a finer one: {check.get('reason', 'no displacements')}"
    numbers = (f"the misfit at the fit {check['misfit_over_floor_mesh']:.2f} x the floor on its {check['elements']} "
               f"elements, {check['misfit_over_floor_finer']:.2f} x on {check['finer_elements']}; chi^2 of their "
               f"difference {check['chi2_disc']:.0f}, limit sqrt(2n) = {check['limit']:.0f}")
    if check["adequate"]:
        return f"mesh fine enough for these measurements ({numbers})"
    return (f"MESH TOO COARSE for these measurements ({numbers}): verdicts on the misfit carry its discretization "
            f"error; identify again with --elements {check['finer_elements']} or more")
