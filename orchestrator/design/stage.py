"""calfit design's stage: targets and identified slices in, design.json and its page out.

1. TARGET.toml read and checked (`targets`); the slices of the run folder or the volume study (`slices`), each
   target tied to the slices it holds on (a height to its slice, refused when there is none);
2. the garment by Levenberg-Marquardt (`solve`) from the case's own tension, on the identified parameters; then,
   while a min/max target is met with less than the asked probability, its margin from the spread over the draws
   and the tension (`uncertainty`) at the current design, and the solve again from there (at most MARGIN_PASSES
   times), so that each is met with the asked probability where the fabric's range allows;
3. the probabilities at the final design; infeasible when a target is missed at the identified parameters, the
   closest design then given with each target's shortfall;
4. Laplace's law beside it (`laplace`): its prediction for the designed garment, the garment it would have chosen,
   and what that garment gives through the FE model, with its probabilities;
5. the fabric's stretch and the circumference to knit at each height, when TARGET.toml gives the tensile test;
6. DIR/design.json, DIR/report/index.html and its figures (`report`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..core.errors import CaseError
from ..core.files import write_json
from . import laplace
from .slices import PROFILE_NAMES, DesignSlice, evaluate, read_slices
from .solve import Problem, levenberg_marquardt, shortfalls
from .targets import Targets, read_targets
from .uncertainty import DEFAULT_DRAWS, margins, spread

DESIGN_JSON = "design.json"
MET_TOLERANCE_MMHG = 0.05     # a target missed by less than this at the identified parameters counts as met
PROFILE_ANGLES_DEG = tuple(range(0, 360, 15))
MARGIN_PASSES = 3             # margins from the spread, and the solve again, at most this many times
PROBABILITY_SLACK = 0.01      # a probability this far under the one asked is taken as reached (the draws' error)


def run_design(source, target_path, out, *, workers: int = 1, draws: int | None = None,
               say: Callable[[str], None] | None = None, report: bool = True) -> dict:
    """The design of the module text; returns design.json's content."""
    began = time.perf_counter()
    say = say or (lambda line: None)
    out = Path(out)
    targets = read_targets(target_path)
    slices = read_slices(source, harmonics=targets.design.harmonics, slice_height=targets.design.slice_height)
    _check_places(targets, slices, Path(source))
    draws = draws or targets.design.draws or DEFAULT_DRAWS
    tension_rel = (targets.design.tension_rel_uncertainty if targets.design.tension_rel_uncertainty is not None
                   else slices[0].tension_rel_uncertainty)
    heights = [piece.height_name for piece in slices]

    def fe(k, tension, profile, theta=None):
        return evaluate(slices[k], tension, profile, theta)

    problem = Problem(targets, len(slices), heights, fe, targets.design.harmonics, workers=workers)
    low, high = targets.design.tension_range_N_per_mm
    start = np.concatenate([[np.clip(piece.tension_N_per_mm, low, high)] + [0.0] * problem.n_profile
                            for piece in slices])
    say(f"designing for {len(slices)} slice(s), {len(targets.targets)} target(s), T in [{low:g}, {high:g}] N/mm")
    first = levenberg_marquardt(problem, start, say=say)
    runs = first.engine_runs
    uncertain = spread(problem, slices, first.v, draws=draws, tension_rel=tension_rel, workers=workers)
    runs += uncertain.engine_runs
    solution, passes = first, 0
    bounded = [t.index for t in targets.targets if t.aim_mmHg is None]
    while (bounded or uncertain.graduation_probability is not None) and passes < MARGIN_PASSES \
            and not _probable(uncertain, bounded, targets.design.probability):
        # the spread grows with the pressure (the tension's share is relative): the margins again where they led
        passes += 1
        problem.margins = margins(problem, uncertain, targets.design.probability)
        say(f"margins for a probability of {targets.design.probability:g} (pass {passes}): " + ", ".join(
            f"{_margin_name(targets, key)} {m:.2f} mmHg" for key, m in problem.margins.items()))
        solution = levenberg_marquardt(problem, solution.v, say=say)
        runs += solution.engine_runs
        uncertain = spread(problem, slices, solution.v, draws=draws, tension_rel=tension_rel, workers=workers)
        runs += uncertain.engine_runs
    central = solution.responses
    missed = [s for s in shortfalls(problem, central) if s["shortfall_mmHg"] > MET_TOLERANCE_MMHG]
    graduation_ok = _graduated(problem, central)
    feasible = not missed and graduation_ok
    if not feasible:
        say("infeasible: " + "; ".join(f"{s['name']} misses by {s['shortfall_mmHg']:.2f} mmHg" for s in missed)
            + ("" if graduation_ok else "; the graduation is not met"))

    # Laplace's law: its view of the designed garment, and its own garment seen by the FE model
    laplace_problem = Problem(targets, len(slices), heights, lambda k, t, p, theta=None: laplace.evaluate(
        slices[k], t, p), targets.design.harmonics)
    laplace_solution = levenberg_marquardt(laplace_problem, start)
    laplace_of_design = [laplace.evaluate(piece, t, p) for piece, (t, p) in zip(slices, problem.split(solution.v))]
    laplace_fe = problem.responses(np.asarray(laplace_solution.v))
    runs += len(slices) * (1 if slices[0].laplace else 2)
    laplace_spread = spread(problem, slices, laplace_solution.v, draws=draws, tension_rel=tension_rel,
                            workers=workers)
    runs += laplace_spread.engine_runs
    result = {
        "source": str(Path(source).resolve()), "target_file": str(Path(target_path).resolve()),
        "status": "designed" if feasible else "infeasible", "feasible": feasible,
        "tension_N_per_mm": tension_table(problem, slices, solution.v),
        "tension_range_N_per_mm": [low, high], "harmonics": targets.design.harmonics,
        "probability_asked": targets.design.probability,
        "targets": target_rows(problem, central, uncertain),
        "graduated": targets.graduated, "graduation_probability": uncertain.graduation_probability,
        "shortfalls": missed,
        "slices": slice_rows(slices, problem, solution.v, central, laplace_of_design),
        "laplace": {"tension_N_per_mm": tension_table(problem, slices, laplace_solution.v),
                    "targets": target_rows(problem, laplace_fe, laplace_spread),
                    "slices": slice_rows(slices, problem, laplace_solution.v, laplace_fe,
                                         [laplace.evaluate(piece, t, p) for piece, (t, p)
                                          in zip(slices, problem.split(laplace_solution.v))]),
                    "graduation_probability": laplace_spread.graduation_probability},
        "sensitivity": ("the engine's: *SENSITIVITY, PRESSURE=YES of TENSION, SKIN"
                        + (" and the PROFILE lines" if problem.n_profile else "")) if slices[0].laplace
        else "a forward difference of 1 % of T (the explicit band has no Laplace load to differentiate)",
        "draws": uncertain.draws, "tension_rel_uncertainty": tension_rel,
        "iterations": first.iterations, "margin_passes": passes,
        "engine_runs": runs, "wall_time_s": time.perf_counter() - began,
    }
    if targets.fabric is not None:
        result["fabric"] = fabric_rows(targets, problem, slices, solution.v, central)
    out.mkdir(parents=True, exist_ok=True)
    if report:
        from .report import write_design_report

        result["report"] = str(write_design_report(out, result, slices, problem, solution).relative_to(out))
    result["wall_time_s"] = time.perf_counter() - began
    write_json(out / DESIGN_JSON, result)
    return result


def _probable(result, indices, asked: float) -> bool:
    """Every min/max target, and the graduation, met with the probability asked."""
    graduation = result.graduation_probability
    return all(result.probability[i] >= asked - PROBABILITY_SLACK for i in indices) and \
        (graduation is None or graduation >= asked - PROBABILITY_SLACK)


def _margin_name(targets: Targets, key) -> str:
    if isinstance(key[0], int):
        return f"{targets.targets[key[0] - 1].name} [{key[1]}]"
    return f"{key[0]} [{key[1]}]"


def _check_places(targets: Targets, slices: list[DesignSlice], source: Path) -> None:
    named = {piece.height_name for piece in slices}
    for target in targets.targets:
        if target.height is not None and target.height not in named:
            fix = (f"write slice_height = \"{target.height}\" under [design] if this slice is at {target.height}"
                   if len(slices) == 1 else "name that height in the volume case's [study] compression_heights_mm")
            raise CaseError(targets.path, f"[[target]] {target.index} ({target.name}) holds at {target.height}, and "
                                          f"{source} has no slice named {target.height}", fix)
        if target.kind == "landmark":
            held = [k for k, piece in enumerate(slices) if target.height is None or piece.height_name == target.height]
            lacking = [slices[k].run_dir for k in held if target.where not in slices[k].landmarks]
            if lacking:
                raise CaseError(targets.path, f"[[target]] {target.index} names landmark {target.where!r}, which "
                                              f"{lacking[0] / 'case.toml'} does not have",
                                "use one of " + ", ".join(slices[0].landmarks) + " or add it to [landmarks]")


def _graduated(problem: Problem, responses: list) -> bool:
    """The graduation met at the identified parameters (its residuals read the responses alone; v only sizes the
    weak terms, which are left out here)."""
    if not problem.targets.graduated or problem.n_slices < 2:
        return True
    r, _, labels = problem.residuals(np.zeros(problem.n_slices * problem.per_slice), responses)
    return all(value <= MET_TOLERANCE_MMHG for value, label in zip(r, labels)
               if label.startswith(("graduation", "D <=")))


def tension_table(problem: Problem, slices: list[DesignSlice], v) -> float | dict:
    """T as design.json gives it: a number (one slice, uniform), else a table against height and angle."""
    parts = problem.split(v)
    if len(slices) == 1 and not problem.n_profile:
        return parts[0][0]
    table = {"heights_mm": [piece.height_mm for piece in slices], "height_names": [p.height_name for p in slices],
             "tension_N_per_mm": [t for t, _ in parts]}
    if problem.n_profile:
        angles = np.radians(PROFILE_ANGLES_DEG)
        table["angles_deg"] = list(PROFILE_ANGLES_DEG)
        table["profile"] = [dict(zip(PROFILE_NAMES, map(float, p))) for _, p in parts]
        table["values"] = [[float(t * (1 + sum(c * (np.cos if n[0] == "a" else np.sin)(int(n[1]) * a)
                                               for n, c in zip(PROFILE_NAMES, p)))) for a in angles]
                           for t, p in parts]
        table["angle_convention"] = "the deck's polar angle about the skin's centroid, image frame (x right, y down)"
    return table


def target_rows(problem: Problem, responses: list, result) -> list[dict]:
    rows = []
    for target in problem.targets.targets:
        held = problem.applies(target)
        values = [responses[k].value(target.kind, target.where) for k in held]
        # the slice nearest missing: the lowest against a minimum, the highest against a maximum
        k = held[int(np.argmin(values))] if target.min_mmHg is not None and target.max_mmHg is None else \
            held[int(np.argmax(values))] if target.max_mmHg is not None and target.min_mmHg is None else held[0]
        value = responses[k].value(target.kind, target.where)
        std = result.std((target.index, k))
        rows.append({"name": target.name, "kind": target.kind, "where": target.where, "height": target.height,
                     "min_mmHg": target.min_mmHg, "max_mmHg": target.max_mmHg, "aim_mmHg": target.aim_mmHg,
                     "source": target.source, "value": value, "unit": "mmHg", "std_mmHg": std,
                     "slice": k, "values_mmHg": values, "probability_met": result.probability[target.index],
                     "probability_se": result.probability_se[target.index]})
    return rows


def slice_rows(slices: list[DesignSlice], problem: Problem, v, responses: list, laplace_responses: list) -> list[dict]:
    rows = []
    for piece, (tension, profile), fe, law in zip(slices, problem.split(v), responses, laplace_responses):
        rows.append({"slice": piece.name, "height_name": piece.height_name, "height_mm": piece.height_mm,
                     "effects": list(piece.model.effects), "garment_model": piece.model.garment,
                     "tension_N_per_mm": tension, "profile": [float(c) for c in profile],
                     "landmarks_mmHg": fe.landmarks, "skin_mean_mmHg": fe.skin_mean, "skin_max_mmHg": fe.regions,
                     "laplace_landmarks_mmHg": law.landmarks, "laplace_skin_mean_mmHg": law.skin_mean,
                     "laplace_skin_max_mmHg": law.regions,
                     "unloaded_perimeter_mm": piece.unloaded_perimeter_mm,
                     "deformed_perimeter_mm": fe.deformed_perimeter_mm})
    return rows


def fabric_rows(targets: Targets, problem: Problem, slices, v, responses) -> list[dict]:
    """The fabric's stretch at each height's designed tension (the tensile test read backwards) and the
    circumference to knit: the leg's girth under the garment (the FE's deformed skin) over that stretch."""
    fabric = targets.fabric
    rows = []
    for piece, (tension, _), fe in zip(slices, problem.split(v), responses):
        inside = fabric.tension_N_per_mm[0] <= tension <= fabric.tension_N_per_mm[-1]
        stretch = float(np.interp(tension, fabric.tension_N_per_mm, fabric.stretch)) if inside else None
        rows.append({"slice": piece.name, "height_name": piece.height_name, "tension_N_per_mm": tension,
                     "stretch": stretch, "leg_circumference_mm": fe.deformed_perimeter_mm,
                     "knit_circumference_mm": fe.deformed_perimeter_mm / stretch if stretch else None,
                     "note": None if inside else "the tension is outside the tensile test's range"})
    return rows
