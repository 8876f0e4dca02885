"""The diagnosis as a loop: rank the catalog on the residual, refit, add the effect that pays, rank again on the new
residual, and go on until the model reaches its floor (forward-backward stepwise selection).

Step 0 is the identified model. At each step the catalog is ranked on the current model's residual at its fitted
theta (`diagnosis.diagnose`: the score test, design-effect corrected), and several candidates are refitted from there
(`refit.refit_whitened`), not only the best: the linear score misjudges effects far from linear (a stiffness ratio of
3 is ln 3 = 1.1 from zero; a band's response to a volume change). Refitted are the best MIN_REFITTED by score among
those whose own score is significant at alpha, every other whose statistic is at least SCORE_FRACTION of the best's,
and those the score cannot tell from the best (`EffectScore.tied_with`), at most MAX_REFITTED; beside them the best
straight cut of the muscle (`locate.locate_cuts`: a compartment behind a septum the image does not show) when its
score is significant, its line fitted by `_refine_cut` and counted as two parameters more. Of the refits, the one
with the lowest BIC is the choice, and it is added when both
  (a) its own likelihood-ratio test is significant at alpha: the drop of chi^2 from the current model divided by the
      design effect D of the current model's residual (the score's correction, `score.design_effect`: a smooth model
      error does not count as many independent pieces of evidence), against chi^2 with the effect's q degrees of
      freedom; and
  (b) its BIC is below the current model's by more than 2 ln m, m the candidates refitted: the choice among m counted,
      as a prior 1/m on each (as the choice of a patch's place, `locate`).
After an addition, every effect added before it is tried out again (backward): refitted without it, it goes when the
BIC without it is within REMOVAL_BIC of the model's or lower and the drop of chi^2 it brings (by the design effect of
the model without it) is not significant at alpha. Of several such, the one whose removal leaves the lowest BIC goes,
and the others are tried again.

The loop stops when the model an addition (or a removal) made reaches its floor: its misfit over the floor, judged
against the floor with the skin's uncertainty estimated again at its parameters when the images estimated it
(`verdict.judged_ratio`), at most FLOOR_AGREEMENT. Within it the error model agrees with the measured errors, and an
effect's own test rests on that error model being right to better than it was measured to be: inside the floor a
significant addition is as likely the error model's (or the other program's mesh and law's) structure as physics.
Measured on the foreign cases from their images alone: tension_profile was added to blind-04 at 1.16 x (p = 3e-05,
BIC lower by 4), drainage to blind-02 at 1.08 x (p = 4e-04), neither of them hidden; the true additions of those
cases came at 1.9 x and above. The identified model (step 0) is ranked whatever its misfit: that is the first turn
of the diagnosis, whose false alarms are measured (benchmarks/diagnose.py --false-alarms), and a faint effect of few
parameters that the effect's own test sees below the omnibus test is found there. The loop stops too when nothing is
significant on its residual (the ranking's best on its own score test, Bonferroni over the effects,
`diagnosis.diagnose`): "nothing significant"; when no refit is accepted; or after MAX_STEPS additions and removals.
The acceptance of a refit ((a), (b)) is what keeps the noise from adding effects above the floor.

Ties. When another refit's BIC lies within TIE_BIC of the chosen one's and it too passes (a) and (b), the data cannot
choose between them: the step says so, the verdict names both, and `final.alternatives` lists the model with the
other (effects, misfit over floor under the identified model's weights, BIC). The path goes on from the lower BIC.

Every refit runs through the run's evaluators (the run folder's log), in the same order on a second run, so a killed
diagnosis resumes without running the engine again for what it had done. Each step records the engine runs and the
wall time it took (ranking the previous model's residual, the refits, the backward refits, the floor at its fit).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from scipy import stats

from ..model.effects import CATALOG, CUT_PARAMETER
from ..model.forward import LegModel
from ..model.heterogeneity import cut_name, cut_share, is_cut, parse_cut
from ..model.regions import LegFrame
from .candidates import with_changes
from .diagnosis import Diagnosis, diagnose
from .locate import CUT_AREA, CUT_NORMALS, CUT_STEP_MM, PatchScore
from .maps import level_points
from .refit import Refit, refit_model, refit_whitened
from .score import (
    ALPHA,
    FLOOR_AGREEMENT,
    EffectScore,
    design_effect,
    neighbour_correlation,
)
from .verdict import judged_ratio

MAX_STEPS = 4            # additions and removals; two or three effects missing at once is what real legs showed
MIN_REFITTED = 3         # the best three by score are refitted at each step...
SCORE_FRACTION = 0.5     # ...and every other whose statistic is at least half the best's...
MAX_REFITTED = 5         # ...up to five refits a step
TIE_BIC = 2.0            # BIC within 2: the data cannot choose between two models (a Bayes factor under e)
REMOVAL_BIC = 2.0        # backward: an effect goes when the BIC without it is within 2 of the model's, or lower
NESTED = (("friction", "bridging"),)   # (larger, smaller): the larger's columns hold the smaller's
CUT_GEOMETRY = 2         # a cut's line: its normal's angle and its offset, fitted beside its ratio
CUT_REFINE_REFITS = 20   # the line's compass search: at most twenty refits...
CUT_REFINE_MIN_DEG = 0.9  # ...down to steps of about a degree (and 0.3 mm: the two steps are halved together)


@dataclass
class Tried:
    """A candidate refitted at a step: its likelihood-ratio test against the current model and its BIC."""

    effect: str
    dof: int
    score_statistic: float            # the ranking's (linear) statistic
    misfit_over_floor: float | None   # under the identified model's weights
    bic: float | None
    statistic: float | None           # chi^2 drop / design effect of the smaller model's residual
    p_value: float | None
    accepted: bool = False            # passes (a) and (b) (module text)
    failure: str | None = None        # the engine could not solve it somewhere
    fit: Refit | None = field(default=None, repr=False)
    residual_mm: np.ndarray | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        return {"effect": self.effect, "dof": self.dof, "score_statistic": self.score_statistic,
                "misfit_over_floor": self.misfit_over_floor, "bic": self.bic, "statistic": self.statistic,
                "p_value": self.p_value, "accepted": self.accepted, "failure": self.failure}


@dataclass
class Step:
    """A model on the path: the identified one, or one effect added to or removed from the one before."""

    step: int
    action: str                       # identified | added | removed
    effect: str | None
    effects: list[str]                # every effect in the model (the identified model's too)
    fit: Refit
    model: LegModel = field(repr=False)
    residual_mm: np.ndarray = field(repr=False)
    tried: list[Tried] = field(default_factory=list)      # the refits of the previous model that chose this one
    ties: list[str] = field(default_factory=list)         # effects whose refit was as good (BIC within TIE_BIC)
    removals_tried: list[dict] = field(default_factory=list)   # the backward refits made after this step
    dofs: dict[str, int] = field(default_factory=dict)    # each added effect's degrees of freedom, as added
    bic: float = 0.0                  # the fit's, the switch to the band counted (`counted_bic`)
    engine_runs: int = 0
    wall_time_s: float = 0.0

    @property
    def misfit_over_floor(self) -> float:
        return judged_ratio(self.fit)

    def as_dict(self) -> dict:
        intervals = self.fit.intervals or {}
        lower = intervals.get("lower") or [None] * len(self.fit.parameters)
        upper = intervals.get("upper") or [None] * len(self.fit.parameters)
        return {"step": self.step, "action": self.action, "effect": self.effect, "effects": list(self.effects),
                "misfit_over_floor": self.misfit_over_floor,
                "misfit_over_floor_identified_weights": self.fit.misfit_over_floor,
                "misfit": self.fit.misfit, "chi2": self.fit.chi2, "bic": self.bic, "aic": self.fit.aic,
                "parameters": {name: {"value": float(value), "lower95": low, "upper95": high}
                               for name, value, low, high in zip(self.fit.parameters, self.fit.theta, lower, upper)},
                "tried": [t.as_dict() for t in self.tried], "ties": list(self.ties),
                "removals_tried": list(self.removals_tried), "engine_runs": self.engine_runs,
                "wall_time_s": self.wall_time_s}


@dataclass
class Path:
    steps: list[Step]
    stopped: str                      # floor | nothing significant | not accepted | steps | no refit | not asked
    stopping: dict                    # the last, unsuccessful, attempt: its refits, engine runs and wall time
    first_tried: list[Tried] = field(default_factory=list)   # the refits of the identified model's candidates

    @property
    def final(self) -> Step:
        return self.steps[-1]

    @property
    def reached_floor(self) -> bool:
        return len(self.steps) > 1 and self.final.misfit_over_floor <= FLOOR_AGREEMENT

    def alternatives(self) -> list[dict]:
        """The models as good as the path's at some step (BIC within TIE_BIC): the step's model with the other
        effect."""
        found = []
        for k, step in enumerate(self.steps[1:], 1):
            for t in step.tried:
                if t.effect in step.ties:
                    found.append({"effects": list(self.steps[k - 1].effects) + [t.effect],
                                  "misfit_over_floor": t.misfit_over_floor, "bic": t.bic, "step": k,
                                  "instead_of": step.effect})
        return found

    def final_dict(self, doubt: bool = False) -> dict:
        """diagnosis.json's "final": the final model's effects (the identified model's too), its misfit over the floor
        and whether it explains the measurements to their floor (within FLOOR_AGREEMENT; not when `doubt`: the
        error model does not hold, or a local change fits better), the models as good as it on the way."""
        explained = self.final.misfit_over_floor <= FLOOR_AGREEMENT and not doubt
        return {"effects": list(self.final.effects), "misfit_over_floor": self.final.misfit_over_floor,
                "explained": bool(explained), "alternatives": self.alternatives(), "bic": self.final.bic,
                "stopped": self.stopped, "stopping": self.stopping}


class _Counted:
    """The run's evaluator factory, counting the engine runs of every evaluator it makes."""

    def __init__(self, factory):
        self.factory, self.evaluators = factory, []

    def __call__(self, model, **options):
        evaluator = self.factory(model, **options)
        self.evaluators.append(evaluator)
        return evaluator

    @property
    def launched(self) -> int:
        return sum(getattr(e, "launched", 0) for e in self.evaluators)


def refit_candidates(ranking: Sequence[EffectScore], alpha: float = ALPHA) -> list[str]:
    """The effects refitted at a step (module text), best score first. Of two nested effects (NESTED: friction's
    columns hold bridging's and dr/dmu) only the one the score prefers is refitted, by its p-value on its own
    degrees of freedom: the score's test between them (a band's refit is the dearest there is)."""
    scored = [s for s in ranking if s.p_value < alpha]
    dropped = set()
    for larger, smaller in NESTED:
        pair = [s for s in scored if s.effect in (larger, smaller)]
        if len(pair) == 2:   # the worse p-value goes; on a tie, the larger effect
            dropped.add(max(pair, key=lambda s: (s.p_value, s.effect == larger)).effect)
    scored = [s for s in scored if s.effect not in dropped]
    if not scored:
        return []
    best = scored[0]
    names = [s.effect for s in scored[:MIN_REFITTED]]
    names += [s.effect for s in scored[MIN_REFITTED:] if s.statistic >= SCORE_FRACTION * best.statistic]
    names += [name for name in best.tied_with if name not in names and name not in dropped]
    return names[:MAX_REFITTED]


def likelihood_ratio(chi2_smaller: float, chi2_larger: float, dof: int, deff: float) -> tuple[float, float]:
    """The likelihood-ratio statistic of the larger model against the smaller (known sigma: the drop of chi^2),
    divided by the design effect of the smaller model's residual, and its p-value on chi^2 with dof."""
    statistic = max(chi2_smaller - chi2_larger, 0.0) / max(deff, 1.0)
    return float(statistic), float(stats.chi2.sf(statistic, max(dof, 1)))


def choose_addition(current_bic: float, tried: Sequence[Tried],
                    alpha: float = ALPHA) -> tuple[Tried | None, list[Tried]]:
    """The refit with the lowest BIC when it passes (a) and (b) (module text), and those tied with it; marks each
    refit's `accepted`."""
    penalty = 2.0 * np.log(max(len(tried), 1))
    fitted = [t for t in tried if t.bic is not None]
    for t in fitted:
        t.accepted = bool(t.p_value < alpha and current_bic - t.bic > penalty)
    if not fitted:
        return None, []
    best = min(fitted, key=lambda t: t.bic)
    if not best.accepted:
        return None, []
    return best, [t for t in fitted if t is not best and t.accepted and t.bic - best.bic < TIE_BIC]


def choose_removal(current_chi2: float, current_bic: float, without: Sequence[dict],
                   alpha: float = ALPHA) -> dict | None:
    """Of the refits without an earlier-added effect ({"effect", "chi2", "bic", "dof", "design_effect"}), the one whose
    removal leaves the lowest BIC among those within REMOVAL_BIC of the model's or lower whose drop is not significant
    (module text); marks each with its statistic, p-value and `removable`."""
    for option in without:
        if option.get("bic") is None:
            option["removable"] = False
            continue
        option["statistic"], option["p_value"] = likelihood_ratio(option["chi2"], current_chi2, option["dof"],
                                                                  option["design_effect"])
        option["removable"] = bool(option["bic"] <= current_bic + REMOVAL_BIC and option["p_value"] >= alpha)
    removable = [o for o in without if o["removable"]]
    return min(removable, key=lambda o: o["bic"]) if removable else None


def counted_bic(fit: Refit, effects: Sequence[str], garment: str, n_residuals: int) -> float:
    """A fit's BIC with the switch from Laplace's law to the explicit band (bridging, friction) counted as the one
    parameter it is in the effect's test (`candidates.garment_parameters`): the band's model has no parameter for it,
    so its BIC alone would let it in for free; and a cut's line, fitted outside its model (`_refine_cut`), as the
    CUT_GEOMETRY parameters it is."""
    switched = garment == "laplace" and any(name in CATALOG and CATALOG[name].apply is None for name in effects)
    cuts = sum(1 for name in effects if is_cut(name))
    return float(fit.bic + (np.log(n_residuals) if switched else 0.0) + CUT_GEOMETRY * cuts * np.log(n_residuals))


def _theta_for(model: LegModel, fit: Refit) -> list[float]:
    """A start for `model` from a fit of another model of the same leg: each parameter by name, the model's start
    where the fit has no such parameter."""
    values = dict(zip(fit.parameters, fit.theta))
    start = model.start()
    return [float(values.get(name, default)) for name, default in zip(model.space.names, start)]


def stepwise(evaluator_factory, model: LegModel, objective, frame: LegFrame, first: Diagnosis, identified: Refit, *,
             own_floor: Callable[[Refit, np.ndarray], dict | None] | None = None, alpha: float = ALPHA,
             engine_sensitivities: bool = True, progress: bool = True, side_by_side: bool = False,
             parallel: int = 1, max_steps: int = MAX_STEPS) -> Path:
    """The forward-backward path from the identified model (module text).

    evaluator_factory(model, progress=None, workers=None) -> Evaluator, as `diagnose`'s; first: the diagnosis of the
    identified model at its theta (step 0's ranking); identified: its fit (`refit.summarize_fit`); own_floor(fit,
    residual_mm): the floor with the skin's uncertainty estimated again at a fit's parameters, or None (set as the
    accepted fits' `own_floor`); side_by_side: as `diagnose`'s; parallel: refits run at once, each in a thread with
    its own evaluator running one engine at a time, silently (a step's refits do not depend on one another; the
    engine runs one thread, so on two cores two refits take the time of one)."""
    count = _Counted(evaluator_factory)
    base_effects = list(model.effects)
    counted = lambda fit, effects: counted_bic(fit, effects, model.garment, first.n_residuals)   # noqa: E731
    current = Step(0, "identified", None, base_effects, identified, model, np.asarray(first.maps.residual_mm, float),
                   bic=counted(identified, base_effects))
    steps, diagnosis = [current], first
    positions, rows = objective.positions_mm, level_points(objective)

    def mark():
        return count.launched, time.perf_counter()

    def spent(since) -> dict:
        return {"engine_runs": count.launched - since[0], "wall_time_s": time.perf_counter() - since[1]}

    # a step's cost is what reaching it took: the ranking of the model before it (the identified model's, `first`,
    # was made before), its refits, the floor at its fit and the backward refits after it
    since = (-first.engine_runs, time.perf_counter() - first.wall_time_s)
    first_tried: list[Tried] = []
    stopped, tried = "steps", []
    while len(steps) - 1 < max_steps:
        if len(steps) > 1 and current.misfit_over_floor <= FLOOR_AGREEMENT:
            stopped = "floor"   # within the error model's agreement (module text): nothing is left to explain
            break
        if diagnosis is None:
            diagnosis = diagnose(count, current.model, current.fit.theta, objective, frame, alpha=alpha,
                                 engine_sensitivities=engine_sensitivities, progress=progress,
                                 side_by_side=side_by_side)
        if not diagnosis.ranking or not diagnosis.ranking[0].significant:
            stopped = "nothing significant"   # what is left is outside the catalog
            break
        scores = {s.effect: s for s in diagnosis.ranking}
        names = refit_candidates(diagnosis.ranking, alpha)
        for cut in diagnosis.cuts[:1]:
            if cut.significant:   # the best straight boundary of a stiffness change, beside the catalog's
                scores[cut.effect] = cut_score(cut)
                names.append(cut.effect)
        tried = _side_by_side(lambda factory, name: _try_addition(factory, current, name, scores[name],
                                                                  diagnosis.design_effect, objective, counted),
                              count, names, parallel)
        choice, ties = choose_addition(current.bic, tried, alpha)
        first_tried = tried if len(steps) == 1 else first_tried
        if choice is None:
            stopped = "not accepted" if any(t.fit is not None for t in tried) else "no refit"
            break
        current = Step(len(steps), "added", choice.effect, current.effects + [choice.effect], choice.fit,
                       refit_model(current.model, [choice.effect]), choice.residual_mm, tried,
                       [t.effect for t in ties], dofs={**current.dofs, choice.effect: choice.dof}, bic=choice.bic)
        current = _refit_cut_line(count, current, objective, counted)
        if own_floor is not None:
            current.fit.own_floor = own_floor(current.fit, current.residual_mm)
        cost = spent(since)
        current.engine_runs, current.wall_time_s = cost["engine_runs"], cost["wall_time_s"]
        steps.append(current)
        since, diagnosis, tried = mark(), None, []
        while len(steps) - 1 < max_steps:   # backward: the effects added before this one, tried out again
            removed = _try_removals(count, model, base_effects, current, choice.effect, objective, positions, rows,
                                    alpha, own_floor, counted, parallel)
            cost = spent(since)
            if removed is None:   # the refits that removed nothing are the last step's
                current.engine_runs += cost["engine_runs"]
                current.wall_time_s += cost["wall_time_s"]
                since = mark()
                break
            removed.engine_runs, removed.wall_time_s = cost["engine_runs"], cost["wall_time_s"]
            steps.append(removed)
            current, since = removed, mark()
    stopping = {"step": len(steps), "tried": [t.as_dict() for t in tried], **spent(since)}
    return Path(steps, stopped, stopping, first_tried)


def identified_only(model: LegModel, first: Diagnosis, identified: Refit) -> Path:
    """The path of a diagnosis that was not asked to walk it (refits named, or none): the identified model alone."""
    step = Step(0, "identified", None, list(model.effects), identified, model,
                np.asarray(first.maps.residual_mm, float))
    return Path([step], "not asked", {"step": 1, "tried": [], "engine_runs": 0, "wall_time_s": 0.0})


def _side_by_side(work, count: _Counted, names: Sequence[str], parallel: int) -> list:
    """[work(factory, name) for name in names], `parallel` at a time in threads whose evaluators run their engine
    themselves and silently (one worker: no process forked from a thread, as `candidates.GarmentRuns`)."""
    if parallel < 2 or len(names) < 2:
        return [work(count, name) for name in names]
    quiet = lambda model, **options: count(model, progress=False, workers=1)   # noqa: E731
    with ThreadPoolExecutor(max_workers=min(parallel, len(names))) as pool:
        return list(pool.map(lambda name: work(quiet, name), names))


def cut_score(cut: PatchScore) -> EffectScore:
    """The best straight cut (`locate.locate_cuts`) as a candidate of the step: its ratio and its line's two
    coordinates (`_refine_cut`), its score's p-value Bonferroni over the places scored."""
    return EffectScore(cut.effect, [CUT_PARAMETER], cut.statistic, 1 + CUT_GEOMETRY, cut.p_value, 0.0,
                       cut.predicted_misfit, [1.0], [float(np.log(cut.predicted_ratio))], cut.significant)


def _refine_cut(count, base: LegModel, base_theta, name: str, fit: Refit, r: np.ndarray,
                objective) -> tuple[str, Refit, np.ndarray]:
    """The cut's line fitted: a compass search on its normal's angle and its offset from the scored place (steps of
    the scoring grid, halved when no neighbour lowers chi^2), each place's constants and ratio refitted from the best
    place's, at most CUT_REFINE_REFITS refits. The scored place is only a start: the score's columns are the probe's
    groups weighted by area, and it is linear at ratio 1 (blind-03: the scored line 3 degrees and 2.4 mm off left
    1.25 x the floor, the true one 1.09 x; a ratio of 3.7 was scored 6 mm off). The changed part stays the smaller
    of the two (`locate.CUT_AREA`): its other side is the same field with the ratio inverted, but with the tissue's
    constants moved by the ratio, up to their bounds (blind-03's muscle C10 reached its bound of 30 kPa there)."""
    best = (name, fit, r)
    steps = [360.0 / CUT_NORMALS, CUT_STEP_MM]
    p = base.space.size
    refits = 0
    mesh = base.mesh
    # the other side of the same line, the ratio inverted, where that side is the smaller too (a line through the
    # middle): from a softer half the tissue's constants may have gone to their bounds
    flipped = _moved(parse_cut(name), 180.0, 0.0, flip=True)
    if _smaller_side(mesh, flipped):
        refits += 1
        try:
            flip_fit, flip_r = refit_whitened(count, base, base_theta, [flipped], objective,
                                              effect_start=[-v for v in fit.theta[p:]])
            if flip_fit.chi2 < fit.chi2:
                best = (flipped, flip_fit, flip_r)
        except RuntimeError:   # the engine cannot solve that side: the scored one goes on
            pass
    while refits < CUT_REFINE_REFITS and steps[0] >= CUT_REFINE_MIN_DEG:
        cut, moved = parse_cut(best[0]), False
        for d_angle, d_offset in ((steps[0], 0.0), (-steps[0], 0.0), (0.0, steps[1]), (0.0, -steps[1])):
            trial = _moved(cut, d_angle, d_offset)
            if not _smaller_side(mesh, trial):
                continue
            refits += 1
            try:
                trial_fit, trial_r = refit_whitened(count, base, best[1].theta[:p], [trial], objective,
                                                    effect_start=best[1].theta[p:])
            except RuntimeError:   # the engine cannot solve that place: the others are tried
                continue
            if trial_fit.chi2 < best[1].chi2:
                best, moved = (trial, trial_fit, trial_r), True
        if not moved:
            steps = [steps[0] / 2.0, steps[1] / 2.0]
    return best


def _moved(cut, d_angle: float, d_offset: float, flip: bool = False) -> str:
    """The name of `cut` turned by d_angle and moved by d_offset along its normal (flip: the offset's sign turned
    too, the same line seen from its other side)."""
    offset = -cut.offset_mm if flip else cut.offset_mm + d_offset
    return cut_name(cut.kind, round((cut.normal_deg + d_angle) % 360.0, 4), round(offset, 4))


def _smaller_side(mesh, name: str) -> bool:
    """Does the cut's changed part hold the share of its tissue the scored cuts hold (`locate.CUT_AREA`)?"""
    return CUT_AREA[0] <= cut_share(mesh, name) <= CUT_AREA[1]


def _refit_cut_line(count, step: Step, objective, counted) -> Step:
    """After an effect joins a model that holds a cut, the cut's line fitted again with it (`_refine_cut`): the line
    fitted before the effect took up what the effect explains (an MRI phantom's line 3 degrees and 1.4 mm off
    without the curvature law, which heterogeneity then had to mend). The step with the better line, or as it was."""
    cut = next((name for name in step.effects if is_cut(name)), None)
    if cut is None or step.effect == cut:
        return step
    others = [name for name in step.effects if name != cut]
    base = with_changes(step.model, effects=tuple(name for name in step.model.effects if name != cut))
    theta = _theta_for(base, step.fit)
    ratio = [float(step.fit.theta[step.fit.parameters.index(CUT_PARAMETER)])]
    try:
        fit, r = refit_whitened(count, base, theta, [cut], objective, effect_start=ratio)
        name, fit, r = _refine_cut(count, base, theta, cut, fit, r, objective)
    except RuntimeError:   # the engine cannot solve it: the line stays where it was fitted
        return step
    if fit.chi2 >= step.fit.chi2:
        return step
    effects = others + [name]
    fit.effects = effects
    fit.own_floor = step.fit.own_floor
    dofs = {(name if key == cut else key): value for key, value in step.dofs.items()}
    return replace(step, effects=effects, fit=fit, model=refit_model(base, [name]), residual_mm=objective.residual_mm(r),
                   dofs=dofs, bic=counted(fit, effects))


def _try_addition(count, current: Step, name: str, score: EffectScore, deff: float, objective, counted) -> Tried:
    """A candidate refitted from the current model (a cut's line fitted too: `_refine_cut`; its BIC counts the
    line's two coordinates)."""
    try:
        fit, r = refit_whitened(count, current.model, current.fit.theta, [name], objective)
        if is_cut(name):
            name, fit, r = _refine_cut(count, current.model, current.fit.theta, name, fit, r, objective)
    except RuntimeError as error:   # the engine cannot solve the refitted model somewhere: said, not fatal
        return Tried(name, score.dof, score.statistic, None, None, None, None, failure=str(error))
    fit.effects = current.effects + [name]   # the band's model lists no bridging: named by the effects asked for
    statistic, p_value = likelihood_ratio(current.fit.chi2, fit.chi2, score.dof, deff)
    return Tried(name, score.dof, score.statistic, fit.misfit_over_floor, counted(fit, fit.effects), statistic, p_value,
                 fit=fit,
                 residual_mm=objective.residual_mm(r))


def _try_removals(count, model: LegModel, base_effects: list[str], current: Step, last: str, objective, positions,
                  rows, alpha: float, own_floor, counted, parallel: int = 1) -> Step | None:
    """The backward step after `last` was added: each effect added before it refitted out (module text); the Step
    without the one that goes, or None. The refits tried are kept in current.removals_tried."""
    fits = {}

    def without(factory, name: str) -> dict:
        remaining = [e for e in current.effects if e != name]
        reduced = refit_model(model, [e for e in remaining if e not in base_effects])
        try:
            fit, r = refit_whitened(factory, reduced, _theta_for(reduced, current.fit), [], objective)
        except RuntimeError as error:
            return {"effect": name, "bic": None, "failure": str(error)}
        fit.effects = remaining
        fits[name] = (fit, reduced, objective.residual_mm(r))
        return {"effect": name, "chi2": fit.chi2, "bic": counted(fit, remaining), "dof": current.dofs.get(name, 1),
                "design_effect": design_effect(neighbour_correlation(positions, r, rows)),
                "misfit_over_floor": fit.misfit_over_floor}

    earlier = [name for name in current.effects if name not in base_effects and name != last]
    options = _side_by_side(without, count, earlier, parallel)
    removal = choose_removal(current.fit.chi2, current.bic, options, alpha)
    current.removals_tried = options
    if removal is None:
        return None
    fit, reduced, residual_mm = fits[removal["effect"]]
    if own_floor is not None:
        fit.own_floor = own_floor(fit, residual_mm)
    dofs = {k: v for k, v in current.dofs.items() if k != removal["effect"]}
    return Step(current.step + 1, "removed", removal["effect"], list(fit.effects), fit, reduced, residual_mm,
                dofs=dofs, bic=removal["bic"])


# --- the path in words ------------------------------------------------------------------------------------------------

def _label(step: Step) -> str:
    name = step.effect if step.action == "added" else f"{step.effect} out again"
    if step.action == "added" and is_cut(step.effect) and CUT_PARAMETER in step.fit.parameters:
        cut = parse_cut(step.effect)
        ratio = float(np.exp(step.fit.theta[step.fit.parameters.index(CUT_PARAMETER)]))
        name = (f"the {cut.kind} beyond a straight line, its stiffness x{ratio:.2f} (the line's normal at "
                f"{cut.normal_deg:g} deg, {cut.offset_mm:g} mm from the leg's centre: {step.effect})")
    if step.ties:
        name += f" (or {' or '.join(step.ties)}: BIC within {TIE_BIC:g}, the data cannot tell them apart)"
    return name


def _refused(tried: Sequence[dict], bic: float) -> str:
    """Why the last attempt's best refit was not added."""
    fitted = [t for t in tried if t["bic"] is not None]
    if not fitted:
        return "every refit failed" if tried else "no effect was refitted"
    best = min(fitted, key=lambda t: t["bic"])
    penalty = 2.0 * np.log(max(len(tried), 1))
    why = (f"its own test p = {best['p_value']:.2g}" if not best["accepted"] and bic - best["bic"] > penalty
           else f"BIC {best['bic']:.1f} against {bic:.1f}, {penalty:.1f} less needed with the choice among "
                f"{len(tried)} counted")
    return (f"the best refit, {best['effect']}, leaves {best['misfit_over_floor']:.2f} x the floor and is not added "
            f"({why})")


def path_verdict(path: Path, first: Diagnosis) -> tuple[bool, str]:
    """(explained, the verdict in one sentence): the effects added in turn and the misfit over the floor at each step,
    then whether the final model reaches the floor. A path that added nothing keeps the ranking's verdict, or says
    why the refits were not added."""
    ratios = " -> ".join(f"{step.misfit_over_floor:.2f}" for step in path.steps)
    if len(path.steps) == 1:
        if not path.stopping["tried"]:
            return False, first.verdict
        return False, (f"misfit {path.steps[0].misfit_over_floor:.2f} x the noise floor; "
                       f"{_refused(path.stopping['tried'], path.final.bic)}: no catalog effect explains the residual")
    chain = ", then ".join(_label(step) for step in path.steps[1:]) + f": {ratios} x the floor"
    final = path.final
    effects = ",".join(final.effects)
    if path.reached_floor:
        return True, (f"{chain}; the model with {', '.join(final.effects)} reaches the floor, within the "
                      f"{FLOOR_AGREEMENT:g} x the error model agrees with the measured errors "
                      f"(calfit identify CASE --effects {effects}, or --effects final)")
    stop = {"nothing significant": "nothing more in the catalog is significant on its residual",
            "steps": f"the {len(path.steps) - 1} steps allowed are done",
            "no refit": "every refit failed"}.get(path.stopped) or _refused(path.stopping["tried"], final.bic)
    return False, (f"{chain}; it stays {final.misfit_over_floor:.2f} x the floor, beyond the {FLOOR_AGREEMENT:g} x "
                   f"within which the error model agrees with the measured errors, and {stop}: no catalog effect "
                   f"explains the residual left (the model with {', '.join(final.effects)} is the best found: "
                   f"--effects {effects})")


def path_lines(path: Sequence[dict], final: dict) -> list[str]:
    """diagnosis.json's path and final as a table (calfit diagnose)."""
    lines = ["the path, one effect at a time (misfit over the floor; BIC; engine runs and wall time of the step):",
             f"{'step':<5}{'':<28}{'x floor':>9}{'BIC':>11}{'runs':>6}{'s':>8}  refitted (x floor, BIC)"]
    for entry in path:
        label = {"identified": "identified model"}.get(entry["action"], f"{'+' if entry['action'] == 'added' else '-'} "
                                                                         f"{entry['effect']}")
        tried = ", ".join(f"{t['effect']} {t['misfit_over_floor']:.2f}, {t['bic']:.1f}" if t["bic"] is not None
                          else f"{t['effect']} failed" for t in entry["tried"])
        lines.append(f"{entry['step']:<5}{label:<28}{entry['misfit_over_floor']:>9.2f}{entry['bic']:>11.1f}"
                     f"{entry['engine_runs']:>6}{entry['wall_time_s']:>8.1f}  {tried}")
    stopping = final.get("stopping") or {}
    if stopping.get("tried"):
        tried = ", ".join(f"{t['effect']} {t['misfit_over_floor']:.2f}, {t['bic']:.1f}" if t["bic"] is not None
                          else f"{t['effect']} failed" for t in stopping["tried"])
        lines.append(f"{'':<5}{'(not added)':<28}{'':>9}{'':>11}{stopping['engine_runs']:>6}"
                     f"{stopping['wall_time_s']:>8.1f}  {tried}")
    lines.append(f"final: {', '.join(final['effects']) or 'the identified model'}, {final['misfit_over_floor']:.2f} x "
                 f"the floor, {'explained' if final['explained'] else 'not explained'} (stopped: {final['stopped']})")
    lines += [f"  as good: {', '.join(a['effects'])} ({a['misfit_over_floor']:.2f} x, BIC {a['bic']:.1f}) instead of "
              f"{a['instead_of']} at step {a['step']}" for a in final.get("alternatives", [])]
    return lines
