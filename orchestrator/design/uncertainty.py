"""The probability that the designed garment meets each target, over what is not known of the leg and the fabric.

The leg: the Monte-Carlo draws of the identified parameters (montecarlo.json's `samples`: refits to noise draws of
the measurements, or the accepted draws of Avril et al.'s threshold), `draws` of them evenly spaced, each solved
under the designed garment (one engine run a slice a draw, with the tension's sensitivity). The fabric: the
knitted tension is off by a relative error N(0, s) (TARGET.toml's tension_rel_uncertainty, else case.toml's), the
same all along the garment (one fabric, one knitting), taken at TENSION_DRAWS normal quantiles (a quadrature of
its distribution, not a sample) and carried to every quantity at first order by the engine's d/dT (pressure is close to linear in T on these legs: the demo's landmark pressures
change by 0.05 % of their slope between T and 1.01 T). A target is met in a (draw, tension) pair when it is met at
every slice it holds on; its probability is the share of pairs, given with the binomial standard error of the
draws: the spread of the per-draw shares over the leg's draws (the tension's quadrature adds no sampling error).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .solve import Problem
from .standards import BELOW_KNEE_SHARE_MAX

TENSION_DRAWS = 400
DEFAULT_DRAWS = 20


@dataclass
class Spread:
    """Per (target index, slice): the quantity's values over the pairs (mmHg); per target: the probability."""

    values: dict
    probability: dict
    probability_se: dict
    graduation_probability: float | None
    draws: int
    tension_rel: float
    engine_runs: int

    def std(self, key) -> float:
        return float(np.std(self.values[key], ddof=1))


def draw_subset(samples: list, draws: int) -> list:
    if len(samples) <= draws:
        return list(samples)
    return [samples[int(i)] for i in np.linspace(0, len(samples) - 1, draws).round()]


def spread(problem: Problem, slices: list, v, *, draws: int = DEFAULT_DRAWS, tension_rel: float,
           evaluate=None, workers: int = 1) -> Spread:
    """The quantities over the draws and the tension's error at design v, and each target's probability."""
    from .slices import evaluate as engine_evaluate

    evaluate = evaluate or engine_evaluate
    design = problem.split(v)
    subsets = [draw_subset(piece.samples, draws) for piece in slices]
    n = min(len(s) for s in subsets)
    jobs = [(k, j) for k in range(len(slices)) for j in range(n)]
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        answers = list(pool.map(lambda job: evaluate(slices[job[0]], design[job[0]][0], design[job[0]][1],
                                                     subsets[job[0]][job[1]]), jobs))
    by = {job: answer for job, answer in zip(jobs, answers)}
    from scipy.stats import norm

    # the tension's error at the normal quantiles of (i + 1/2) / TENSION_DRAWS: a quadrature of its distribution,
    # so that the probabilities carry no sampling error of their own from it
    epsilon = (tension_rel * norm.ppf((np.arange(TENSION_DRAWS) + 0.5) / TENSION_DRAWS) if tension_rel > 0
               else np.zeros(1))

    def values(k: int, pick) -> np.ndarray:
        """(draws, tension draws) of a quantity: pick(response) -> (value, d/dT)."""
        out = np.empty((n, len(epsilon)))
        for j in range(n):
            q, dq = pick(by[(k, j)])
            out[j] = q + dq * design[k][0] * epsilon
        return out

    table, probability, se = {}, {}, {}
    for target in problem.targets.targets:
        met = np.ones((n, len(epsilon)), bool)
        for k in problem.applies(target):
            q = values(k, lambda r, t=target: (r.value(t.kind, t.where), r.gradient(t.kind, t.where)[0]))
            table[(target.index, k)] = q.ravel()
            met &= target.met(q)
        per_draw = met.mean(axis=1)
        probability[target.index] = float(met.mean())
        se[target.index] = float(np.std(per_draw, ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    graduation = None
    if problem.targets.graduated and len(slices) > 1:
        skins = [values(k, lambda r: (r.skin_mean, r.d_skin_mean[0])) for k in range(len(slices))]
        ok = np.ones_like(skins[0], bool)
        for k in range(len(slices) - 1):
            table[("graduation", k)] = (skins[k] - skins[k + 1]).ravel()
            ok &= skins[k + 1] <= skins[k] + 1e-9
        if "B" in problem.heights and "D" in problem.heights:
            room = BELOW_KNEE_SHARE_MAX * skins[problem.heights.index("B")] - skins[problem.heights.index("D")]
            table[("below knee", 0)] = room.ravel()
            ok &= room >= -1e-9
        graduation = float(ok.mean())
    return Spread(table, probability, se, graduation, n, tension_rel, len(jobs) * (1 if slices[0].laplace else 2))


def margins(problem: Problem, result: Spread, probability: float) -> dict:
    """(target index, slice) -> z(probability) x the quantity's standard deviation, for the min/max targets; and
    ("graduation", k), ("below knee", 0) -> the same of the graduation's differences (the fall from slice k to the
    next, 0.7 p_B - p_D)."""
    from scipy.stats import norm

    z = float(norm.ppf(probability))
    aims = {target.index for target in problem.targets.targets if target.aim_mmHg is not None}
    out = {key: z * result.std(key) for key in result.values if isinstance(key[0], int) and key[0] not in aims}
    # the graduation holds when all its differences do: each at 1 - (1 - probability) / m (Bonferroni)
    graduation = [key for key in result.values if not isinstance(key[0], int)]
    if graduation:
        z_each = float(norm.ppf(1.0 - (1.0 - probability) / len(graduation)))
        out.update({key: z_each * result.std(key) for key in graduation})
    return out
