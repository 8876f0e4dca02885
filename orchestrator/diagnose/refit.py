"""Refit. `refit` identifies again with the effect's parameters free (Levenberg-Marquardt from the fitted
point, effect at zero) and compares misfit, AIC = chi^2 + 2k and BIC = chi^2 + k ln n (known sigma:
-2 ln L = chi^2 + const) before and after, so that an effect that does not pay for its parameters is
seen not to.

The refitted model's 95 % intervals are linearized at its fit (`linearized_intervals`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy import stats

from ..engine.results import OK
from ..fit.identify import FitResult, interval_identifiable, levenberg_marquardt
from ..model.effects import effect
from ..model.forward import LegModel
from .candidates import FRICTION_PROBE_MU, garment_model, with_changes
from .maps import level_misfits
from .score import ALPHA, information_criteria, residuals_of

REFIT_FTOL = 1e-5            # LM stops when chi^2 falls by less than this fraction (a useless effect crawls)



@dataclass
class Refit:
    effects: list[str]
    parameters: list[str]
    theta: list[float]
    misfit: float
    misfit_over_floor: float
    chi2: float
    aic: float
    bic: float
    fit: dict
    levels: list[dict] = field(default_factory=list)   # several socks: each level's misfit (`level_misfits`)
    # the misfit against the floor with the skin's uncertainty estimated again at this refit's parameters (DIC data;
    # the identification estimated it at the baseline fit's): {"misfit", "misfit_over_floor"}, or None
    own_floor: dict | None = None
    # 95 % intervals of the parameters linearized at this fit (`linearized_intervals`), None without a Jacobian
    intervals: dict | None = None
    # where groups carry their own materials (heterogeneity, a patch): C10 in kPa by tissue and quarter of the leg
    # (`heterogeneity.stiffness_field_kpa`), None otherwise
    stiffness_field: dict | None = None

    def as_dict(self) -> dict:
        return asdict(self)

    def parameter_text(self) -> str:
        """name = value for each parameter, with its 95 % interval when the fit has one; a parameter whose interval
        is wider than identify's identifiability rule is marked: the refit moves it, the data do not fix it."""
        if not self.intervals:
            return ", ".join(f"{n}={v:.4g}" for n, v in zip(self.parameters, self.theta))
        def bound(value: float | None, side: str) -> str:   # None: a direction the data do not see
            return f"{side} unbounded" if value is None else f"{value:.4g}"

        return ", ".join(f"{n}={v:.4g} [{bound(low, 'below')}, {bound(high, 'above')}]"
                         f"{'' if ok else ' not identifiable'}"
                         for n, v, low, high, ok in zip(self.parameters, self.theta, self.intervals["lower"],
                                                        self.intervals["upper"], self.intervals["identifiable"]))



def linearized_intervals(model: LegModel, theta: Sequence[float], standard_error_x: Sequence[float | None],
                         confidence: float = 0.95) -> dict | None:
    """The parameters' intervals at a least-squares fit from the standard errors of x (ln theta, or theta / scale
    for an additive effect parameter; `identify.linearised_standard_errors`: sqrt(diag (J^T J)^-1), inflated by the
    residual's chi^2 / dof where that exceeds 1). Identifiable as `identify.noise_monte_carlo` says it
    (`identify.interval_identifiable`); a direction the data do not see gives an unbounded interval. A
    refit has no Monte-Carlo of its own; this says which of its numbers the data fix (a parameter that trades with
    the effect just added can move far with little change of the misfit)."""
    if standard_error_x is None or len(standard_error_x) == 0 or len(standard_error_x) != len(theta):
        return None
    space = model.space
    z = float(stats.norm.ppf(0.5 + confidence / 2.0))
    x = space.to_x(theta)
    se = np.array([np.inf if e is None else float(e) for e in standard_error_x])
    seen = np.isfinite(se)
    lower = np.where(seen, space.from_x(x - z * np.where(seen, se, 0.0)), -np.inf)
    upper = np.where(seen, space.from_x(x + z * np.where(seen, se, 0.0)), np.inf)
    half, identifiable = interval_identifiable(lower, upper, theta, np.array(space.linear))
    finite = lambda values: [float(v) if np.isfinite(v) else None for v in values]   # noqa: E731 (JSON has no inf)
    return {"confidence": confidence, "lower": finite(lower), "upper": finite(upper),
            "relative_half_width": finite(half), "identifiable": [bool(v) for v in identifiable],
            "not_identifiable": [n for n, ok in zip(space.names, identifiable) if not ok],
            "method": "linearized at the fit: sqrt(diag (J^T J)^-1) of the whitened residual, inflated by chi^2/dof "
                      "where above 1"}



def refit_model(model: LegModel, effects: Sequence[str]) -> LegModel:
    """The model that `refit` fits with these effects added: the catalog's in its deck, the garment's (friction,
    bridging) by switching it to the band (`garment_model`); the model itself without any."""
    if not effects:
        return model
    garment = [name for name in effects if effect(name).apply is None]
    others = tuple(name for name in effects if name not in garment)
    extended = with_changes(model, effects=model.effects + others)
    return garment_model(extended, garment) if garment else extended



def refit(evaluator_factory, model: LegModel, theta: Sequence[float], effects: Sequence[str], objective, *,
          max_iterations: int = 25) -> tuple[Refit, np.ndarray]:
    """`refit_whitened`, its residual as u_model - u_measured (mm) at the points."""
    summary, r = refit_whitened(evaluator_factory, model, theta, effects, objective, max_iterations=max_iterations)
    return summary, objective.residual_mm(r)


def refit_whitened(evaluator_factory, model: LegModel, theta: Sequence[float], effects: Sequence[str], objective, *,
                   max_iterations: int = 25, effect_start: Sequence[float] | None = None) -> tuple[Refit, np.ndarray]:
    """Levenberg-Marquardt with the effects' parameters free (starting at zero), from the fitted theta and, unless
    that fit settled (`settled`), from the usual start (Avril et al. Table 2 central values); the better fit is kept.
    The second start matters when the missing effect dragged the baseline fit to a bound or far from the tissue's
    values; after a fit at the noise floor with no parameter on a bound it could only move chi^2 within the noise
    (with friction, refits from two starts took 110 of a diagnosis's 123 runs).
    effect_start: the effects' parameters' start in place of zero (a neighbour's fit of the same effect).
    Returns the fit and its whitened residual r (`objectives.DisplacementResidualObjective.weigh`)."""
    extended = refit_model(model, effects)
    # friction starts where the diagnosis probed it: at mu = 0 the friction forces vanish with their derivative's
    # one-sided difference, and Levenberg-Marquardt may not leave the bound
    extra = [(model.friction_mu or FRICTION_PROBE_MU) if name == "mu" else 0.0
             for name in extended.space.names[model.space.size:]]
    if effect_start is not None:
        extra = [float(v) for v in effect_start]
    starts = [list(map(float, theta)) + extra, model.start() + extra]
    with evaluator_factory(extended) as evaluator:
        fits = [levenberg_marquardt(evaluator, starts[0], max_iterations=max_iterations, ftol=REFIT_FTOL)]
        if not settled(extended, evaluator(fits[0].theta), objective):
            fits.append(levenberg_marquardt(evaluator, starts[1], max_iterations=max_iterations, ftol=REFIT_FTOL))
        fit = min(fits, key=lambda f: f.cost)
        record = evaluator(fit.theta)
    # named by the effects asked for: the garment's band model lists none (bridging) or friction alone
    summary = replace(summarize_fit(extended, fit, record, objective), effects=list(model.effects) + list(effects))
    return summary, residuals_of(record)


def settled(model: LegModel, record: dict, objective, alpha: float = ALPHA) -> bool:
    """A fit that another start cannot better but within the noise: its chi^2 not above the noise's (the lack-of-fit
    test at `alpha`) and no parameter on its search box's edge."""
    if record["status"] != OK:
        return False
    r = residuals_of(record)
    p = model.space.size
    if stats.chi2.sf(float(r @ r), len(r) - p - objective.nuisance_dof) < alpha:
        return False
    theta = np.asarray(record["theta"], float)
    return not np.any(np.isclose(theta, model.space.lower) | np.isclose(theta, model.space.upper))



def summarize_fit(model: LegModel, fit: FitResult, record: dict, objective) -> Refit:
    r = residuals_of(record)
    chi2 = float(r @ r)
    criteria = information_criteria(chi2, model.space.size, len(r))
    floor = objective.noise_floor(model.space.size)
    return Refit(list(model.effects), list(model.space.names), list(fit.theta), float(record["cost"]),
                 float(record["cost"]) / floor, chi2, criteria["aic"], criteria["bic"], fit.as_dict(),
                 level_misfits(objective, r, model.space.size),
                 intervals=linearized_intervals(model, fit.theta, fit.standard_error_x))
