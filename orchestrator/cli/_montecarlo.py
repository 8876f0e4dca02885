"""Parameter intervals by Monte-Carlo acceptance (Avril et al. sec. 2.2.6 and 3.1, Table 2).

    calfit montecarlo RUN_DIR [--draws N] [--threshold-factor F | --threshold X] [--seed S] [--workers N] [--json]

Around the identified point: profiles along each parameter, then N log-uniform draws in the box
they bound (within a factor 2); draws whose misfit is at most the threshold (default 1.5 times the
identified misfit) are kept and their ranges are the intervals. Parameters whose kept values span
more than a factor 1.5 are reported as poorly identified. Failed engine runs (no convergence,
bad deck, timeout) are recorded and counted, never fatal. Writes RUN_DIR/montecarlo.json.
"""

from __future__ import annotations

import argparse

from ..pipeline import intervals_summary, run_montecarlo
from ..study import RunFolderError
from ._common import add_parallel_arguments, emit, fail, parallel_options

HELP = "parameter intervals by Monte-Carlo acceptance below a misfit threshold (Table 2)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder of `calfit identify`")
    parser.add_argument("--draws", type=int, default=400, help="random draws (default 400)")
    parser.add_argument("--threshold-factor", type=float, default=1.5, help="keep misfit <= factor * best (default 1.5)")
    parser.add_argument("--threshold", type=float, help="absolute misfit threshold (overrides the factor)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_parallel_arguments(parser)


def run(args: argparse.Namespace) -> int:
    try:
        result = run_montecarlo(args.run_dir, draws=args.draws, threshold=args.threshold,
                                threshold_factor=args.threshold_factor, seed=args.seed, **parallel_options(args))
    except (RunFolderError, ValueError) as error:
        return fail(str(error))
    lines = intervals_summary(result)
    lines.append(f"{result['accepted']} of {result['draws']} draws kept (misfit <= {result['threshold']:.4g}); "
                 f"{result['failed']} failed evaluation(s) recorded")
    for failure in result["failures"][:5]:
        lines.append(f"  failed: {failure['status']}: {failure['message'][:160]}")
    emit(args, result, lines)
    return 0
