"""Write the HTML report of a run (figures as Avril et al. Figs. 1, 2, 4, 5 and Tables 1-4).

    calfit report RUN_DIR [--truth TRUTH_DIR] [--quiet]

Needs identification.json, montecarlo.json and pressures.json in RUN_DIR. With --truth (a phantom's
truth folder) the true parameters are shown beside the intervals. Prints the page's path.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.files import read_json
from ..report.run_report import write_report
from ..run.setup import PARAMETERS_FILE
from ._common import add_output_arguments, fail, honours_quiet

HELP = "write the run's HTML report with its figures and tables"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", help="run folder")
    parser.add_argument("--truth", help="truth folder of a phantom case (shows the true parameters)")
    add_output_arguments(parser, json_help=None)


@honours_quiet
def run(args: argparse.Namespace) -> int:
    try:
        truth = (read_json(Path(args.truth) / PARAMETERS_FILE, "calfit phantom")["parameters_kPa"]
                 if args.truth else None)
        page = write_report(args.run_dir, truth)
    except (ValueError, RuntimeError) as error:   # a CalfitError is reported by `cli.main`
        return fail(str(error))
    print(page)
    return 0
