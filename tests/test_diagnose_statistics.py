"""The statistics of the diagnosis (orchestrator.diagnose) on linear models where the answers are exact."""

import numpy as np
import pytest
from scipy import stats

from orchestrator.diagnose import (design_effect, information_criteria, neighbour_correlation, noise_floor,
                                   residual_maps, score_effect)


def _linear_problem(seed=0, n=400, p=4):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(n, p))
    g = rng.normal(size=(n, 1)) + J @ rng.normal(size=(p, 1))   # partly absorbed by the fitted parameters
    return rng, J, g


def _refit_reduction(r, J, G):
    """Exact chi^2 drop of a linear least-squares refit with the extra columns G."""
    before = r - J @ np.linalg.lstsq(J, r, rcond=None)[0]
    A = np.hstack([J, G])
    after = r - A @ np.linalg.lstsq(A, r, rcond=None)[0]
    return float(before @ before - after @ after)


def test_predicted_reduction_is_the_exact_drop_of_a_linear_refit():
    rng, J, g = _linear_problem()
    data = 0.7 * g[:, 0] + rng.normal(size=len(g))
    r = J @ np.linalg.lstsq(J, data, rcond=None)[0] - data        # model - measured at the baseline optimum
    score = score_effect(r, J, g, chi2_to_misfit=1.0, deff=1.0)
    assert score["predicted_reduction"] == pytest.approx(_refit_reduction(r, J, g), rel=1e-10)
    refitted_effect = np.linalg.lstsq(np.hstack([J, g]), data, rcond=None)[0][-1]
    assert score["step"][0] == pytest.approx(refitted_effect, rel=1e-10)


def test_an_effect_the_fitted_parameters_mimic_scores_zero():
    rng, J, _ = _linear_problem()
    g = J @ np.array([[1.0], [-2.0], [0.5], [0.0]])
    r = rng.normal(size=len(J))
    score = score_effect(r - J @ np.linalg.lstsq(J, r, rcond=None)[0], J, g, 1.0, 1.0)
    assert score["orthogonal_fraction"][0] < 1e-12
    assert score["statistic"] < 1e-12


def test_the_statistic_is_chi2_under_the_null():
    rng, J, g = _linear_problem(seed=3)
    G = np.hstack([g, rng.normal(size=(len(g), 1))])
    statistics = []
    for _ in range(2000):
        noise = rng.normal(size=len(J))
        r = noise - J @ np.linalg.lstsq(J, noise, rcond=None)[0]
        statistics.append(score_effect(r, J, G, 1.0, 1.0)["statistic"])
    rejected = np.mean(stats.chi2.sf(statistics, 2) < 0.05)
    assert 0.035 < rejected < 0.065


def test_neighbour_correlation_tells_noise_from_a_smooth_field():
    rng = np.random.default_rng(1)
    xy = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0)), -1).reshape(-1, 2)
    noise = rng.normal(size=(len(xy), 2))
    smooth = np.stack([np.sin(xy[:, 0] / 8), np.cos(xy[:, 1] / 8)], 1)
    assert abs(neighbour_correlation(xy, noise.ravel())) < 0.1
    assert neighbour_correlation(xy, smooth.ravel()) > 0.95
    assert design_effect(0.0) == 1.0 and design_effect(-0.3) == 1.0
    assert design_effect(0.5) == pytest.approx(3.0)


def test_noise_floor_and_information_criteria():
    assert noise_floor(np.full(100, 0.05), 4) == pytest.approx(0.0025 * 196 / 200)
    ic = information_criteria(250.0, 5, 400)
    assert ic["aic"] == 260.0 and ic["bic"] == pytest.approx(250.0 + 5 * np.log(400))


def test_residual_maps_put_the_residual_in_its_sector():
    angles = np.radians(np.arange(0, 360, 5) + 2.5)
    xy = 50.0 + 20.0 * np.stack([np.cos(angles), np.sin(angles)], 1)
    residual = np.zeros_like(xy)
    hot = (np.degrees(angles) > 90) & (np.degrees(angles) < 120)
    residual[hot] = 0.3 * (xy[hot] - 50.0) / 20.0     # outwards, in the sector 90-120 degrees
    maps = residual_maps(xy, residual, np.ones(len(xy), int), np.array([50.0, 50.0]))
    assert maps.worst_sector_deg == 105.0
    assert maps.sector_radial_mm[3] == pytest.approx(0.3)
    assert maps.per_region_rms_mm["fat"] == pytest.approx(np.sqrt(hot.mean()) * 0.3)
