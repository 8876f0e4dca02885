"""Run calfit-fe on one deck and print its result summary.

    calfit solve DECK.inp [-o OUTDIR] [--threads N] [--timeout S] [--json] [--quiet]

Exit code: 0 converged, 2 bad deck (the engine's FILE:LINE message on stderr),
3 not converged (the last converged state is written), 4 engine failure.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..core.errors import EngineFailed
from ..engine.results import EngineResults
from ..engine.runner import run_engine
from ._common import (
    add_output_arguments,
    folder,
    honours_quiet,
    positive_number,
    show_progress,
    whole_number,
)

HELP = "run the FE engine on one deck and summarize the result"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("deck", help="input deck (.inp)")
    parser.add_argument("-o", "--out", type=folder, help="output folder (default: DECK without .inp, plus .out)")
    parser.add_argument("--threads", type=whole_number(1), default=None,
                        help="engine threads (default: OMP_NUM_THREADS, else the cores other programs leave idle)")
    parser.add_argument("--timeout", type=positive_number, default=3600.0, help="seconds before the run is stopped")
    add_output_arguments(parser, json_help="print the engine's summary.json on stdout")


def describe(results: EngineResults) -> str:
    """Human-readable summary of a run: status, size, Newton histories, extremes."""
    s = results.summary
    lines = [
        f"status      {s['status']}  ({s['wall_time_s']:.3f} s, linear solver {s['linear_solver']})",
        f"model       {s['n_nodes']} nodes, {s['n_elements']} elements, {s['n_free_dof']} free of {s['n_dof']} DOF",
    ]
    for step in s["steps"]:
        lines.append(
            f"step {step['step']}      {step['status']}: {step['n_increments']} increments, "
            f"{step['n_cutbacks']} cut-backs, {step['newton_iterations']} Newton iterations"
        )
        for inc in step["increments"]:
            history = " ".join(f"{r:.1e}" for r in inc["residual_norms"])
            lines.append(f"  t={inc['time']:<8.4g} |R|/|F|: {history}{'' if inc['converged'] else '  (cut back)'}")
    u = results.displacement()
    lines.append(f"max |u|     {float((u**2).sum(axis=1).max() ** 0.5):.6g}")
    lines.append(f"results     {results.outdir}")
    return "\n".join(lines)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        # the engine's progress lines are echoed unless the output is JSON or quiet
        outcome = run_engine(args.deck, args.out, threads=args.threads, timeout_s=args.timeout,
                             echo=show_progress(args) and not args.json)
    except EngineFailed as error:   # exit code 4; a refused deck (DeckRejected, 2) is reported by `cli.main`
        print(error, file=sys.stderr)
        return 4
    results = EngineResults(outcome.outdir)
    if args.json:
        print(json.dumps(results.summary))
    else:
        print(describe(results))
    return 0 if outcome.converged else 3
