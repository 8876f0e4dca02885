"""Where the fitted model fails, which effect of the catalog is missing, and what adding it gains.

The diagnosis ranks every catalog effect missing from the fitted model on its residual (`diagnose`); its pieces,
each a module of this package: the score and the information criteria (`score`), the residual maps (`maps`), the
effects tried and the garment band's columns (`candidates`), the places of a local change (`locate`), the refit
(`refit`), the verdict and ties (`verdict`) and the forward-backward path of refits (`stepwise`).

Several garment levels (two socks, `levels.LevelsModel`): the model is one leg under each tension. r stacks every
level's residual, whitened together (`levels.JointDisplacementObjective`), and so does every column G (each level's
deck carries the effect), so an effect is scored, and refitted, on all the levels at once. The neighbour correlation
is taken within each level (the levels share their windows' places), and each level's own misfit over its own floor
and its residual maps say where, level by level, the model fails (`level_misfits`, `level_maps`).

Verdict. If the best significant effect's predicted misfit F - reduction reaches EXPLAINED_FACTOR times
the noise floor, that effect explains the residual; otherwise the diagnosis says that no catalog effect
explains it and points at where the residual is, in words (`regions.LegFrame`): the tissue, the
anatomical sector around the leg in degrees and the depth under the skin of the region that holds the
largest share of the squared residual.

Ties. The linear score cannot choose between effects whose statistics lie within TIE_FRACTION of the best's, nor
between effects that are each predicted to explain the residual: the best and up to MAX_TIED of those are refitted,
and the lowest BIC among the refits that converged wins (`settle_ties`). A best effect whose refit failed explains
nothing: its prediction was not checked.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np
from scipy import stats

from ..engine.runner import Evaluator
from ..fit.identify import jacobian_in_x, steps_into_box
from ..model.effects import LOCAL_PROBE, effect
from ..model.forward import LegModel
from ..model.heterogeneity import is_cut
from ..model.regions import LegFrame
from .candidates import (
    GarmentRuns,
    candidate_effects,
    garment_columns,
    garment_parameters,
    with_changes,
)
from .locate import PatchScore, locate, locate_cuts
from .maps import ResidualMaps, level_maps, level_misfits, level_points, residual_maps
from .score import (
    ALPHA,
    EXPLAINED_FACTOR,
    EffectScore,
    design_effect,
    neighbour_correlation,
    residuals_of,
    score_effect,
)

TIE_FRACTION = 0.1           # statistics within 10 % of the best: the score cannot tell them apart, refits do

MAX_TIED = 3                 # effects predicted to explain are refitted beside the best up to this many ties

FD_FRACTION = 1.0            # forward-difference step of an effect parameter, in units of its scale



@dataclass
class Diagnosis:
    effects_in_model: list[str]
    parameters: list[str]
    theta: list[float]
    misfit: float
    noise_floor: float
    chi2: float
    n_residuals: int
    lack_of_fit_p: float
    design_effect: float
    neighbour_correlation: float
    ranking: list[EffectScore]
    explained: bool
    verdict: str
    maps: ResidualMaps
    engine_runs: int
    sensitivities_from: str
    wall_time_s: float
    not_ranked: dict[str, str] = field(default_factory=dict)
    patches: list[PatchScore] = field(default_factory=list)   # where a local stiffness change would help, best first
    cuts: list[PatchScore] = field(default_factory=list)      # the best straight boundary of a stiffness change
    levels: list[dict] = field(default_factory=list)   # several socks: each level's misfit and floor (`level_misfits`)
    level_maps: list[ResidualMaps] = field(default_factory=list)   # and its residual maps, level by level

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> Diagnosis:
        names = {f for f in cls.__dataclass_fields__}
        values = {k: v for k, v in data.items() if k in names}
        values["ranking"] = [EffectScore(**s) for s in data["ranking"]]
        values["maps"] = ResidualMaps(**data["maps"])
        values["patches"] = [PatchScore(**p) for p in data.get("patches", [])]
        values["cuts"] = [PatchScore(**p) for p in data.get("cuts", [])]
        values["level_maps"] = [ResidualMaps(**m) for m in data.get("level_maps", [])]
        return cls(**values)



def probe_jacobian(evaluator: Evaluator, theta: Sequence[float]) -> tuple[np.ndarray, np.ndarray, str]:
    """r and dr/dtheta of the evaluator's model at theta: from the engine's sensitivities where the record has
    them, forward differences for the other columns (`identify.jacobian_in_x`: steps of 1e-3 in ln theta for
    constants, FD_FRACTION x `scale` for effects); the source says which."""
    space = evaluator.model.space
    theta = np.asarray(theta, float)
    record = evaluator(theta)
    r = residuals_of(record)
    x = space.to_x(theta)
    steps = steps_into_box(space, x, np.where(np.array(space.linear), FD_FRACTION, 1e-3))
    J, missing = jacobian_in_x(evaluator, record, x, steps, tag="diagnosis", label="diagnosis sensitivities")
    J = J / np.where(np.array(space.linear), np.array(space.scale), theta)[None, :]   # dr/dx -> dr/dtheta
    if not missing:
        return r, J, "engine"
    source = ("finite differences" if len(missing) == len(theta) else
              f"engine, finite differences for {', '.join(space.names[j] for j in missing)}")
    return r, J, source



def diagnose(evaluator_factory, model: LegModel, theta: Sequence[float], objective, frame: LegFrame, *,
             alpha: float = ALPHA, engine_sensitivities: bool = True, progress: bool = True,
             side_by_side: bool = False) -> Diagnosis:
    """Rank the catalog effects missing from `model` fitted at theta (module text).

    evaluator_factory(model, progress=None, workers=None) -> Evaluator: evaluations go through the run's log like
    any other (None: the run's settings); objective: the `DisplacementResidualObjective` of the measurements (its
    floor, its nuisance, its residual in mm); frame: how regions are named; progress: show the wait for the
    garment band's runs; side_by_side: the run may use more than one engine at a time, so the band's runs go beside
    the ranking's probe (`GarmentRuns`)."""
    began = time.perf_counter()
    candidates, skipped = candidate_effects(model)
    # friction and bridging are not written into a deck state (no sensitivity): the band's own runs give their columns
    garment_effects = [name for name in candidates if effect(name).apply is None]
    candidates = [name for name in candidates if effect(name).apply is not None]
    # the local probe's many columns (material constants, which the engine differentiates with or without friction)
    # are one back-substitution each with the engine's sensitivities, an engine run each by finite differences:
    # without the former, the diagnosis does not locate
    probing = (LOCAL_PROBE.name,) if engine_sensitivities else ()
    probe = with_changes(model, effects=model.effects + tuple(candidates) + probing,
                         engine_sensitivities=engine_sensitivities)
    probe_sets = list(model.mesh.element_sets()) + [group.name for group in probe.groups]
    p = model.space.size
    theta_probe = list(map(float, theta)) + [0.0] * (probe.space.size - p)
    # beside the probe only when the engine gives its columns (one run, in this process: no pool forked from a
    # process whose threads run the band)
    with GarmentRuns(evaluator_factory, model, theta, garment_effects,
                     side_by_side and engine_sensitivities) as band_runs:
        with evaluator_factory(probe) as evaluator:
            r, jacobian, source = probe_jacobian(evaluator, theta_probe)
            runs = evaluator.launched
        columns = {}
        if garment_effects:
            try:
                columns, garment_runs = garment_columns(band_runs, r, progress)
                runs += garment_runs
            except RuntimeError as error:   # the band does not go on at these constants: said, the rest is ranked
                skipped.update({name: f"the explicit band was not solved at the fitted constants ({error})"
                                for name in garment_effects})
    n = len(r)
    chi2 = float(r @ r)
    residual_mm = objective.residual_mm(r)
    misfit = objective.cost_of(r)
    floor = objective.noise_floor(p)
    chi2_to_misfit = misfit / chi2 if chi2 > 0 else 0.0
    lack_of_fit_p = float(stats.chi2.sf(chi2, n - p - objective.nuisance_dof))
    positions_mm = objective.positions_mm
    rho = neighbour_correlation(positions_mm, r, level_points(objective))
    deff = design_effect(rho)
    # dr/dtheta of the fitted parameters (the projection onto their span does not depend on how columns are scaled)
    J = jacobian[:, :p]
    ranking = []
    column = p
    for name in candidates:
        parameters = [prm.name for prm in effect(name).parameters(probe_sets, list(model.mesh.node_sets),
                                                                  model.garment)]
        G = jacobian[:, column:column + len(parameters)]
        column += len(parameters)
        score = score_effect(r, J, G, chi2_to_misfit, deff)
        q = len(parameters)
        ranking.append(EffectScore(name, parameters, score["statistic"], q, float(stats.chi2.sf(score["statistic"], q)),
                                   score["predicted_reduction"], misfit - score["predicted_reduction"],
                                   score["orthogonal_fraction"], score["step"]))
    for name, G in columns.items():
        score = score_effect(r, J, G, chi2_to_misfit, deff)
        q = G.shape[1]
        ranking.append(EffectScore(name, garment_parameters(model, name), score["statistic"], q,
                                   float(stats.chi2.sf(score["statistic"], q)), score["predicted_reduction"],
                                   misfit - score["predicted_reduction"], score["orthogonal_fraction"], score["step"]))
    ranking.sort(key=lambda s: (s.p_value, -s.statistic))
    lack_of_fit = lack_of_fit_p < alpha
    # an effect is significant on its own score test, Bonferroni over the m effects tried, whatever the omnibus
    # lack-of-fit test says: that test spreads its n - p - k degrees of freedom over every direction of the residual,
    # so it misses what the effect's q-dimensional test sees. A one-parameter effect that lowers chi^2 by delta is
    # seen by the score test from delta ~ chi^2_1(1 - alpha/m) ~ 12 on, by the lack-of-fit test only from
    # delta ~ z sqrt(2 (n - p - k)) ~ 57 on with n = 300 (blind-04, 150 points: the unloaded-curvature law scored
    # p = 1.7e-05 at 0.90 x the floor, and the conjunction of both tests said "nothing is missing"). Requiring both
    # made the test stricter than its stated alpha, not more honest; the score alone already holds the chance of
    # naming an effect that is absent to alpha (benchmarks/diagnose.py --false-alarms measures it).
    for score in ranking:
        score.significant = bool(score.p_value < alpha / max(len(ranking), 1))
    if ranking and ranking[0].significant:
        # effects whose residual signatures the fitted parameters leave nearly alike (e.g. drainage of the muscle
        # and an axial stretch of the whole slice, where the fat is thin): the linear score ranks them by a hair,
        # so they are refitted, and their misfits decide. So are effects that are each predicted to explain the
        # residual: near the floor the prediction cannot choose between them (a faint stiffening scored 114
        # against a friction band's 136, both predicted at 1.4-1.5 x the floor), the refits can.
        top = ranking[0]
        close = [s.effect for s in ranking[1:] if s.significant and s.statistic >= (1 - TIE_FRACTION) * top.statistic]
        explaining = [s.effect for s in ranking[1:] if s.significant and s.effect not in close
                      and max(top.predicted_misfit, s.predicted_misfit) <= EXPLAINED_FACTOR * floor]
        top.tied_with = close + explaining[:max(0, MAX_TIED - len(close))]
    explained, verdict = ranking_verdict(ranking, misfit, floor, lack_of_fit)
    maps = residual_maps(positions_mm, residual_mm, frame)
    patches, cuts = [], []
    if probing and lack_of_fit and source.startswith("engine"):
        local = jacobian[:, column:column + len(probe.groups)]
        patches = locate(r, J, local, probe.groups, frame, chi2_to_misfit, deff, misfit, alpha)
        if not any(is_cut(name) for name in model.effects):   # one cut per model
            cuts = locate_cuts(r, J, local, probe.groups, probe.mesh, frame, chi2_to_misfit, deff, misfit, alpha)
    return Diagnosis(list(model.effects), list(model.space.names), list(map(float, theta)), misfit, floor, chi2, n,
                     lack_of_fit_p, deff, rho, ranking, explained, verdict, maps, runs, source,
                     time.perf_counter() - began, skipped, patches, cuts, level_misfits(objective, r, p),
                     level_maps(objective, residual_mm, frame))



def ranking_verdict(ranking: list[EffectScore], misfit: float, floor: float, lack_of_fit: bool) -> tuple[bool, str]:
    ratio = misfit / floor if floor > 0 else np.inf
    significant = [s for s in ranking if s.significant]
    if not lack_of_fit and not significant:
        return False, f"the model fits to the noise floor (misfit {ratio:.2f} x the floor): no effect is missing"
    if not significant:
        return False, (f"misfit {ratio:.2f} x the noise floor, and no catalog effect explains the residual "
                       "significantly: the missing physics is outside the catalog")
    best = significant[0]
    after = best.predicted_misfit / floor
    # within the noise as a whole, and yet one effect's signature is in the residual (its own test)
    seen = ("" if lack_of_fit else f", within the noise as a whole, but {best.effect}'s own test sees its signature "
                                   f"in the residual (p = {best.p_value:.2g}, Bonferroni over {len(ranking)} effects)")
    if after <= EXPLAINED_FACTOR:
        return True, (f"misfit {ratio:.2f} x the noise floor{seen}; {best.effect} explains it (predicted "
                      f"{after:.2f} x the floor after the refit)")
    return False, (f"misfit {ratio:.2f} x the noise floor{seen}; the best effect, {best.effect}, would leave "
                   f"{after:.2f} x the floor: no catalog effect explains the residual")
