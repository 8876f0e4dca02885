"""Identify the tissue parameters of a case (Avril et al. sec. 2.2.5; Bouten and Drapier sec. 2.6).

    calfit identify CASE_DIR --out RUN_DIR [--method nm|lm] [--objective auto|mismatch|displacement]
                    [--starts one|table1] [--start C10f C10m Kvf Kvm] [--effects NAME[,NAME]] [--workers N]
                    [--scheduler ADDRESS] [--json]

The case is read, segmented, aligned on the bones and meshed (400 T3 elements; --order 2: T6), then the four
parameters (C10 and Kv of fat and muscle, kPa) are fitted: Nelder-Mead on the contour mismatch M
or on the displacement residual F (points.csv), or Levenberg-Marquardt on F's residual vector.
--starts table1 runs from the initial values of Avril et al. Table 1 (each parameter +-10 %).
Every evaluation is logged in RUN_DIR/evaluations.jsonl: run the same command again after an
interruption and it resumes without repeating one. Writes RUN_DIR/identification.json.
--effects adds catalog effects (`calfit diagnose --catalog`), their parameters fitted from zero.
"""

from __future__ import annotations

import argparse
import sys

from ..effects import EffectError, parse_effects
from ..imaging.errors import CaseError
from ..pipeline import OBJECTIVES, fit_summary, run_identify
from ._common import add_parallel_arguments, emit, fail, parallel_options

HELP = "fit the tissue parameters of a case (Nelder-Mead or Levenberg-Marquardt)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("case_dir", help="case folder (case.toml, unloaded and loaded images, ...)")
    parser.add_argument("--out", required=True, help="run folder (created; reused to resume)")
    parser.add_argument("--method", choices=("nm", "lm"), default="nm", help="nm: Nelder-Mead (default), lm: Levenberg-Marquardt")
    parser.add_argument("--objective", choices=("auto",) + OBJECTIVES, default="auto",
                        help="mismatch: contour mismatch M; displacement: F at points.csv (auto: F if points.csv exists)")
    parser.add_argument("--starts", choices=("one", "table1"), default="one", help="one start, or the starts of Table 1")
    parser.add_argument("--start", type=float, nargs=4, metavar=("C10F", "C10M", "KVF", "KVM"),
                        help="initial values in kPa (default: Avril et al. Table 2 central values)")
    parser.add_argument("--elements", type=int, default=400, help="elements of the identification mesh (default 400)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=1,
                        help="1: CPE3 (the first paper, default); 2: CPE6, for effects that change volume")
    parser.add_argument("--effects", help="comma-separated catalog effects whose parameters are fitted too "
                                           "(calfit diagnose --catalog lists them)")
    add_parallel_arguments(parser)


def run(args: argparse.Namespace) -> int:
    try:
        result = run_identify(args.case_dir, args.out, method=args.method, objective=args.objective, start=args.start,
                              starts=args.starts, n_elements=args.elements, order=args.order,
                              effects=parse_effects(args.effects),
                              progress=True, **parallel_options(args))
    except (CaseError, EffectError, ValueError, RuntimeError) as error:
        return fail(str(error))
    lines = [fit_summary(fit, result["parameters"]) for fit in result["fits"]]
    lines.append(f"best ({result['objective']}): " + fit_summary(result["best"], result["parameters"]))
    lines.append(f"run folder {args.out}; next: calfit montecarlo {args.out}")
    emit(args, result, lines)
    print(f"identification written to {args.out}/identification.json", file=sys.stderr)
    return 0
