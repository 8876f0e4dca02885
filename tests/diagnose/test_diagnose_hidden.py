"""Diagnosis on data with a hidden effect, from the images only (issues 6 and 12): the case is made by the
engine with an effect of the catalog switched on, on a finer mesh of the phantom's own geometry (8,000 CPE6)
than the fit (2,000 CPE6 of calfit's segmentation of I0), with image noise and a rigid scanner motion; the case
folder holds the two images and case.toml only (no labels beyond what calfit segments, no points.csv). The
displacements are measured by DIC, the baseline model (Avril et al.: C10 and Kv of fat and muscle) is
identified by Levenberg-Marquardt, then diagnosed.

For each hidden effect: the baseline misfit is far above the noise floor (lack of fit p < 1e-6), the hidden effect
ranks first and is significant, the refit with it comes within 1.2x the floor, and a refit with a wrong effect
lowers the misfit far less (at most half of the hidden effect's drop, and not to the floor; see WRONG_EFFECT_SHARE)
with a BIC that says so. A control case (no hidden effect) reports nothing significant; a case with a local swelling
of the fat (outside the catalog) is reported as not explained by any catalog effect, with the residual located in
its sector.

The effect sizes are those of a calf under a garment: 5 % fluid loss of the muscle, 5 % axial elongation,
0.2 mm of fibular motion, 8 % and 5 % first harmonics of the garment tension, C20 of 3 and 6 MPa (strain
stiffening: the smaller values C10 absorbs), compartments stiffer or softer by a factor 3 (labelled
by the case's segmentation here; `test_diagnose_heterogeneity` finds them at the septa of I0), and the garment's
pressure taken from the unloaded leg's curvature.

Two cases are faint, and their baseline is only required to lack fit at the diagnosis' own level (p < ALPHA), not
clearly: the unloaded curvature on the first renderer's nearly round leg (at its largest, the whole pressure from
the unloaded curvature, p = 0.005), and the stiffening on the second renderer's images, whose poorer texture raises
the floor (p = 0.006). Both are still ranked first, significant, and refitted to the floor.
Measured (this machine, engine sensitivities), misfit / floor: see the issue note.
"""

import re

import pytest
from hidden_physics import OEDEMA_SECTOR_DEG, oedema
from renderers import RENDERERS, phantom

from orchestrator.core.frame import RigidMotion
from orchestrator.diagnose.score import ALPHA
from orchestrator.model.regions import SECTORS
from orchestrator.phantom.cases import make_phantom_case
from orchestrator.run.stages import run_diagnose, run_identify

SCANNER_MOTION = RigidMotion(1.0, (0.6, -0.4), (75.0, 75.0))
# How much of the hidden effect's drop in misfit (and in BIC) a wrong effect may take. DIC measures relative to the
# bones found in the images, so its fit profiles out a rigid motion of the whole field (`measure.Measurements.
# rigid_nuisance`), and with that freedom the fibula's motion mimics part of a drainage even on exact data: on the
# first renderer's cases with the true field at points every 6 mm (0.02 mm noise), bone_motion takes 29.9 % of a
# hidden drainage's drop and drainage 26.7 % of a hidden bone motion's with the rigid nuisance, 3.4 % and 7.8 %
# without it. Through the images the share depends on how much of the floor the skin's uncertainty takes: with the
# skin's error measured on the skin itself (0.006 mm RMS over 55 mm, 2-3 % of the floor) bone_motion takes 43 % of a
# hidden drainage's drop on the first renderer's images and 20 % on the second's, and the wrong effects of bone
# motion and out-of-plane stretch 34-35 %; with the fixed 0.018 mm over 8 mm that stood before (22 % of the floor,
# which discounted part of the drainage's signature as skin error) it took 28 %. So a wrong effect may take half of
# the drop, and must leave the misfit clearly above the floor (the right one reaches it) unless the case is faint:
# 4.8-67 x on these cases.
WRONG_EFFECT_SHARE = 1.0 / 2.0
WRONG_EFFECT_LEAVES = 1.25              # times the floor a wrong effect's refit stays above at least
SECTOR_DEG = 360.0 / SECTORS            # the width of the diagnosis' sectors (`diagnose.residual_maps`)
CLEAR_LACK_OF_FIT_P = 1e-6

HIDDEN = {
    "drainage": dict(values={"dv_muscle": -0.05}, wrong="bone_motion"),
    "tension_profile": dict(values={"a1": 0.08, "b1": -0.05}, wrong="drainage"),
    "bone_motion": dict(values={"ux_BONE2": 0.2, "uy_BONE2": -0.15}, wrong="drainage"),
    "stiffening": dict(values={"C20_fat": 3000.0, "C20_muscle": 6000.0}, wrong="drainage", faint_on=("mri",)),
    "out_of_plane": dict(values={"eps_z": 0.05}, wrong="bone_motion"),
    # the garment's pressure taken from the unloaded leg's curvature, as another program's calf cases were made
    "unloaded_curvature": dict(values={"alpha_unloaded": 1.0}, wrong="drainage", faint_on=("calf",)),
    # a fibular motion mimics a third of the lateral compartment's signature, so the wrong effect is drainage
    "compartments": dict(values={"dC10_COMPARTMENT5": -0.6, "dC10_COMPARTMENT6": 2.0, "dC10_COMPARTMENT7": -0.6},
                         wrong="drainage", labels="compartments"),
}
# every hidden-effect case is slow (the drainage one took 106 s of the fast suite); the fast suite keeps the control
# here and the compartments found at the septa (`test_diagnose_heterogeneity`)


def diagnosed(tmp_path_factory, name, *, renderer="calf", effects=None, refit="auto", labels=None, edit_deck=None):
    folder = tmp_path_factory.mktemp(f"{renderer}-{name}")
    case, _ = make_phantom_case(folder / "case", phantom=phantom(renderer), effects=effects, labels=labels,
                                rigid=SCANNER_MOTION, points_spacing_mm=None, edit_deck=edit_deck)
    identification = run_identify(case, folder / "run", workers=2, progress=False)
    assert identification["data"]["source"] == "dic"
    return run_diagnose(folder / "run", refit_effects=refit, workers=2, progress=False)


@pytest.fixture(scope="module", params=[pytest.param((r, n), id=f"{r}-{n}", marks=pytest.mark.slow)
                                        for r in RENDERERS for n in HIDDEN])
def hidden(request, tmp_path_factory):
    renderer, name = request.param
    spec = HIDDEN[name]
    result = diagnosed(tmp_path_factory, name, renderer=renderer, effects={name: spec["values"]},
                       refit=["auto", spec["wrong"]], labels=spec.get("labels"))
    return name, spec, {**result, "renderer": renderer}


def _refit(result, effect):
    return next(fit for fit in result["refits"] if fit["effects"] == [effect])


def test_the_baseline_misfit_is_clearly_above_the_noise_floor(hidden):
    _, spec, result = hidden
    if result["renderer"] in spec.get("faint_on", ()):
        # a faint case: the effect at this size hardly shows through this renderer's images (module text); the
        # diagnosis must still find the baseline lacking at its own level
        assert result["lack_of_fit_p"] < ALPHA
    else:
        assert result["lack_of_fit_p"] < CLEAR_LACK_OF_FIT_P and result["before"]["misfit_over_floor"] > 1.25


def test_the_hidden_effect_ranks_first(hidden):
    name, _, result = hidden
    best = result["ranking"][0]
    assert best["effect"] == name and best["significant"], result["verdict"]


def test_the_refit_with_the_hidden_effect_reaches_the_noise_floor(hidden):
    """Against the floor with the skin's uncertainty estimated at the refit's parameters (the baseline's may be far)."""
    name, _, result = hidden
    refitted = _refit(result, name)
    assert refitted["own_floor"] is not None
    assert refitted["own_floor"]["misfit_over_floor"] <= 1.2
    assert result["explained"], result["verdict"]


def test_a_wrong_effect_lowers_the_misfit_far_less_and_the_bic_says_so(hidden):
    name, spec, result = hidden
    before, right, wrong = result["before"], _refit(result, name), _refit(result, spec["wrong"])
    assert before["misfit"] - wrong["misfit"] <= WRONG_EFFECT_SHARE * (before["misfit"] - right["misfit"])
    if result["renderer"] not in spec.get("faint_on", ()):   # a faint case's baseline is itself near the floor
        assert wrong["misfit_over_floor"] > WRONG_EFFECT_LEAVES
    assert wrong["bic"] > right["bic"] + 10.0
    assert wrong["bic"] > before["bic"] - WRONG_EFFECT_SHARE * (before["bic"] - right["bic"])


@pytest.mark.parametrize("renderer", ["calf", pytest.param("mri", marks=pytest.mark.slow)])
def test_without_a_hidden_effect_nothing_is_significant(tmp_path_factory, renderer):
    result = diagnosed(tmp_path_factory, "control", renderer=renderer)
    assert not any(score["significant"] for score in result["ranking"]), result["verdict"]
    assert 0.8 < result["misfit"] / result["noise_floor"] < 1.2
    assert "noise floor" in result["verdict"] and not result["refits"]
    assert not any(p["significant"] for p in result["patches"]) and result["local"] is None   # no patch proposed


@pytest.mark.slow
@pytest.mark.parametrize("renderer", RENDERERS)
def test_physics_outside_the_catalog_is_reported_as_unexplained_and_located(tmp_path_factory, renderer):
    result = diagnosed(tmp_path_factory, "oedema", renderer=renderer, edit_deck=oedema)
    assert result["before"]["misfit_over_floor"] >= 2.0
    assert not result["explained"]
    assert "no catalog effect explains the residual" in result["verdict"]
    maps = result["maps"]
    # the region the verdict names lies in the swollen sector; the sector of largest residual (every
    # tissue) in it or next to it: the swelling pushes the tissue beside it too (second renderer: 315 deg, the
    # sector 300-330, while the verdict names the fat at 240-270 deg)
    low, high = (float(v) for v in re.search(r"sector (\d+)-(\d+) deg", maps["worst_region"]).groups())
    assert OEDEMA_SECTOR_DEG[0] <= low < high <= OEDEMA_SECTOR_DEG[1], maps["worst_region"]
    assert OEDEMA_SECTOR_DEG[0] - SECTOR_DEG <= maps["worst_sector_deg"] <= OEDEMA_SECTOR_DEG[1] + SECTOR_DEG
    assert max(maps["per_region_rms_mm"], key=maps["per_region_rms_mm"].get) == "fat"
    # the region is named as a clinician reads it: tissue, anatomical sector in degrees, depth under the skin
    assert maps["worst_region"].startswith("fat, ") and " sector " in maps["worst_region"]
    assert "under the skin" in maps["worst_region"] and maps["worst_region"] in result["verdict"]
    assert "label" not in result["verdict"]
