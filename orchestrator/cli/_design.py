"""The garment this leg needs, designed through its identified tissues against the compression standards.

    calfit design RUN_DIR|STUDY_DIR --target TARGET.toml --out DIR [--draws 20] [--workers N] [--json] [--quiet]

RUN_DIR is an identified run folder (calfit identify and calfit montecarlo), STUDY_DIR a volume study (calfit
study on a volume case). TARGET.toml lists the targets: pressures at landmarks, the skin's pressure at the heights
B, B1, C, D or a class of RAL-GZ 387 (and the French and British classes), a maximum over a region (the tibial
crest), the fabric's feasible tension range and, optionally, a knitted-in tension profile and the fabric's tensile
test (docs/design-garment.md). Levenberg-Marquardt with the engine's tension sensitivities finds the tension per
height; each target's probability is taken over the Monte-Carlo draws and the tension's uncertainty; Laplace's law
P = T / r is shown beside it, with the garment it alone would have chosen. Writes DIR/design.json and
DIR/report/index.html.
"""

from __future__ import annotations

import argparse

from ..design.report import target_lines
from ..design.stage import run_design
from ._common import (
    add_output_arguments,
    emit,
    fail,
    folder,
    honours_quiet,
    notice,
    show_progress,
    whole_number,
)

HELP = "the garment that meets pressure targets on this leg (tension per height, probabilities, Laplace beside it)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="RUN_DIR|STUDY_DIR", help="identified run folder, or volume study folder")
    parser.add_argument("--target", required=True, metavar="TARGET.toml", help="the targets (docs/design-garment.md)")
    parser.add_argument("--out", type=folder, required=True, help="output folder (design.json, report/)")
    parser.add_argument("--draws", type=whole_number(2), help="Monte-Carlo draws the design is checked over "
                                                               "(default: TARGET.toml's, else 20)")
    parser.add_argument("--workers", type=whole_number(1), default=2, help="engine runs in parallel (default 2)")
    add_output_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        result = run_design(args.source, args.target, args.out, workers=args.workers, draws=args.draws,
                            say=(lambda line: notice(args, line)) if show_progress(args) else None)
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    tension = result["tension_N_per_mm"]
    lines = [f"status: {result['status']}",
             "tension: " + (f"{tension:.4f} N/mm" if isinstance(tension, float) else
                            ", ".join(f"{n or h:}: {t:.4f}" for n, h, t in zip(tension["height_names"],
                                                                               tension["heights_mm"],
                                                                               tension["tension_N_per_mm"]))
                            + " N/mm")]
    lines += target_lines(result)
    law = result["laplace"]
    law_t = law["tension_N_per_mm"]
    lines.append("Laplace's law alone would choose " + (f"{law_t:.4f} N/mm" if isinstance(law_t, float) else
                                                        ", ".join(f"{t:.4f}" for t in law_t["tension_N_per_mm"])
                                                        + " N/mm") + "; through the FE model it gives:")
    lines += ["  " + line for line in target_lines(law)]
    lines.append(f"{result['engine_runs']} engine runs in {result['wall_time_s']:.1f} s; "
                 f"{args.out}/design.json, {args.out}/{result.get('report', '')}")
    emit(args, result, lines)
    return 0
