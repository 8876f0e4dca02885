"""The stages of a run, each reading and writing files in the run folder (what the CLI calls).

measure (measurements.*): DIC between the two images, relative to the bones (`measure`);
identify (identification.json): Levenberg-Marquardt (or Nelder-Mead) from one start or from the
starts of Avril et al. Table 1, on the displacement residual F (Bouten and Drapier eq. 2) at the
DIC windows or at points.csv, weighted by their covariance, then again with the model's geometry
uncertainty (`geometry_uncertainty`); or on the contour mismatch M (Avril et al. sec. 2.2.5);
montecarlo (montecarlo.json): intervals around the best fit (Table 2), over the measurement noise or
by Avril et al.'s acceptance; pressures (pressures.json): landmark pressures over draws in the
intervals and with the tension +-10 % (Tables 3 and 4); diagnose (diagnosis.json). Every engine
evaluation goes through one `runner.Evaluator` per stage on the run's log (evaluations.jsonl), so
any stage interrupted and started again resumes without repeating an evaluation.

A case with more garment levels ([[garment.levels]]) is measured at every level (the same windows of I0),
identified and drawn by the Monte-Carlo on all of them at once (`levels`: one evaluation solves every level),
its pressures (and with the explicit garment, each level's band) given at every level, and diagnosed on all of
them at once, each level's own misfit and residual maps reported (`diagnose`)."""

from __future__ import annotations

import tempfile
import threading
from pathlib import Path
from typing import Sequence

import numpy as np

from ..case.folder import read_model_choice
from ..core.digits import PLUS_MINUS, interval_uncertainty, rounded, with_uncertainty
from ..core.errors import RunFolderError
from ..core.files import read_json, write_json
from ..core.run_lock import holds_run_folder
from ..core.units import MMHG_PER_KPA
from ..engine.runner import LOG_NAME, EvaluationLog, Evaluator
from ..fit.geometry_uncertainty import (
    INTERFACE_UNCERTAINTY_PX,
    SKIN_UNCERTAINTY_PX,
    covariance_of,
    discard_without_columns,
    measured_skin_sigma,
    skin_perimeter_mm,
)
from ..fit.geometry_uncertainty import read_covariance as read_geometry_covariance
from ..fit.geometry_uncertainty import write as write_geometry
from ..fit.identify import (
    NOISE_DRAWS,
    levenberg_marquardt,
    monte_carlo,
    multistart,
    noise_monte_carlo,
    pressure_spreads,
    pressure_uncertainty,
    table1_starts,
)
from ..fit.levels import AtTension
from ..measure.measurements import (
    DEFAULT_WINDOW_PX,
    DEFAULT_WINDOW_SHAPE,
    measure_dic,
    read_window_table,
    write_measurements,
)
from ..measure.prefilter import PREFILTER_SIGMA_PX
from ..model.garment_state import band_state
from .diagnose_stage import run_diagnose  # noqa: F401 (the stage imported from here, as every stage)
from .discretization import FINER_FACTOR, discretization_check, discretization_line
from .identified import floor_calibration, identified_data
from .identified import level_images as _level_images
from .identified import level_skin_columns as _level_skin_columns
from .setup import SETUP_ARRAYS, SETUP_JSON, RunSetup, load_run, prepare_run
from .timings import current_timings, stage, timed

OBJECTIVES = ("contour", "displacement")
REFINEMENT_JSON = "refinement.json"   # a run meshed again: the finer mesh's size, its start, the coarser mesh's fit
# the skin's uncertainty is estimated again where the fit it weighs ends, at most SKIN_PASSES times, until that fit
# moves no parameter by more than SKIN_SETTLED_X in the fit's coordinates (ln theta: 5 %) or by more than
# SKIN_SETTLED_SE of its own standard error there: an effect's share is additive, and a move of 0.01 in a share
# known to +-0.18 (a foreign control at 0.54 mm pixels, fitted at 1.01 x the floor) is no move
SKIN_PASSES = 3
SKIN_SETTLED_X = 0.05
SKIN_SETTLED_SE = 0.2
OBJECTIVE_ALIASES = {"mismatch": "contour"}   # the name runs written before the images-first path used
# (elements, order) of the identification mesh: measured displacements resolve more than the 400 T3 of Avril et
# al. (sec. 2.2.1), which the contour mismatch keeps. 1,000 CPE6 reach the phantom's fine solution to a fifth of
# the DIC noise, 400 CPE6 to twice it; but the fat is a soft layer one or two elements of 1,000 thick, and that
# error is not noise: at the truth of the second phantom's softest fat (C10 2.5 kPa) the model alone moved the
# fit's C10 of fat by -1.5 % (1,000 CPE6), -0.5 % (2,000) and -0.5 % (4,000), against a 95 % half width of 2.3 %.
# 2,000 cost 4 s of a case's 19 s to its diagnosis (benchmarks/loop.py images_first, 23 s).
DEFAULT_MESH = {"displacement": (2000, 2), "contour": (400, 1)}
# The band with friction locks in where each skin node first touched, which the mesh resolves more slowly than the
# rest: at the truth, on the images' mesh of a 2,000-element phantom (0.02 mm points), the band's misfit is 1.33 x
# the noise floor with 1,000 elements and 1.19 x with 2,000 (frictionless: 1.13 and 1.15)
FRICTION_MESH_ELEMENTS = 2000


def choose_objective(objective: str, method: str) -> str:
    """auto: the displacement residual (measured from the images, or points.csv); contour: the mismatch M."""
    objective = OBJECTIVE_ALIASES.get(objective, objective)
    if objective == "auto":
        objective = "displacement"
    if objective not in OBJECTIVES:
        raise ValueError(f"the objective is one of auto, {', '.join(OBJECTIVES)}, not {objective!r}")
    if method == "lm" and objective != "displacement":
        raise ValueError("Levenberg-Marquardt needs a residual vector: use --objective displacement")
    return objective


def _objective(setup: RunSetup, name: str, data: str = "auto"):
    if OBJECTIVE_ALIASES.get(name, name) == "contour":
        return setup.mismatch_objective()
    return setup.displacement_objective(data)


def _setup(case_dir, run_dir: Path, n_elements: int | None, order: int | None, objective: str = "displacement") -> RunSetup:
    """The run folder's setup, prepared now if it has none; meshed with n_elements of order (default: the
    objective's, `DEFAULT_MESH`; FRICTION_MESH_ELEMENTS under the band with friction). A run folder keeps the mesh
    it was made with: asking for another is an error."""
    default_elements, default_order = DEFAULT_MESH[objective]
    choice = read_model_choice(case_dir)
    if choice.garment == "explicit" and choice.friction > 0:
        default_elements = max(default_elements, FRICTION_MESH_ELEMENTS)
    if choice.order is not None and order is not None and order != choice.order:
        raise ValueError(f"{Path(case_dir) / 'case.toml'} asks for {choice.element} elements (order {choice.order}); "
                         f"--order {order} disagrees: give one of them")
    order = order or choice.order
    if (run_dir / SETUP_JSON).is_file():
        setup = load_run(run_dir)
        if order is not None and order != setup.mesh.order:
            raise ValueError(f"{run_dir} was meshed with order {setup.mesh.order} elements; give --out another "
                             f"folder for order {order}")
        if n_elements is not None and abs(len(setup.mesh.elements) - n_elements) > 0.05 * n_elements:
            raise ValueError(f"{run_dir} was meshed with {len(setup.mesh.elements)} elements; give --out another "
                             f"folder for {n_elements}")
        return setup
    return prepare_run(case_dir, run_dir, n_elements=n_elements or default_elements, order=order or default_order)


@holds_run_folder(create=True)
def run_measure(case_dir, run_dir, *, window_px: int = DEFAULT_WINDOW_PX, step_px: int | None = None,
                roi_spacing_mm: float | None = None, n_elements: int | None = None, order: int | None = None,
                prefilter_px: float = PREFILTER_SIGMA_PX, respect_outline: bool = False, workers: int = 1,
                window_shape: str = DEFAULT_WINDOW_SHAPE) -> dict:
    """Measure the displacements from the two images by DIC (`measure.measure_dic`, both images smoothed by a
    Gaussian of prefilter_px first, the windows of shape function `window_shape` matched in `workers` local
    processes) into the run folder
    (measurements.csv, .npz, .json, .png); returns the summary."""
    run_dir = Path(run_dir)
    setup = _setup(case_dir, run_dir, n_elements, order)
    case = setup.case
    with stage("measure"):
        _, table, summary = measure_dic(case.unloaded, case.loaded, setup.labels_unloaded, case.pixel_size_mm, setup.motion,
                                        landmarks=case.landmarks, window_px=window_px, step_px=step_px,
                                        roi_spacing_mm=roi_spacing_mm, prefilter_px=prefilter_px,
                                        respect_outline=respect_outline, workers=workers,
                                        fat_shift_mm=setup.fat_shift_mm, window_shape=window_shape)
    summary["window_mm"] = window_px * min(case.pixel_size_mm)
    summary["setup_lines"] = setup.setup_lines()
    for level, motion in zip(case.levels, setup.level_motions):
        # the same windows of I0, correlated with this level's image and its own motion of the bones
        with stage("measure"):
            _, level_table, level_summary = measure_dic(
                case.unloaded, level.image, setup.labels_unloaded, case.pixel_size_mm, motion,
                landmarks=case.landmarks, window_px=window_px, step_px=step_px, roi_spacing_mm=roi_spacing_mm,
                prefilter_px=prefilter_px, respect_outline=respect_outline, workers=workers,
                fat_shift_mm=setup.fat_shift_mm, window_shape=window_shape)
        level_summary.update(window_mm=summary["window_mm"], level=level.number, image=level.path.name,
                             tension_N_per_mm=level.tension_N_per_mm)
        write_measurements(run_dir, level_table, level_summary, case.unloaded, case.pixel_size_mm, level.number)
        summary.setdefault("levels", []).append({key: level_summary[key] for key in (
            "level", "image", "tension_N_per_mm", "windows", "kept", "median_sigma_mm")})
    write_measurements(run_dir, table, summary, case.unloaded, case.pixel_size_mm)
    return summary


@timed()
@holds_run_folder(create=True)
def run_identify(case_dir, run_dir, *, method: str = "lm", objective: str = "auto", data: str = "auto",
                 window_px: int = DEFAULT_WINDOW_PX, start: Sequence[float] | None = None, starts: str = "one",
                 n_elements: int | None = None, order: int | None = None, effects: Sequence[str] = (),
                 engine_sensitivities: bool = True,
                 skin_sigma_mm: float | None = None, skin_uncertainty: bool = True, workers: int = 1,
                 scheduler: str | None = None, timeout_s: float = 120.0, progress: bool = True,
                 verbose: bool = False) -> dict:
    """Prepare (or reload) the run folder and identify; returns and writes identification.json.
    data: "points" (points.csv), "dic" (measured from the images, now if the run folder has no measurements yet,
    with `window_px`) or "auto" (points.csv when the case has one); effects: catalog effects whose parameters are
    fitted too (they start at zero, effect off); order: 1 for CPE3 (Avril et al.), 2 for CPE6 (volumetric effects
    such as drainage need it: CPE3 is too stiff in dilatation)."""
    run_dir = Path(run_dir)
    objective = choose_objective(objective, method)
    refinement, n_elements, start = _resumed_refinement(run_dir, n_elements, start, effects)
    setup = _setup(case_dir, run_dir, n_elements, order, objective)
    if objective == "contour" and setup.case.levels:
        raise ValueError(f"the contour mismatch compares I0 with one loaded image, and {setup.case.files['toml']} has "
                         f"{len(setup.case.tensions)} garment levels to fit jointly: use --objective displacement")
    source = setup.data_source(data)
    local_workers = 1 if scheduler else workers   # the DIC's processes and the skin's threads, on this machine
    measured = None   # the measurements of every garment level, the first level's first
    if objective == "displacement":
        measured = _first_measurements(setup, case_dir, run_dir, source, window_px, local_workers)
    setup.model = setup.model_with(effects, sensitivities=(method == "lm" and engine_sensitivities))
    base = list(start) if start is not None else setup.model.base_start
    # a start of the laws' constants (effects off), or a whole theta (a fit carried to a finer mesh)
    start_points = [s if len(s) == setup.model.space.size else setup.model.start(s)
                    for s in (table1_starts(base) if starts == "table1" else [base])]

    def fit_from(points, scorer, label, timed_as="fit"):
        with stage(timed_as), Evaluator(setup.at_every_level(setup.model), scorer, run_dir, workers=workers,
                                        scheduler=scheduler, timeout_s=timeout_s, progress=progress, verbose=verbose,
                                        label=label) as evaluator:
            found = ([levenberg_marquardt(evaluator, s) for s in points] if method == "lm"
                     else multistart(evaluator, points))
        return found, min(found, key=lambda fit: fit.cost)

    skin = measured is not None and source == "dic" and skin_uncertainty
    if skin:
        _mesh_ahead(setup, measured)
    fits, best = fit_from(start_points, setup.objective_of(measured) if measured is not None
                          else setup.mismatch_objective(), "identify")
    geometry = None
    if skin:
        fits, best, measured, geometry = _fit_with_skin_uncertainty(setup, run_dir, source, measured, fits, best,
                                                                    fit_from, skin_sigma_mm, local_workers)
    result = _identification_record(setup, case_dir, run_dir, method, objective, source, measured, fits, best,
                                    geometry)
    if measured is not None:
        # whether the misfit's floor holds on this mesh: its discretization error against the measurements' noise
        with stage("discretization check"):
            check = discretization_check(setup, best.theta, measured[0], run_dir, workers=workers,
                                         timeout_s=timeout_s)
        result["discretization"] = check
        result["setup_lines"].append(discretization_line(check))
        if check.get("checked") and not check["adequate"] and n_elements is None:
            # the default mesh is too coarse for these measurements: meshed again with the check's finer mesh and
            # fitted from where this fit ended (once: a mesh the user asks for, as this one is, is kept and judged)
            _discard_mesh(run_dir)
            write_json(run_dir / REFINEMENT_JSON, {
                "finer_elements": check["finer_elements"], "effects": list(effects), "start": list(best.theta),
                "coarser_mesh": {"elements": check["elements"], "best": result["best"],
                                 "misfit_over_floor": result["misfit_over_floor"], "discretization": check}})
            return run_identify(case_dir, run_dir, method=method, objective=objective, data=data,
                                window_px=window_px, starts=starts, order=setup.mesh.order, effects=effects,
                                engine_sensitivities=engine_sensitivities, skin_sigma_mm=skin_sigma_mm,
                                skin_uncertainty=skin_uncertainty, workers=workers, scheduler=scheduler,
                                timeout_s=timeout_s, progress=progress, verbose=verbose)
    if refinement:
        _say_refinement(result, refinement, len(setup.mesh.elements))
    result["timings"] = current_timings()
    write_json(run_dir / "identification.json", result)
    return result


def _resumed_refinement(run_dir: Path, n_elements: int | None, start, effects: Sequence[str]):
    """(the refinement record or None, n_elements, start) of an identification resumed after its default mesh was
    found too coarse. A run resumed after that goes on from the same place on the same finer mesh, so that its
    evaluations replay; another identification in the folder, with other effects, keeps the finer mesh and starts
    as it would."""
    if n_elements is not None or start is not None or not (run_dir / REFINEMENT_JSON).is_file():
        return None, n_elements, start
    refinement = read_json(run_dir / REFINEMENT_JSON, "calfit identify")
    if refinement["effects"] == list(effects):
        return refinement, refinement["finer_elements"], refinement["start"]
    return None, refinement["finer_elements"], start


def _first_measurements(setup: RunSetup, case_dir, run_dir: Path, source: str, window_px: int, workers: int):
    """The measurements of every garment level (the first level's first), measured now from the images if the run
    folder has none yet, weighed by the measurement's error alone: whatever skin uncertainty an earlier or
    interrupted identification left in the run folder, a resumed run then replays the same fits as an uninterrupted
    one."""
    levels = range(1, len(setup.case.tensions) + 1)
    if source == "dic" and any(read_window_table(run_dir, level) is None for level in levels):
        run_measure(case_dir, run_dir, window_px=window_px, workers=workers)
    if setup.case.levels:
        # skin uncertainties stored per level without their columns (before the levels' common skin error was
        # kept) cannot be joined: they are estimated again (`_fit_with_skin_uncertainty`)
        discard_without_columns(run_dir, levels)
    return setup.level_measurements(source, with_geometry=False)


def _mesh_ahead(setup: RunSetup, measured) -> threading.Thread:
    """The meshes the stages after the fit solve on, made (with what the measurements see of them) while the fit's
    engine runs: the skin's shifted interfaces (`geometry_uncertainty`) and the discretization check's finer mesh.
    None depends on the parameters; each is made once a run (`RunSetup.shifted_mesh`, `mesh_again`), so a stage
    that asks for one before it is ready waits for it, and one that failed here is made again there."""
    from ..fit.geometry_uncertainty import SHIFT_STEP_MM, SHIFTS

    def make() -> None:
        try:
            setup.tissue_curves()
            setup.compartment_labels()
            for interface, sign in SHIFTS:
                for level_measured in measured:
                    level_measured.observation(setup.shifted_mesh(interface, sign * SHIFT_STEP_MM))
            measured[0].observation(setup.mesh_again(FINER_FACTOR * len(setup.mesh.elements)))
        except Exception:   # made again, and its error said, where it is needed
            pass

    thread = threading.Thread(target=make, name="calfit-mesh-ahead", daemon=True)
    thread.start()
    return thread


def _fit_with_skin_uncertainty(setup: RunSetup, run_dir: Path, source: str, measured, fits, best, fit_from,
                               skin_sigma_mm: float | None, workers: int):
    """The uncertainty of the model's skin, estimated where the measurements put the parameters, then the fit again
    with it in the weights (geometry_uncertainty); every garment level's windows under its own tension, with the
    columns that make it kept, from which the joint fit forms the covariance between the levels. Estimated again
    where that fit ends, until it ends where it was estimated: a first fit without it can be dragged far (a foreign
    case's, by a missing tension profile, to the bounds of C10 and Kv of fat, where the skin's uncertainty came out
    8 times what it is at the fit it then weighed). Returns (fits, best, measured with it, geometry record)."""
    pixel = min(setup.case.pixel_size_mm)
    variance = setup.skin_mode_variance_mm2
    if skin_sigma_mm is None:   # the skin's error as its own spectrum measured it (geometry_uncertainty)
        skin_sigma_mm = (SKIN_UNCERTAINTY_PX * pixel if variance is None else measured_skin_sigma(
            skin_perimeter_mm(setup.mesh), variance, setup.skin_cutoff_mm))
    options = dict(effects=setup.model.effects, skin_sigma_mm=skin_sigma_mm,
                   interface_sigma_mm=INTERFACE_UNCERTAINTY_PX * pixel, cutoff_mm=setup.skin_cutoff_mm)
    first, passes = best, []
    for _ in range(SKIN_PASSES):
        estimated_at = best.theta
        for level, level_measured in enumerate(measured, start=1):
            stored = read_geometry_covariance(run_dir, 2 * len(level_measured), level)
            if not _estimated_for(stored, setup.model.effects, estimated_at):
                with stage("skin's uncertainty"):
                    columns, weights, info = _level_skin_columns(setup, estimated_at, level_measured, level,
                                                                 options, workers)
                kept = (columns, weights) if setup.case.levels else ()
                write_geometry(run_dir, covariance_of(columns, weights), info, level, *kept)
        weighed = setup.level_measurements(source)   # with the skin's uncertainty just written
        fits_again, best = fit_from([estimated_at], setup.objective_of(weighed),
                                    "identify again, with the skin's uncertainty", "fit with the skin's uncertainty")
        passes.append(fits_again)
        moved = np.abs(setup.model.space.to_x(best.theta) - setup.model.space.to_x(estimated_at))
        settled = _settled(moved, best)
        if settled:
            break
    fits = [first] + [fit for fits_again in passes for fit in fits_again]
    geometry = dict(read_geometry_covariance(run_dir, 2 * len(weighed[0]))[1],
                    measurement_share_of_variance=_measurement_share(weighed), passes=len(passes), settled=settled)
    return fits, best, weighed, geometry


def _estimated_for(stored, effects, theta) -> bool:
    """Was the skin's uncertainty that a run folder holds (`read_geometry_covariance`) estimated for this model at
    these parameters? A folder identified again with other effects (`--effects final`) holds another model's."""
    if stored is None:
        return False
    info = stored[1]
    return (list(info.get("effects", [])) == list(effects) and len(info["theta"]) == len(theta)
            and bool(np.allclose(info["theta"], theta, rtol=1e-9)))


def _identification_record(setup: RunSetup, case_dir, run_dir: Path, method: str, objective: str, source: str,
                           measured, fits, best, geometry: dict | None) -> dict:
    """identification.json's content: the data, the model, the fits, the floor and each level's own fit."""
    scorer = setup.objective_of(measured) if measured is not None else setup.mismatch_objective()
    result = {"case_dir": str(Path(case_dir).resolve()), "method": method, "objective": objective,
              "data": {"source": source if measured is not None else "contours",
                       "description": ("; ".join(m.description for m in measured) if measured is not None
                                       else "contours of I0 and I1"),
                       "count": sum(len(m) for m in measured) if measured is not None else 0},
              "effects": list(setup.model.effects), "parameters": list(setup.model.space.names),
              "units": setup.model.space.units, "unit_of": list(setup.model.space.unit_of),
              "best": best.as_dict(), "fits": [fit.as_dict() for fit in fits], "compartments": setup.compartments,
              "setup_lines": setup.setup_lines(),
              "engine_runs_total": len(EvaluationLog(run_dir / LOG_NAME))}
    if geometry is not None:
        result["geometry_uncertainty"] = geometry
        if not geometry["settled"]:
            result["setup_lines"].append(
                f"skin's uncertainty: estimated {geometry['passes']} times where the fit it weighed ended, and that fit "
                f"still moved (a parameter by over {100 * SKIN_SETTLED_X:.0f} % and over {SKIN_SETTLED_SE:g} of its "
                "standard error): the floor holds the last estimate's; a model this far from the data is lacking "
                "something (calfit diagnose)")
    if measured is not None:
        result["noise_floor"] = scorer.noise_floor(setup.model.space.size)
        result["misfit_over_floor"] = best.cost / result["noise_floor"]
        if source == "dic":
            result["floor_calibration"] = floor_calibration(run_dir)
        if setup.case.levels:
            result["levels"] = _level_fits(setup, scorer, measured, best.theta)
    return result


def _say_refinement(result: dict, refinement: dict, elements: int) -> None:
    """The identification's setup lines say that the default mesh was found too coarse and meshed again."""
    coarser = refinement["coarser_mesh"]
    result["coarser_mesh"] = coarser
    check = coarser["discretization"]
    result["setup_lines"].insert(-1, f"meshed again with {elements} elements: on the default "
                                     f"{check['elements']} the misfit at the fit was "
                                     f"{check['misfit_over_floor_mesh']:.2f} x the floor and "
                                     f"{check['misfit_over_floor_finer']:.2f} x on the finer mesh, a "
                                     "discretization error above what the noise hides")


def _discard_mesh(run_dir: Path) -> None:
    """A run folder's mesh and what was made on it (the setup, the skin's geometric covariance), so that the next
    identification meshes it again; the measurements and the evaluations' log stay (their keys hold the mesh)."""
    for path in [run_dir / SETUP_JSON, run_dir / SETUP_ARRAYS, *run_dir.glob("geometry_uncertainty*.npz")]:
        path.unlink(missing_ok=True)


def floor_sentence(calibration: dict) -> str:
    """One sentence saying how the floor was calibrated (`floor_calibration`)."""
    rejected = ", ".join(f"{count} {status}" for status, count in calibration["status"].items() if status != "kept")
    agreement = calibration.get("residual_over_predicted")
    estimated, used = calibration["image_noise_sigma_estimated"], calibration["image_noise_sigma"]
    return (f"The floor rests on the DIC's error model calibrated on these images: image noise "
            f"{used[0]:.4g} (I0) and {used[1]:.4g} (I1)"
            + (f", {used[0] / estimated[0]:.2f} times what each image's own pixels gave, as the windows' residuals "
               "showed" if not np.isclose(used[0], estimated[0], rtol=1e-3) else "")
            + f"; both prefiltered by a Gaussian of {calibration['prefilter_px']:g} px; edges drawn within "
            f"{calibration['edge_position_sigma_px']:.3f} px, found in the same residuals"
            + (f" (their noise {agreement:.2f} times the images' estimate)" if agreement is not None else "")
            + _point_sampling_clause(calibration.get("point_sampling"))
            + f"; {calibration['kept']} of {calibration['windows']} windows kept"
            + (f" ({rejected})" if rejected else "") + "."
            + (f" Warning: {calibration['through_plane_warning']}." if calibration.get("through_plane_warning") else ""))


def _point_sampling_clause(point_sampling: dict | None) -> str:
    """What `floor_sentence` says of images a renderer point-sampled (`imaging.drawing`), nothing for a scanner's."""
    if not point_sampling:
        return ""
    share = point_sampling.get("share_of_variance")
    return (f"; the images' boundaries drawn with {point_sampling['samples_per_side']} x "
            f"{point_sampling['samples_per_side']} point samples a pixel (p = {point_sampling['p_value']:.1e}), "
            "a renderer's drawing, whose error where they run along the pixel grid adds "
            + (f"{share:.0%} of the windows' variance" if share is not None else "to the windows' variance"))


def _settled(moved_x: np.ndarray, fit) -> bool:
    """Whether a fit weighed by the skin's uncertainty ended where that uncertainty was estimated: no parameter moved
    (|x change|, `moved_x`) by more than SKIN_SETTLED_X, or each that did by less than SKIN_SETTLED_SE of its standard
    error at the fit (`identify.FitResult.standard_error_x`; None, unseen by the data, counts as infinite)."""
    errors = np.array([np.inf if e is None else e for e in fit.standard_error_x] or np.zeros(len(moved_x)), float)
    return bool(np.all((moved_x <= SKIN_SETTLED_X) | (moved_x <= SKIN_SETTLED_SE * errors)))


def _measurement_share(measured) -> float:
    """The share of the measurement noise (not the model's geometry) in the variance of every level's data."""
    total = sum(np.trace(m.covariance_mm2) for m in measured)
    noise = sum(np.trace(m.covariance_mm2 if m.measurement_covariance_mm2 is None else m.measurement_covariance_mm2)
                for m in measured)
    return float(noise / total)


def _level_fits(setup: RunSetup, scorer, measured, theta) -> list[dict]:
    """Each garment level of a joint fit: its image, tension, measurements and own misfit over its own floor (the
    evaluation at theta is read back from the run's log)."""
    with Evaluator(setup.at_every_level(setup.model), scorer, setup.run_dir, progress=False) as evaluator:
        record = evaluator(theta)
    images = _level_images(setup)
    misfits = record["outputs"].get("level_misfits") or [None] * len(images)
    rows = []
    for part, image, tension, level_measured, misfit in zip(scorer.parts, images, setup.case.tensions, measured,
                                                           misfits):
        # each level's floor counts its share of the fitted parameters: p n_k / n
        floor = part.noise_floor(setup.model.space.size * part.n_residuals / scorer.n_residuals)
        rows.append({"image": image, "tension_N_per_mm": tension, "count": len(level_measured),
                     "misfit": misfit, "misfit_over_floor": None if misfit is None else misfit / floor})
    return rows


@holds_run_folder()
def run_montecarlo(run_dir, *, method: str = "auto", draws: int | None = None, threshold: float | None = None,
                   threshold_factor: float = 1.5, seed: int = 0, workers: int = 1, scheduler: str | None = None,
                   timeout_s: float = 120.0, progress: bool = True, verbose: bool = False) -> dict:
    """Parameter intervals of an identified run, written to montecarlo.json. method: "noise" (refits to data sets
    drawn from the measurements' covariance, `identify.noise_monte_carlo`; the default with measured
    displacements), "threshold" (Avril et al.'s acceptance below a misfit threshold, `identify.monte_carlo`; the
    default, and the only way, with the contour mismatch)."""
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    objective_name = identification["objective"]
    if method == "auto":
        method = "noise" if objective_name == "displacement" else "threshold"
    if method not in ("noise", "threshold"):
        raise ValueError(f"the Monte-Carlo method is auto, noise or threshold, not {method!r}")
    if method == "noise" and objective_name != "displacement":
        raise ValueError("the noise Monte-Carlo needs measured displacements (their covariance): identify with "
                         "--objective displacement, or use --method threshold")
    setup.model = setup.model_with(identification.get("effects", ()), sensitivities=(method == "noise"))
    objective = _objective(setup, objective_name, identified_data(identification))
    best = identification["best"]
    with Evaluator(setup.at_every_level(setup.model), objective, run_dir, workers=workers, scheduler=scheduler,
                   timeout_s=timeout_s, progress=progress, verbose=verbose, label="montecarlo") as evaluator:
        if method == "noise":
            result = noise_monte_carlo(evaluator, best["theta"], draws=draws or NOISE_DRAWS, seed=seed,
                                       nuisance_dof=objective.nuisance_dof).as_dict()
        else:
            result = monte_carlo(evaluator, identification["parameters"], best["theta"], best["cost"],
                                 draws=draws or 400, threshold=threshold, threshold_factor=threshold_factor,
                                 seed=seed).as_dict()
            result["method"] = "threshold"
    write_json(run_dir / "montecarlo.json", result)
    return result


@holds_run_folder()
def run_pressures(run_dir, *, draws: int = 30, seed: int = 1, workers: int = 1, scheduler: str | None = None,
                  timeout_s: float = 120.0, progress: bool = True, verbose: bool = False) -> dict:
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    montecarlo = read_json(run_dir / "montecarlo.json", "calfit montecarlo RUN_DIR")
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    # the identified model, its effects included: the intervals hold their parameters too
    setup.model = setup.model_with(identification.get("effects", ()))
    if len(montecarlo["central"]) != setup.model.space.size:
        raise RunFolderError(f"{run_dir / 'montecarlo.json'} holds {len(montecarlo['central'])} parameters and the "
                             f"identified model ({', '.join(setup.model.space.names)}) has {setup.model.space.size}: "
                             "run calfit montecarlo RUN_DIR again after the identification")
    objective = setup.pressure_objective()
    # the pressure objective's cost is the largest landmark pressure, not a misfit: kept off the progress line
    with Evaluator(setup.model, objective, run_dir, workers=workers, scheduler=scheduler, timeout_s=timeout_s,
                   progress=progress, verbose=verbose, label="pressures", cost_is_misfit=False) as evaluator:
        stats = pressure_uncertainty(evaluator, objective.names, montecarlo["lower"], montecarlo["upper"],
                                     montecarlo["central"], setup.case.tension_N_per_mm, draws=draws,
                                     tension_rel=setup.case.tension_rel_uncertainty, seed=seed)
    result = stats.as_dict()
    result["landmarks_from"] = setup.landmarks()[1]
    levels = []
    for level in setup.case.levels:
        # the same draws in the intervals, the same landmarks, under this level's garment
        with Evaluator(AtTension(setup.model, level.tension_N_per_mm), objective, run_dir, workers=workers,
                       scheduler=scheduler, timeout_s=timeout_s, progress=progress, verbose=verbose,
                       label=f"pressures, garment level {level.number}", cost_is_misfit=False) as evaluator:
            level_stats = pressure_uncertainty(evaluator, objective.names, montecarlo["lower"], montecarlo["upper"],
                                               montecarlo["central"], level.tension_N_per_mm, draws=draws,
                                               tension_rel=setup.case.tension_rel_uncertainty, seed=seed)
        levels.append({"level": level.number, "image": level.path.name, **level_stats.as_dict()})
        if setup.model.band is not None:
            levels[-1]["band"] = _band_on_the_leg(setup, montecarlo["central"],
                                                  AtTension(setup.model, level.tension_N_per_mm))
    if levels:
        result["levels"] = levels
    if setup.model.band is not None:
        result["band"] = _band_on_the_leg(setup, montecarlo["central"])
    write_json(run_dir / "pressures.json", result)
    return result


def _band_on_the_leg(setup: RunSetup, theta: Sequence[float], model: AtTension | None = None) -> dict:
    """The explicit band's contact pressure, shear, status and slip around the leg, its bridges and its hoop force at
    theta, under the case's own garment or another level's (`model`: the run's model at that level's tension; the
    band's shape is the same, its fabric stiffer or softer: `garment_state` reads the forces from the engine)."""
    with tempfile.TemporaryDirectory(prefix="calfit-band-") as scratch:
        results = setup.solve(theta, Path(scratch), model)
        state = band_state(results, setup.mesh, setup.model.band, setup.frame(), setup.model.friction_at(theta))
    return {"theta": [float(v) for v in theta], **state.as_dict()}


def pressure_summary(result: dict) -> list[str]:
    """Human lines: each landmark's pressure with its whole spread, then the parameters' share (Table 3) and the
    tension's (Table 4), each number to the digits its uncertainty allows (`digits`); then every more garment
    level."""
    rel = f"{100 * result['tension_rel']:g} %"
    lines = [f"{'landmark':<18} {'pressure (kPa)':>16} {'(mmHg)':>12} | {'parameters':>10} {'tension ' + rel:>14} | "
             f"{'T+' + rel:>8} {'T-' + rel:>8}"]
    for name, mean, parameters, tension, total, plus, minus in zip(result["landmarks"], result["mean_kPa"],
                                                                   *pressure_spreads(result), result["plus_kPa"],
                                                                   result["minus_kPa"]):
        lines.append(f"{name:<18} {with_uncertainty(mean, total):>16} "
                     f"{with_uncertainty(mean * MMHG_PER_KPA, total * MMHG_PER_KPA):>12} | "
                     f"{rounded(parameters, parameters):>10} {rounded(tension, tension):>14} | "
                     f"{rounded(plus, total):>8} {rounded(minus, total):>8}")
    if result.get("landmarks_from") == "segmentation":
        lines.append("landmarks: case.toml names none, so the first paper's five are placed from I0's segmentation "
                     "(the veins where they usually run; a [landmarks] table in case.toml puts them elsewhere)")
    lines.append(f"pressure: mean over the parameters' draws {PLUS_MINUS} both spreads in quadrature; parameters: std "
                 f"over the draws (Table 3); tension: the pressure's change for {PLUS_MINUS}{rel} of it, one standard "
                 "deviation (Table 4)")
    for level in result.get("levels", []):
        lines.append(f"garment level {level['level']}: {level['image']} at {level['tension_N_per_mm']:g} N/mm")
        lines += pressure_summary(level)
    return lines


def intervals_summary(result: dict) -> list[str]:
    noise = result.get("method") == "noise"
    lines = [f"{'parameter':<12} {'lower':>8} {'upper':>8} {'central':>8}  identification"]
    for k, name in enumerate(result["names"]):
        if noise:
            flag = (f"{PLUS_MINUS}{100 * result['relative_half_width'][k]:.1f} % " +
                    ("identifiable" if result["identifiable"][k] else "NOT identifiable") +
                    (", ON A BOUND" if name in result["on_bound"] else ""))
        else:
            flag = "POOR" if name in result["poorly_identified"] else "good"
        spread = interval_uncertainty(result["lower"][k], result["upper"][k])
        lower, upper, central = (rounded(result[key][k], spread) for key in ("lower", "upper", "central"))
        lines.append(f"{name:<12} {lower:>8} {upper:>8} {central:>8}  {flag}")
    if noise:
        lines.append(f"{100 * result['confidence']:.0f} % intervals from {result['draws'] - result['failed']} refitted "
                     f"noise draws" + (f", noise variance inflated x{result['inflation']:.2f} (misfit above its floor)"
                                       if result["inflation"] > 1.0 else ""))
        lines += sum_only_lines(result)
    return lines


def sum_only_lines(montecarlo: dict) -> list[str]:
    """A sentence per pair of parameters that act only through their sum (identify.NoiseMonteCarloResult.sums)."""
    return [f"{a} and {b} act only through their sum, {total['value']:.4g} in [{total['lower']:.4g}, "
            f"{total['upper']:.4g}] ({'identifiable' if total['identifiable'] else 'NOT identifiable either'}); each "
            "alone is not identifiable, its interval the search box." for total in montecarlo.get("sums", [])
            for a, b in [total["names"]]]


def fit_summary(fit: dict, names: Sequence[str], units: Sequence[str] | None = None) -> str:
    """One line per fit: each parameter with its unit (`identification.json`'s unit_of; kPa for all when not given,
    none for a dimensionless share), the misfit and the cost."""
    units = units or ["kPa"] * len(names)
    values = ", ".join(f"{n} = {v:.3f}" + ("" if unit == "1" else f" {unit}")
                       for n, v, unit in zip(names, fit["theta"], units))
    return (f"{fit['method']}: {values}; misfit {fit['cost']:.5g}; {fit['iterations']} iterations, "
            f"{fit['evaluations']} evaluations, {fit['engine_runs']} engine runs ({fit['from_log']} from the log), "
            f"{fit['wall_time_s']:.1f} s")
