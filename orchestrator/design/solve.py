"""The garment that meets the targets: Levenberg-Marquardt on the tension per height (and the profile's
coefficients) within the fabric's feasible range.

The unknowns are, slice by slice, T (N/mm) and with harmonics the profile's a_k, b_k (`slices`). The residuals, in
mmHg:

- a target with an aim (a value, or a class's middle) r = q - aim;
- a minimum r = max(0, min + margin - q), a maximum r = max(0, q - max + margin): zero once met with the margin,
  which is z(probability) times the quantity's standard deviation over the parameters' draws and the tension's
  uncertainty (`uncertainty`; 0 on the first pass);
- with the graduation (RAL-GZ 387/1, `standards`), between neighbouring slices r = max(0, p_upper - p_lower + margin)
  on the skin's mean pressure, and at D r = max(0, p_D - 0.7 p_B + margin), the margins those differences' own;
- weak terms that choose among garments meeting everything alike: T towards the fabric's lowest tension (the
  lightest garment that meets a minimum; ECONOMY_WEIGHT leaves a minimum short by about ECONOMY_WEIGHT^2 T / (dq/dT),
  1e-3 mmHg on a calf), the profile's coefficients towards 0 (a uniform knit) and, along a volume, T's second
  difference towards 0 (a smooth tension where no target holds it).

The Jacobian is the engine's (`slices.evaluate`: d/dT and d/da_k of every quantity, the chain rule for the
hinges), block by block, since a slice's pressures depend on its own garment only. A step is the damped
Gauss-Newton step (J'J + lambda diag(J'J)) dv = -J'r projected into the bounds; it is taken when the cost falls,
and lambda shrinks, else lambda grows. The result says whether every target is met at the identified parameters:
when not, no garment within the bounds meets them, and the design returned is the closest one (the least-squares
point within the bounds) with each target's shortfall."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .standards import BELOW_KNEE_SHARE_MAX
from .targets import Target, Targets

ECONOMY_WEIGHT = 1.0          # mmHg of residual per N/mm above the fabric's lowest tension
PROFILE_WEIGHT = 2.0          # mmHg of residual per unit of a profile coefficient: prefer a uniform knit
SMOOTHNESS_WEIGHT = 20.0      # mmHg per N/mm of T's second difference along the leg
MAX_ITERATIONS = 20
STEP_TOLERANCE = 1e-4         # N/mm (and profile units): the last step's size at convergence


@dataclass
class Problem:
    """The slices, the targets and what each applies to; `evaluator(slice index, T, profile)` -> `Response`."""

    targets: Targets
    n_slices: int
    heights: list[str | None]          # each slice's named height
    evaluator: Callable
    harmonics: int = 0
    margins: dict = field(default_factory=dict)    # (target index, slice) -> mmHg
    workers: int = 1

    @property
    def n_profile(self) -> int:
        return 2 * self.harmonics

    @property
    def per_slice(self) -> int:
        return 1 + self.n_profile

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low, high = self.targets.design.tension_range_N_per_mm
        p = self.targets.design.profile_max
        lower = np.tile([low] + [-p] * self.n_profile, self.n_slices)
        upper = np.tile([high] + [p] * self.n_profile, self.n_slices)
        return lower, upper

    def applies(self, target: Target) -> list[int]:
        """The slices a target holds on: its named height's, else every slice."""
        if target.height is None:
            return list(range(self.n_slices))
        return [k for k, name in enumerate(self.heights) if name == target.height]

    def split(self, v: np.ndarray) -> list[tuple[float, np.ndarray]]:
        v = np.asarray(v, float).reshape(self.n_slices, self.per_slice)
        return [(float(row[0]), row[1:]) for row in v]

    def responses(self, v: np.ndarray) -> list:
        jobs = self.split(v)
        with ThreadPoolExecutor(max_workers=max(1, self.workers)) as pool:
            return list(pool.map(lambda k: self.evaluator(k, *jobs[k]), range(self.n_slices)))

    def residuals(self, v: np.ndarray, responses: list) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """(r, J, labels) at v."""
        rows, grads, labels = [], [], []
        size = self.n_slices * self.per_slice

        def add(value, gradient_by_slice: dict, label):
            g = np.zeros(size)
            for k, grad in gradient_by_slice.items():
                g[k * self.per_slice:(k + 1) * self.per_slice] += grad
            rows.append(value)
            grads.append(g)
            labels.append(label)

        for target in self.targets.targets:
            for k in self.applies(target):
                q = responses[k].value(target.kind, target.where)
                dq = responses[k].gradient(target.kind, target.where)
                margin = self.margins.get((target.index, k), 0.0)
                label = f"{target.name} [{k}]"
                if target.aim_mmHg is not None:
                    add(q - target.aim_mmHg, {k: dq}, label)
                    continue
                if target.min_mmHg is not None:
                    short = target.min_mmHg + margin - q
                    add(max(0.0, short), {k: -dq if short > 0 else 0 * dq}, label)
                if target.max_mmHg is not None:
                    over = q - target.max_mmHg + margin
                    add(max(0.0, over), {k: dq if over > 0 else 0 * dq}, label)
        if self.targets.graduated and self.n_slices > 1:
            for k in range(self.n_slices - 1):
                rise = responses[k + 1].skin_mean - responses[k].skin_mean + self.margins.get(("graduation", k), 0.0)
                active = rise > 0
                add(max(0.0, rise), {k + 1: responses[k + 1].d_skin_mean * active,
                                     k: -responses[k].d_skin_mean * active}, f"graduation [{k}->{k + 1}]")
            if "B" in self.heights and "D" in self.heights:
                b, d = self.heights.index("B"), self.heights.index("D")
                over = (responses[d].skin_mean - BELOW_KNEE_SHARE_MAX * responses[b].skin_mean
                        + self.margins.get(("below knee", 0), 0.0))
                active = over > 0
                add(max(0.0, over), {d: responses[d].d_skin_mean * active,
                                     b: -BELOW_KNEE_SHARE_MAX * responses[b].d_skin_mean * active}, "D <= 0.7 B")
        lowest = self.targets.design.tension_range_N_per_mm[0]
        for k, (tension, profile) in enumerate(self.split(v)):
            unit = np.zeros(self.per_slice)
            unit[0] = ECONOMY_WEIGHT
            add(ECONOMY_WEIGHT * (tension - lowest), {k: unit}, f"economy [{k}]")
            for j, c in enumerate(profile):
                g = np.zeros(self.per_slice)
                g[1 + j] = PROFILE_WEIGHT
                add(PROFILE_WEIGHT * c, {k: g}, f"profile [{k}]")
        if self.n_slices > 2:
            tension = np.array([t for t, _ in self.split(v)])
            for k in range(1, self.n_slices - 1):
                unit = np.zeros(self.per_slice)
                unit[0] = 1.0
                add(SMOOTHNESS_WEIGHT * (tension[k - 1] - 2 * tension[k] + tension[k + 1]),
                    {k - 1: SMOOTHNESS_WEIGHT * unit, k: -2 * SMOOTHNESS_WEIGHT * unit,
                     k + 1: SMOOTHNESS_WEIGHT * unit}, f"smoothness [{k}]")
        return np.array(rows, float), np.array(grads, float).reshape(len(rows), size), labels


@dataclass
class Solution:
    v: list[float]
    cost: float
    iterations: int
    engine_runs: int
    converged: bool
    history: list[dict]
    wall_time_s: float
    responses: list = field(default_factory=list, repr=False)


def levenberg_marquardt(problem: Problem, start: Sequence[float], *, max_iterations: int = MAX_ITERATIONS,
                        say: Callable[[str], None] | None = None) -> Solution:
    """The bounded LM of the module text from `start`."""
    began = time.perf_counter()
    lower, upper = problem.bounds()
    v = np.clip(np.asarray(start, float), lower, upper)
    responses = problem.responses(v)
    runs = problem.n_slices
    r, J, _ = problem.residuals(v, responses)
    cost = 0.5 * float(r @ r)
    lam, history, converged, iteration = 1e-3, [{"v": v.tolist(), "cost": cost}], False, 0
    for iteration in range(1, max_iterations + 1):
        if cost < 1e-10:
            converged = True
            break
        A = J.T @ J
        g = J.T @ r
        step_taken = False
        for _ in range(8):
            damping = lam * np.diag(np.diag(A)) + 1e-12 * np.eye(len(v))
            try:
                step = np.linalg.solve(A + damping, -g)
            except np.linalg.LinAlgError:
                step = -g / (np.max(np.abs(np.diag(A))) + 1e-12)
            trial = np.clip(v + step, lower, upper)
            moved = trial - v
            if np.max(np.abs(moved)) < STEP_TOLERANCE:
                converged = True
                break
            trial_responses = problem.responses(trial)
            runs += problem.n_slices
            r_new, J_new, _ = problem.residuals(trial, trial_responses)
            cost_new = 0.5 * float(r_new @ r_new)
            if cost_new < cost:
                v, r, J, cost, responses = trial, r_new, J_new, cost_new, trial_responses
                lam = max(lam / 3.0, 1e-7)
                step_taken = True
                history.append({"v": v.tolist(), "cost": cost})
                if say:
                    say(f"design step {iteration}: cost {cost:.4g} mmHg^2, T = "
                        + ", ".join(f"{t:.4f}" for t, _ in problem.split(v)) + " N/mm")
                if np.max(np.abs(moved)) < STEP_TOLERANCE:
                    converged = True
                break
            lam *= 4.0
        if converged or not step_taken:
            converged = converged or not step_taken
            break
    return Solution(v.tolist(), cost, iteration, runs, converged, history, time.perf_counter() - began, responses)


def shortfalls(problem: Problem, responses: list) -> list[dict]:
    """Each target's value at every slice it applies to and by how much it misses (mmHg; 0 met)."""
    out = []
    for target in problem.targets.targets:
        for k in problem.applies(target):
            q = responses[k].value(target.kind, target.where)
            gap = 0.0
            if target.min_mmHg is not None:
                gap = max(gap, target.min_mmHg - q)
            if target.max_mmHg is not None:
                gap = max(gap, q - target.max_mmHg)
            out.append({"target": target.index, "name": target.name, "slice": k, "value_mmHg": q,
                        "shortfall_mmHg": gap})
    return out
