"""The stages of a run, each reading and writing JSON files in the run folder (what the CLI calls).

identify (RUN_DIR/identification.json): Nelder-Mead or Levenberg-Marquardt from one start or
from the starts of Avril et al. Table 1, on the contour mismatch M (sec. 2.2.5) or the
displacement residual F (Bouten and Drapier eq. 2); montecarlo (montecarlo.json): intervals
around the best fit (Table 2); pressures (pressures.json): landmark pressures over draws in the
intervals and with the tension +-10 % (Tables 3 and 4). Every engine evaluation goes through
one `runner.Evaluator` per stage on the run's log (evaluations.jsonl), so any stage interrupted
and started again resumes without repeating an evaluation.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from dataclasses import asdict

from .diagnose import ALPHA, diagnose, refit, refit_verdict, residual_maps, settle_ties, summarize_fit
from .forward import TABLE2_CENTRAL_KPA
from .identify import FitResult, levenberg_marquardt, monte_carlo, multistart, pressure_uncertainty, table1_starts
from .runner import LOG_NAME, EvaluationLog, Evaluator
from .study import RunSetup, load_run, prepare_run, read_json, write_json

OBJECTIVES = ("mismatch", "displacement")


def choose_objective(setup: RunSetup, objective: str, method: str) -> str:
    if objective == "auto":
        objective = "displacement" if (method == "lm" or setup.case.points is not None) else "mismatch"
    if method == "lm" and objective != "displacement":
        raise ValueError("Levenberg-Marquardt needs a residual vector: use --objective displacement (points.csv)")
    return objective


def _objective(setup: RunSetup, name: str):
    return setup.mismatch_objective() if name == "mismatch" else setup.displacement_objective()


def run_identify(case_dir, run_dir, *, method: str = "nm", objective: str = "auto", start: Sequence[float] | None = None,
                 starts: str = "one", n_elements: int = 400, order: int = 1, effects: Sequence[str] = (),
                 engine_sensitivities: bool = True, workers: int = 1, scheduler: str | None = None,
                 timeout_s: float = 120.0, progress: bool = True) -> dict:
    """Prepare (or reload) the run folder and identify; returns and writes identification.json.
    effects: catalog effects whose parameters are fitted too (they start at zero, effect off); order: 1 for CPE3
    (Avril et al.), 2 for CPE6 (volumetric effects such as drainage need it: CPE3 is too stiff in dilatation)."""
    run_dir = Path(run_dir)
    setup = (load_run(run_dir) if (run_dir / "setup.json").is_file()
             else prepare_run(case_dir, run_dir, n_elements=n_elements, order=order))
    objective = choose_objective(setup, objective, method)
    setup.model = setup.model_with(effects, sensitivities=(method == "lm" and engine_sensitivities))
    base = list(start) if start is not None else list(TABLE2_CENTRAL_KPA)
    start_points = [setup.model.start(s) for s in (table1_starts(base) if starts == "table1" else [base])]
    with Evaluator(setup.model, _objective(setup, objective), run_dir, workers=workers, scheduler=scheduler,
                   timeout_s=timeout_s, progress=progress) as evaluator:
        if method == "lm":
            fits = [levenberg_marquardt(evaluator, s) for s in start_points]
        else:
            fits = multistart(evaluator, start_points)
    best = min(fits, key=lambda fit: fit.cost)
    result = {"case_dir": str(Path(case_dir).resolve()), "method": method, "objective": objective,
              "effects": list(setup.model.effects), "parameters": list(setup.model.space.names),
              "units": setup.model.space.units, "unit_of": list(setup.model.space.unit_of),
              "best": best.as_dict(), "fits": [fit.as_dict() for fit in fits],
              "engine_runs_total": len(EvaluationLog(run_dir / LOG_NAME))}
    write_json(run_dir / "identification.json", result)
    return result


def run_montecarlo(run_dir, *, draws: int = 400, threshold: float | None = None, threshold_factor: float = 1.5,
                   seed: int = 0, workers: int = 1, scheduler: str | None = None, timeout_s: float = 120.0,
                   progress: bool = True) -> dict:
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    setup.model = setup.model_with(identification.get("effects", ()))
    best = identification["best"]
    with Evaluator(setup.model, _objective(setup, identification["objective"]), run_dir, workers=workers,
                   scheduler=scheduler, timeout_s=timeout_s, progress=progress) as evaluator:
        result = monte_carlo(evaluator, identification["parameters"], best["theta"], best["cost"], draws=draws,
                             threshold=threshold, threshold_factor=threshold_factor, seed=seed).as_dict()
    write_json(run_dir / "montecarlo.json", result)
    return result


def run_pressures(run_dir, *, draws: int = 30, seed: int = 1, workers: int = 1, scheduler: str | None = None,
                  timeout_s: float = 120.0, progress: bool = True) -> dict:
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    montecarlo = read_json(run_dir / "montecarlo.json", "calfit montecarlo RUN_DIR")
    objective = setup.pressure_objective()
    with Evaluator(setup.model, objective, run_dir, workers=workers, scheduler=scheduler, timeout_s=timeout_s,
                   progress=progress) as evaluator:
        stats = pressure_uncertainty(evaluator, objective.names, montecarlo["lower"], montecarlo["upper"],
                                     montecarlo["central"], setup.case.tension_N_per_mm, draws=draws,
                                     tension_rel=setup.case.tension_rel_uncertainty, seed=seed)
    result = stats.as_dict()
    write_json(run_dir / "pressures.json", result)
    return result


def run_diagnose(run_dir, *, refit_effects: Sequence[str] | str = "auto", alpha: float = ALPHA,
                 engine_sensitivities: bool = True, workers: int = 1, scheduler: str | None = None,
                 timeout_s: float = 120.0, progress: bool = True) -> dict:
    """Diagnose the identified model of a run; refit with `refit_effects`: "auto" (the best-ranked effect when it
    is significant, with those the score cannot tell from it), "none", effect names, or "auto" and names.
    Writes and returns diagnosis.json."""
    run_dir = Path(run_dir)
    setup = load_run(run_dir)
    identification = read_json(run_dir / "identification.json", "calfit identify CASE_DIR --out RUN_DIR")
    if identification["objective"] != "displacement":
        raise ValueError("the diagnosis compares the model with measured displacements: identify with "
                         "--objective displacement (points.csv) first")
    model = setup.model_with(identification.get("effects", ()), sensitivities=engine_sensitivities)
    objective = setup.displacement_objective()
    points = setup.case.points

    def evaluator_for(m):
        return Evaluator(m, objective, run_dir, workers=workers, scheduler=scheduler, timeout_s=timeout_s,
                         progress=progress)

    theta = identification["best"]["theta"]
    regions, centre = setup.point_regions(), setup.leg_centre_mm()
    diagnosis = diagnose(evaluator_for, model, theta, points.position_mm, points.sigma_mm, regions, centre,
                         alpha=alpha, engine_sensitivities=engine_sensitivities)
    with evaluator_for(model) as evaluator:
        before = summarize_fit(model, FitResult(**identification["best"]), evaluator(theta), points.sigma_mm)
    requested = [refit_effects] if isinstance(refit_effects, str) else list(refit_effects)
    top = diagnosis.ranking[0] if diagnosis.ranking and diagnosis.ranking[0].significant else None
    names = ([top.effect] + top.tied_with if top and "auto" in requested else [])
    names += [n for n in requested if n not in ("auto", "none") and n not in names]
    after, after_maps = [], []
    for name in names:
        fit, residual = refit(evaluator_for, model, theta, [name], points.sigma_mm)
        after.append(fit)
        after_maps.append(residual_maps(points.position_mm, residual, regions, centre))
    settle_ties(diagnosis, after)
    diagnosis.explained, diagnosis.verdict = refit_verdict(diagnosis, after)
    if not diagnosis.explained:
        maps = diagnosis.maps
        diagnosis.verdict += (f"; the residual is largest in the sector around {maps.worst_sector_deg:.0f} deg "
                              f"(RMS {max(maps.sector_rms_mm):.3f} mm) and in the "
                              f"{max(maps.per_region_rms_mm, key=maps.per_region_rms_mm.get)}")
    result = diagnosis.as_dict()
    result["before"] = before.as_dict()
    result["refits"] = [fit.as_dict() for fit in after]
    result["maps_after"] = [asdict(m) for m in after_maps]
    write_json(run_dir / "diagnosis.json", result)
    return result


def pressure_summary(result: dict) -> list[str]:
    """Human lines of Table 3 and Table 4."""
    lines = [f"{'landmark':<18} {'mean kPa':>9} {'std':>6} {'CV %':>6} | {'T':>6} {'T+10%':>7} {'T-10%':>7}"]
    for k, name in enumerate(result["landmarks"]):
        lines.append(f"{name:<18} {result['mean_kPa'][k]:9.2f} {result['std_kPa'][k]:6.2f} {result['cv_percent'][k]:6.1f} | "
                     f"{result['central_kPa'][k]:6.2f} {result['plus_kPa'][k]:7.2f} {result['minus_kPa'][k]:7.2f}")
    return lines


def intervals_summary(result: dict) -> list[str]:
    lines = [f"{'parameter':<12} {'lower':>8} {'upper':>8} {'central':>8}  identification"]
    for k, name in enumerate(result["names"]):
        flag = "POOR" if name in result["poorly_identified"] else "good"
        lines.append(f"{name:<12} {result['lower'][k]:8.2f} {result['upper'][k]:8.2f} {result['central'][k]:8.2f}  {flag}")
    return lines


def fit_summary(fit: dict, names: Sequence[str]) -> str:
    values = ", ".join(f"{n} = {v:.3f}" for n, v in zip(names, fit["theta"]))
    return (f"{fit['method']}: {values} kPa; misfit {fit['cost']:.5g}; {fit['iterations']} iterations, "
            f"{fit['evaluations']} evaluations, {fit['engine_runs']} engine runs ({fit['from_log']} from the log), "
            f"{fit['wall_time_s']:.1f} s")


def relative_errors(theta: Sequence[float], truth: Sequence[float]) -> np.ndarray:
    return np.abs(np.asarray(theta) - np.asarray(truth)) / np.asarray(truth)
