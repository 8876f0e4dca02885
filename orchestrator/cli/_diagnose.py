"""Where the identified model fails and which physical effect is missing (docs/method/diagnosis.md).

    calfit diagnose RUN_DIR [--refit auto|none|EFFECT[,EFFECT]|auto,EFFECT] [--alpha 0.01] [--no-engine-sensitivities]
                    [--workers N] [--json] [--quiet]
    calfit diagnose --catalog

Compares the model identified by `calfit identify` with the measured displacements (the DIC windows
measured from the images, or points.csv): the misfit against the noise floor of the measurements (their
covariance and the model's geometry uncertainty), the residual per tissue and per sector around the leg
(named by anatomy: "fat, posterior sector 240-270 deg, 0-5 mm under the skin"), and for every catalog
effect not in the model its score
statistic, p-value (corrected for residuals correlated in space) and the misfit a refit with it
would reach. Then (--refit auto) walks the path: the best candidates refitted, the one that pays
added, the catalog ranked again on the new residual, an effect later ones make unneeded removed,
until the model reaches its floor or nothing significant is left; or refits with the effects named,
or not at all. Prints the before/after table (misfit, AIC, BIC, parameters), the path (misfit over
the floor at each step) and the verdict in one sentence. Writes RUN_DIR/diagnosis.json ("path",
"final"); `calfit report RUN_DIR` draws the error falling and each step's residual side by side.
`calfit identify CASE --out RUN --effects final` fits the final model (or --effects NAME,... any).
"""

from __future__ import annotations

import argparse

from ..diagnose.diagnosis import Diagnosis
from ..diagnose.refit import Refit
from ..diagnose.score import ALPHA
from ..diagnose.stepwise import path_lines
from ..diagnose.verdict import comparison_lines, level_lines, ranking_lines
from ..model.effects import describe, parse_effects
from ..run.diagnose_stage import landmark_pressure_lines
from ..run.stages import run_diagnose
from ..run.timings import timing_line
from ._common import add_parallel_arguments, emit, fail, honours_quiet, parallel_options

HELP = "rank the physical effects missing from an identified model, add them one after another down to the floor"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", nargs="?", help="run folder of `calfit identify` (measured displacements)")
    parser.add_argument("--refit", default="auto",
                        help="auto: refit with the best effect when significant (default); none; effect names, "
                             "comma-separated, each refitted on its own; or both, e.g. auto,bone_motion")
    parser.add_argument("--alpha", type=float, default=ALPHA, help=f"significance level (default {ALPHA})")
    parser.add_argument("--no-engine-sensitivities", action="store_true",
                        help="finite differences instead of the engine's du/dtheta")
    parser.add_argument("--catalog", action="store_true", help="list the effect catalog and exit")
    add_parallel_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    if args.catalog:
        print("\n".join(describe()))
        return 0
    if not args.run_dir:
        return fail("give the run folder: calfit diagnose RUN_DIR (or --catalog)")
    try:
        requested = [n.strip() for n in args.refit.split(",") if n.strip()]
        refit = [n for n in requested if n in ("auto", "none")] + list(parse_effects([n for n in requested
                                                                                    if n not in ("auto", "none")]))
        result = run_diagnose(args.run_dir, refit_effects=refit, alpha=args.alpha,
                              engine_sensitivities=not args.no_engine_sensitivities, **parallel_options(args))
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    lines = ranking_lines(Diagnosis.from_dict(result))
    before, after = Refit(**result["before"]), [Refit(**fit) for fit in result["refits"]]
    if after:
        lines += [""] + comparison_lines(before, after)
    if result.get("levels"):
        lines += [""] + level_lines(result["levels"], before, after)
    if len(result.get("path", [])) > 1 or (result.get("final") or {}).get("stopping", {}).get("tried"):
        lines += [""] + path_lines(result["path"], result["final"])
    pressures = landmark_pressure_lines((result.get("final") or {}).get("landmark_pressures"))
    if pressures:
        lines += ["", "the pressures at the landmarks, from the identified model to the final one:"] + pressures
    lines.append(f"{result['engine_runs']} engine runs for the ranking, {result['wall_time_s']:.1f} s; "
                 f"written to {args.run_dir}/diagnosis.json")
    lines.append(f"verdict: {result['verdict']}")
    lines += [line for line in [timing_line(result.get("timings"))] if line]
    emit(args, result, lines)
    return 0
