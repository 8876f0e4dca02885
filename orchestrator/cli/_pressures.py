"""Landmark pressures and their uncertainty (Avril et al. sec. 4.2 and 4.5, Tables 3 and 4).

    calfit pressures RUN_DIR [--draws 30] [--seed S] [--workers N] [--json] [--quiet]

Draws the parameters uniformly in the Monte-Carlo intervals, solves each draw and reads the
hydrostatic pressure -tr(sigma)/3 at the five landmarks of case.toml: mean, standard deviation
and coefficient of variation (Table 3); then the central values with the garment tension
±10 % (Table 4). Writes RUN_DIR/pressures.json.
"""

from __future__ import annotations

import argparse

from ..run.stages import pressure_summary, run_pressures
from ._common import (
    add_parallel_arguments,
    emit,
    fail,
    honours_quiet,
    parallel_options,
    whole_number,
)

HELP = "pressures at the landmarks with their uncertainty (Tables 3 and 4)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder of `calfit identify` and `calfit montecarlo`")
    parser.add_argument("--draws", type=whole_number(1), default=30, help="draws in the intervals (default 30, as the paper)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    add_parallel_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        result = run_pressures(args.run_dir, draws=args.draws, seed=args.seed, **parallel_options(args))
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    lines = pressure_summary(result)
    lines.append(f"{result['draws']} draws in {result['wall_time_s']:.2f} s; {result['failed']} failed evaluation(s)")
    emit(args, result, lines)
    return 0
