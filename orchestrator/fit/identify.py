"""Identification of material parameters and the uncertainty of what they predict.

The optimizers work on x = ln(theta) for the positive material constants (relative steps) and on
x = theta / scale for the additive effect parameters (`forward.ParameterSpace.to_x`), through an
`runner.Evaluator`, so that every engine run is cached and logged:

- `nelder_mead`: minimise a scalar misfit (Avril et al. sec. 2.2.5: M(theta); or F(theta) of
  Bouten and Drapier eq. 2), scipy's Nelder-Mead; a failed engine run (no convergence, ...)
  counts as +inf and the simplex moves away from it.
- `levenberg_marquardt`: minimise F = r.r / (2N) over the residual vector r(theta) (Bouten and
  Drapier sec. 2.6), the Jacobian J_ij = dr_i / dx_j from the engine's sensitivities du/dtheta when
  the evaluation carries them (`outputs["jacobian"]`, one engine run per iteration), otherwise by
  forward differences, its p columns evaluated in parallel; step (J^T J + lambda diag J^T J) dx = -J^T r, lambda divided by 3 on
  success and multiplied by 4 on failure.
- `multistart`: Nelder-Mead from several initial values (Avril et al. Table 1).
- `monte_carlo`: draws around the identified point, kept when the misfit is below a threshold;
  the ranges of the kept draws are the parameter intervals and their midpoints the central
  values (sec. 2.2.6, 3.1, Table 2). A parameter whose kept values span a wide range is
  poorly identified (the first paper found the fat C10 weak). What the contour mismatch M allows.
- `noise_monte_carlo`: 95 % intervals from refits to synthetic data sets drawn from the
  measurements' covariance (a parametric bootstrap; the default with measured displacements,
  whose noise is known).
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

from ..engine.results import OK
from ..engine.runner import Evaluator

FD_STEP = 1e-3           # forward-difference step in ln(theta): 0.1 %
MAX_LM_STEP = 1.0        # largest LM step in x: a factor e in a constant, `scale` in an effect parameter
# Levenberg-Marquardt's stagnation test: over STALL_ITERATIONS accepted steps chi^2 fell by less than STALL_CHI2 s^2,
# s^2 = chi^2 / (n - p) the residual's variance per degree of freedom (1 where the model holds, the model error's
# inflation where it does not, as in the noise Monte-Carlo). A fall of 0.01 s^2 in chi^2 moves the parameters by
# about a tenth of their standard error: what is left to gain is noise. A model that lacks an effect crawls there
# otherwise: the second paper's leg with a hidden drainage, fitted without it from the images, took 54 runs for a
# 0.7 % fall (the fat's pair swinging 0.34-1.52 kPa along a direction the data barely see), each step accepted.
STALL_ITERATIONS = 3
STALL_CHI2 = 0.01
MAX_EXPLORED_FACTOR = 2.0      # Monte-Carlo draws within best / 2 .. best * 2
PROFILE_OFFSETS = np.array([-1.0, -0.5, -0.25, -0.125, 0.125, 0.25, 0.5, 1.0])   # in units of ln(max factor)
POORLY_IDENTIFIED_RATIO = 1.5  # kept values span more than a factor 1.5 (upper / lower)
NOISE_DRAWS = 200              # synthetic data sets of the noise Monte-Carlo
MIN_NOISE_DRAWS = 10           # fewer draws leave the intervals' 2.5 % and 97.5 % quantiles to one or two samples
IDENTIFIABLE_HALF_WIDTH = 0.10 # a 95 % interval within +-10 % of the value: identifiable


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
    # the standard error of each x at the fit, sqrt(diag (J^T J)^-1) times s >= 1 (`linearised_standard_errors`),
    # None for one the data do not see; empty where the method has no Jacobian (Nelder-Mead)
    standard_error_x: list[float | None] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def _cost(record: dict) -> float:
    return float(record["cost"]) if record["status"] == OK else np.inf


def parameter_space(evaluator: Evaluator):
    """The evaluator's model's parameter space (ln theta for all parameters when the model has none)."""
    from ..model.forward import ParameterSpace

    space = getattr(evaluator.model, "space", None)
    return space if isinstance(space, ParameterSpace) else None


def _to_x(space, theta) -> np.ndarray:
    return space.to_x(theta) if space is not None else np.log(np.asarray(theta, float))


def _from_x(space, x) -> np.ndarray:
    """theta of x, inside the box (x is clipped to the box first: theta is monotone in x, and a wild step in
    ln theta would overflow exp before the clip)."""
    if space is None:
        return np.exp(np.asarray(x, float))
    return space.clip(space.from_x(np.clip(x, space.to_x(space.lower), space.to_x(space.upper))))


def _dtheta_dx(space, theta) -> np.ndarray:
    """d theta / d x per parameter: theta for ln theta, scale for the additive parameters."""
    theta = np.asarray(theta, float)
    if space is None:
        return theta
    return np.where(np.array(space.linear), np.array(space.scale), theta)


def residual_jacobian(model, record: dict, theta, partial: bool = False) -> np.ndarray | None:
    """dr/dtheta (n_residuals x p) from the engine sensitivities of an evaluation record: the objective stores
    dr/d(engine parameter) (`outputs["sensitivity"]`), the model says how its parameters map onto the engine's
    (`sensitivity_map`: du/dtheta_j = sum factor x du/d(engine name), None for a parameter the engine does not
    differentiate, e.g. a load under friction). None when the record or the model has none; a column missing from
    the record makes the whole None, or with `partial` that column NaN (`missing_columns` lists them, to difference)."""
    stored = record["outputs"].get("sensitivity") if record["status"] == OK else None
    mapping = getattr(model, "sensitivity_map", None)
    if not stored or mapping is None:
        return None
    columns = []
    for name, terms in mapping(theta).items():
        if terms is None or any(line not in stored for line, _ in terms):
            if not partial:
                return None
            columns.append(None)
            continue
        columns.append(sum(factor * np.asarray(stored[line], float) for line, factor in terms))
    n = next((len(c) for c in columns if c is not None), None)
    if n is None:
        return None
    return np.column_stack([np.full(n, np.nan) if c is None else c for c in columns])


def missing_columns(jacobian: np.ndarray | None, p: int) -> list[int]:
    """The columns of a (partial) engine Jacobian that must be differenced: all of them without one."""
    return list(range(p)) if jacobian is None else [j for j in range(p) if np.isnan(jacobian[:, j]).any()]


def _damped_step(J: np.ndarray, r: np.ndarray, lam: float, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Levenberg-Marquardt's step with its bounds: argmin |J s + r|^2 + lam s^T D s over low <= s <= high, D =
    diag(J^T J) (Marquardt's scaling). The bounds hold the trust region and the search box. Solved as bounded linear
    least squares (BVLS), a parameter that would leave the region stops at its edge while the others take their best
    step given it: a step cut to the region along the unbounded step's direction took the whole direction with a
    parameter the data hardly fix (the second paper's fat from its images bounced between e and 1/e, 7 runs rejected
    in a row), and damping it until the whole step fits slowed every other parameter (a foreign case's baseline
    reached 50 iterations, 6.1 x the floor, against 3.7 x)."""
    damping = np.sqrt(lam * (np.sum(J * J, axis=0) + 1e-30))
    A = np.vstack([J, np.diag(damping)])
    b = np.concatenate([-r, np.zeros(len(damping))])
    low, high = np.minimum(low, -1e-15), np.maximum(high, 1e-15)   # BVLS needs low < high: a parameter on the box
    return optimize.lsq_linear(A, b, bounds=(low, high), method="bvls").x


def steps_into_box(space, x: np.ndarray, step=FD_STEP) -> np.ndarray:
    """Forward-difference steps in x of size `step` (one, or one per parameter), each pointing into the search box
    (a parameter on its upper bound steps down)."""
    step = np.broadcast_to(np.asarray(step, float), np.shape(x))
    return np.where(_to_x(space, _from_x(space, x + step)) > x + 0.5 * step, step, -step)


def jacobian_in_x(evaluator: Evaluator, record: dict, x: np.ndarray, steps: np.ndarray, *, tag: str,
                  label: str) -> tuple[np.ndarray, list[int]]:
    """dr/dx at x (`record` the evaluation there) and the columns that were differenced: the engine's sensitivities
    where the record has them (chain rule through theta(x)), one-sided differences x + steps[j] e_j for the others,
    in one parallel batch of runs that carry no sensitivities (a difference needs the displacements alone, and
    through friction each column carried costs a back-substitution at every increment: the diagnosis's probe of
    281 columns ran 4 x as long as the run alone). A probe the engine cannot solve (contact with friction) is tried
    on the other side; RuntimeError when both sides fail."""
    space = parameter_space(evaluator)
    theta = _from_x(space, x)
    r = np.asarray(record["outputs"]["residuals"], float)
    p = len(x)
    engine = residual_jacobian(evaluator.model, record, theta, partial=True)
    J = np.zeros((len(r), p)) if engine is None else engine * _dtheta_dx(space, theta)[None, :]
    missing = missing_columns(engine, p)
    if not missing:
        return J, missing
    steps = np.array(steps, float)
    options = {"sensitivities": False} if getattr(evaluator.model, "engine_sensitivities", False) else None

    def difference(columns: Sequence[int], label_now: str) -> dict[int, dict]:
        probes = [_from_x(space, x + steps[j] * np.eye(p)[j]) for j in columns]
        return dict(zip(columns, evaluator.evaluate(probes, options=options, tag=tag, label=label_now)))

    records = difference(missing, label)
    failed = [j for j, rec in records.items() if rec["status"] != OK]
    if failed:
        steps[failed] *= -1.0
        records.update(difference(failed, f"{label}, other side"))
        if any(records[j]["status"] != OK for j in failed):
            raise RuntimeError("the engine failed in a finite-difference probe on both sides: "
                               + "; ".join(records[j]["message"] for j in failed if records[j]["status"] != OK))
    for j in missing:
        J[:, j] = (np.asarray(records[j]["outputs"]["residuals"], float) - r) / steps[j]
    return J, missing


def nelder_mead(evaluator: Evaluator, start: Sequence[float], *, xatol: float = 2e-3, fatol: float = 1e-6,
                max_evaluations: int = 400, initial_step: float = 0.15) -> FitResult:
    """Nelder-Mead in ln(theta) from `start`; initial simplex: each parameter +initial_step (15 %)."""
    launched0, replayed0, began = evaluator.launched, evaluator.replayed, time.perf_counter()
    space = parameter_space(evaluator)
    x0 = _to_x(space, start)
    simplex = np.vstack([x0] + [x0 + initial_step * np.eye(len(x0))[j] for j in range(len(x0))])
    history: list[float] = []
    calls = 0

    def misfit(x):
        nonlocal calls
        calls += 1
        value = _cost(evaluator(_from_x(space, x)))
        if not history or value < history[-1]:
            history.append(value)
        return value

    result = optimize.minimize(misfit, x0, method="Nelder-Mead",
                               options={"xatol": xatol, "fatol": fatol, "maxfev": max_evaluations,
                                        "initial_simplex": simplex})
    return FitResult("nelder-mead", list(map(float, start)), _from_x(space, result.x).tolist(), float(result.fun),
                     int(result.nit), calls, evaluator.launched - launched0, evaluator.replayed - replayed0,
                     time.perf_counter() - began, bool(result.success), str(result.message), history)


def levenberg_marquardt(evaluator: Evaluator, start: Sequence[float], *, max_iterations: int = 50,
                        xtol: float = 1e-4, ftol: float = 1e-10, lam: float = 1e-3) -> FitResult:
    """Levenberg-Marquardt on the residual vector `outputs["residuals"]` of the evaluator's objective
    (chi^2 = r.r); the reported cost and history are the objective's own cost (F, eq. 2). Steps have no part
    along the direction in which a pair that acts only through its sum (`_sum_only_directions`) changes but not its
    sum: the misfit is flat there but for a differenced Jacobian's noise, on which the steps would wander to the
    box's edge (the second paper's fat went to C01 = 0.05, its lower bound, in 24 iterations and 115 runs). Such a
    pair steps as one parameter (`_step_basis`), so the bounds hold the step without giving it a part along that
    direction (a step projected after the bounds had clipped one of the two moved the pair's split)."""
    launched0, replayed0, began = evaluator.launched, evaluator.replayed, time.perf_counter()
    space = parameter_space(evaluator)
    x = _to_x(space, start)
    p = len(x)

    def residuals(record: dict) -> np.ndarray | None:
        return np.asarray(record["outputs"]["residuals"]) if record["status"] == OK else None

    current = evaluator(_from_x(space, x))
    r = residuals(current)
    if r is None:
        raise RuntimeError(f"the engine failed at the start point {list(start)}: {current['message']}")
    chi2, history = float(r @ r), [float(current["cost"])]
    accepted_chi2 = [chi2]
    evaluations, converged, message, iteration = 1, False, "maximum number of iterations reached", 0
    J = None
    for iteration in range(1, max_iterations + 1):
        J, missing = jacobian_in_x(evaluator, current, x, steps_into_box(space, x), tag="lm-jacobian",
                                   label=f"LM Jacobian {iteration}")
        evaluations += len(missing)
        pairs = _sum_only_directions(evaluator, _from_x(space, x))[1]
        if space is not None:   # a pair one of whose members is on the box's edge steps apart: the box holds that one
            edge = np.isclose(x, space.to_x(space.lower), atol=1e-9) | np.isclose(x, space.to_x(space.upper), atol=1e-9)
            pairs = [(i, j) for i, j in pairs if not (edge[i] or edge[j])]
        basis = _step_basis(p, pairs, _from_x(space, x))
        # the step's room: the trust region (MAX_LM_STEP in every x) within the search box, as bounds on the
        # coordinates z of step = basis z (each column of the basis is >= 0, so a bound on z is the tightest of its
        # parameters')
        low, high = np.full(p, -MAX_LM_STEP), np.full(p, MAX_LM_STEP)
        if space is not None:
            low, high = np.maximum(low, space.to_x(space.lower) - x), np.minimum(high, space.to_x(space.upper) - x)
        spans = np.where(basis > 0, 1.0, np.nan) / np.where(basis > 0, basis, 1.0)
        z_low, z_high = np.nanmax(low[:, None] * spans, axis=0), np.nanmin(high[:, None] * spans, axis=0)
        improved = False
        while lam < 1e12:
            step = basis @ _damped_step(J @ basis, r, lam, z_low, z_high)
            trial = evaluator(_from_x(space, x + step))
            evaluations += 1
            r_trial = residuals(trial)
            trial_chi2 = float(r_trial @ r_trial) if r_trial is not None else np.inf
            if trial_chi2 < chi2:
                relative_drop = (chi2 - trial_chi2) / max(chi2, 1e-300)
                x, r, chi2, current, lam, improved = x + step, r_trial, trial_chi2, trial, max(lam / 3.0, 1e-12), True
                history.append(float(current["cost"]))
                break
            lam *= 4.0
        if not improved:
            converged, message = True, "no step lowers the misfit (at a minimum to engine precision)"
            break
        if np.max(np.abs(step)) < xtol or relative_drop < ftol:
            converged, message = True, "step or misfit change below tolerance"
            break
        accepted_chi2.append(chi2)
        if (len(accepted_chi2) > STALL_ITERATIONS and accepted_chi2[-1 - STALL_ITERATIONS] - chi2
                < STALL_CHI2 * chi2 / max(len(r) - p, 1)):
            converged, message = True, (f"chi^2 fell by less than {STALL_CHI2:g} of its variance per degree of "
                                        f"freedom over {STALL_ITERATIONS} iterations (stalled)")
            break
    # the last Jacobian, at the fit or one step before it: the curvature that sets the step sets the error too
    return FitResult("levenberg-marquardt", list(map(float, start)), _from_x(space, x).tolist(), float(current["cost"]),
                     iteration, evaluations, evaluator.launched - launched0, evaluator.replayed - replayed0,
                     time.perf_counter() - began, converged, message, history,
                     [] if J is None else [float(e) if np.isfinite(e) else None
                                           for e in linearised_standard_errors(J, chi2, len(r) - p)])


def interval_identifiable(lower, upper, value, linear, half_width: float = IDENTIFIABLE_HALF_WIDTH
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(relative half width, identifiable) of each parameter's interval [lower, upper] about its value: identifiable
    when the half width is at most `half_width` of the value; an additive effect parameter (`linear`) has no
    relative width, and is identifiable when its interval excludes zero. An unbounded interval is neither."""
    lower, upper, value = (np.asarray(v, float) for v in (lower, upper, value))
    half = (upper - lower) / (2.0 * np.maximum(np.abs(value), 1e-300))
    return half, np.where(linear, (lower > 0) | (upper < 0), half <= half_width)


def linearised_standard_errors(jacobian: np.ndarray, chi2: float, dof: int) -> np.ndarray:
    """(p,) sqrt(diag (J^T J)^-1) of whitened residuals (r.r = chi^2, J = dr/dx): the standard error of each x at a
    least-squares fit, times s = sqrt(chi^2 / dof) where that exceeds 1 (the residual's own variance, as the noise
    Monte-Carlo inflates it where the model lacks something). A direction the data do not see (an eigenvalue of
    J^T J below 1e-12 of the largest) gives its parameters an infinite error rather than the pseudo-inverse's zero."""
    information = jacobian.T @ jacobian
    eigenvalues, vectors = np.linalg.eigh(information)
    seen = eigenvalues > 1e-12 * max(float(eigenvalues.max()), 1e-300)
    variance = (vectors[:, seen] ** 2) @ (1.0 / eigenvalues[seen])
    variance[np.any(np.abs(vectors[:, ~seen]) > 1e-6, axis=1)] = np.inf
    return np.sqrt(variance * max(1.0, chi2 / max(dof, 1)))


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
    best: list[float]
    best_cost: float
    threshold: float
    draws: int
    failed: int
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
    wall_time_s: float

    def as_dict(self) -> dict:
        return asdict(self)


def monte_carlo(evaluator: Evaluator, names: Sequence[str], best: Sequence[float], best_cost: float, *,
                draws: int = 400, threshold: float | None = None, threshold_factor: float = 1.5, seed: int = 0,
                max_factor: float = MAX_EXPLORED_FACTOR) -> MonteCarloResult:
    """Monte-Carlo intervals around an identified point (Avril et al. sec. 2.2.6).

    1. Profiles: the misfit along each parameter axis through `best`, at best * max_factor**s for
       s in PROFILE_OFFSETS (one parallel batch); the box of the draws reaches, on each side, 1.5 times
       the first offset whose misfit exceeds the threshold (at most max_factor).
    2. `draws` log-uniform draws in that box (one parallel batch); those with misfit <= threshold
       are kept, and their ranges (with the kept profile points) are the intervals.
    A parameter is poorly identified when its kept values span more than POORLY_IDENTIFIED_RATIO
    (upper / lower) or reach the edge of the explored range (best * max_factor**+-1).
    """
    began = time.perf_counter()
    best = np.asarray(best, float)
    space = parameter_space(evaluator)
    if space is not None and any(space.linear):
        raise ValueError("Monte-Carlo intervals are drawn in ln(theta) around positive constants; the effect "
                         f"parameters {[n for n, lin in zip(space.names, space.linear) if lin]} are additive: "
                         "fix them at their identified values (a model with fixed_effects) before `calfit montecarlo`")
    threshold = float(threshold if threshold is not None else threshold_factor * best_cost)
    p = len(best)
    span = np.log(max_factor)
    offsets = PROFILE_OFFSETS * span
    profile_thetas = [best * np.exp(offset * np.eye(p)[j]) for j in range(p) for offset in offsets]
    profile = evaluator.evaluate(profile_thetas, tag="profile", label="profiles")
    profile_costs = np.array([_cost(rec) for rec in profile]).reshape(p, len(offsets))
    box_low, box_high = np.empty(p), np.empty(p)
    for j in range(p):
        below = [o for o, c in zip(offsets, profile_costs[j]) if o < 0 and c > threshold]
        above = [o for o, c in zip(offsets, profile_costs[j]) if o > 0 and c > threshold]
        box_low[j] = max(1.5 * max(below), -span) if below else -span
        box_high[j] = min(1.5 * min(above), span) if above else span
    rng = np.random.default_rng(seed)
    logs = np.log(best) + box_low + (box_high - box_low) * rng.random((draws, p))
    thetas = np.exp(logs)
    records = evaluator.evaluate(thetas.tolist(), tag="monte-carlo", label="Monte-Carlo")
    costs = np.array([_cost(rec) for rec in records])
    all_thetas = np.vstack([thetas, np.array(profile_thetas), best[None, :]])
    all_costs = np.concatenate([costs, profile_costs.ravel(), [best_cost]])
    kept = all_costs <= threshold
    lower, upper = all_thetas[kept].min(axis=0), all_thetas[kept].max(axis=0)
    edge = (np.log(upper / best) >= span * 0.999) | (np.log(best / lower) >= span * 0.999)
    poorly = [name for name, ratio, at_edge in zip(names, upper / lower, edge)
              if ratio > POORLY_IDENTIFIED_RATIO or at_edge]
    failures = [{"theta": rec["theta"], "status": rec["status"], "message": rec["message"]}
                for rec in profile + records if rec["status"] != OK]
    return MonteCarloResult(list(names), best.tolist(), float(best_cost), threshold, draws, len(failures),
                            (best * np.exp(box_low)).tolist(), (best * np.exp(box_high)).tolist(), lower.tolist(),
                            upper.tolist(), ((lower + upper) / 2).tolist(), int(kept[:draws].sum()), poorly,
                            thetas.tolist(), [None if not np.isfinite(c) else float(c) for c in costs], failures,
                            time.perf_counter() - began)


@dataclass
class NoiseMonteCarloResult:
    """Parameter intervals from refits of the identification to synthetic data sets (`noise_monte_carlo`)."""

    names: list[str]
    best: list[float]
    draws: int
    failed: int
    inflation: float                 # the noise's variance factor: chi^2 / (n - p - k) when above 1, else 1
    confidence: float
    lower: list[float]
    upper: list[float]
    central: list[float]
    relative_half_width: list[float]
    identifiable: list[bool]
    poorly_identified: list[str]
    on_bound: list[str]
    samples: list[list[float]]
    engine_runs: int
    wall_time_s: float
    method: str = "noise"
    undetermined: list[str] = field(default_factory=list)   # in a direction the data do not fix: interval = box
    # pairs that act only through their sum (forward.LegModel.sum_only): the sum's value and interval
    sums: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def _engine_or_fd_jacobian(evaluator: Evaluator, record: dict, space, x: np.ndarray) -> np.ndarray:
    """dr/dx at x: the engine's sensitivities, forward differences (FD_STEP) for the columns it does not give."""
    try:
        return jacobian_in_x(evaluator, record, x, steps_into_box(space, x), tag="mc-jacobian",
                             label="Monte-Carlo Jacobian")[0]
    except RuntimeError as error:
        raise RuntimeError(f"at the identified point: {error}") from None


def _free_directions(J: np.ndarray, noise_scale: float, width_x: np.ndarray, identifiable_half_width: float,
                     structural: Sequence[np.ndarray] = ()) -> tuple[np.ndarray, np.ndarray]:
    """The directions of x that the data fix, and the parameters that they do not.

    A right singular vector v_i of J is free when the 95 % noise spread along it, 2 noise_scale / s_i, is longer
    than the box across in that direction (sum_j |v_ij| width_j, wherever the fit lies in it): the misfit is flat
    to within the noise across the whole box (C10 and C01 of an incompressible tissue in plane strain, which act
    only through their sum), and a Gauss-Newton step along it amplifies the noise by 1 / s_i and sends the draws
    to the box's corners. `structural`: unit directions of x known to leave the model unchanged (`sum_only`),
    taken out of J first, so that a finite-difference Jacobian's noise along them cannot pass for information. A
    parameter is undetermined when a free direction spreads it over more than twice the identifiable half width
    (in x: a relative change for the constants). Returns ((p, k) orthonormal fixed directions, (p,) bool
    undetermined)."""
    _, singular, vt = np.linalg.svd(_without(J, structural), full_matrices=False)
    spread = 2.0 * noise_scale / np.maximum(singular, 1e-300)
    free = spread > np.abs(vt) @ width_x
    undetermined = np.any(free[:, None] & (np.abs(vt) * spread[:, None] > 2.0 * identifiable_half_width), axis=0)
    return vt[~free].T, undetermined


def _without(a: np.ndarray, directions: Sequence[np.ndarray]) -> np.ndarray:
    """a (a Jacobian, rows over x, or a step in x) without its parts along orthonormal directions of x."""
    for direction in directions:
        a = a - np.multiply.outer(a @ direction, direction)
    return a


def _step_basis(p: int, pairs: Sequence[tuple[int, int]], theta: np.ndarray) -> np.ndarray:
    """Columns that span the steps in x = ln theta which leave every sum-only pair's split alone: a unit column per
    parameter, one column (a, b)/|(a, b)| for a pair (a, b) (the normal of its flat direction (b, -a))."""
    merged = {j for _, j in pairs}
    columns = []
    for k in range(p):
        if k in merged:
            continue
        column = np.zeros(p)
        column[k] = 1.0
        for i, j in pairs:
            if i == k:
                column[j] = theta[j] / theta[i]
        columns.append(column / np.linalg.norm(column))
    return np.column_stack(columns)


def _sum_only_directions(evaluator: Evaluator, best: np.ndarray) -> tuple[list[np.ndarray], list[tuple[int, int]]]:
    """The model's pairs of parameters that act only through their sum, as unit directions of x at `best` (x = ln
    theta: d(a + b) = a dx_a + b dx_b = 0 along (b, -a)) and as index pairs."""
    names = list(getattr(getattr(evaluator.model, "space", None), "names", ()))
    pairs = [(names.index(a), names.index(b)) for a, b in getattr(evaluator.model, "sum_only", ())
             if a in names and b in names]
    directions = []
    for i, j in pairs:
        direction = np.zeros(len(best))
        direction[i], direction[j] = best[j], -best[i]
        directions.append(direction / np.linalg.norm(direction))
    return directions, pairs


def noise_monte_carlo(evaluator: Evaluator, best: Sequence[float], *, draws: int = NOISE_DRAWS,
                      confidence: float = 0.95, nuisance_dof: int = 0, seed: int = 0,
                      identifiable_half_width: float = IDENTIFIABLE_HALF_WIDTH) -> NoiseMonteCarloResult:
    """Monte-Carlo intervals over the measurement noise (a parametric bootstrap).

    The residual is whitened, r = C^-1/2 (O u(theta) - d), so a synthetic data set d_k = O u(theta_hat) + C^1/2 e_k
    with e_k ~ N(0, s^2 I) (the noise the measurements' covariance describes, overlaps of DIC windows and the
    model's geometry uncertainty included) has the residual r_k(theta) = r(theta) - r(theta_hat) - e_k: refitting
    it needs no new data, only r at new theta. Each draw is refitted by two Gauss-Newton steps in x (ln theta
    for constants): the first on the Jacobian at theta_hat, the second at the point it reaches (one engine run
    per draw, with the engine's sensitivities; their batch runs in parallel). s^2 = chi^2 / (n - p - k) when the
    fit is above its floor (the remaining misfit counted as noise, the usual inflation), 1 otherwise. The
    intervals are the central `confidence` quantiles of the refitted draws; a parameter is identifiable when
    its interval's half width is at most `identifiable_half_width` of its value, and reported as on a bound when
    a fifth of its draws end on the box's edge. Directions of x that the data do not fix (`_free_directions`) are
    left out of the refits; a parameter they move is `undetermined`: not identifiable, its interval the whole box.
    Pairs that the model says act only through their sum are among those directions, whatever J says, and their
    sum's interval is reported (`sums`)."""
    if draws < MIN_NOISE_DRAWS:
        raise ValueError(f"the noise Monte-Carlo needs at least {MIN_NOISE_DRAWS} draws for its quantiles, not "
                         f"{draws}: ask for more (--draws {MIN_NOISE_DRAWS} or above)")
    began = time.perf_counter()
    launched0 = evaluator.launched
    space = parameter_space(evaluator)
    best = np.asarray(best, float)
    x_hat = _to_x(space, best)
    record = evaluator(best)
    if record["status"] != OK:
        raise RuntimeError(f"the engine failed at the identified point: {record['message']}")
    r_hat = np.asarray(record["outputs"]["residuals"], float)
    J = _engine_or_fd_jacobian(evaluator, record, space, x_hat)
    n, p = J.shape
    inflation = max(1.0, float(r_hat @ r_hat) / max(n - p - nuisance_dof, 1))
    noise = np.sqrt(inflation) * np.random.default_rng(seed).standard_normal((draws, n))
    box_low = np.array(space.lower) if space is not None else np.full(p, -np.inf)
    box_high = np.array(space.upper) if space is not None else np.full(p, np.inf)
    width_x = _to_x(space, box_high) - _to_x(space, box_low) if space is not None else np.full(p, np.inf)
    structural, pairs = _sum_only_directions(evaluator, best)
    basis, undetermined = _free_directions(J, np.sqrt(inflation), width_x, identifiable_half_width, structural)

    def refit_step(jacobian: np.ndarray, residuals: np.ndarray) -> np.ndarray:
        """argmin |J dx - residual| over dx in the determined directions, one column per residual column."""
        coefficients, *_ = np.linalg.lstsq(jacobian @ basis, residuals, rcond=None)
        return basis @ coefficients

    steps = refit_step(J, noise.T)                                    # (p, draws)
    x_first = x_hat[None, :] + steps.T
    thetas = [_from_x(space, x).tolist() for x in x_first]
    records = evaluator.evaluate(thetas, tag="noise-mc", label="noise Monte-Carlo")
    samples, failed = [], 0
    for k, rec in enumerate(records):
        if rec["status"] != OK:
            failed += 1
            continue
        x_k = _to_x(space, thetas[k])
        residual = np.asarray(rec["outputs"]["residuals"], float) - r_hat - noise[k]
        J_k = _engine_or_fd_jacobian(evaluator, rec, space, x_k)
        samples.append(_from_x(space, x_k + refit_step(J_k, -residual)))
    if len(samples) < max(MIN_NOISE_DRAWS, draws // 2):
        raise RuntimeError(f"the noise Monte-Carlo lost {failed} of {draws} draws to engine failures")
    samples = np.array(samples)
    tail = 50.0 * (1.0 - confidence)
    lower, upper = np.percentile(samples, [tail, 100.0 - tail], axis=0)
    lower, upper = np.where(undetermined, box_low, lower), np.where(undetermined, box_high, upper)
    central = np.median(samples, axis=0)
    linear = np.array(space.linear) if space is not None else np.zeros(p, bool)
    half, identifiable = interval_identifiable(lower, upper, best, linear, identifiable_half_width)
    identifiable &= ~undetermined
    names = list(space.names) if space is not None else [f"theta{j}" for j in range(p)]
    edge = np.mean(np.isclose(samples, box_low) | np.isclose(samples, box_high), axis=0) >= 0.2
    sums = []
    for i, j in pairs:   # what the data do fix of a pair that acts only through its sum
        total = samples[:, i] + samples[:, j]
        low, high = np.percentile(total, [tail, 100.0 - tail])
        value = best[i] + best[j]
        sums.append({"names": [names[i], names[j]], "value": float(value), "lower": float(low), "upper": float(high),
                     "identifiable": bool((high - low) / (2.0 * value) <= identifiable_half_width)})
    return NoiseMonteCarloResult(names, best.tolist(), draws, failed, inflation, confidence, lower.tolist(),
                                 upper.tolist(), central.tolist(), half.tolist(), identifiable.tolist(),
                                 [nm for nm, ok in zip(names, identifiable) if not ok],
                                 [nm for nm, e in zip(names, edge) if e], samples.tolist(),
                                 evaluator.launched - launched0, time.perf_counter() - began,
                                 undetermined=[nm for nm, u in zip(names, undetermined) if u], sums=sums)


@dataclass
class PressureStatistics:
    """Landmark pressures (kPa) over draws in the intervals (Table 3) and with the tension +-10 % (Table 4).

    std_kPa is the parameters' share alone. The tension's uncertainty (tension_rel, one standard deviation) moves the
    pressure by tension_std_kPa = (plus - minus) / 2, the central difference of Table 4; total_std_kPa adds the two
    in quadrature (independent sources): the spread a designer quotes. On the phantom leg the parameters give
    0.001-0.004 kPa and the tension 0.25 kPa."""

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
    tension_std_kPa: list[float]
    total_std_kPa: list[float]
    samples_kPa: list[list[float]]
    wall_time_s: float

    def as_dict(self) -> dict:
        return asdict(self)


def pressure_spreads(pressures: dict) -> tuple[list[float], list[float], list[float]]:
    """(parameters' std, tension's std, both in quadrature) of each landmark's pressure, kPa
    (`PressureStatistics`; computed from Table 4 for a pressures.json written before they were kept)."""
    parameters = np.asarray(pressures["std_kPa"], float)
    tension = np.asarray(pressures.get("tension_std_kPa")
                         or np.abs(np.subtract(pressures["plus_kPa"], pressures["minus_kPa"])) / 2.0, float)
    return parameters.tolist(), tension.tolist(), np.hypot(parameters, tension).tolist()


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
    tension_std = np.abs(plus - minus) / 2.0
    return PressureStatistics(list(landmarks), draws, len(failed), mean.tolist(), std.tolist(),
                              (100 * std / np.abs(mean)).tolist(), base.tolist(), tension, tension_rel, plus.tolist(),
                              minus.tolist(), (100 * (plus - base) / np.abs(base)).tolist(),
                              (100 * (base - minus) / np.abs(base)).tolist(), tension_std.tolist(),
                              np.hypot(std, tension_std).tolist(), samples.tolist(), time.perf_counter() - began)
