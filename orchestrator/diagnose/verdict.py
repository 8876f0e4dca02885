"""The verdict once refits have been made: ties settled by the refits' BIC, the misfit a refit reached (not its
prediction) said against the floor, the local change weighed against the catalog, and the diagnosis as text
(ranking, before/after table, garment levels)."""

from __future__ import annotations

from dataclasses import asdict
from typing import Sequence

import numpy as np
from scipy import stats

from ..core.digits import PLUS_MINUS
from ..model.heterogeneity import PATCH_PREFIX, patch_groups, stiffness_field_text
from .diagnosis import Diagnosis
from .locate import PatchScore
from .refit import Refit
from .score import EXPLAINED_FACTOR, FLOOR_AGREEMENT


def settle_ties(diagnosis: Diagnosis, refits: Sequence[Refit]) -> None:
    """Reorder the best-ranked effect and those tied with it by the BIC of their single-effect refits."""
    if not diagnosis.ranking or not diagnosis.ranking[0].tied_with:
        return
    group = [diagnosis.ranking[0].effect] + diagnosis.ranking[0].tied_with
    bic = {f.effects[-1]: f.bic for f in refits if len(f.effects) >= 1 and f.effects[-1] in group}
    if not bic:
        return
    tied = [s for s in diagnosis.ranking if s.effect in group]
    rest = [s for s in diagnosis.ranking if s.effect not in group]
    tied.sort(key=lambda s: bic.get(s.effect, np.inf))   # an effect whose refit failed cannot win
    for s in tied:
        s.tied_with = [name for name in group if name != s.effect] if s is tied[0] else []
    diagnosis.ranking = tied + rest



def below_floor(fit: Refit, values: int, nuisance_dof: int, alpha: float) -> str | None:
    """The caution when a model fits significantly better than its noise floor allows: its misfit below
    1 / FLOOR_AGREEMENT of the floor (outside the band within which the error model agrees with the measured errors)
    and noise alone reaching so low at p < alpha (chi^2's lower tail on the fit's degrees of freedom). The error
    model then overstates the random part of the errors, and an error smooth enough for the parameters to take up
    fits so (a study's slices resampled between a volume's slices: docs/validation/volumes.md), so the intervals are
    not to be trusted. None when the fit is within its floor."""
    ratio = judged_ratio(fit)
    dof = values - len(fit.parameters) - nuisance_dof
    if dof <= 0 or ratio >= 1.0 / FLOOR_AGREEMENT:
        return None
    p_low = float(stats.chi2.cdf(ratio * dof, dof))
    if p_low >= alpha:
        return None
    return (f"the model fits at {ratio:.2f} x the floor, below the {1.0 / FLOOR_AGREEMENT:g} x within which the "
            f"error model agrees with the measured errors (p = {p_low:.1g} that noise alone fits so well): the error "
            "model overstates the random part of these errors, and what error is left the parameters may have taken "
            "up, so the intervals are not to be trusted")


def refit_verdict(diagnosis: Diagnosis, refits: Sequence[Refit]) -> tuple[bool, str]:
    """The verdict once the best-ranked effect has been refitted: the misfit it reaches, not its linearized
    prediction, says whether it explains the residual."""
    if not diagnosis.ranking or not diagnosis.ranking[0].significant:
        return diagnosis.explained, diagnosis.verdict
    best = diagnosis.ranking[0].effect
    done = [f for f in refits if f.effects[-1:] == [best]]
    if not done:
        return diagnosis.explained, diagnosis.verdict
    ratio = judged_ratio(done[0])
    floor = ("" if done[0].own_floor is None else
             f" ({done[0].misfit_over_floor:.2f} with the skin's uncertainty of the baseline fit)")
    tie = diagnosis.ranking[0].tied_with
    settled = (f" (the score could not tell it from {', '.join(tie)}; their refits decided, by BIC)" if tie else "")
    if ratio <= EXPLAINED_FACTOR:
        short = ("" if ratio <= FLOOR_AGREEMENT else
                 f"; that is still above the floor, beyond the {FLOOR_AGREEMENT:g} x within which the error model "
                 f"agrees with the measured errors: {best} explains most of the residual, not all of it")
        field = ("" if not done[0].stiffness_field else
                 f"; its stiffness field, C10 area-weighted: {stiffness_field_text(done[0].stiffness_field)} (the "
                 f"refit's C10 of a tissue is the field's reference, not the tissue's constant)")
        return True, (f"misfit {diagnosis.misfit / diagnosis.noise_floor:.2f} x the noise floor; {best} explains it: "
                      f"refitted with it, the misfit is {ratio:.2f} x the floor{floor}{settled}{short}"
                      f"{unfixed_constants(diagnosis, done[0])}{field}")
    return False, (f"misfit {diagnosis.misfit / diagnosis.noise_floor:.2f} x the noise floor; the best effect, {best}, "
                   f"refitted, leaves {ratio:.2f} x the floor{floor}: no catalog effect explains the residual")



def judged_ratio(fit: Refit) -> float:
    """A refit's misfit over the floor as its verdict judges it: against its own floor when the skin's uncertainty
    was estimated again at its parameters (the baseline's may be far from the refit's, a baseline on a bound)."""
    return fit.misfit_over_floor if fit.own_floor is None else fit.own_floor["misfit_over_floor"]



def unfixed_constants(diagnosis: Diagnosis, fit: Refit) -> str:
    """The verdict's words for the identified model's own parameters that the explaining refit leaves outside
    identify's identifiability rule (their linearized 95 % interval): the effect added trades with them, so their
    refitted values are not to be read as measured."""
    intervals = fit.intervals or {}
    loose = [(name, half) for name, half, ok in zip(fit.parameters, intervals.get("relative_half_width", []),
                                                    intervals.get("identifiable", []))
             if not ok and name in diagnosis.parameters]
    if not loose:
        return ""
    return ("; in that refit the data do not fix " + ", ".join(
        f"{name} (95 % interval {'unbounded' if half is None else f'{PLUS_MINUS}{100 * half:.1f} %'})" for name, half in loose))



def weigh_local(diagnosis: Diagnosis, patch: PatchScore, before: Refit, after: Refit,
                catalog_refits: Sequence[Refit]) -> dict:
    """Does a stiffness change in the best-scored place bring the misfit to the floor, and pay on BIC for its
    parameter and for the choice of its place among the places tried (2 ln N: each place a priori 1/N)? When a
    catalog effect explained the residual, the local change is its rival: if the local change wins on that BIC,
    the catalog no longer explains (`explained` false) and the verdict says so. Updates the diagnosis' verdict;
    returns the local refit's summary (diagnosis.json "local")."""
    ratio = float(np.exp(after.theta[after.parameters.index("dlnE_patch")]))
    bic = after.bic + 2.0 * np.log(max(patch.places_tried, 1))
    explains = after.misfit_over_floor <= EXPLAINED_FACTOR and bic < before.bic
    numbers = (f"stiffness x{ratio:.2f} there, {patch.area_cm2:.1f} cm2; refitted, the misfit is {after.misfit_over_floor:.2f} "
               f"x the floor, BIC {bic:.1f} with the choice of place counted, against {before.bic:.1f}")
    rival = None
    if diagnosis.explained:
        explaining = [f for f in catalog_refits if f.misfit_over_floor <= EXPLAINED_FACTOR]
        rival = min(explaining, key=lambda f: f.bic) if explaining else None
    if rival is not None and explains and bic < rival.bic:
        diagnosis.explained = False
        diagnosis.verdict += (f"; but a local stiffness change in the {patch.place} fits better ({numbers}; "
                              f"{', '.join(rival.effects[-1:])} BIC {rival.bic:.1f}): no catalog effect explains the "
                              f"residual better than a local change")
    elif rival is None and explains:
        diagnosis.verdict += f"; a local stiffness change in the {patch.place} does ({numbers})"
    elif rival is None:
        diagnosis.verdict += f"; nor does a local stiffness change in the {patch.place}, the best place found ({numbers})"
    else:
        diagnosis.verdict += (f"; a local stiffness change in the {patch.place}, refitted, does not fit better "
                              f"({numbers}; {', '.join(rival.effects[-1:])} BIC {rival.bic:.1f})")
    return {"patch": asdict(patch), "refitted": True, "ratio": ratio, "explains": bool(explains and (rival is None or bic < rival.bic)),
            "misfit_over_floor": after.misfit_over_floor, "bic": bic, "bic_unpenalized": after.bic,
            "bic_before": before.bic, "bic_catalog": rival.bic if rival is not None else None,
            "aic": after.aic, "aic_before": before.aic, "verdict": diagnosis.verdict}



def local_refit_unneeded(diagnosis: Diagnosis, patch: PatchScore, catalog_ratio: float | None = None) -> str | None:
    """Why the local change's refit can be left out, or None to run it. It is the rival of a catalog effect whose
    refit explained the residual; when the two are compared on the same linearization at the identified fit (the
    score test's predicted chi^2 with the BIC's penalties, the place's 2 ln N included) and the catalog effect is
    predicted better, the refit cannot be expected to change the verdict. Under friction it costs tens of runs of
    minutes each (the second paper's drainage case: 24 runs for 2e-4 of the misfit). Said in the verdict.
    Unless the catalog effect's refit stayed above the floor (catalog_ratio, its misfit over the floor, beyond
    FLOOR_AGREEMENT): then the linearization was wrong about it, and may be about the local change, which a large
    change of stiffness leaves far from linear (a muscle three times stiffer: ln 3 = 1.1), so it is refitted."""
    if not diagnosis.explained or not diagnosis.ranking or diagnosis.misfit <= 0.0:
        return None
    if catalog_ratio is not None and catalog_ratio > FLOOR_AGREEMENT:
        return None
    best = diagnosis.ranking[0]
    to_chi2 = diagnosis.chi2 / diagnosis.misfit
    log_n = np.log(diagnosis.n_residuals)
    bic_catalog = best.predicted_misfit * to_chi2 + best.dof * log_n
    bic_local = patch.predicted_misfit * to_chi2 + log_n + 2.0 * np.log(max(patch.places_tried, 1))
    if bic_local < bic_catalog:
        return None
    floor = diagnosis.noise_floor
    return (f"a local stiffness change in the {patch.place} was not refitted: linearized at the identified fit it "
            f"leaves {patch.predicted_misfit / floor:.2f} x the floor (BIC {bic_local:.1f} with the choice of place "
            f"counted), {best.effect} {best.predicted_misfit / floor:.2f} x (BIC {bic_catalog:.1f}), and "
            f"{best.effect}'s refit confirmed it")



def ranking_lines(diagnosis: Diagnosis) -> list[str]:
    lines = [f"misfit {diagnosis.misfit:.4g} mm^2 = {diagnosis.misfit / diagnosis.noise_floor:.2f} x the noise floor "
             f"{diagnosis.noise_floor:.4g} mm^2 (chi^2 {diagnosis.chi2:.1f} for n = {diagnosis.n_residuals}, lack of fit "
             f"p = {diagnosis.lack_of_fit_p:.2g}); neighbour correlation {diagnosis.neighbour_correlation:.2f}, "
             f"design effect {diagnosis.design_effect:.2f}; sensitivities from {diagnosis.sensitivities_from}",
             f"{'rank':<5}{'effect':<17}{'q':>2}{'statistic':>11}{'p-value':>10}{'pred. misfit':>14}{'|g_perp|/|g|':>14}  significant"]
    for k, s in enumerate(diagnosis.ranking, 1):
        fraction = ", ".join(f"{v:.2f}" for v in s.orthogonal_fraction)
        lines.append(f"{k:<5}{s.effect:<17}{s.dof:>2}{s.statistic:>11.4g}{s.p_value:>10.2g}"
                     f"{s.predicted_misfit / diagnosis.noise_floor:>12.2f} x  {fraction:>12}  {'YES' if s.significant else 'no'}"
                     + (f"  (tied with {', '.join(s.tied_with)}: settled by refit)" if s.tied_with else ""))
    for name, reason in diagnosis.not_ranked.items():
        lines.append(f"     {name:<17} not ranked: {reason}")
    if diagnosis.patches:
        lines.append("places for a local stiffness change (score, predicted misfit, stiffness ratio, linearized):")
        lines += [f"  {k}. {p.place}, {p.area_cm2:.1f} cm2: statistic {p.statistic:.1f}, p = {p.p_value:.2g} over "
                  f"{p.places_tried} places, {p.predicted_misfit / diagnosis.noise_floor:.2f} x the floor, "
                  f"stiffness x{p.predicted_ratio:.2f}{'' if p.significant else ' (not significant)'}"
                  for k, p in enumerate(diagnosis.patches, 1)]
    lines.append(diagnosis.verdict)
    return lines



def effect_label(name: str) -> str:
    """An effect as a table shows it: a patch by its size, not its list of groups."""
    return f"local change ({len(patch_groups(name))} groups)" if name.startswith(PATCH_PREFIX) else name



def model_label(effects: Sequence[str]) -> str:
    """A refitted model as tables name it: "baseline" or "+ " and its added effects."""
    return "+ " + ", ".join(map(effect_label, effects)) if effects else "baseline"



def level_rows(levels: Sequence[dict], before: Refit, after: Sequence[Refit]) -> list[list]:
    """Per garment level (diagnosis.json "levels"): its number, image, tension, its own misfit over its floor for the
    identified model and after each refit, and where its residual is largest: where, level by level, the model
    fails."""
    return [[level["level"], level.get("image", ""), level.get("tension_N_per_mm", float("nan"))]
            + [fit.levels[k]["misfit_over_floor"] if len(fit.levels) > k else float("nan") for fit in (before, *after)]
            + [level.get("worst_region", "")] for k, level in enumerate(levels)]



def level_lines(levels: Sequence[dict], before: Refit, after: Sequence[Refit]) -> list[str]:
    """`level_rows` as text."""
    labels = [model_label(fit.effects) for fit in (before, *after)]
    widths = [max(12, len(label) + 2) for label in labels]
    lines = [f"{'level':<6}{'image':<22}{'N/mm':>7}" + "".join(f"{label:>{w}}" for label, w in zip(labels, widths))
             + "  largest share of the residual (identified model)"]
    for row in level_rows(levels, before, after):
        lines.append(f"{row[0]:<6}{row[1]:<22}{row[2]:>7.3g}"
                     + "".join(f"{v:>{w - 2}.2f} x" for v, w in zip(row[3:-1], widths)) + f"  {row[-1]}")
    return ["misfit over each garment level's own floor:"] + lines



def comparison_lines(before: Refit, after: Sequence[Refit]) -> list[str]:
    lines = [f"{'model':<28}{'k':>3}{'misfit mm^2':>13}{'x floor':>9}{'AIC':>11}{'BIC':>11}  parameters"]
    for fit in (before, *after):
        label = model_label(fit.effects)
        values = fit.parameter_text()
        lines.append(f"{label:<28}{len(fit.parameters):>3}{fit.misfit:>13.4g}{fit.misfit_over_floor:>9.2f}"
                     f"{fit.aic:>11.1f}{fit.bic:>11.1f}  {values}")
    lines += [f"{model_label(fit.effects)}: {fit.own_floor['misfit_over_floor']:.2f} x the floor with the skin's "
              "uncertainty estimated again at its own parameters" for fit in after if fit.own_floor]
    return lines
