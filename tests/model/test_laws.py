"""Laws per tissue (orchestrator/core/materials.py, docs/case-folder.md "The model"): case.toml's
[model.<tissue>] tables, the parameters they make, the deck materials they write, and the engine sensitivities
mapped onto them (Kv of a D1 law through D1 = 1/Kv).

- Errors of the [model.<tissue>] tables: tests/case/test_case_model.py.
- Parameter names `<constant>_<tissue>`, by constant then tissue; the first paper's model keeps its four.
- Deck materials: MOONEY-RIVLIN, POLYNOMIAL N=2 (three terms), NEO HOOKE with D1 = 0, REDUCED POLYNOMIAL when
  the stiffening effect adds C20 to neo_hooke; refused: stiffening on a law that has C20, incompressible on
  displacement elements.
- du/dtheta of C10, C01 and Kv (kPa) of a Mooney-Rivlin fat and of a neo-Hookean muscle from the engine's
  sensitivities and `LegModel.sensitivity_map` equal central differences of engine runs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orchestrator.core.errors import MaterialError
from orchestrator.core.materials import TissueLaw
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import run_engine, write_mesh_include
from orchestrator.model.forward import LEG_PARAMETERS, LegModel
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.mesh import truth_mesh


@pytest.fixture(scope="module")
def leg_mesh():
    return truth_mesh(CalfPhantom(), n_elements=600, order=2, supersampling=1)


def _material_block(deck: str, name: str) -> tuple[str, list[float]]:
    lines = deck.splitlines()
    at = lines.index(f"*MATERIAL, NAME={name}")
    return lines[at + 1], [float(v) for v in lines[at + 2].split(",")]


def test_laws_make_their_parameters_and_deck_materials(leg_mesh):
    default = LegModel(leg_mesh, 0.16)
    assert default.space.names == LEG_PARAMETERS and default.base_start == [4.5, 11.2, 106.0, 69.5]
    assert _material_block(default.deck([4.5, 11.2, 106.0, 69.5]), "FAT") == ("*HYPERELASTIC, AVRIL", [0.0045, 0.106])

    tissues = {"fat": TissueLaw("mooney_rivlin", 3, fixed={"C20": -0.04}),
               "muscle": TissueLaw("neo_hooke", incompressible=True)}
    model = LegModel(leg_mesh, 0.16, tissues=tissues, hybrid=True)
    assert model.space.names == ("C10_fat", "C10_muscle", "C01_fat", "Kv_fat")
    assert model.space.linear == (False,) * 4 and model.sum_only == []     # the fat compressible: C10, C01 apart
    incompressible_fat = {"fat": TissueLaw("mooney_rivlin", incompressible=True)}
    assert LegModel(leg_mesh, 0.16, tissues=incompressible_fat, hybrid=True).sum_only == [("C10_fat", "C01_fat")]
    deck = model.deck([1.4, 0.9, 1.0, 50.0])
    assert _material_block(deck, "FAT") == ("*HYPERELASTIC, POLYNOMIAL, N=2",
                                            pytest.approx([1.4e-3, 1.0e-3, -4e-5, 0.0, 0.0, 1 / 0.05, 0.0]))
    assert _material_block(deck, "MUSCLE") == ("*HYPERELASTIC, NEO HOOKE", [0.9e-3, 0.0])

    stiffened = LegModel(leg_mesh, 0.16, tissues={"fat": TissueLaw("neo_hooke")}, effects=("stiffening",))
    assert stiffened.space.names == ("C10_fat", "C10_muscle", "Kv_fat", "Kv_muscle", "C20_fat", "C20_muscle")
    header, constants = _material_block(stiffened.deck([2.0, 11.0, 100.0, 70.0, 300.0, 0.0]), "FAT")
    assert header == "*HYPERELASTIC, REDUCED POLYNOMIAL, N=2" and constants == pytest.approx([2e-3, 0.3, 1 / 0.1, 0.0])

    free_c20 = LegModel(leg_mesh, 0.16, tissues={"muscle": TissueLaw("reduced_polynomial", 3)})
    assert free_c20.space.names[:6] == ("C10_fat", "C10_muscle", "C20_muscle", "C30_muscle", "Kv_fat", "Kv_muscle")
    assert free_c20.space.linear[2:4] == (True, True) and free_c20.base_start[2:4] == [0.0, 0.0]

    with pytest.raises(MaterialError, match="C20 already"):
        LegModel(leg_mesh, 0.16, tissues={"fat": tissues["fat"]}, effects=("stiffening",))
    with pytest.raises(MaterialError, match="CPE6H"):
        LegModel(leg_mesh, 0.16, tissues={"muscle": tissues["muscle"]})
    with pytest.raises(MaterialError, match="no COMPARTMENT7 elements"):
        LegModel(leg_mesh, 0.16, tissues={"compartment7": TissueLaw("neo_hooke")})


def _engine_displacement(model: LegModel, theta, folder: Path) -> EngineResults:
    folder.mkdir(parents=True, exist_ok=True)
    write_mesh_include(model, folder)
    (folder / "deck.inp").write_text(model.deck(theta))
    outcome = run_engine(folder / "deck.inp", folder / "out", threads=1, timeout_s=120)
    assert outcome.converged
    return EngineResults(outcome.outdir)


def test_sensitivities_of_the_laws_constants_match_differences_of_runs(leg_mesh, tmp_path):
    tissues = {"fat": TissueLaw("mooney_rivlin"), "muscle": TissueLaw("neo_hooke")}
    model = LegModel(leg_mesh, 0.16, tissues=tissues, engine_sensitivities=True)
    theta = np.array([2.0, 9.0, 1.2, 90.0, 60.0])   # C10 fat, C10 muscle, C01 fat, Kv fat, Kv muscle (kPa)
    assert model.space.names == ("C10_fat", "C10_muscle", "C01_fat", "Kv_fat", "Kv_muscle")
    engine = _engine_displacement(model, theta, tmp_path / "at").sensitivities()
    plain = LegModel(leg_mesh, 0.16, tissues=tissues)
    for j, (name, terms) in enumerate(model.sensitivity_map(theta).items()):
        analytic = sum(factor * engine[line] for line, factor in terms)
        step = 1e-3 * theta[j]
        shifted = [_engine_displacement(plain, theta + sign * step * np.eye(len(theta))[j],
                                        tmp_path / f"{name}{sign:+d}").displacement() for sign in (1, -1)]
        difference = (shifted[0] - shifted[1]) / (2 * step)
        error = np.abs(analytic[:len(difference)] - difference).max() / np.abs(difference).max()
        print(f"{name}: max |du/dtheta| {np.abs(difference).max():.3e} mm/kPa, relative error {error:.1e}")
        assert error < 1e-4, name


def test_directions_the_data_do_not_fix_leave_their_parameters_undetermined():
    """C10 and C01 of an incompressible tissue in plane strain act through their sum only: in x = ln theta the
    Jacobian's columns are C10 g and C01 g. The noise Monte-Carlo must leave that direction out (not send every
    draw to the box's corners) and call both undetermined, while a third, independent parameter stays fixed and
    gets the plain least-squares refit."""
    from orchestrator.fit.identify import _free_directions

    rng = np.random.default_rng(3)
    g, h = rng.standard_normal(200), rng.standard_normal(200)
    c10, c01 = 1.4, 1.0
    J = np.column_stack([c10 * g, c01 * g, h])
    x_low, x_high = np.log([0.1, 0.05, 20.0]), np.log([30.0, 30.0, 200.0])
    basis, undetermined = _free_directions(J, 1.0, x_high - x_low, 0.10)
    assert undetermined.tolist() == [True, True, False] and basis.shape == (3, 2)
    noise = rng.standard_normal(200)
    step = basis @ np.linalg.lstsq(J @ basis, noise, rcond=None)[0]
    assert abs(step[0] * c10 + step[1] * c01) > 0 and abs(step[0] * c01 - step[1] * c10) < 1e-12   # along the sum only

    # differenced with friction, the columns carry the runs' noise (5 % here): J alone now calls the pair fixed, and
    # the Monte-Carlo would send its draws to the box's corners; the model's word that only the sum acts prevails
    noisy = J + 0.05 * np.column_stack([rng.standard_normal(200), rng.standard_normal(200), np.zeros(200)])
    assert not _free_directions(noisy, 1.0, x_high - x_low, 0.10)[1].any()
    along = np.array([c01, -c10, 0.0]) / np.hypot(c01, c10)
    basis, undetermined = _free_directions(noisy, 1.0, x_high - x_low, 0.10, structural=[along])
    assert undetermined.tolist() == [True, True, False] and basis.shape == (3, 2) and np.abs(basis.T @ along).max() < 1e-12

    well_posed = np.column_stack([g, h, rng.standard_normal(200)])
    basis, undetermined = _free_directions(well_posed, 1.0, x_high - x_low, 0.10)
    assert not undetermined.any()
    np.testing.assert_allclose(basis @ np.linalg.lstsq(well_posed @ basis, noise, rcond=None)[0],
                               np.linalg.lstsq(well_posed, noise, rcond=None)[0], atol=1e-12)


def test_effects_follow_laws_of_any_size(leg_mesh):
    """The effects' parameters come after the laws' constants, however many: a Mooney-Rivlin fat (five constants in
    all) with drainage and stiffening writes dv and both C20 where they belong."""
    model = LegModel(leg_mesh, 0.16, tissues={"fat": TissueLaw("mooney_rivlin")}, effects=("drainage", "stiffening"))
    assert model.space.names == ("C10_fat", "C10_muscle", "C01_fat", "Kv_fat", "Kv_muscle", "dv_muscle", "C20_fat",
                                 "C20_muscle")
    deck = model.deck([1.4, 11.0, 1.0, 90.0, 60.0, -0.04, 200.0, 300.0])
    assert "*VOLUME CHANGE, ELSET=MUSCLE\n-0.04\n" in deck
    assert _material_block(deck, "FAT") == ("*HYPERELASTIC, POLYNOMIAL, N=2",
                                            pytest.approx([1.4e-3, 1e-3, 0.2, 0.0, 0.0, 1 / 0.09, 0.0]))
    assert _material_block(deck, "MUSCLE") == ("*HYPERELASTIC, AVRIL", pytest.approx([11e-3, 0.06, 0.3]))


def test_the_skins_pressure_sensitivities_come_with_a_fitted_tension_profile(leg_mesh):
    """The skin's uncertainty asks the engine for du/da_k, du/db_k of the garment's profile on top of a model's
    own lines. A model fitting the tension profile (a1 to b2) without the engine's sensitivities lost A1 and B1 from
    its deck, and `calfit identify --effects tension_profile` stopped with KeyError 'PROFILE:GARMENT:A1'."""
    from orchestrator.fit.geometry_uncertainty import (
        profile_lines,
        skin_pressure_sensitivities,
    )

    model = LegModel(leg_mesh, 0.16, effects=("tension_profile",), engine_sensitivities=False)
    theta = [4.5, 11.2, 106.0, 69.5, 0.2, -0.1, 0.05, 0.02]
    assert all(line in model.deck(theta, extra_sensitivities=profile_lines(2)) for line in profile_lines(2))
    found = skin_pressure_sensitivities(model, theta, 2)
    assert sorted(found) == sorted(profile_lines(2))
    assert all(np.abs(du).max() > 1e-3 for du in found.values())


def test_under_the_band_the_skins_modes_move_the_skin_itself(leg_mesh):
    """With the explicit band the skin's uncertainty asks the engine for the SHAPE sensitivities (the skin's nodes
    moved, orchestrator.fit.geometry_uncertainty), not a Laplace profile the band's deck has no place for, and only those
    lines: the model's own are not needed there."""
    from orchestrator.fit.geometry_uncertainty import (
        shape_lines,
        skin_mode_lines,
        skin_pressure_sensitivities,
    )

    model = LegModel(leg_mesh, 0.16, garment="explicit", friction_mu=0.3)
    theta = [3.4, 14.1, 85.0, 52.0]
    assert skin_mode_lines(model, 2) == shape_lines(2) == ["SHAPE, SKIN, A1", "SHAPE, SKIN, B1", "SHAPE, SKIN, A2",
                                                           "SHAPE, SKIN, B2"]
    deck = model.deck(theta, extra_sensitivities=shape_lines(2), own_sensitivities=False)
    assert "MATERIAL, MUSCLE" not in deck
    assert deck.split("*SENSITIVITY\n")[1].split("**")[0].split("\n")[:4] == shape_lines(2)
    found = skin_pressure_sensitivities(model, theta, 2)
    assert sorted(found) == sorted(shape_lines(2))
    # du per mm of offset: the tissue under the band moves by a good part of the offset
    assert all(0.05 < np.abs(du).max() < 2.0 for du in found.values()), {k: np.abs(v).max() for k, v in found.items()}


class _SumOnlyEvaluator:
    """A stand-in for the engine's evaluator: residuals g (C10_fat + C01_fat - fat_sum) + h (C10_muscle - 0.9) and a
    jitter of 1e-4 that changes with theta, as a differenced run under friction has (its Newton tolerance)."""

    def __init__(self, sum_only, fat_sum=2.4):
        from types import SimpleNamespace

        from orchestrator.model.forward import ParameterSpace
        space = ParameterSpace(("C10_fat", "C10_muscle", "C01_fat"), (0.1, 0.1, 0.05), (30.0, 30.0, 30.0))
        self.model = SimpleNamespace(space=space, sum_only=sum_only)
        self.launched = self.replayed = 0
        rng = np.random.default_rng(5)
        self.g, self.h = rng.standard_normal(300), rng.standard_normal(300)
        self.fat_sum = fat_sum

    def evaluate(self, thetas, *, options=None, tag="", label=""):
        records = []
        for theta in thetas:
            fat, muscle = theta[0] + theta[2], theta[1]
            jitter = 1e-4 * np.random.default_rng(abs(hash(tuple(np.round(theta, 12))))).standard_normal(300)
            r = self.g * (fat - self.fat_sum) + self.h * (muscle - 0.9) + jitter
            self.launched += 1
            records.append({"status": "ok", "cost": float(r @ r), "outputs": {"residuals": r.tolist()}})
        return records

    def __call__(self, theta):
        return self.evaluate([theta])[0]


def test_levenberg_marquardt_does_not_wander_along_a_sum():
    """C10 and C01 of an incompressible fat act only through their sum: LM fits the sum and the muscle, and leaves
    the pair's split where it started (1:1 here) instead of following the differenced Jacobian's jitter along it."""
    from orchestrator.fit.identify import levenberg_marquardt

    fit = levenberg_marquardt(_SumOnlyEvaluator([("C10_fat", "C01_fat")]), [2.25, 5.6, 2.25])
    c10, muscle, c01 = fit.theta
    assert fit.converged and abs(c10 + c01 - 2.4) < 1e-3 and abs(muscle - 0.9) < 1e-3
    assert abs(c10 / c01 - 1.0) < 0.01, fit.theta                      # without the projection: 1.05


def test_levenberg_marquardt_moves_the_other_of_a_pair_whose_one_is_on_its_bound():
    """The pair steps as one while both are inside the box; once C10_fat is on its lower bound (0.1) C01_fat
    alone takes the rest of the sum (0.18)."""
    from orchestrator.fit.identify import levenberg_marquardt

    fit = levenberg_marquardt(_SumOnlyEvaluator([("C10_fat", "C01_fat")], fat_sum=0.18), [0.5, 5.6, 0.5])
    c10, muscle, c01 = fit.theta
    assert fit.converged and abs(c10 + c01 - 0.18) < 1e-3 and abs(muscle - 0.9) < 1e-3, fit.theta
    assert c10 == pytest.approx(0.1, rel=1e-6)


def test_a_sum_only_pair_is_reported_by_its_sum():
    from orchestrator.run.stages import intervals_summary

    result = {"method": "noise", "names": ["C10_fat", "C10_muscle", "C01_fat"], "lower": [0.1, 0.88, 0.05],
              "upper": [30.0, 0.91, 30.0], "central": [1.2, 0.9, 1.2], "relative_half_width": [12.0, 0.016, 12.0],
              "identifiable": [False, True, False], "on_bound": [], "confidence": 0.95, "draws": 30, "failed": 0,
              "inflation": 1.0, "sums": [{"names": ["C10_fat", "C01_fat"], "value": 2.45, "lower": 1.92, "upper": 2.81,
                                          "identifiable": False}]}
    lines = intervals_summary(result)
    assert lines[-1] == ("C10_fat and C01_fat act only through their sum, 2.45 in [1.92, 2.81] (NOT identifiable "
                         "either); each alone is not identifiable, its interval the search box.")
