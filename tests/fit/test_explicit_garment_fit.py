"""Identification with the second paper's explicit garment: `LegModel(garment="explicit")` writes the
band of orchestrator.meshing.garment_band around the leg, put on with frictionless penalty contact
(templates/leg_garment.inp.j2), and asks the engine for du/dtheta through the contact, so that
Levenberg-Marquardt needs no finite-difference runs.

The truth is made on a finer leg mesh than the fit's (900 against 500 T6 elements: the same analytic leg), at
parameters drawn in the physiological box (not the fit's start), and read at 150 points inside the leg with
0.02 mm of noise. Checked: the fit converges with the engine's sensitivities, its misfit is at the noise floor
(within 1.5x: two meshes), and the well-identified muscle constant C10 is within 10 % of the truth (the fat's C10
and the bulk moduli are weakly identified by in-plane displacements, as in Avril et al. Table 1). Also: the deck
carries the band and the constants' *SENSITIVITY lines, with and without friction, and the objectives read the
leg's rows of a result that holds the band's too. With friction (mu = 0.3) the same: the engine carries the
sensitivities along the put-on's path, and Levenberg-Marquardt still differences no run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orchestrator.core.materials import AVRIL_BOUNDS_KPA
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import (
    LOG_NAME,
    Evaluator,
    run_engine,
    write_mesh_include,
)
from orchestrator.fit.identify import levenberg_marquardt
from orchestrator.fit.objectives import DisplacementResidualObjective
from orchestrator.meshing import leg_slice_mesh
from orchestrator.model.forward import (
    LEG_PARAMETERS,
    TABLE2_CENTRAL_KPA,
    LegModel,
    MeshInterpolator,
)

TENSION = 0.16  # N/mm
SIGMA_MM = 0.02
N_POINTS = 150


def _truth(seed: int) -> np.ndarray:
    """Parameters drawn log-uniformly in the middle half of the physiological box (kPa)."""
    rng = np.random.default_rng(seed)
    box = [AVRIL_BOUNDS_KPA[tissue][constant] for constant, tissue in (name.split("_") for name in LEG_PARAMETERS)]
    low, high = np.log(np.array(box)).T
    middle = 0.5 * (low + high)
    return np.exp(middle + 0.5 * (high - low) * rng.uniform(-0.5, 0.5, 4))


def _points(mesh, seed: int) -> np.ndarray:
    """N_POINTS element centroids of the truth mesh's soft tissue (never on a boundary of either mesh)."""
    centroids = mesh.nodes[mesh.elements[:, :3]].mean(axis=1)
    return np.random.default_rng(seed).choice(centroids, N_POINTS, replace=False)


@pytest.fixture(scope="module")
def meshes():
    return leg_slice_mesh(900, order=2), leg_slice_mesh(500, order=2)


def test_explicit_deck_carries_the_band_and_the_constants_sensitivities(meshes):
    _, fit_mesh = meshes
    frictionless = LegModel(fit_mesh, TENSION, garment="explicit", engine_sensitivities=True)
    text = frictionless.deck(TABLE2_CENTRAL_KPA)
    assert "*CONTACT PAIR" in text and "*SENSITIVITY" in text and "MATERIAL, FAT, C10" in text
    assert "GARMENT_NODES" in frictionless.mesh_text
    with_friction = LegModel(fit_mesh, TENSION, garment="explicit", friction_mu=0.3, engine_sensitivities=True)
    text = with_friction.deck(TABLE2_CENTRAL_KPA)   # carried along the loading path through friction
    assert "*FRICTION" in text and "*SENSITIVITY" in text and "MATERIAL, MUSCLE, KV" in text
    with pytest.raises(ValueError, match="Laplace's law"):
        LegModel(fit_mesh, TENSION, garment="explicit", effects=("tension_profile",))
    with pytest.raises(ValueError, match="needs garment = 'explicit'"):
        LegModel(fit_mesh, TENSION, friction_mu=0.3)


@pytest.mark.parametrize("seed, friction_mu", [pytest.param(4, 0.0), pytest.param(11, 0.0), pytest.param(7, 0.3),
                                               pytest.param(8, 0.0, marks=pytest.mark.slow)])
def test_explicit_garment_parameters_are_identified_back(tmp_path, meshes, seed, friction_mu):
    """With friction (mu = 0.3, the second paper's) the phantom and the fit share it, and the Jacobian still comes
    from the engine, its sensitivities carried along the put-on's path."""
    truth_mesh, fit_mesh = meshes
    truth = _truth(seed)
    truth_model = LegModel(truth_mesh, TENSION, garment="explicit", friction_mu=friction_mu)
    folder = tmp_path / "truth"
    folder.mkdir()
    write_mesh_include(truth_model, folder)
    (folder / "deck.inp").write_text(truth_model.deck(truth.tolist()))
    outcome = run_engine(folder / "deck.inp", folder / "out", threads=None)
    assert outcome.converged
    positions = _points(truth_mesh, seed)
    nodal = EngineResults(outcome.outdir).displacement()[: len(truth_mesh.nodes)]
    exact = MeshInterpolator(truth_mesh).weights(positions) @ nodal
    measured = exact + np.random.default_rng(seed + 1).normal(0.0, SIGMA_MM, exact.shape)

    model = LegModel(fit_mesh, TENSION, garment="explicit", friction_mu=friction_mu, engine_sensitivities=True)
    objective = DisplacementResidualObjective.at_points(fit_mesh, positions, measured, np.full(N_POINTS, SIGMA_MM))
    with Evaluator(model, objective, tmp_path / "fit", workers=1, progress=False) as evaluator:
        fit = levenberg_marquardt(evaluator, TABLE2_CENTRAL_KPA)
    error = (np.array(fit.theta) - truth) / truth
    floor = objective.noise_floor(model.space.size)
    print(f"truth {np.round(truth, 2)} kPa, fit {np.round(fit.theta, 2)}, errors {np.round(100 * error, 1)} %, "
          f"misfit {fit.cost / floor:.2f} x floor, {fit.iterations} iterations, {fit.engine_runs} engine runs")
    assert fit.converged, fit.message
    # the Jacobian came from the engine: no finite-difference probe among the runs (only steps, kept or refused)
    records = [json.loads(line) for line in (tmp_path / "fit" / LOG_NAME).read_text().splitlines()]
    assert len(records) == fit.engine_runs and not any(record["tag"] == "lm-jacobian" for record in records)
    assert fit.cost < 1.5 * floor
    assert abs(error[1]) < 0.10                    # C10 of muscle
