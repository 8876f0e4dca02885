"""The statistics of the diagnosis (orchestrator.diagnose) on linear models where the answers are exact."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

from orchestrator.diagnose.diagnosis import Diagnosis
from orchestrator.diagnose.maps import residual_maps
from orchestrator.diagnose.refit import Refit, settled
from orchestrator.diagnose.score import (
    EXPLAINED_FACTOR,
    FLOOR_AGREEMENT,
    EffectScore,
    design_effect,
    information_criteria,
    neighbour_correlation,
    score_effect,
)
from orchestrator.diagnose.verdict import below_floor, local_refit_unneeded, refit_verdict
from orchestrator.engine.results import OK
from orchestrator.fit.identify import linearised_standard_errors
from orchestrator.fit.objectives import DisplacementResidualObjective
from orchestrator.measure.measurements import Measurements
from orchestrator.model.forward import ParameterSpace, annulus_mesh
from orchestrator.model.regions import LegFrame


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


def test_the_neighbour_of_a_garment_levels_window_is_in_the_same_level():
    """Two socks measured with the same windows of I0: stacked, each window's nearest point is its twin at the other
    level, whose noise is another draw; the correlation is taken within each level."""
    rng = np.random.default_rng(2)
    xy = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2)
    noise = rng.normal(size=(2 * len(xy), 2))
    same = np.vstack([noise[:len(xy)], noise[:len(xy)]])      # the twins equal: a stacked search calls it smooth
    stacked, levels = np.vstack([xy, xy]), [slice(0, len(xy)), slice(len(xy), 2 * len(xy))]
    assert neighbour_correlation(stacked, same.ravel()) > 0.99
    assert abs(neighbour_correlation(stacked, same.ravel(), levels)) < 0.1
    smooth = np.tile(np.stack([np.sin(xy[:, 0] / 8), np.cos(xy[:, 1] / 8)], 1), (2, 1))
    assert neighbour_correlation(stacked, smooth.ravel(), levels) > 0.95


def _correlated_measurements(n_points=150, rigid=False, seed=0):
    """Points on an annulus with a covariance that couples neighbours (as overlapping DIC windows do)."""
    rng = np.random.default_rng(seed)
    angles = rng.uniform(0, 2 * np.pi, n_points)
    radii = rng.uniform(12.0, 38.0, n_points)
    xy = np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1)
    distance = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)
    sigma = rng.uniform(0.005, 0.02, n_points)
    correlation = np.exp(-(distance / 4.0) ** 2)
    covariance = np.kron(correlation * np.outer(sigma, sigma), np.eye(2))
    return Measurements("test", xy, np.zeros_like(xy), covariance, None, rigid)


@pytest.mark.parametrize("rigid", [False, True])
def test_the_whitened_misfit_of_correlated_noise_sits_at_its_floor(rigid):
    """F / floor of pure noise drawn from the measurement covariance averages 1: the whitening by C^-1/2 and the
    rigid nuisance projection (3 degrees of freedom) are what the floor assumes."""
    measurements = _correlated_measurements(rigid=rigid)
    mesh = annulus_mesh()
    rng = np.random.default_rng(1)
    factor = np.linalg.cholesky(measurements.covariance_mm2)
    ratios = []
    for _ in range(300):
        measurements.displacement_mm = (factor @ rng.normal(size=factor.shape[0])).reshape(-1, 2)
        objective = DisplacementResidualObjective(mesh, measurements)
        ratios.append(objective.cost_of(objective.residuals(np.zeros((len(mesh.nodes), 2)))) / objective.noise_floor(0))
    assert objective.nuisance_dof == (3 if rigid else 0)
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.02)
    assert objective.noise_floor(4) == pytest.approx(measurements.reference_variance_mm2 * (300 - 4 - objective.nuisance_dof) / 300)


def test_information_criteria():
    ic = information_criteria(250.0, 5, 400)
    assert ic["aic"] == 260.0 and ic["bic"] == pytest.approx(250.0 + 5 * np.log(400))


def _leg_labels():
    """A round leg (0.5 mm pixels): fat ring, muscle, the tibia at the top of the image, the fibula to its right."""
    rows, cols = np.indices((200, 200))
    x, y = (cols + 0.5) * 0.5, (rows + 0.5) * 0.5
    labels = np.zeros((200, 200), np.uint8)
    labels[np.hypot(x - 50, y - 50) < 40] = 1
    labels[np.hypot(x - 50, y - 50) < 30] = 2
    labels[np.hypot(x - 50, y - 28) < 6] = 3
    labels[np.hypot(x - 70, y - 52) < 4] = 3
    return labels


def test_residual_maps_put_the_residual_in_its_sector_and_name_it():
    frame = LegFrame.from_labels(_leg_labels(), (0.5, 0.5))
    angles = np.radians(np.arange(0, 360, 5) + 2.5)
    xy = 50.0 + 33.0 * np.stack([np.cos(angles), -np.sin(angles)], 1)   # display angles: y points down
    residual = np.zeros_like(xy)
    hot = (np.degrees(angles) > 90) & (np.degrees(angles) < 120)
    residual[hot] = 0.3 * (xy[hot] - 50.0) / 33.0     # outwards, in the sector 90-120 degrees
    maps = residual_maps(xy, residual, frame)
    assert maps.worst_sector_deg == 105.0
    assert maps.sector_radial_mm[3] == pytest.approx(0.3)
    assert maps.per_region_rms_mm["fat"] == pytest.approx(np.sqrt(hot.mean()) * 0.3)
    assert maps.worst_region == "fat, anterior sector 90-120 deg, 5-10 mm under the skin"
    assert maps.worst_region_share == pytest.approx(1.0)
    assert "label" not in " ".join(maps.sector_names)


def test_the_leg_frame_names_directions_from_the_bones():
    frame = LegFrame.from_labels(_leg_labels(), (0.5, 0.5))
    assert frame.direction(90.0) == "anterior"        # the tibia is at the top of the image
    assert frame.direction(0.0) == "lateral"          # the fibula is to the right of it
    assert frame.direction(270.0) == "posterior" and frame.direction(180.0) == "medial"
    assert frame.tissues(np.array([[50.0, 50.0], [50.0, 15.0], [0.5, 0.5]])) == ["muscle", "fat", "outside the leg"]
    assert frame.depth_mm(np.array([[50.0, 12.0]]))[0] == pytest.approx(2.0, abs=0.5)
    mirrored = LegFrame.from_labels(_leg_labels()[:, ::-1], (0.5, 0.5))
    assert mirrored.direction(180.0) == "lateral" and mirrored.direction(0.0) == "medial"


def test_a_refit_is_settled_at_the_noise_floor_inside_its_box():
    """`settled` spares a refit its second start only when another start could better it but within the noise."""
    model = SimpleNamespace(space=ParameterSpace(("C10_fat", "dv_muscle"), (0.5, -0.2), (20.0, 0.2),
                                                 linear=(False, True)))
    objective = SimpleNamespace(nuisance_dof=3)
    noise = np.random.default_rng(3).standard_normal(600)

    def record(theta, residuals):
        return {"status": OK, "theta": theta, "outputs": {"residuals": list(residuals)}}

    assert settled(model, record([4.5, -0.05], noise), objective)
    assert not settled(model, record([4.5, -0.05], 1.3 * noise), objective)   # chi^2 / dof 1.7: a lack of fit
    assert not settled(model, record([0.5, -0.05], noise), objective)         # a constant on its lower bound
    assert not settled(model, record([4.5, 0.2], noise), objective)           # an effect on its upper bound
    assert not settled(model, {"status": "failed", "theta": [4.5, 0.0], "message": "diverged"}, objective)


def test_the_local_change_is_refitted_only_when_it_could_rival_the_catalog():
    """`local_refit_unneeded` compares the local change and the explaining catalog effect on the same linearization
    (exact on a linear model): the refit is left out when the catalog effect is predicted better on BIC, the place's
    choice counted, and is run when the local change could win, when nothing explained the residual, or when the
    catalog effect's refit stayed above the floor."""
    rng, J, g = _linear_problem(seed=5)
    local = rng.normal(size=(len(J), 1))
    n = len(J)

    def screened(catalog_share, places, explained=True, catalog_ratio=None):
        data = catalog_share * 0.6 * g[:, 0] + (1.0 - catalog_share) * 0.6 * local[:, 0] + rng.normal(size=n)
        r = J @ np.linalg.lstsq(J, data, rcond=None)[0] - data
        chi2 = float(r @ r)
        catalog, patch = (score_effect(r, J, column, 1.0, 1.0) for column in (g, local))
        ranking = [SimpleNamespace(effect="drainage", dof=1, predicted_misfit=chi2 - catalog["predicted_reduction"])]
        diagnosis = SimpleNamespace(explained=explained, ranking=ranking, misfit=chi2, chi2=chi2, n_residuals=n,
                                    noise_floor=float(n))
        place = SimpleNamespace(place="muscle, posterior sector", places_tried=places,
                                predicted_misfit=chi2 - patch["predicted_reduction"])
        return local_refit_unneeded(diagnosis, place, catalog_ratio)

    reason = screened(1.0, places=40)
    assert reason and "not refitted" in reason and "drainage" in reason
    assert "not refitted" in (screened(1.0, places=40, catalog_ratio=FLOOR_AGREEMENT) or "")   # at the floor
    assert screened(0.0, places=40) is None                  # the local change is the better explanation
    assert screened(1.0, places=40, explained=False) is None  # nothing explained: the local change is the lead
    # the catalog effect's refit stayed above the floor: the linearization that preferred it is not trusted
    assert screened(1.0, places=40, catalog_ratio=1.43) is None


def test_a_refits_linearized_intervals_hold_the_truth_95_times_in_100_and_name_what_the_data_do_not_fix():
    """`linearized_intervals` at a least-squares fit of a linear model in x (ln theta for the two constants, theta /
    scale for an additive effect parameter), whitened data of unit noise, 400 draws: each 95 % interval holds the
    truth 95 +- 3.5 % of the time; the constant the data see weakly (a 25 % half width) is the one named not
    identifiable, the additive parameter is identifiable because its interval excludes zero; a direction the data
    do not see gives an unbounded interval. The verdict's words name the identified model's constants that the
    refit leaves loose, not the effect's own parameters."""
    from orchestrator.diagnose.refit import linearized_intervals
    from orchestrator.diagnose.verdict import unfixed_constants

    rng = np.random.default_rng(3)
    space = ParameterSpace(("C10_fat", "C10_muscle", "dv_muscle"), (0.1, 0.1, -1.0), (100.0, 100.0, 1.0),
                           linear=(False, False, True), scale=(1.0, 1.0, 0.01))
    model, truth = SimpleNamespace(space=space), np.array([4.5, 11.2, 0.02])
    n = 60
    jacobian = rng.normal(size=(n, 3)) * np.array([0.5, 40.0, 1.5])   # dr/dx: C10_fat barely seen
    covered, loose = np.zeros(3), []
    for _ in range(400):
        data = jacobian @ space.to_x(truth) + rng.normal(size=n)
        x, *_ = np.linalg.lstsq(jacobian, data, rcond=None)
        r = data - jacobian @ x
        intervals = linearized_intervals(model, space.from_x(x), linearised_standard_errors(jacobian, r @ r, n - 3))
        covered += (np.array(intervals["lower"]) <= truth) & (truth <= np.array(intervals["upper"]))
        loose.append(tuple(intervals["not_identifiable"]))
    print("coverage", covered / 400)
    assert np.all(np.abs(covered / 400 - 0.95) <= 0.035)
    assert set(loose) == {("C10_fat",)}

    unseen = linearized_intervals(model, truth, [0.01, None, 0.05])
    assert unseen["lower"][1] is None and unseen["upper"][1] is None and not unseen["identifiable"][1]
    assert linearized_intervals(model, truth, []) is None   # Nelder-Mead: no Jacobian, no interval
    shown = Refit(["drainage"], list(space.names), truth.tolist(), 1e-3, 1.0, 100.0, 0.0, 0.0, {}, intervals=unseen)
    assert "C10_muscle=11.2 [below unbounded, above unbounded] not identifiable" in shown.parameter_text()

    refit = Refit(["drainage"], list(space.names), truth.tolist(), 1e-3, 1.0, 100.0, 0.0, 0.0, {},
                  intervals=linearized_intervals(model, truth, [0.2, 0.01, 5.0]))
    words = unfixed_constants(SimpleNamespace(parameters=["C10_fat", "C10_muscle"]), refit)
    assert words.startswith("; in that refit the data do not fix C10_fat (95 % interval ±")
    assert "dv_muscle" not in words and "C10_muscle" not in words
    assert "[" in refit.parameter_text() and "C10_fat=4.5 [" in refit.parameter_text()


@pytest.mark.parametrize("refit_ratio", [0.96, 1.2, 1.43, 1.7])
def test_an_explaining_refit_above_the_floor_s_agreement_is_said_to_leave_part_of_the_residual(refit_ratio):
    best = EffectScore("heterogeneity", ["h_cos1_muscle"], 443.0, 1, 1e-90, 3.7, 1.0, [0.9], [0.4], significant=True)
    diagnosis = Diagnosis(["unloaded_curvature"], ["C10_fat"], [3.0], 8.47, 1.0, 4017.0, 482, 0.0, 7.2, 0.75, [best],
                          True, "", None, 0, "engine", 0.0)
    fit = Refit(["unloaded_curvature", "heterogeneity"], ["C10_fat", "h_cos1_muscle"], [3.0, 0.4], refit_ratio,
                refit_ratio, 0.0, 0.0, 0.0, {})
    explained, verdict = refit_verdict(diagnosis, [fit])
    assert explained == (refit_ratio <= EXPLAINED_FACTOR)
    assert f"{refit_ratio:.2f} x the floor" in verdict
    partly = "explains most of the residual, not all of it" in verdict
    assert partly == (FLOOR_AGREEMENT < refit_ratio <= EXPLAINED_FACTOR), verdict


def test_a_fit_below_its_floor_is_a_caution_at_most_as_often_as_alpha_under_the_noise():
    """A model that fits better than the noise allows says that its error model overstates the errors: at 0.61 x
    the floor on 310 values (a volume study's slice resampled between slices), and at most alpha of the time when
    the misfit is chi^2 noise of the fit's degrees of freedom; a small set of values at 0.78 x is no evidence."""
    def fit_at(ratio: float, parameters: int = 4) -> Refit:
        return Refit(["unloaded_curvature"], [f"p{k}" for k in range(parameters)], [1.0] * parameters, ratio, ratio,
                     0.0, 0.0, 0.0, {})

    caution = below_floor(fit_at(0.61), 310, 3, 0.01)
    assert caution and "0.61 x the floor" in caution and "0.8 x" in caution and "not to be trusted" in caution
    assert below_floor(fit_at(0.95), 310, 3, 0.01) is None
    assert stats.chi2.cdf(0.78 * 113, 113) > 0.01 and below_floor(fit_at(0.78), 120, 3, 0.01) is None
    rng = np.random.default_rng(11)
    for values in (60, 310, 2000):
        dof = values - 4 - 3
        ratios = rng.chisquare(dof, 4000) / dof
        fired = sum(below_floor(fit_at(r), values, 3, 0.01) is not None for r in ratios)
        assert fired <= 4000 * 0.01 + 3 * np.sqrt(4000 * 0.01), (values, fired)
