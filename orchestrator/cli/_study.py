"""A cohort of cases through the whole pipeline on a Dask cluster.

    calfit study STUDY --out DIR [--workers N] [--scheduler ADDRESS] [--elements N] [--draws N]
                 [--pressure-draws N] [--stages identify,montecarlo,pressures,diagnose] [--timeout S]
                 [--json] [--quiet]

STUDY is a folder of case folders (a cohort), or a volume case: a case folder whose unloaded and loaded images
are 3D volumes (DICOM series or 3D NIfTI) and whose case.toml has a [study] table of heights; it is cut into
one slice case per height first (DIR/slices/, DIR/slices.json: the loaded volume aligned on the bones in 3D).

Each case is measured, identified, given its intervals, its landmark pressures (when case.toml names landmarks)
and its diagnosis, as one task on dask.distributed: a LocalCluster of --workers processes on this machine, or
the cluster whose scheduler is at --scheduler (its workers must see STUDY and DIR at the same paths).
DIR/cases/<case>/ is each case's run folder; DIR/study.csv (and study.parquet with pyarrow) has one row per
case, rewritten as each finishes; DIR/study.json sums it up and DIR/report/index.html shows it (profiles along
the leg and the pressure at the heights B to D for a volume, the distributions, the cases whose model fails).
Run the same command again after an interruption: the cases done are skipped, the others resume where they
stopped.
"""

from __future__ import annotations

import argparse
import os

from ..study.cohort import STAGES, CaseOptions, run_study
from ._common import (
    add_output_arguments,
    emit,
    fail,
    folder,
    honours_quiet,
    notice,
    positive_number,
    whole_number,
)

HELP = "a cohort of cases through the whole pipeline on a Dask cluster, one table row per case"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("study", help="folder of case folders (each with case.toml and its images), or a volume "
                                      "case (3D volumes and a [study] table of heights)")
    parser.add_argument("--out", type=folder, required=True, help="study folder (created; reused to resume)")
    parser.add_argument("--workers", type=whole_number(1), default=min(2, os.cpu_count() or 1),
                        help="cases in parallel on this machine, one engine each (default: 2 or the core count)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="Dask distributed scheduler (e.g. tcp://host:8786): run the cases there")
    parser.add_argument("--elements", type=whole_number(1), help="elements of each identification mesh (default 2000)")
    parser.add_argument("--draws", type=whole_number(1), help="noise Monte-Carlo draws per case (default 200)")
    parser.add_argument("--pressure-draws", type=whole_number(1), default=30,
                        help="parameter draws of each case's pressure study (default 30, as the paper)")
    parser.add_argument("--stages", default=",".join(STAGES),
                        help="comma-separated stages of each case: identify,montecarlo and any of pressures,diagnose "
                             "(default: all four)")
    parser.add_argument("--timeout", type=positive_number, default=120.0, help="seconds before one engine run is stopped")
    add_output_arguments(parser)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        options = CaseOptions(n_elements=args.elements, draws=args.draws, pressure_draws=args.pressure_draws,
                              timeout_s=args.timeout, stages=tuple(s.strip() for s in args.stages.split(",")))
        summary = run_study(args.study, args.out, options, workers=args.workers, scheduler=args.scheduler,
                            report=lambda line: notice(args, line))
    except (ValueError, OSError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    emit(args, summary, [f"{summary['done']} of {summary['cases']} cases done; failed: "
                         f"{', '.join(summary['failed']) or 'none'}; table: {args.out}/{summary['table']}; "
                         f"report: {args.out}/{summary['report']}"])
    return 0 if not summary["failed"] else 1
