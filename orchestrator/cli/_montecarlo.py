"""Parameter intervals of an identified run (Avril et al. sec. 2.2.6 and 3.1, Table 2).

    calfit montecarlo RUN_DIR [--method auto|noise|threshold] [--draws N] [--threshold-factor F | --threshold X]
                      [--seed S] [--workers N] [--json] [--quiet]

noise (the default after a fit to measured displacements): 95 % intervals from refits to N synthetic data
sets (default 200) drawn from the measurements' covariance (overlapping DIC windows and the model's
geometry uncertainty included; inflated by the misfit over its floor when above 1), two Gauss-Newton steps
each with the engine's sensitivities. A parameter is identifiable when its interval lies within ±10 % of its
value; one whose draws pile on the search box's edge is reported as on a bound.
threshold (Avril et al.; the only choice after the contour mismatch): profiles along each parameter, then N
log-uniform draws (default 400) in the box they bound (within a factor 2); draws whose misfit is at most the
threshold (default 1.5 times the identified misfit) are kept and their ranges are the intervals; parameters
whose kept values span more than a factor 1.5 are poorly identified.
Failed engine runs are recorded and counted, never fatal. Writes RUN_DIR/montecarlo.json.
"""

from __future__ import annotations

import argparse

from ..run.stages import intervals_summary, run_montecarlo
from ._common import (
    add_parallel_arguments,
    emit,
    fail,
    honours_quiet,
    parallel_options,
    whole_number,
)

HELP = "parameter intervals by Monte-Carlo: over the measurement noise, or below a misfit threshold (Table 2)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder of `calfit identify`")
    parser.add_argument("--method", choices=("auto", "noise", "threshold"), default="auto",
                        help="noise: refits to data drawn from the measurements' covariance (default with measured "
                             "displacements); threshold: Avril et al.'s acceptance (default with the contour mismatch)")
    parser.add_argument("--draws", type=whole_number(1), help="random draws (default 200 noise, 400 threshold)")
    parser.add_argument("--threshold-factor", type=float, default=1.5, help="keep misfit <= factor * best (default 1.5)")
    parser.add_argument("--threshold", type=float, help="absolute misfit threshold (overrides the factor)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_parallel_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        result = run_montecarlo(args.run_dir, method=args.method, draws=args.draws, threshold=args.threshold,
                                threshold_factor=args.threshold_factor, seed=args.seed, **parallel_options(args))
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    lines = intervals_summary(result)
    if result["method"] == "threshold":
        lines.append(f"{result['accepted']} of {result['draws']} draws kept (misfit <= {result['threshold']:.4g}); "
                     f"{result['failed']} failed evaluation(s) recorded")
        for failure in result["failures"][:5]:
            lines.append(f"  failed: {failure['status']}: {failure['message'][:160]}")
    else:
        lines.append(f"{result['engine_runs']} engine runs, {result['failed']} failed draw(s), {result['wall_time_s']:.1f} s")
    emit(args, result, lines)
    return 0
