"""The diagnose stage (diagnosis.json): the identified model of a run diagnosed on its measured displacements
(`diagnose.diagnosis`), refitted with the effects it names, its verdict judged, the local change weighed, and the
residual drawn (diagnosis.png, one per garment level with several socks)."""

from __future__ import annotations

import re
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.errors import EffectError, RunFolderError
from ..core.files import read_json, write_json
from ..core.run_lock import holds_run_folder
from ..diagnose.diagnosis import diagnose
from ..diagnose.figure import diagnosis_figure, path_figure, path_maps_figure
from ..diagnose.locate import patch_elements
from ..diagnose.maps import level_maps, residual_maps
from ..diagnose.refit import refit, refit_model, summarize_fit
from ..diagnose.score import ALPHA
from ..diagnose.stepwise import identified_only, path_verdict, stepwise
from ..diagnose.verdict import (
    below_floor,
    judged_ratio,
    local_refit_unneeded,
    refit_verdict,
    settle_ties,
    weigh_local,
)
from ..engine.runner import Evaluator
from ..fit.geometry_uncertainty import covariance_of
from ..core.units import KPA_PER_MPA, MMHG_PER_KPA
from ..fit.identify import FitResult
from ..fit.objectives import LandmarkPressure, leg_rows
from ..model.effects import effect, parse_effects
from ..model.heterogeneity import stiffness_field_kpa
from .discretization import discretization_line
from .identified import (
    floor_calibration,
    identified_data,
    level_images,
    level_skin_columns,
)
from .setup import load_run
from .timings import current_timings, stage, timed


def landmark_pressures(setup, path) -> dict | None:
    """The hydrostatic pressure -tr(sigma)/3 at the run's landmarks (`RunSetup.landmarks`) under the identified model
    and under the path's final one, each at its fitted parameters, one engine run each: what the missing physics
    changes where a garment designer reads the pressure (the deep veins). None when the path added nothing, or the
    landmarks cannot be placed."""
    if len(path.steps) < 2:
        return None
    try:
        landmarks, source = setup.landmarks()
    except RunFolderError:
        return None
    objective = LandmarkPressure(setup.mesh, landmarks)
    found = {"landmarks": objective.names, "landmarks_from": source}
    with tempfile.TemporaryDirectory(prefix="calfit-landmarks-") as scratch:
        for key, step in (("baseline_kPa", path.steps[0]), ("final_kPa", path.final)):
            model = setup.model_with(step.effects)   # the case's own garment: the first level's with several
            values = dict(zip(step.fit.parameters, step.fit.theta))
            theta = [float(values.get(name, start)) for name, start in zip(model.space.names, model.start())]
            try:
                results = setup.solve(theta, Path(scratch) / key, model)
            except RuntimeError as error:   # said, not fatal: the diagnosis stands without it
                return {**found, "failure": str(error)}
            pressure = leg_rows(results.point_field("pressure"), len(setup.mesh.nodes)) * KPA_PER_MPA
            found[key] = [float(v) for v in objective.weights @ pressure]
    return found


def landmark_pressure_lines(found: dict | None) -> list[str]:
    """Human lines: each landmark's pressure under the identified model and under the final one (kPa, mmHg)."""
    if not found or "final_kPa" not in found:
        return [] if not found else [f"landmark pressures not computed: {found['failure']}"]
    lines = [f"{'landmark':<18} {'identified (kPa)':>17} {'final (kPa)':>12} {'change':>8}  (mmHg: identified, final)"]
    for name, before, after in zip(found["landmarks"], found["baseline_kPa"], found["final_kPa"]):
        change = f"{100 * (after - before) / abs(before):+.0f} %" if abs(before) > 1e-9 else ""
        lines.append(f"{name:<18} {before:>17.2f} {after:>12.2f} {change:>8}  "
                     f"({before * MMHG_PER_KPA:.1f}, {after * MMHG_PER_KPA:.1f})")
    if found["landmarks_from"] == "segmentation":
        lines.append("landmarks placed from I0's segmentation (case.toml names none)")
    return lines


def _stiffness_field(model, fit, frame) -> dict | None:
    """The refit's C10 by tissue and quarter of the leg where its effects give groups their own materials."""
    refitted = refit_model(model, fit.effects[len(model.effects):])
    return stiffness_field_kpa(refitted, fit.theta, frame) if refitted.groups else None


@timed()
@holds_run_folder()
def run_diagnose(run_dir, *, refit_effects: Sequence[str] | str = "auto", alpha: float = ALPHA,
                 engine_sensitivities: bool = True, workers: int = 1, scheduler: str | None = None,
                 timeout_s: float = 120.0, progress: bool = True, verbose: bool = False) -> dict:
    """Diagnose the identified model of a run; refit with `refit_effects`: "auto" (the forward-backward path,
    `diagnose.stepwise`: the best candidates refitted, the one that pays added, ranked again on the new residual,
    until the floor or nothing significant), "none", effect names (each refitted on the identified model alone, as
    the one step of old), or "auto" and names. Writes and returns diagnosis.json: the identified model's ranking
    and its candidates' refits ("ranking", "refits"), the "path" (one entry per step: effects, misfit over floor,
    BIC, parameters with 95 % intervals) and the "final" model (effects, misfit over floor, explained, alternatives);
    the verdict says the path in one sentence ("verdict_first_step": the first refit's, as it was said alone)."""
    run_dir = Path(run_dir)
    shown = progress
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    if identification["objective"] != "displacement":
        raise ValueError("the diagnosis compares the model with measured displacements (DIC from the images, or "
                         "points.csv): identify with --objective displacement (the default) first")
    # several socks: every effect is scored on all the levels at once (one deck per level, whitened together)
    model = setup.fit_model(identification.get("effects", ()), sensitivities=engine_sensitivities)
    objective = setup.displacement_objective(identified_data(identification))

    def evaluator_for(m, progress=None, workers=workers):
        # the ranking probes every candidate effect at once; a refit adds one or two
        added = [name for name in m.effects if name not in model.effects]
        stage = ("diagnose" if not added else f"diagnose + {', '.join(added)}" if len(added) <= 2
                 else "diagnose, ranking the candidate effects")
        return Evaluator(m, objective, run_dir, workers=workers, scheduler=scheduler, timeout_s=timeout_s,
                         progress=shown if progress is None else progress and shown, verbose=verbose, label=stage)

    theta = identification["best"]["theta"]
    frame = setup.frame()
    with stage("ranking"):
        diagnosis = diagnose(evaluator_for, model, theta, objective, frame, alpha=alpha,
                             engine_sensitivities=engine_sensitivities, progress=shown,
                             side_by_side=bool(scheduler) or workers > 1)
    with evaluator_for(model) as evaluator:
        before = summarize_fit(model, FitResult(**identification["best"]), evaluator(theta), objective)
    requested = [refit_effects] if isinstance(refit_effects, str) else list(refit_effects)
    stepping = "auto" in requested

    def own_floor(fit, residual):
        with stage("skin's uncertainty at the refits"):
            return _refit_own_floor(setup, identification, fit, residual)

    with stage("stepwise refits"):
        path = (stepwise(evaluator_for, model, objective, frame, diagnosis, before, alpha=alpha, own_floor=own_floor,
                         engine_sensitivities=engine_sensitivities, progress=shown,
                         side_by_side=bool(scheduler) or workers > 1, parallel=workers)
                if stepping else identified_only(model, diagnosis, before))
    # the refits of the identified model's candidates, the path's first, are the diagnosis' "refits"
    after = [t.fit for t in path.first_tried if t.fit is not None]
    refit_failures = {t.effect: t.failure for t in path.first_tried if t.failure}
    residuals = {t.effect: t.residual_mm for t in path.first_tried if t.fit is not None}
    after_maps = [residual_maps(objective.positions_mm, residuals[fit.effects[-1]], frame) for fit in after]
    after_level_maps = [level_maps(objective, residuals[fit.effects[-1]], frame) for fit in after]
    names = [n for n in requested if n not in ("auto", "none") and n not in residuals and n not in refit_failures]
    for name in names:
        try:
            with stage("named refits"):
                fit, residual = refit(evaluator_for, model, theta, [name], objective)
        except RuntimeError as error:   # the engine cannot solve the refitted model somewhere: said, not fatal
            refit_failures[name] = str(error)
            continue
        after.append(fit)
        residuals[name] = residual
        after_maps.append(residual_maps(objective.positions_mm, residual, frame))
        after_level_maps.append(level_maps(objective, residual, frame))
    settle_ties(diagnosis, after)
    for fit in after:
        fit.stiffness_field = _stiffness_field(model, fit, frame)
    best = diagnosis.ranking[0].effect if diagnosis.ranking else None
    best_refit = next((f for f in after if f.effects[-1:] == [best]), None)   # None: not refitted, or it failed
    if best_refit is not None and best_refit.own_floor is None:
        best_refit.own_floor = own_floor(best_refit, residuals[best])
    stepped_explained, stepped_verdict = path_verdict(path, diagnosis)
    first_explained, first_verdict = refit_verdict(diagnosis, after)
    if best in refit_failures:
        # a prediction the refit could not check is not an explanation
        first_explained = False
        first_verdict += f"; but its refit failed ({refit_failures[best]}), so that is not confirmed"
    # the path's verdict when it was walked; the first refit's (as the one step of old) when effects were named
    diagnosis.explained, diagnosis.verdict = ((stepped_explained, stepped_verdict) if stepping
                                              else (first_explained, first_verdict))
    catalog = [path.final.fit] if len(path.steps) > 1 else after   # what a local change is weighed against
    check = identification.get("discretization") or {}
    if check.get("checked") and not check["adequate"]:
        # a misfit that the mesh inflates: every verdict on it says so (`discretization`)
        diagnosis.verdict += f"; caution: {discretization_line(check)}"
    unexplained = not diagnosis.explained and diagnosis.lack_of_fit_p < alpha
    # where what is left unexplained lies: the final model's residual when the path added effects
    walked = len(path.steps) > 1
    maps = residual_maps(objective.positions_mm, path.final.residual_mm, frame) if walked else diagnosis.maps
    if unexplained and maps.worst_region:
        whose = "the final model's residual" if walked else "the residual"
        diagnosis.verdict += (f"; {whose} is largest in the {maps.worst_region} (RMS {maps.worst_region_rms_mm:.3f} mm, "
                              f"{100 * maps.worst_region_share:.0f} % of the squared residual)")
    local = None
    if diagnosis.lack_of_fit_p < alpha and diagnosis.patches and diagnosis.patches[0].significant:
        patch = diagnosis.patches[0]
        ratio = (path.final.misfit_over_floor if len(path.steps) > 1
                 else None if best_refit is None else judged_ratio(best_refit))
        unneeded = local_refit_unneeded(diagnosis, patch, ratio)
        if unneeded:
            diagnosis.verdict += f"; {unneeded}"
            local = {"patch": asdict(patch), "refitted": False, "explains": False, "reason": unneeded,
                     "verdict": diagnosis.verdict}
        else:
            with stage("local refit"):
                fit, residual = refit(evaluator_for, model, theta, [patch.effect], objective)
            fit.stiffness_field = _stiffness_field(model, fit, frame)
            local = weigh_local(diagnosis, patch, before, fit, catalog)
            after.append(fit)
            after_maps.append(residual_maps(objective.positions_mm, residual, frame))
            after_level_maps.append(level_maps(objective, residual, frame))
    warning = (floor_calibration(run_dir).get("through_plane_warning") if identified_data(identification) == "dic"
               else None)
    if warning:
        # an error model that does not hold judges every effect wrongly: the verdict says so first
        diagnosis.explained = False
        diagnosis.verdict = f"caution: {warning}; {diagnosis.verdict}"
    too_good = below_floor(path.final.fit, diagnosis.n_residuals, objective.nuisance_dof, alpha)
    if too_good:
        # a fit better than the noise allows: the error model does not hold there either
        diagnosis.explained = False
        diagnosis.verdict += f"; caution: {too_good}"
    result = diagnosis.as_dict()
    result["before"] = before.as_dict()
    result["refits"] = [fit.as_dict() for fit in after]
    result["refit_failures"] = refit_failures
    result["maps_after"] = [asdict(m) for m in after_maps]
    if diagnosis.levels:
        for k, (row, image, tension) in enumerate(zip(result["levels"], level_images(setup), setup.case.tensions)):
            row.update(image=image, tension_N_per_mm=tension, worst_region=diagnosis.level_maps[k].worst_region)
        result["level_maps_after"] = [[asdict(m) for m in maps] for maps in after_level_maps]
    result["local"] = local
    result["verdict_first_step"] = first_verdict
    result["path"] = [step.as_dict() for step in path.steps]
    # the final model explains the measurements when it reaches their floor, unless the error model does not hold
    # there (a through-plane warning, a fit below the floor) or a local stiffness change fits better than the
    # catalog's effects
    result["final"] = path.final_dict(doubt=bool(warning) or bool(too_good) or bool(local and local.get("explains")))
    result["final"]["below_floor"] = bool(too_good)
    with stage("landmark pressures"):
        result["final"]["landmark_pressures"] = landmark_pressures(setup, path)
    path_maps = [diagnosis.maps] + [residual_maps(objective.positions_mm, step.residual_mm, frame)
                                    for step in path.steps[1:]]
    result["path_maps"] = [asdict(m) for m in path_maps]
    with stage("figures"):
        if len(path.steps) > 1:
            path_figure(run_dir / "diagnosis-path.png", result["path"])
            path_maps_figure(run_dir / "diagnosis-path-maps.png", setup.case.unloaded, setup.case.pixel_size_mm,
                             path_maps, result["path"])
        patch = (patch_elements(model, local["patch"]["effect"]), local["patch"]["place"]) if local else (None, "")
        diagnosis_figure(run_dir / "diagnosis.png", setup.case.unloaded, setup.case.pixel_size_mm, diagnosis.maps,
                         setup.mesh, *patch, title="every garment level, one arrow each" if diagnosis.levels else "")
        for k, maps in enumerate(diagnosis.level_maps, 1):
            diagnosis_figure(run_dir / f"diagnosis-level-{k}.png", setup.case.unloaded, setup.case.pixel_size_mm,
                             maps, setup.mesh, *patch, title=f"garment level {k} ({result['levels'][k - 1]['image']}, "
                                                             f"{result['levels'][k - 1]['tension_N_per_mm']:g} N/mm)")
    result["timings"] = current_timings()   # the figures included: the record is written last
    write_json(run_dir / "diagnosis.json", result)
    return result


def requested_effects(text: str | Sequence[str] | None, run_dir) -> tuple[str, ...]:
    """The effects `calfit identify --effects` names: catalog names, comma-separated; the list a diagnosis' verdict
    prints ("drainage, then unloaded_curvature", "a + b"); or "final", the final model of RUN_DIR/diagnosis.json
    (its effects, the identified model's included)."""
    if not text:
        return ()
    if isinstance(text, str) and text.strip() == "final":
        path = Path(run_dir) / "diagnosis.json"
        final = read_json(path, "calfit diagnose").get("final") if path.is_file() else None
        if final is None:
            raise EffectError(f"--effects final takes the final model of {path}, and "
                              + ("that diagnosis has none (written before the diagnosis walked its path)"
                                 if path.is_file() else "there is none")
                              + f": run calfit diagnose {run_dir} first")
        return parse_effects(final["effects"])
    names = re.split(r",|\bthen\b|\+", text) if isinstance(text, str) else list(text)
    return parse_effects([name.strip() for name in names if name.strip()])


def _refit_own_floor(setup, identification: dict, fit, residual_mm: np.ndarray) -> dict | None:
    """The refit's misfit against the noise floor with the skin's uncertainty estimated again at the refit's
    parameters (`geometry_uncertainty`, as the identification did at the baseline fit's), for DIC data refitted with
    catalog effects; None otherwise. Its residual (mm, each level's fitted rigid motion removed) is weighed again:
    no run of the model, only those of the skin's modes."""
    geometry = identification.get("geometry_uncertainty")
    if geometry is None or any(effect(name).apply is None for name in fit.effects):
        return None
    options = dict(effects=tuple(fit.effects), skin_sigma_mm=geometry["skin_sigma_mm"],
                   interface_sigma_mm=geometry["interface_sigma_mm"], cutoff_mm=geometry["cutoff_mm"])
    measured = []
    for level, level_measured in enumerate(setup.level_measurements("dic", with_geometry=False), start=1):
        columns, weights, _ = level_skin_columns(setup, fit.theta, level_measured, level, options)
        kept = (columns, weights) if setup.case.levels else ()   # the joint fit's blocks between levels
        measured.append(level_measured.with_model_covariance(
            covariance_of(columns, weights), f"skin uncertain by {geometry['skin_sigma_mm']:.3f} mm RMS, at the refit",
            *kept))
    own = setup.objective_of(measured)
    misfit = own.cost_of(own.weigh(np.asarray(residual_mm, float).ravel()))
    return {"misfit": misfit, "misfit_over_floor": misfit / own.noise_floor(len(fit.theta))}
