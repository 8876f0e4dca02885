"""The effects a diagnosis can try on a model, and the garment's effects' columns from the explicit band's runs.

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
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Sequence

import numpy as np

from ..engine.progress import Progress
from ..fit.levels import LevelsModel
from ..model.effects import CATALOG, effect
from ..model.forward import LegModel
from .score import residuals_of

FRICTION_PROBE_MU = 0.05     # forward-difference step of the friction coefficient from a frictionless band

# The probe from a frictionless band (a Laplace-law model's diagnosis) releases the band in tenths, not the fit's
# twentieths: its reference, the frictionless band, does not depend on the path, and one probe needs no grid shared
# with other points of a fit. On calfit's images-first phantom the probe took 6.5 s in tenths against 9.5 s, its
# column of leg displacements 0.995 correlated with the twentieths' (11 % RMS apart; fifths: 4.0 s, 0.985, 20 %).
# From a band with friction (its own model's diagnosis) the reference has a path, so the probe keeps its grid.
FRICTION_PROBE_RELEASE_STATIC = (0.1, 1.0, 1e-5, 0.1)

# the band's own variant that is not ranked on a model of the band, and why (said in diagnosis.json "not_ranked"); its
# prestretch varying around the leg is the catalog's band_profile
BAND_VARIANTS_NOT_RANKED = {
    "band stiffness": "a band stiffer by a factor s carries s T at the same stretch, and the tissues' moduli scaled by "
                      "s then give the same displacements (both x1.5 moved the leg by 3.3 um of 0.98 mm, "
                      "tests/model/test_garment.py; 3.1 um at mu = 0.3): displacements cannot tell it from the tissues' "
                      "scale; the tension's uncertainty carries it into the pressures (Table 4)",
}



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
    band = residuals_of(records["band"]) if "band" in records else r
    columns = {"bridging": (band - r)[:, None]}
    if "friction" in runs.names:
        slope = (residuals_of(records["sliding"]) - band) / FRICTION_PROBE_MU
        columns["friction"] = slope[:, None] if runs.model.garment == "explicit" else np.column_stack([band - r, slope])
    return {name: columns[name] for name in runs.names}, runs.launched



def garment_parameters(model: LegModel, name: str) -> list[str]:
    """The parameters a garment effect's columns stand for (`garment_columns`)."""
    switch = [] if model.garment == "explicit" else ["bridging"]
    return switch + (["mu"] if name == "friction" else [])
