"""The diagnosis of the second paper's model, the explicit garment band.

The band's deck (templates/leg_garment.inp.j2) carries the catalog's effects on the tissues and bones, written into
its last step, once the band is on the leg; the effects of Laplace's law itself (a tension profile, the unloaded
curvature) and bridging (what the band does) have no meaning there. Checked here:

- which effects the diagnosis tries on the band, and why it skips the others;
- the deck: the effects' keywords in step 4, their *SENSITIVITY lines, and the engine's du/dtheta through the
  frictionless contact against differences of whole put-on runs (drainage, the fibula's motion, the axial stretch);
- slow, images only: a phantom made with the frictionless band at constants that are not the fit's start, on a finer
  mesh of the phantom's own shapes (8,000 CPE6 against the fit's 1,000 of calfit's segmentation), with a rigid
  scanner motion and image noise, identified with the band and diagnosed: a hidden drainage is ranked first and
  its refit reaches the noise floor; a control shows nothing significant.
"""

from __future__ import annotations

import numpy as np
import pytest
from hidden_physics import assert_found_or_nothing, identified_and_diagnosed

from orchestrator.core.frame import RigidMotion
from orchestrator.diagnose.candidates import candidate_effects, garment_model
from orchestrator.engine.results import EngineResults
from orchestrator.engine.runner import run_engine, write_mesh_include
from orchestrator.model.forward import TABLE2_CENTRAL_KPA, LegModel
from orchestrator.phantom import CalfPhantom
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.phantom.mesh import truth_mesh

TENSION = 0.16   # N/mm
TRUTH_KPA = (3.4, 14.1, 85.0, 52.0)   # not the fit's start (Table 2: 4.5, 11.2, 106, 69.5)
SCANNER_MOTION = RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0))


@pytest.fixture(scope="module")
def leg_mesh():
    return truth_mesh(CalfPhantom(), n_elements=600, order=2, supersampling=1)


def test_the_band_is_diagnosed_with_the_effects_its_deck_carries(leg_mesh):
    candidates, skipped = candidate_effects(LegModel(leg_mesh, TENSION, garment="explicit"))
    assert {"drainage", "bone_motion", "stiffening", "out_of_plane", "heterogeneity", "friction"} <= set(candidates)
    assert "bridges the skin's concave parts already" in skipped["bridging"]
    for name in ("tension_profile", "unloaded_curvature"):
        assert "Laplace's law" in skipped[name]
    # a band with friction: its coefficient, fixed in the model, is freed
    band = LegModel(leg_mesh, TENSION, garment="explicit", friction_mu=0.3)
    assert "friction" in candidate_effects(band)[0]
    freed = garment_model(band, ("friction",))
    assert freed.space.names[-1] == "mu" and freed.friction_mu == 0.0 and not freed.engine_sensitivities
    # a Laplace-law model with an effect of Laplace's law cannot be switched to the band
    with pytest.raises(ValueError, match="cannot carry tension_profile"):
        garment_model(LegModel(leg_mesh, TENSION, effects=("tension_profile",)))


def _solve(model: LegModel, theta, folder) -> EngineResults:
    folder.mkdir()
    write_mesh_include(model, folder)
    (folder / "deck.inp").write_text(model.deck(theta))
    outcome = run_engine(folder / "deck.inp", folder / "out")
    assert outcome.converged, outcome
    return EngineResults(outcome.outdir)


@pytest.mark.parametrize("effects, values, step", [(("drainage",), [-0.04], [1e-4]),
                                                   (("bone_motion",), [0.15, -0.1], [1e-3, 1e-3]),
                                                   (("out_of_plane",), [0.03], [1e-4])])
def test_the_effects_act_under_the_band_and_the_engine_differentiates_them(tmp_path, leg_mesh, effects, values, step):
    model = LegModel(leg_mesh, TENSION, garment="explicit", effects=effects, engine_sensitivities=True)
    theta = list(TABLE2_CENTRAL_KPA) + values
    text = model.deck(theta)
    last_step = text.rsplit("*STEP", 1)[1]
    keyword = {"drainage": "*VOLUME CHANGE, ELSET=MUSCLE", "bone_motion": "*RIGID MOTION, NSET=BONE2",
               "out_of_plane": "*AXIAL STRETCH"}[effects[0]]
    assert keyword in last_step and text.count(keyword) == 1       # in the last step only: under the garment
    leg = len(leg_mesh.nodes)
    result = _solve(model, theta, tmp_path / "at")
    engine = result.sensitivities()
    without = _solve(LegModel(leg_mesh, TENSION, garment="explicit"), list(TABLE2_CENTRAL_KPA), tmp_path / "without")
    assert np.abs(result.displacement()[:leg] - without.displacement()[:leg]).max() > 0.05   # the effect moves the leg
    plain = LegModel(leg_mesh, TENSION, garment="explicit", effects=effects)
    lines = model.sensitivity_map(theta)
    for k, name in enumerate(model.space.names[len(TABLE2_CENTRAL_KPA):]):
        moved = list(theta)
        moved[len(TABLE2_CENTRAL_KPA) + k] += step[k]
        difference = (_solve(plain, moved, tmp_path / name).displacement()[:leg] - result.displacement()[:leg]) / step[k]
        (line, factor), = lines[name]
        derivative = factor * engine[line][:leg, -2:]
        # a forward difference of whole runs: its truncation is about the step's share of the effect
        assert np.abs(derivative - difference).max() <= 1e-3 * np.abs(difference).max(), name


@pytest.fixture(scope="module", params=[pytest.param("drainage", marks=pytest.mark.slow),
                                        pytest.param("control", marks=pytest.mark.slow)])
def band_diagnosis(request, tmp_path_factory):
    name = request.param
    folder = tmp_path_factory.mktemp(f"band-{name}")
    hidden = {"drainage": {"dv_muscle": -0.05}} if name == "drainage" else None
    case, _ = make_phantom_case(folder / "case", theta_kPa=TRUTH_KPA, rigid=SCANNER_MOTION, points_spacing_mm=None,
                                garment="explicit", effects=hidden)
    return name, identified_and_diagnosed(case, folder / "run", name, '\n[model]\ngarment = "explicit"\n')


def test_the_band_s_hidden_effect_is_found_and_refitted_to_the_floor(band_diagnosis):
    assert_found_or_nothing(*band_diagnosis)
