"""Where the fitted model fails, which effect of the catalog is missing, and what adding it gains.

Residual. r = P C^-1/2 (u_model - u_measured) at the measured points or DIC windows (Bouten and Drapier
eq. 2 weighted by the measurements' covariance C, both components, n = 2N values; P removes the k nuisance
directions, the residual rigid motion of the bones for DIC; `objectives.DisplacementResidualObjective`), at
the identified parameters theta of p fitted parameters. The misfit is F = s^2 r.r / n (mm^2, the
identification's cost, s^2 the mean variance of one component); for a correct model its expectation is the
noise floor F_0 = s^2 (n - p - k) / n, and r.r is chi^2 with n - p - k degrees of freedom.

Which effect is missing (DESIGN.md). For every catalog effect not in the model, G = dr/dphi at phi = 0
(n x q, its q parameters), from the engine's sensitivities when it gives them (one run), otherwise by
forward differences of step `scale`. Its part that the fitted parameters cannot absorb is
G_perp = G - J (J^T J)^-1 J^T G (J = dr/dx, x the optimizer's variables). Linearized, refitting with
the effect lowers chi^2 = r.r by U^T M^-1 U with U = G_perp^T r and M = G_perp^T G_perp (the predicted
reduction; for q = 1 it is (g_perp^T r)^2 / g_perp^T g_perp), and the score statistic
S = U^T M^-1 U / (sigma^2 D) is chi^2 with q degrees of freedom when the effect is absent (r is
normalized: sigma = 1). D >= 1 is the design effect of residuals correlated in space: with rho the
correlation of each point's residual with its nearest neighbour's, D = (1 + rho) / (1 - rho) (the AR(1)
variance inflation, i.e. an effective sample size n / D); independent noise has rho ~ 0 and D = 1, a
smooth misfit pattern a large D, which keeps a smooth model error from passing for many independent
pieces of evidence. |g_perp| / |g| tells how much of the effect the fitted parameters would mimic
(0: all of it). Effects are ranked by S; one is significant when its p-value is below alpha / m
(Bonferroni over the m effects tried) and the misfit itself is above the noise floor (chi^2 test).

The garment's effects (friction, bridging) are not in the Laplace-law deck: they replace p = T / r by the explicit
band (`garment_model`: penalty contact, Bouten and Drapier sec. 2.5, carrying the model's effects on the tissues).
Bridging is a switch s from Laplace's law (s = 0) to the frictionless band (s = 1), G = r_band - r (one run of the
band at theta); friction is the switch and the friction coefficient, G = [r_band - r, dr/dmu] with dr/dmu a forward
difference of the band's runs at mu = 0 and FRICTION_PROBE_MU (no engine sensitivity through friction). Friction's
columns nest bridging's, so their p-values (2 and 1 degrees of freedom) decide between them. The refit of either
identifies the band model (with mu free for friction) from the fitted point.

A model of the band itself (the second paper's, `[model] garment = "explicit"`) is diagnosed the same way with the
effects its deck carries (`effects.Effect.garments`: those of the tissues and bones, written into the band's last
step), their columns through the frictionless contact from the engine; friction is the column dr/dmu alone, at
the band's own coefficient (0, or the one the model fixed: its refit frees it). Through friction the engine carries
the sensitivities along the put-on's path of what acts on the elements (material constants, hence the local probe,
and a volume change or an axial stretch that the last step brings in); a bone's rigid motion and the band's prestretch
profile (band_profile) are differences of runs there.

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

Locate. When the misfit is above the floor, every place a local stiffness change may take is scored the
same way, as a one-parameter effect: the material groups of `heterogeneity` (15-degree sectors, depth bands),
contiguous in one tissue kind over 1 to 6 sectors (up to 90 degrees) and a run of bands, its column the sum of
its groups' dr/dln E (E every modulus of the group, the `local` probe, one engine run). The best places that share no group are reported
(tissue, sector, depth, area; Bonferroni over the N places tried), and the best is refitted (`patch:...`). Its
BIC counts the choice of the place among N, 2 ln N on top of its parameter's ln n (a prior 1/N on each place).
It explains when it reaches EXPLAINED_FACTOR x the floor with a BIC below the baseline's; when a catalog
effect explained the residual too, the lower BIC wins, and a local change that wins takes "explained" away
from the catalog (`weigh_local`).

Refit. `refit` identifies again with the effect's parameters free (Levenberg-Marquardt from the fitted
point, effect at zero) and compares misfit, AIC = chi^2 + 2k and BIC = chi^2 + k ln n (known sigma:
-2 ln L = chi^2 + const) before and after, so that an effect that does not pay for its parameters is
seen not to.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy import stats
from scipy.spatial import cKDTree

from ..engine.runner import OK, Evaluator, Progress
from ..fit.identify import FitResult, interval_identifiable, jacobian_in_x, levenberg_marquardt, steps_into_box
from ..fit.levels import LevelsModel
from ..model.effects import CATALOG, LOCAL_PROBE, effect
from ..model.forward import LegModel
from ..model.heterogeneity import (
    PATCH_PREFIX,
    SECTOR_DEG,
    Group,
    groups_for,
    patch_candidates,
    patch_groups,
    patch_name,
    stiffness_field_text,
)
from ..model.regions import SECTORS, LegFrame, depth_band

ALPHA = 0.01
REFIT_FTOL = 1e-5            # LM stops when chi^2 falls by less than this fraction (a useless effect crawls)
TIE_FRACTION = 0.1           # statistics within 10 % of the best: the score cannot tell them apart, refits do
MAX_TIED = 3                 # effects predicted to explain are refitted beside the best up to this many ties
EXPLAINED_FACTOR = 1.5       # predicted misfit within 1.5 x the noise floor: the effect explains the residual
# the error model agrees with the measured errors to a chi^2/n of 0.8-1.25 (benchmarks/imaging.py: every band, pooled
# over the cases of both renderers and of another program): an explaining refit above 1.25 x has not reached the
# floor, and the verdict says so
FLOOR_AGREEMENT = 1.25
MAX_DESIGN_EFFECT = 100.0
ORTHOGONAL_ROUNDOFF = 1e-8   # |g_perp| / |g| below this: the fitted parameters absorb the effect entirely
FD_FRACTION = 1.0            # forward-difference step of an effect parameter, in units of its scale
FRICTION_PROBE_MU = 0.05     # forward-difference step of the friction coefficient from a frictionless band
# The probe from a frictionless band (a Laplace-law model's diagnosis) releases the band in tenths, not the fit's
# twentieths: its reference, the frictionless band, does not depend on the path, and one probe needs no grid shared
# with other points of a fit. On calfit's images-first phantom the probe took 6.5 s in tenths against 9.5 s, its
# column of leg displacements 0.995 correlated with the twentieths' (11 % RMS apart; fifths: 4.0 s, 0.985, 20 %).
# From a band with friction (its own model's diagnosis) the reference has a path, so the probe keeps its grid.
FRICTION_PROBE_RELEASE_STATIC = (0.1, 1.0, 1e-5, 0.1)
MIN_REGION_POINTS = 3        # a named region holds at least this many measurements
PATCHES_KEPT = 3             # candidate places for a local stiffness change reported, best first
# the band's own variant that is not ranked on a model of the band, and why (said in diagnosis.json "not_ranked"); its
# prestretch varying around the leg is the catalog's band_profile
BAND_VARIANTS_NOT_RANKED = {
    "band stiffness": "a band stiffer by a factor s carries s T at the same stretch, and the tissues' moduli scaled by "
                      "s then give the same displacements (both x1.5 moved the leg by 3.3 um of 0.98 mm, "
                      "tests/model/test_garment.py; 3.1 um at mu = 0.3): displacements cannot tell it from the tissues' "
                      "scale; the tension's uncertainty carries it into the pressures (Table 4)",
}


@dataclass
class EffectScore:
    effect: str
    parameters: list[str]
    statistic: float
    dof: int
    p_value: float
    predicted_reduction: float        # of the misfit F, mm^2
    predicted_misfit: float           # F - reduction, mm^2
    orthogonal_fraction: list[float]  # |g_perp| / |g| per parameter
    predicted_values: list[float]     # the linearized refit's parameter values
    significant: bool = False
    tied_with: list[str] = field(default_factory=list)   # effects the score cannot tell from this one


@dataclass
class ResidualMaps:
    """The residual where it is: vectors at the points, RMS per tissue and per angular sector."""

    positions_mm: list[list[float]]
    residual_mm: list[list[float]]          # u_model - u_measured at each point
    per_region_rms_mm: dict[str, float]     # per tissue
    sector_centre_deg: list[float]          # display angles, counter-clockwise from the image's +x axis
    sector_rms_mm: list[float]
    sector_radial_mm: list[float]           # mean radial component (+ outwards: the model is too far out)
    sector_count: list[int]
    centre_mm: list[float]
    worst_sector_deg: float
    sector_names: list[str] = field(default_factory=list)   # "posterior sector 240-270 deg"
    worst_region: str = ""                  # "fat, posterior sector 240-270 deg, 0-5 mm under the skin"
    worst_region_rms_mm: float = 0.0
    worst_region_share: float = 0.0         # its share of the sum of squared residuals


@dataclass
class PatchScore:
    """A candidate place for a local stiffness change: contiguous material groups of one tissue (module text)."""

    effect: str                       # patch:<groups>, the effect that refits it
    tissue: str                       # fat or muscle
    sector_deg: list[float]           # [start, end], display angles counter-clockwise
    centre_deg: float
    depth_mm: list[float]             # [min, max] distance to the skin of its elements' centroids
    area_cm2: float
    place: str                        # "muscle, posterior sector 240-330 deg, 12-35 mm under the skin"
    statistic: float
    p_value: float                    # Bonferroni over the candidates tried
    predicted_misfit: float
    predicted_ratio: float            # stiffness in the patch / stiffness of the tissue, linearized
    significant: bool = False
    places_tried: int = 1             # candidates scored: the choice of this one costs 2 ln N on BIC


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
    levels: list[dict] = field(default_factory=list)   # several socks: each level's misfit and floor (`level_misfits`)
    level_maps: list[ResidualMaps] = field(default_factory=list)   # and its residual maps, level by level

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "Diagnosis":
        names = {f for f in cls.__dataclass_fields__}
        values = {k: v for k, v in data.items() if k in names}
        values["ranking"] = [EffectScore(**s) for s in data["ranking"]]
        values["maps"] = ResidualMaps(**data["maps"])
        values["patches"] = [PatchScore(**p) for p in data.get("patches", [])]
        values["level_maps"] = [ResidualMaps(**m) for m in data.get("level_maps", [])]
        return cls(**values)


# --- statistics ---------------------------------------------------------------------------------

def neighbour_correlation(positions_mm: np.ndarray, residual: np.ndarray,
                          levels: Sequence[slice] | None = None) -> float:
    """Correlation of each point's residual vector with that of its nearest neighbour in the same garment level
    (`levels`: each level's rows; the levels' windows are the same windows of I0, each its own twin otherwise)."""
    vectors = np.asarray(residual, float).reshape(-1, 2)
    positions_mm = np.asarray(positions_mm, float)
    products = squares = 0.0
    for rows in levels or [slice(0, len(vectors))]:
        own, places = vectors[rows], positions_mm[rows]
        if len(own) < 3:
            continue
        _, nearest = cKDTree(places).query(places, k=2)
        products += float(np.sum(own * own[nearest[:, 1]]))
        squares += float(np.sum(own * own))
    return products / max(squares, 1e-300) if squares else 0.0


def design_effect(rho: float) -> float:
    rho = min(max(rho, 0.0), 0.999)
    return float(min((1.0 + rho) / (1.0 - rho), MAX_DESIGN_EFFECT))


def score_effect(r: np.ndarray, J: np.ndarray, G: np.ndarray, chi2_to_misfit: float, deff: float) -> dict:
    """Score statistic, predicted reduction and orthogonal fractions of one effect (module text)."""
    Q, _ = np.linalg.qr(J)
    G_perp = G - Q @ (Q.T @ G)
    r_perp = r - Q @ (Q.T @ r)
    norms = np.linalg.norm(G, axis=0)
    fraction = np.linalg.norm(G_perp, axis=0) / np.where(norms > 0, norms, 1.0)
    # in units of |g|, so that a direction the fitted parameters absorb (round-off left) counts as zero
    unit = G_perp / np.where(norms > 0, norms, 1.0)
    unit[:, fraction < ORTHOGONAL_ROUNDOFF] = 0.0
    U = unit.T @ r_perp
    solution, *_ = np.linalg.lstsq(unit.T @ unit, U, rcond=ORTHOGONAL_ROUNDOFF)
    reduction = float(max(U @ solution, 0.0))
    return {"statistic": reduction / deff, "reduction_chi2": reduction,
            "predicted_reduction": reduction * chi2_to_misfit, "orthogonal_fraction": fraction.tolist(),
            "step": (-solution / np.where(norms > 0, norms, 1.0)).tolist()}


def information_criteria(chi2: float, k: int, n: int) -> dict:
    return {"chi2": chi2, "k": k, "aic": chi2 + 2 * k, "bic": chi2 + k * np.log(n)}


# --- residual maps --------------------------------------------------------------------------------

def level_points(objective) -> list[slice]:
    """The rows of each garment level's points in the objective's stacked positions (one slice for one level)."""
    slices = getattr(objective, "slices", None)
    if not slices:
        return [slice(0, len(objective.positions_mm))]
    return [slice(rows.start // 2, rows.stop // 2) for rows in slices]


def level_misfits(objective, r: np.ndarray, n_parameters: int) -> list[dict]:
    """Each garment level's own misfit and noise floor at the joint residual r (`levels.JointDisplacementObjective.
    level_misfits`): which level the model fails at. Empty for one level."""
    parts = getattr(objective, "parts", None)
    if not parts:
        return []
    # each level's floor counts its share of the fitted parameters, p n_k / n (as identification.json's levels)
    floors = [part.noise_floor(n_parameters * part.n_residuals / objective.n_residuals) for part in parts]
    return [{"level": k, "misfit": float(misfit), "noise_floor": floor, "misfit_over_floor": float(misfit) / floor}
            for k, (floor, misfit) in enumerate(zip(floors, objective.level_misfits(r)), 1)]


def level_maps(objective, residual_mm: np.ndarray, frame: LegFrame) -> list[ResidualMaps]:
    """The residual maps of each garment level's points (`residual_maps`); empty for one level."""
    if not getattr(objective, "parts", None):
        return []
    residual_mm = np.asarray(residual_mm, float).reshape(-1, 2)
    return [residual_maps(objective.positions_mm[rows], residual_mm[rows], frame) for rows in level_points(objective)]


def residual_maps(positions_mm: np.ndarray, residual_mm: np.ndarray, frame: LegFrame) -> ResidualMaps:
    """The residual per tissue and per sector, and the named region (tissue, sector, depth band) that holds
    the largest share of its squares."""
    positions_mm = np.asarray(positions_mm, float)
    residual_mm = np.asarray(residual_mm, float).reshape(-1, 2)
    squared = np.sum(residual_mm ** 2, axis=1)
    tissues = np.array(frame.tissues(positions_mm))
    per_region = {str(name): float(np.sqrt(np.mean(squared[tissues == name]))) for name in np.unique(tissues)}
    offset = positions_mm - frame.centre_mm
    radial = np.sum(residual_mm * offset, axis=1) / np.maximum(np.linalg.norm(offset, axis=1), 1e-12)
    sector = frame.sectors(positions_mm)
    centres = ((np.arange(SECTORS) + 0.5) * 360.0 / SECTORS).tolist()
    rms, mean_radial, count = [], [], []
    for k in range(SECTORS):
        inside = sector == k
        count.append(int(inside.sum()))
        rms.append(float(np.sqrt(np.mean(squared[inside]))) if inside.any() else 0.0)
        mean_radial.append(float(np.mean(radial[inside])) if inside.any() else 0.0)
    bands = np.array([depth_band(d) for d in frame.depth_mm(positions_mm)])
    worst, worst_sum, worst_rms = "", -1.0, 0.0
    for key in {(t, k, b) for t, k, b in zip(tissues, sector, bands)}:
        inside = (tissues == key[0]) & (sector == key[1]) & (bands == key[2])
        if inside.sum() >= MIN_REGION_POINTS and squared[inside].sum() > worst_sum:
            worst_sum, worst_rms = float(squared[inside].sum()), float(np.sqrt(np.mean(squared[inside])))
            worst = f"{key[0]}, {frame.sector_label(int(key[1]))}, {key[2]}"
    return ResidualMaps(positions_mm.tolist(), residual_mm.tolist(), per_region, centres, rms, mean_radial, count,
                        frame.centre_mm.tolist(), float(centres[int(np.argmax(rms))]),
                        [frame.sector_label(k) for k in range(SECTORS)], worst, worst_rms,
                        worst_sum / max(float(squared.sum()), 1e-300))


# --- the diagnosis ------------------------------------------------------------------------------

def candidate_effects(model: LegModel) -> tuple[list[str], dict[str, str]]:
    """Catalog effects that the diagnosis can try on this model, and why the others are not tried. On a Laplace-law
    model the garment's effects (friction, bridging) are tried by switching to the explicit band (`garment_model`),
    which carries the model's effects on the tissues and bones but not those of Laplace's law itself. On the explicit
    band, every effect its deck carries is tried (`effects.Effect.garments`), and friction: switched on, or its fixed
    coefficient freed."""
    sets, nodes = list(model.mesh.element_sets()), list(model.mesh.node_sets)
    blockers = laplace_only(model)
    candidates, skipped = [], {}
    for name, item in CATALOG.items():
        if name in model.effects or name in model.fixed_effects:
            continue
        if model.garment == "laplace" and item.garments == ("explicit",) and item.apply is not None:
            reason = ("it is the explicit band's own, held by friction: diagnose a model of the band ([model] "
                      "garment = \"explicit\" and friction in case.toml)")
        elif model.garment == "laplace" and "laplace" not in item.garments:   # friction, bridging: switch to the band
            reason = (f"the explicit band it needs cannot carry {', '.join(blockers)}, which belong to Laplace's law"
                      if blockers else None)
        else:
            reason = (item.unavailable(sets, nodes, model.garment) or model.law_conflict(name)
                      or model.garment_conflict(name))
        if reason:
            skipped[name] = reason
        else:
            candidates.append(name)
    if model.garment == "explicit":
        skipped.update(BAND_VARIANTS_NOT_RANKED)
    return candidates, skipped


def with_changes(model, **changes):
    """`dataclasses.replace` of the leg model, or of the one leg model under every garment level of a
    `levels.LevelsModel` (the diagnosis of several socks adds its effects to every level)."""
    return model.replace(**changes) if isinstance(model, LevelsModel) else replace(model, **changes)


def laplace_only(model: LegModel) -> list[str]:
    """What of a model the explicit band cannot carry: the effects (fitted or fixed) and the tabulated tension
    profile that change Laplace's law itself."""
    named = [name for name in tuple(model.effects) + tuple(model.fixed_effects) if "explicit" not in effect(name).garments]
    return named + (["the tabulated tension profile"] if model.tension_profile else [])


def garment_model(model: LegModel, effects: Sequence[str] = ()) -> LegModel:
    """The model of the garment's effects: the model's mesh, laws, elements, tension and effects with the explicit
    band (Bouten and Drapier sec. 2.5) instead of p = T / r, frictionless, its friction coefficient fitted (the
    parameter mu after the others) when `effects` holds friction. On a model of the band already, the same band."""
    blockers = laplace_only(model)
    if blockers:
        raise ValueError(f"the explicit band cannot carry {', '.join(blockers)}: they belong to Laplace's law")
    return with_changes(model, garment="explicit", friction_mu=0.0 if "friction" in effects else model.friction_mu,
                        effects=tuple(model.effects) + (("friction",) if "friction" in effects else ()))


class GarmentRuns:
    """The explicit band's runs that give the garment's effects their columns (`garment_columns`): the band at
    theta (on a Laplace-law model) and, for friction, the band at FRICTION_PROBE_MU more (released in
    FRICTION_PROBE_RELEASE_STATIC from a frictionless band). They do not depend on the fitted model's residual, so
    with side_by_side (the run may use more than one engine at a time) they start at once, in threads beside the
    ranking's probe: a friction run is most of a diagnosis (in twentieths, 7-9 s of the images-first path's 12 s on
    calfit's phantom; in tenths, 6.5 s). Each thread's evaluator runs its engine itself
    (one worker: no process forked from a thread) and silently (one stage line at a time); `records` shows the
    wait for those still running as a stage of its own. Without side_by_side they run one after the other when
    their records are asked for, each its own stage, as any evaluation.

    evaluator_factory(model, progress=None, workers=None) -> Evaluator (None: as the run's)."""

    def __init__(self, evaluator_factory, model: LegModel, theta: Sequence[float], names: Sequence[str],
                 side_by_side: bool = False):
        self.model, self.names = model, list(names)
        runs = {}
        if self.names and model.garment != "explicit":
            runs["band"] = (garment_model(model), list(theta), {})
        if "friction" in self.names:
            path = {"release_static": FRICTION_PROBE_RELEASE_STATIC} if model.friction_mu == 0.0 else {}
            runs["sliding"] = (garment_model(model, ("friction",)), list(theta) + [model.friction_mu + FRICTION_PROBE_MU],
                               path)
        self._points = {label: (point, options) for label, (_, point, options) in runs.items()}
        self._pool = ThreadPoolExecutor(max_workers=len(runs)) if side_by_side and runs else None
        quiet = {"progress": False, "workers": 1} if self._pool else {}
        self.evaluators = {label: evaluator_factory(m, **quiet) for label, (m, _, _) in runs.items()}
        self._started = {label: self._pool.submit(self.evaluators[label], point, **options)
                         for label, (point, options) in self._points.items()} if self._pool else {}

    def records(self, progress: bool = True) -> dict[str, dict]:
        """Every run's record: waited for, or run now."""
        display = Progress("diagnose, the garment band", progress and bool(self._started))
        display.begin_batch(len(self._started))
        try:
            records = {}
            for label, (point, options) in self._points.items():
                started = self._started.get(label)
                records[label] = started.result() if started else self.evaluators[label](point, **options)
                display.advance(records[label])
        finally:
            display.close()
        return records

    @property
    def launched(self) -> int:
        return sum(e.launched for e in self.evaluators.values())

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        for evaluator in self.evaluators.values():
            evaluator.close()

    def __enter__(self) -> "GarmentRuns":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def garment_columns(runs: GarmentRuns, r: np.ndarray, progress: bool = True) -> tuple[dict[str, np.ndarray], int]:
    """G of the garment's effects at theta (module text) from the band's runs. On a Laplace-law model, bridging is
    a switch s from Laplace's law (s = 0) to the band (s = 1), linearized as r + s (r_band - r); friction adds to it
    dr/dmu at mu = 0 by a forward difference of step FRICTION_PROBE_MU (friction has no engine sensitivity): its two
    columns nest bridging's one, so that their p-values decide between them. On the band's model, friction is that
    difference alone, from the band's own coefficient (0, or the one the model fixed, which its refit frees).
    Returns the columns and the engine runs they took."""
    records = runs.records(progress)
    band = _residuals(records["band"]) if "band" in records else r
    columns = {"bridging": (band - r)[:, None]}
    if "friction" in runs.names:
        slope = (_residuals(records["sliding"]) - band) / FRICTION_PROBE_MU
        columns["friction"] = slope[:, None] if runs.model.garment == "explicit" else np.column_stack([band - r, slope])
    return {name: columns[name] for name in runs.names}, runs.launched


def garment_parameters(model: LegModel, name: str) -> list[str]:
    """The parameters a garment effect's columns stand for (`garment_columns`)."""
    switch = [] if model.garment == "explicit" else ["bridging"]
    return switch + (["mu"] if name == "friction" else [])


def _residuals(record: dict) -> np.ndarray:
    if record["status"] != OK:
        raise RuntimeError(f"the engine failed at the diagnosis point: {record['message']}")
    return np.asarray(record["outputs"]["residuals"], float)


def probe_jacobian(evaluator: Evaluator, theta: Sequence[float]) -> tuple[np.ndarray, np.ndarray, str]:
    """r and dr/dtheta of the evaluator's model at theta: from the engine's sensitivities where the record has
    them, forward differences for the other columns (`identify.jacobian_in_x`: steps of 1e-3 in ln theta for
    constants, FD_FRACTION x `scale` for effects); the source says which."""
    space = evaluator.model.space
    theta = np.asarray(theta, float)
    record = evaluator(theta)
    r = _residuals(record)
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
    for score in ranking:
        score.significant = bool(lack_of_fit and score.p_value < alpha / max(len(ranking), 1))
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
    explained, verdict = _verdict(ranking, misfit, floor, lack_of_fit)
    maps = residual_maps(positions_mm, residual_mm, frame)
    patches = []
    if probing and lack_of_fit and source.startswith("engine"):
        local = jacobian[:, column:column + len(probe.groups)]
        patches = locate(r, J, local, probe.groups, frame, chi2_to_misfit, deff, misfit, alpha)
    return Diagnosis(list(model.effects), list(model.space.names), list(map(float, theta)), misfit, floor, chi2, n,
                     lack_of_fit_p, deff, rho, ranking, explained, verdict, maps, runs, source,
                     time.perf_counter() - began, skipped, patches, level_misfits(objective, r, p),
                     level_maps(objective, residual_mm, frame))


def locate(r: np.ndarray, J: np.ndarray, local: np.ndarray, groups: Sequence[Group], frame: LegFrame,
           chi2_to_misfit: float, deff: float, misfit: float, alpha: float = ALPHA,
           keep: int = PATCHES_KEPT) -> list[PatchScore]:
    """Score every candidate patch (`heterogeneity.patch_candidates`) as a one-parameter effect whose column is
    the sum of its groups' dr/dlnE (module text); the best `keep` places that share no group, best first."""
    Q, _ = np.linalg.qr(J)
    r_perp = r - Q @ (Q.T @ r)
    local_perp = local - Q @ (Q.T @ local)
    candidates = patch_candidates(list(groups))
    scored = []
    for members, start, width in candidates:
        g = local[:, members].sum(axis=1)
        g_perp = local_perp[:, members].sum(axis=1)
        norm2 = float(g_perp @ g_perp)
        if norm2 <= (ORTHOGONAL_ROUNDOFF * np.linalg.norm(g)) ** 2:
            continue
        projection = float(g_perp @ r_perp)
        scored.append((projection ** 2 / norm2, -projection / norm2, members, start, width))
    scored.sort(key=lambda item: -item[0])
    chosen, used = [], set()
    for reduction, step, members, start, width in scored:
        if used & set(members):
            continue
        used |= set(members)
        statistic = reduction / deff
        p_value = float(min(1.0, stats.chi2.sf(statistic, 1) * len(candidates)))
        chosen.append(_patch_score([groups[k] for k in members], start, width, frame, statistic, p_value,
                                   misfit - reduction * chi2_to_misfit, float(np.exp(step)), p_value < alpha,
                                   len(candidates)))
        if len(chosen) == keep:
            break
    return chosen


def _patch_score(members: Sequence[Group], start: int, width: int, frame: LegFrame, statistic: float,
                 p_value: float, predicted_misfit: float, ratio: float, significant: bool,
                 places_tried: int) -> PatchScore:
    low, high = start * SECTOR_DEG, (start + width) * SECTOR_DEG
    centre = ((low + high) / 2.0) % 360.0
    depth = [min(g.depth_range_mm[0] for g in members), max(g.depth_range_mm[1] for g in members)]
    tissue = members[0].kind
    place = (f"{tissue}, {frame.direction(centre)} sector {low % 360:.0f}-{high % 360 or 360:.0f} deg, "
             f"{depth[0]:.0f}-{depth[1]:.0f} mm under the skin")
    return PatchScore(patch_name([g.name for g in members]), tissue, [low % 360.0, high % 360.0 or 360.0], centre, depth,
                      sum(g.area_mm2 for g in members) / 100.0, place, statistic, p_value, predicted_misfit, ratio,
                      significant, places_tried)


def settle_ties(diagnosis: Diagnosis, refits: Sequence["Refit"]) -> None:
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


def refit_verdict(diagnosis: Diagnosis, refits: Sequence["Refit"]) -> tuple[bool, str]:
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


def judged_ratio(fit: "Refit") -> float:
    """A refit's misfit over the floor as its verdict judges it: against its own floor when the skin's uncertainty
    was estimated again at its parameters (the baseline's may be far from the refit's, a baseline on a bound)."""
    return fit.misfit_over_floor if fit.own_floor is None else fit.own_floor["misfit_over_floor"]


def unfixed_constants(diagnosis: Diagnosis, fit: "Refit") -> str:
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
        f"{name} (95 % interval {'unbounded' if half is None else f'+-{100 * half:.1f} %'})" for name, half in loose))


def _verdict(ranking: list[EffectScore], misfit: float, floor: float, lack_of_fit: bool) -> tuple[bool, str]:
    ratio = misfit / floor if floor > 0 else np.inf
    if not lack_of_fit:
        return False, f"the model fits to the noise floor (misfit {ratio:.2f} x the floor): no effect is missing"
    significant = [s for s in ranking if s.significant]
    if not significant:
        return False, (f"misfit {ratio:.2f} x the noise floor, and no catalog effect explains the residual "
                       "significantly: the missing physics is outside the catalog")
    best = significant[0]
    after = best.predicted_misfit / floor
    if after <= EXPLAINED_FACTOR:
        return True, (f"misfit {ratio:.2f} x the noise floor; {best.effect} explains it (predicted "
                      f"{after:.2f} x the floor after the refit)")
    return False, (f"misfit {ratio:.2f} x the noise floor; the best effect, {best.effect}, would leave "
                   f"{after:.2f} x the floor: no catalog effect explains the residual")


# --- refit --------------------------------------------------------------------------------------

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
    """Levenberg-Marquardt with the effects' parameters free (starting at zero), from the fitted theta and, unless
    that fit settled (`settled`), from the usual start (Avril et al. Table 2 central values); the better fit is kept.
    The second start matters when the missing effect dragged the baseline fit to a bound or far from the tissue's
    values; after a fit at the noise floor with no parameter on a bound it could only move chi^2 within the noise
    (with friction, refits from two starts took 110 of a diagnosis's 123 runs).
    Returns the fit and its residual u_model - u_measured (mm) at the points."""
    extended = refit_model(model, effects)
    # friction starts where the diagnosis probed it: at mu = 0 the friction forces vanish with their derivative's
    # one-sided difference, and Levenberg-Marquardt may not leave the bound
    extra = [(model.friction_mu or FRICTION_PROBE_MU) if name == "mu" else 0.0
             for name in extended.space.names[model.space.size:]]
    starts = [list(map(float, theta)) + extra, model.start() + extra]
    with evaluator_factory(extended) as evaluator:
        fits = [levenberg_marquardt(evaluator, starts[0], max_iterations=max_iterations, ftol=REFIT_FTOL)]
        if not settled(extended, evaluator(fits[0].theta), objective):
            fits.append(levenberg_marquardt(evaluator, starts[1], max_iterations=max_iterations, ftol=REFIT_FTOL))
        fit = min(fits, key=lambda f: f.cost)
        record = evaluator(fit.theta)
    # named by the effects asked for: the garment's band model lists none (bridging) or friction alone
    summary = replace(summarize_fit(extended, fit, record, objective), effects=list(model.effects) + list(effects))
    return summary, objective.residual_mm(_residuals(record))


def settled(model: LegModel, record: dict, objective, alpha: float = ALPHA) -> bool:
    """A fit that another start cannot better but within the noise: its chi^2 not above the noise's (the lack-of-fit
    test at `alpha`) and no parameter on its search box's edge."""
    if record["status"] != OK:
        return False
    r = _residuals(record)
    p = model.space.size
    if stats.chi2.sf(float(r @ r), len(r) - p - objective.nuisance_dof) < alpha:
        return False
    theta = np.asarray(record["theta"], float)
    return not np.any(np.isclose(theta, model.space.lower) | np.isclose(theta, model.space.upper))


def summarize_fit(model: LegModel, fit: FitResult, record: dict, objective) -> Refit:
    r = _residuals(record)
    chi2 = float(r @ r)
    criteria = information_criteria(chi2, model.space.size, len(r))
    floor = objective.noise_floor(model.space.size)
    return Refit(list(model.effects), list(model.space.names), list(fit.theta), float(record["cost"]),
                 float(record["cost"]) / floor, chi2, criteria["aic"], criteria["bic"], fit.as_dict(),
                 level_misfits(objective, r, model.space.size),
                 intervals=linearized_intervals(model, fit.theta, fit.standard_error_x))


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


def patch_elements(model: LegModel, patch_effect: str) -> np.ndarray:
    """0-based elements of the model's mesh in a patch (to draw it)."""
    members = set(patch_groups(patch_effect))
    groups = groups_for(model.mesh, [patch_effect])
    return np.concatenate([g.elements for g in groups if g.name in members] or [np.zeros(0, int)])


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

