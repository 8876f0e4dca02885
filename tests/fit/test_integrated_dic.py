"""Integrated DIC (`orchestrator.fit.integrated`): the parameters fitted to the grey levels directly.

A small engine-made case, made here rather than by `make_phantom_case` to stay fast: the phantom calf
(`CalfPhantom`, band-limited, with its coil bias fixed in the scanner) at 0.54 mm pixels, its exact labels meshed
with 400 CPE6, the engine solved at a truth away from the fit's start, I1 rendered from that field with a scanner
motion and its own noise. The fit uses the same mesh (an inverse crime, on purpose: this checks the machinery, not
the model; benchmarks/integrated_dic.py holds I-DIC against the windows on cases the fit's mesh did not make).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from orchestrator.core.frame import RigidMotion, pixel_centres_mm
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import Evaluator, run_engine, write_mesh_include
from orchestrator.fit.identify import levenberg_marquardt, residual_jacobian
from orchestrator.fit.integrated import IntegratedDIC
from orchestrator.fit.objectives import leg_rows
from orchestrator.meshing import mesh_from_labels
from orchestrator.model.forward import (
    TABLE2_CENTRAL_KPA,
    LegModel,
    MeshInterpolator,
    field_on_pixels,
)
from orchestrator.model.regions import LegFrame
from orchestrator.phantom import CalfPhantom, make_loaded_image, render_unloaded

TRUTH = [3.0, 9.0, 150.0, 45.0]          # kPa: every parameter 20-50 % away from the start (Table 2)
MOTION = RigidMotion(-0.8, (-0.5, 0.3), (75.6, 75.6))


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    phantom = CalfPhantom(image_shape=(280, 280), pixel_size_mm=(0.54, 0.54))
    labels = phantom.geometry.labels_at(*pixel_centres_mm(phantom.image_shape, phantom.pixel_size_mm))
    mesh = mesh_from_labels(labels, phantom.pixel_size_mm, n_elements=400, order=2)
    model = LegModel(mesh, 0.16, engine_sensitivities=True)
    folder = tmp_path_factory.mktemp("idic-truth")
    write_mesh_include(model, folder)
    (folder / "deck.inp").write_text(model.deck(TRUTH))
    outcome = run_engine(folder / "deck.inp", folder / "out", threads=1)
    assert outcome.converged
    nodal = leg_rows(EngineResults(outcome.outdir).displacement(), len(mesh.nodes))
    field = field_on_pixels(MeshInterpolator(mesh).pixel_weights(phantom.image_shape, phantom.pixel_size_mm), nodal,
                            phantom.image_shape)
    unloaded = render_unloaded(phantom, noise_seed=3)
    loaded = make_loaded_image(phantom, field, MOTION, noise_seed=4)
    # the renderer's own noise, not the images' estimate: at 0.54 mm the phantom's texture is fine enough per pixel to
    # pass partly for noise (the estimate is ~1.15 x the true sigma here, ~1.02 x at 0.36 mm), and these tests are of
    # the residual and its weights, not of the estimator (benchmarks/integrated_dic.py runs with the estimate)
    sigma = phantom.contrast.noise_sigma
    objective = IntegratedDIC(mesh, unloaded, loaded, labels, phantom.pixel_size_mm, MOTION, noise_sigma=(sigma, sigma))
    return {"model": model, "objective": objective, "nodal": nodal, "labels": labels, "phantom": phantom,
            "images": (unloaded, loaded), "run": tmp_path_factory.mktemp("idic-run")}


@pytest.fixture(scope="module")
def fitted(case):
    with Evaluator(case["model"], case["objective"], case["run"], progress=False) as evaluator:
        return levenberg_marquardt(evaluator, list(TABLE2_CENTRAL_KPA))


def _solve(model, theta, folder):
    """(nodal u, {parameter: nodal du/dtheta}) of the engine at theta (the model's sensitivity map applied)."""
    folder.mkdir(parents=True)
    write_mesh_include(model, folder)
    (folder / "deck.inp").write_text(model.deck(theta))
    results = EngineResults(run_engine(folder / "deck.inp", folder / "out", threads=1).outdir)
    n, engine = len(model.mesh.nodes), results.sensitivities()
    columns = {name: sum(factor * engine[line][:n] for line, factor in terms)
               for name, terms in model.sensitivity_map(theta).items()}
    return leg_rows(results.displacement(), n), columns


def test_the_jacobian_from_the_engine_sensitivities_is_that_of_the_residual(case, tmp_path):
    """At fixed nuisances, dr/dtheta = grad I1 (at the warped point) . W du/dtheta is the derivative of the residual
    (a central difference of two engine runs per parameter), at a point that is neither the start nor the truth."""
    model, objective, theta = case["model"], case["objective"], [3.6, 10.0, 130.0, 55.0]
    nodal, sensitivities = _solve(model, theta, tmp_path / "at")
    _, g, _, q = objective.profile(objective.displacement(nodal))
    for j, name in enumerate(model.space.names):
        step, sides = 1e-3 * theta[j], []
        for sign in (1.0, -1.0):
            moved = list(theta)
            moved[j] += sign * step
            u = _solve(model, moved, tmp_path / f"{name}{sign:+g}")[0]
            sides.append(objective._whiten * objective._warp(objective.displacement(u), q)[0])
        difference = (sides[0] - sides[1]) / (2 * step)
        column = objective._whiten * np.einsum("ij,ij->i", g, objective.displacement(sensitivities[name]))
        error = np.linalg.norm(difference - column) / np.linalg.norm(difference)
        assert error < 2e-3, f"{name}: the engine's column is {100 * error:.2f} % off the difference"


def test_the_profiled_jacobian_near_the_fit(case):
    """The Jacobian the LM gets (the columns projected off the nuisances, Kaufman's variable projection) against a
    central difference of the profiled residual near the truth, where the term it neglects (proportional to the
    residual) is small: 0.2-0.3 % here, 1-2.5 % where the parameters are 20-50 % off."""
    model, theta = case["model"], [1.02 * v for v in TRUTH]
    with Evaluator(model, case["objective"], case["run"], progress=False) as evaluator:
        jacobian = residual_jacobian(model, evaluator(theta), theta)
        assert jacobian is not None and jacobian.shape == (case["objective"].n_residuals, 4)
        for j in range(4):
            step = 1e-3 * theta[j]
            plus, minus = list(theta), list(theta)
            plus[j] += step
            minus[j] -= step
            difference = (np.array(evaluator(plus)["outputs"]["residuals"])
                          - np.array(evaluator(minus)["outputs"]["residuals"])) / (2 * step)
            error = np.linalg.norm(difference - jacobian[:, j]) / np.linalg.norm(difference)
            assert error < 0.01, f"{model.space.names[j]}: the LM's column is {100 * error:.1f} % off"


def test_the_residual_at_the_truth_is_the_images_noise(case):
    """At the true field (nuisances fitted) every band's grey-level residual is the predicted noise: the floor holds
    on a band-limited image."""
    objective = case["objective"]
    ratios = objective.band_ratios(LegFrame.from_labels(case["labels"], case["phantom"].pixel_size_mm),
                                   nodal_u=case["nodal"])
    for band, value in ratios.items():
        assert 0.8 < value["ratio"] < 1.25, f"{band}: residual variance {value['ratio']:.2f} x the noise"


def test_the_bones_residual_motion_is_profiled_out(case):
    """Told a motion of the bones 0.2 mm and 0.3 deg off, I-DIC finds the difference as its nuisance and the
    residual at the true field stays at the noise; without the nuisances it would not."""
    objective = case["objective"]
    off = copy.copy(objective)
    off.motion = RigidMotion(MOTION.angle_deg + 0.3, (MOTION.translation_mm[0] + 0.2, MOTION.translation_mm[1]),
                             MOTION.centre_mm)
    displacement = objective.displacement(case["nodal"])
    right, wrong = objective.profile(displacement)[0], off.profile(displacement)
    unprofiled = off._warp(displacement, np.zeros(off.nuisance_dof))[0] * off._whiten
    assert abs(wrong[0] @ wrong[0] / (right @ right) - 1.0) < 0.01
    assert unprofiled @ unprofiled / (right @ right) > 3.0
    assert abs(np.degrees(wrong[3][2]) + 0.3) < 0.01


def test_recovers_the_truth_from_the_default_start(case, fitted):
    theta = np.array(fitted.theta)
    error = (theta - TRUTH) / np.array(TRUTH)
    print("I-DIC", np.round(theta, 3), "error %", np.round(100 * error, 2), fitted.engine_runs, "engine runs")
    assert fitted.converged
    assert np.all(np.abs(error[[1, 3]]) < 0.02)     # the muscle, which fills most of the slice
    assert np.all(np.abs(error) < 0.05)


def test_the_misfit_sits_at_its_floor(case, fitted):
    floor = case["objective"].noise_floor(4)
    assert 0.8 < fitted.cost / floor < 1.2
