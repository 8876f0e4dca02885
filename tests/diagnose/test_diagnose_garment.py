"""The garment's effects in the diagnosis (orchestrator/diagnose/diagnosis.py, "The garment's effects").

- A Laplace-law model gets friction and bridging as candidates (the band's runs give their columns), with its effects
  on the tissues carried by the band; with an effect of Laplace's law itself fitted they are skipped with the reason. The band model fits friction's coefficient mu as
  its only effect, writes *FRICTION only for mu > 0, asks the engine for the constants' sensitivities (carried along
  the path through friction) and differences runs for mu and for the effects' parameters, and refuses mu both fixed
  and fitted.
- Slow: a phantom made with the frictionless band on a calf with a groove that the band bridges, then one made with
  the band and friction (mu = 0.3) on the convex calf, each identified with Laplace's law (the default model) and
  diagnosed: the hidden effect is ranked first and its refit explains the residual, to within 1.2 times the noise
  floor (friction's fit on the 2,000 elements that the band with friction is meshed with by default: see the test).
"""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.core.frame import RigidMotion
from orchestrator.diagnose.candidates import candidate_effects, garment_model
from orchestrator.diagnose.refit import refit_model
from orchestrator.engine.decks import sensitivity_blocks
from orchestrator.model.forward import LegModel
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.geometry import CalfGeometry, CalfShape
from orchestrator.phantom.mesh import truth_mesh
from orchestrator.run.stages import run_diagnose, run_identify

TRUTH_KPA = (3.4, 14.1, 85.0, 52.0)   # not the fit's start (Table 2: 4.5, 11.2, 106, 69.5)
SCANNER_MOTION = RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0))


@pytest.fixture(scope="module")
def leg_mesh():
    return truth_mesh(CalfPhantom(), n_elements=600, order=2, supersampling=1)


def test_garment_effects_are_candidates_of_the_laplace_model_without_effects(leg_mesh):
    candidates, skipped = candidate_effects(LegModel(leg_mesh, 0.16))
    assert {"friction", "bridging"} <= set(candidates)
    # the band carries the tissues' effects, not those of Laplace's law itself
    candidates, skipped = candidate_effects(LegModel(leg_mesh, 0.16, effects=("drainage",)))
    assert {"friction", "bridging"} <= set(candidates)
    assert garment_model(LegModel(leg_mesh, 0.16, effects=("drainage",)), ("friction",)).space.names[-2:] == ("dv_muscle", "mu")
    candidates, skipped = candidate_effects(LegModel(leg_mesh, 0.16, effects=("tension_profile",)))
    assert "friction" not in candidates and "cannot carry tension_profile" in skipped["friction"]


def test_the_bands_prestretch_profile_is_a_candidate_where_friction_holds_the_band(leg_mesh):
    held = LegModel(leg_mesh, 0.16, garment="explicit", friction_mu=0.3)
    candidates, skipped = candidate_effects(held)
    assert "band_profile" in candidates and "band stiffness" in skipped
    _, skipped = candidate_effects(LegModel(leg_mesh, 0.16, garment="explicit"))
    assert "slides over the skin" in skipped["band_profile"]
    _, skipped = candidate_effects(LegModel(leg_mesh, 0.16))
    assert "the explicit band's own" in skipped["band_profile"]
    profiled = LegModel(leg_mesh, 0.16, garment="explicit", friction_mu=0.3, effects=("band_profile",))
    assert profiled.space.names[-2:] == ("band_a1", "band_b1")
    assert profiled.deck(list(TRUTH_KPA) + [0.05, 0.0]).count("*VOLUME CHANGE, ELSET=GARMENT_S") == 24


def test_the_band_model_fits_the_friction_coefficient(leg_mesh):
    laplace = LegModel(leg_mesh, 0.16, engine_sensitivities=True)
    band = garment_model(laplace, ("friction",))
    assert band.garment == "explicit" and band.space.names[-1] == "mu"
    with_friction = band.deck(list(TRUTH_KPA) + [0.2])
    assert "*FRICTION\n0.2, 0.1\n" in with_friction and "mu = 0.2" in with_friction
    # through friction the engine carries the constants' sensitivities along the path; mu's column is differenced
    def sensitivity_lines(deck: str) -> list[str]:
        """The parameter lines of every *SENSITIVITY block (a NAME= block's without their weights)."""
        return [line.rsplit(", ", 1)[0] if name else line
                for name, lines in sensitivity_blocks(deck) for line in lines]

    lines = sensitivity_lines(with_friction)
    assert lines and all(line.startswith("MATERIAL, ") for line in lines)
    terms = band.sensitivity_map(list(TRUTH_KPA) + [0.2])
    assert terms["mu"] is None and all(terms[name] for name in band.space.names[:-1])
    # and those of the tissues' volume change and the axial stretch, which the band's last step brings in; not a
    # bone's motion (prescribed) or the band's prestretch profile (set in its second step)
    effects = ("drainage", "out_of_plane", "bone_motion", "band_profile")
    several = LegModel(leg_mesh, 0.16, garment="explicit", friction_mu=0.3, effects=effects, engine_sensitivities=True)
    lines = sensitivity_lines(several.deck(several.start()))
    assert "VOLUME CHANGE, MUSCLE" in lines and "AXIAL STRETCH" in lines
    assert not any(line.startswith(("RIGID MOTION", "VOLUME CHANGE, GARMENT")) for line in lines)
    terms = several.sensitivity_map(several.start())
    assert terms["dv_muscle"] and terms["eps_z"] and terms["band_a1"] is None
    assert all(terms[name] is None for name in several.space.names if name.startswith(("ux_", "uy_", "angle_")))
    assert "*FRICTION" not in band.deck(list(TRUTH_KPA) + [0.0])
    assert garment_model(laplace).engine_sensitivities and "*SENSITIVITY" in garment_model(laplace).deck(TRUTH_KPA)
    with pytest.raises(ValueError, match="both fixed"):
        LegModel(leg_mesh, 0.16, garment="explicit", friction_mu=0.3, effects=("friction",))
    with pytest.raises(ValueError, match="not available on this model"):
        LegModel(leg_mesh, 0.16, garment="explicit", effects=("friction", "unloaded_curvature"))


def test_a_refit_with_a_garment_effect_is_the_band_model(leg_mesh):
    """What the report solves again for each refit (`refit_model`): bridging and friction are the band, not an effect
    of the Laplace-law deck, which refuses them (the report raised on such a refit)."""
    laplace = LegModel(leg_mesh, 0.16, effects=("drainage",))
    bridged = refit_model(laplace, ["bridging"])
    assert bridged.garment == "explicit" and bridged.effects == ("drainage",) and bridged.friction_mu == 0.0
    sliding = refit_model(laplace, ["friction"])
    assert sliding.garment == "explicit" and sliding.space.names[-2:] == ("dv_muscle", "mu")
    assert refit_model(laplace, ["bone_motion"]).effects == ("drainage", "bone_motion")
    with pytest.raises(ValueError, match="not available on this model"):
        LegModel(leg_mesh, 0.16, effects=("drainage", "bridging"))


def _diagnosed(tmp_path, phantom=None, friction_mu: float = 0.0, fit_elements: int | None = None):
    case, _ = make_phantom_case(tmp_path / "case", tmp_path / "truth", theta_kPa=TRUTH_KPA, n_elements=2000,
                                rigid=SCANNER_MOTION, garment="explicit", friction_mu=friction_mu, phantom=phantom)
    identified = run_identify(case, tmp_path / "run", data="points", n_elements=fit_elements, workers=2,
                              progress=False)
    return identified, run_diagnose(tmp_path / "run", workers=2, progress=False)


def _summary(identified, diagnosis) -> str:
    floor = diagnosis["noise_floor"]
    ranking = ", ".join(f"{s['effect']} (p {s['p_value']:.1e})" for s in diagnosis["ranking"][:4])
    refits = "; ".join(f"{'+'.join(f['effects'])}: {f['misfit_over_floor']:.3f} x floor, theta "
                       f"{np.round(f['theta'], 3).tolist()}" for f in diagnosis["refits"])
    return (f"Laplace fit {np.round(identified['best']['theta'], 2).tolist()} at {diagnosis['misfit'] / floor:.2f} x "
            f"floor; ranking {ranking}; refits {refits}; verdict: {diagnosis['verdict']}")


@pytest.mark.slow
def test_bridging_over_a_groove_is_found_and_its_refit_reaches_the_floor(tmp_path):
    """A calf with a posterior groove (15 % of the radius deep, a concave stretch of 16 mm) under the frictionless
    band: Laplace's law pulls the groove outwards (p = T / r < 0) where the band bridges it."""
    grooved = CalfPhantom(geometry=CalfGeometry(CalfShape(dent_depth=0.15)))
    identified, diagnosis = _diagnosed(tmp_path, phantom=grooved)
    print(_summary(identified, diagnosis))
    assert diagnosis["misfit"] > 2.0 * diagnosis["noise_floor"]           # Laplace's law misses it
    assert diagnosis["ranking"][0]["effect"] == "bridging" and diagnosis["ranking"][0]["significant"]
    bridged = next(f for f in diagnosis["refits"] if f["effects"] == ["bridging"])
    assert bridged["misfit_over_floor"] <= 1.2 and diagnosis["explained"]
    assert np.all(np.abs(np.array(bridged["theta"])[[1, 3]] / np.array(TRUTH_KPA)[[1, 3]] - 1) < 0.05)


@pytest.mark.slow
def test_garment_friction_is_found_and_its_refit_reaches_the_floor(tmp_path):
    """The convex calf under the band with Coulomb friction mu = 0.3: the band holds the skin where Laplace's law
    has no tangential traction."""
    # The Laplace fit's mesh is the diagnosis's: 2,000 elements, what a case with friction is meshed with
    # (pipeline.FRICTION_MESH_ELEMENTS). On the default 1,000 the friction refit stops at 1.26 x the floor: the
    # band at the truth's constants and mu is itself 1.33 x there, 1.19 x on 2,000 (measured: 1.18 x after refit)
    identified, diagnosis = _diagnosed(tmp_path, friction_mu=0.3, fit_elements=2000)
    print(_summary(identified, diagnosis))
    assert diagnosis["misfit"] > 2.0 * diagnosis["noise_floor"]
    assert diagnosis["ranking"][0]["effect"] == "friction" and diagnosis["ranking"][0]["significant"]
    refitted = next(f for f in diagnosis["refits"] if f["effects"] == ["friction"])
    assert refitted["misfit_over_floor"] <= 1.2 and diagnosis["explained"]
    assert abs(refitted["theta"][-1] - 0.3) < 0.05                      # the friction coefficient
    assert np.all(np.abs(np.array(refitted["theta"][:4]) / np.array(TRUTH_KPA) - 1) < 0.10)


@pytest.mark.slow
def test_a_band_knitted_unevenly_is_found_on_the_band_with_friction(tmp_path):
    """Issue 29: the band's own variant. A phantom under the band with friction 0.3 whose prestretch varies around
    the leg (natural length x 1 + 0.05 cos phi - 0.03 sin phi), the truth random_truth(4), its own 8,000-element mesh,
    scanner motion, points; fitted and diagnosed with the band of the same friction on 800 elements (every column
    and refit a difference of runs). Measured: identified at 238.7 x the floor (three constants on their bounds), band_profile
    first (statistic 2,895, heterogeneity 2,835 tied), its refit 1.07 x with 0.0491 and -0.0317, the tissues within
    2.1 %; the whole test 14 minutes (856 s)."""
    from orchestrator.phantom.truths import random_truth

    truth = random_truth(4)
    case, _ = make_phantom_case(tmp_path / "case", theta_kPa=truth, rigid=SCANNER_MOTION, garment="explicit",
                                friction_mu=0.3, effects={"band_profile": {"band_a1": 0.05, "band_b1": -0.03}})
    with open(case / "case.toml", "a") as toml:
        toml.write('\n[model]\nelement = "CPE6"\ngarment = "explicit"\nfriction = 0.3\n')
    identified = run_identify(case, tmp_path / "run", data="points", n_elements=800, workers=2, progress=False)
    diagnosis = run_diagnose(tmp_path / "run", workers=2, progress=False)
    print(_summary(identified, diagnosis))
    assert diagnosis["ranking"][0]["effect"] == "band_profile" and diagnosis["ranking"][0]["significant"]
    refitted = next(f for f in diagnosis["refits"] if f["effects"] == ["band_profile"])
    assert refitted["misfit_over_floor"] <= 1.2 and diagnosis["explained"]
    assert np.allclose(refitted["theta"][-2:], [0.05, -0.03], atol=0.005)
    assert np.all(np.abs(np.array(refitted["theta"][:4]) / truth - 1) < 0.05)


def test_the_bands_runs_beside_the_probe_give_the_columns_they_give_one_after_the_other(leg_mesh, tmp_path):
    """`GarmentRuns` side by side (threads, each its engine, one log between them) and one after the other: the same
    bridging and friction columns to the last digit, two runs each, and every line of the shared log whole."""
    import json

    from orchestrator.case.folder import DisplacementPoints
    from orchestrator.diagnose.candidates import GarmentRuns, garment_columns
    from orchestrator.engine.runner import Evaluator
    from orchestrator.fit.objectives import DisplacementResidualObjective
    from orchestrator.measure.measurements import points_measurements

    places = leg_mesh.nodes[:: max(1, len(leg_mesh.nodes) // 40)]
    measured = points_measurements(DisplacementPoints(places, np.zeros_like(places), np.full(len(places), 0.01)))
    objective = DisplacementResidualObjective(leg_mesh, measured)
    laplace = LegModel(leg_mesh, 0.16)
    r = np.zeros(2 * len(places))
    columns = {}
    for side_by_side in (False, True):
        folder = tmp_path / ("side-by-side" if side_by_side else "in-turn")

        def factory(model, progress=None, workers=None):
            return Evaluator(model, objective, folder, workers=workers or 2, progress=False)

        with GarmentRuns(factory, laplace, TRUTH_KPA, ["bridging", "friction"], side_by_side) as runs:
            columns[side_by_side], launched = garment_columns(runs, r, progress=False)
        assert launched == 2
        lines = (folder / "evaluations.jsonl").read_text().splitlines()
        assert len(lines) == 2 and all(json.loads(line)["status"] == "ok" for line in lines)
    for name in ("bridging", "friction"):
        assert np.abs(columns[True][name]).max() > 0.0
        assert np.array_equal(columns[True][name], columns[False][name]), name
