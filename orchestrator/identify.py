"""Identification of material parameters and the uncertainty of what they predict.

The optimizers work on x = ln(theta) (positive parameters, relative steps), through an
`runner.Evaluator`, so that every engine run is cached and logged:

- `nelder_mead`: minimise a scalar misfit (Avril et al. sec. 2.2.5: M(theta); or F(theta) of
  Bouten and Drapier eq. 2), scipy's Nelder-Mead; a failed engine run (no convergence, ...)
  counts as +inf and the simplex moves away from it.
- `levenberg_marquardt`: minimise F = r.r / (2N) over the residual vector r(theta) (Bouten and
  Drapier sec. 2.6), the Jacobian J_ij = dr_i / dx_j by forward differences, its p columns
  evaluated in parallel; step (J^T J + lambda diag J^T J) dx = -J^T r, lambda divided by 3 on
  success and multiplied by 4 on failure.
- `multistart`: Nelder-Mead from several initial values (Avril et al. Table 1).
- `monte_carlo`: draws in a box, kept when the misfit is below a threshold; the ranges of the
  kept draws are the parameter intervals and their midpoints the central values (sec. 2.2.6,
  3.1, Table 2). A parameter whose kept draws fill most of the drawn range is poorly
  identified (the first paper found the fat C10 weak).
- `pressure_uncertainty`: N draws uniformly in the intervals, pressure at the landmarks:
  mean, standard deviation, coefficient of variation (sec. 4.2, Table 3); `tension_sensitivity`:
  central values with the garment tension +-10% (sec. 4.5, Table 4).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np
from scipy import optimize

from .runner import OK, Evaluator

FD_STEP = 1e-3           # forward-difference step in ln(theta): 0.1 %
POORLY_IDENTIFIED_SPAN = 0.5   # kept draws span more than half the drawn range (in ln theta)


@dataclass
class FitResult:
    """The outcome of one identification (theta in the model's units, kPa)."""

    method: str
    start: list[float]
    theta: list[float]
    cost: float
    iterations: int
    evaluations: int
    engine_runs: int
    from_log: int
    wall_time_s: float
    converged: bool
    message: str = ""
    history: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def _cost(record: dict) -> float:
    return float(record["cost"]) if record["status"] == OK else np.inf


def nelder_mead(evaluator: Evaluator, start: Sequence[float], *, xatol: float = 2e-3, fatol: float = 1e-6,
                max_evaluations: int = 400, initial_step: float = 0.15) -> FitResult:
    """Nelder-Mead in ln(theta) from `start`; initial simplex: each parameter +initial_step (15 %)."""
    launched0, replayed0, began = evaluator.launched, evaluator.replayed, time.perf_counter()
    x0 = np.log(np.asarray(start, float))
    simplex = np.vstack([x0] + [x0 + initial_step * np.eye(len(x0))[j] for j in range(len(x0))])
    history: list[float] = []
    calls = 0

    def misfit(x):
        nonlocal calls
        calls += 1
        value = _cost(evaluator(np.exp(x)))
        if not history or value < history[-1]:
            history.append(value)
        return value

    result = optimize.minimize(misfit, x0, method="Nelder-Mead",
                               options={"xatol": xatol, "fatol": fatol, "maxfev": max_evaluations,
                                        "initial_simplex": simplex})
    return FitResult("nelder-mead", list(map(float, start)), np.exp(result.x).tolist(), float(result.fun),
                     int(result.nit), calls, evaluator.launched - launched0, evaluator.replayed - replayed0,
                     time.perf_counter() - began, bool(result.success), str(result.message), history)


def levenberg_marquardt(evaluator: Evaluator, start: Sequence[float], *, max_iterations: int = 50,
                        xtol: float = 1e-4, ftol: float = 1e-10, lam: float = 1e-3) -> FitResult:
    """Levenberg-Marquardt on the residual vector `outputs["residuals"]` of the evaluator's objective."""
    launched0, replayed0, began = evaluator.launched, evaluator.replayed, time.perf_counter()
    x = np.log(np.asarray(start, float))
    p = len(x)

    def residuals(record: dict) -> np.ndarray | None:
        return np.asarray(record["outputs"]["residuals"]) if record["status"] == OK else None

    first = evaluator(np.exp(x))
    r = residuals(first)
    if r is None:
        raise RuntimeError(f"the engine failed at the start point {list(start)}: {first['message']}")
    cost, history = float(r @ r) / len(r), []
    history.append(cost)
    evaluations, converged, message, iteration = 1, False, "maximum number of iterations reached", 0
    for iteration in range(1, max_iterations + 1):
        probes = [np.exp(x + FD_STEP * np.eye(p)[j]) for j in range(p)]
        records = evaluator.evaluate(probes, tag="lm-jacobian", label=f"LM Jacobian {iteration}")
        evaluations += p
        columns = [residuals(rec) for rec in records]
        if any(c is None for c in columns):
            raise RuntimeError("the engine failed in a finite-difference probe: "
                               + "; ".join(rec["message"] for rec in records if rec["status"] != OK))
        J = np.column_stack([(c - r) / FD_STEP for c in columns])
        gradient, normal = J.T @ r, J.T @ J
        improved = False
        while lam < 1e12:
            step = np.linalg.solve(normal + lam * np.diag(np.diag(normal) + 1e-30), -gradient)
            trial = evaluator(np.exp(x + step))
            evaluations += 1
            r_trial = residuals(trial)
            trial_cost = float(r_trial @ r_trial) / len(r_trial) if r_trial is not None else np.inf
            if trial_cost < cost:
                x, r, lam, improved = x + step, r_trial, max(lam / 3.0, 1e-12), True
                relative_drop = (cost - trial_cost) / max(cost, 1e-300)
                cost = trial_cost
                history.append(cost)
                break
            lam *= 4.0
        if not improved:
            converged, message = True, "no step lowers the misfit (at a minimum to engine precision)"
            break
        if np.max(np.abs(step)) < xtol or relative_drop < ftol:
            converged, message = True, "step or misfit change below tolerance"
            break
    # r has 2N entries (x and y at N points), so r.r / len(r) is F of Bouten and Drapier eq. 2 (sigma = 1 mm)
    return FitResult("levenberg-marquardt", list(map(float, start)), np.exp(x).tolist(), cost, iteration, evaluations,
                     evaluator.launched - launched0, evaluator.replayed - replayed0, time.perf_counter() - began, converged,
                     message, history)


def table1_starts(central: Sequence[float], spread: float = 0.1, extra: Sequence[Sequence[float]] = ()) -> list[list[float]]:
    """Initial values as in Avril et al. Table 1: the central values with one parameter at a time
    moved by +-spread, then any extra starting points."""
    central = [float(v) for v in central]
    starts = []
    for j in range(len(central)):
        for sign in (1.0, -1.0):
            start = list(central)
            start[j] *= 1.0 + sign * spread
            starts.append(start)
    return starts + [list(map(float, s)) for s in extra] + [central]


def multistart(evaluator: Evaluator, starts: Sequence[Sequence[float]], **options) -> list[FitResult]:
    return [nelder_mead(evaluator, start, **options) for start in starts]


@dataclass
class MonteCarloResult:
    """Kept draws (misfit <= threshold) and the intervals they span (Avril et al. Table 2)."""

    names: list[str]
    draws: int
    failed: int
    threshold: float
    box_lower: list[float]
    box_upper: list[float]
    lower: list[float]
    upper: list[float]
    central: list[float]
    accepted: int
    poorly_identified: list[str]
    samples: list[list[float]]
    costs: list[float | None]
    failures: list[dict]

    def as_dict(self) -> dict:
        return asdict(self)


def monte_carlo(evaluator: Evaluator, names: Sequence[str], box_lower: Sequence[float], box_upper: Sequence[float],
                draws: int, threshold: float, seed: int = 0, log_uniform: bool = True) -> MonteCarloResult:
    """Draw parameters in the box (log-uniform by default), keep those with misfit <= threshold."""
    rng = np.random.default_rng(seed)
    lo, hi = np.log(box_lower) if log_uniform else np.asarray(box_lower), np.log(box_upper) if log_uniform else np.asarray(box_upper)
    samples = lo + (hi - lo) * rng.random((draws, len(names)))
    thetas = np.exp(samples) if log_uniform else samples
    records = evaluator.evaluate(thetas.tolist(), tag="monte-carlo", label="Monte-Carlo")
    costs = np.array([_cost(rec) for rec in records])
    kept = costs <= threshold
    failures = [{"theta": rec["theta"], "status": rec["status"], "message": rec["message"]}
                for rec in records if rec["status"] != OK]
    if kept.any():
        lower, upper = thetas[kept].min(axis=0), thetas[kept].max(axis=0)
        span = (np.log(upper) - np.log(lower)) / (np.log(box_upper) - np.log(box_lower))
        poorly = [name for name, s in zip(names, span) if s > POORLY_IDENTIFIED_SPAN]
    else:
        lower = upper = np.full(len(names), np.nan)
        poorly = list(names)
    return MonteCarloResult(list(names), draws, len(failures), float(threshold), list(map(float, box_lower)),
                            list(map(float, box_upper)), lower.tolist(), upper.tolist(), ((lower + upper) / 2).tolist(),
                            int(kept.sum()), poorly, thetas.tolist(), [None if not np.isfinite(c) else float(c) for c in costs],
                            failures)


@dataclass
class PressureStatistics:
    """Landmark pressures (kPa) over draws in the intervals (Table 3) and with the tension +-10 % (Table 4)."""

    landmarks: list[str]
    draws: int
    failed: int
    mean_kPa: list[float]
    std_kPa: list[float]
    cv_percent: list[float]
    central_kPa: list[float]
    tension_N_per_mm: float
    tension_rel: float
    plus_kPa: list[float]
    minus_kPa: list[float]
    plus_deviation_percent: list[float]
    minus_deviation_percent: list[float]
    samples_kPa: list[list[float]]
    wall_time_s: float

    def as_dict(self) -> dict:
        return asdict(self)


def _pressures(records: list[dict], names: Sequence[str]) -> np.ndarray:
    return np.array([[rec["outputs"]["pressure_kPa"][n] for n in names] for rec in records if rec["status"] == OK])


def pressure_uncertainty(evaluator: Evaluator, landmarks: Sequence[str], lower: Sequence[float], upper: Sequence[float],
                         central: Sequence[float], tension: float, *, draws: int = 30, tension_rel: float = 0.10,
                         seed: int = 1) -> PressureStatistics:
    """Avril et al. sec. 4.2 (Table 3) and sec. 4.5 (Table 4), in one parallel batch."""
    began = time.perf_counter()
    rng = np.random.default_rng(seed)
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    thetas = lower + (upper - lower) * rng.random((draws, len(lower)))
    records = evaluator.evaluate(thetas.tolist(), tag="uncertainty", label="uncertainty")
    table4 = [evaluator.evaluate([central], options={"tension_N_per_mm": tension * factor}, tag="tension")[0]
              for factor in (1.0, 1.0 + tension_rel, 1.0 - tension_rel)]
    failed = [rec for rec in records + table4 if rec["status"] != OK]
    samples = _pressures(records, landmarks)
    if len(samples) == 0 or any(rec["status"] != OK for rec in table4):
        raise RuntimeError("the pressure study failed: " + "; ".join(rec["message"] for rec in failed[:3]))
    base, plus, minus = (_pressures([rec], landmarks)[0] for rec in table4)
    mean, std = samples.mean(axis=0), samples.std(axis=0, ddof=1) if len(samples) > 1 else np.zeros(len(landmarks))
    return PressureStatistics(list(landmarks), draws, len(failed), mean.tolist(), std.tolist(),
                              (100 * std / np.abs(mean)).tolist(), base.tolist(), tension, tension_rel, plus.tolist(),
                              minus.tolist(), (100 * (plus - base) / np.abs(base)).tolist(),
                              (100 * (base - minus) / np.abs(base)).tolist(), samples.tolist(),
                              time.perf_counter() - began)
