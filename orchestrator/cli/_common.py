"""Options and output shared by the commands: parallel evaluation (--workers, --scheduler, --timeout, --verbose:
the engines' own logs), --json (one JSON object on stdout, nothing else there; progress and logs on stderr) and
--quiet (nothing on stderr but errors; stdout unchanged)."""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import sys
import warnings
from typing import Callable

JSON_HELP = "print one JSON object on stdout (progress and logs go to stderr)"


def add_output_arguments(parser: argparse.ArgumentParser, *, json_help: str | None = JSON_HELP) -> None:
    """--json (unless json_help is None: a command without a JSON result) and --quiet."""
    if json_help is not None:
        parser.add_argument("--json", action="store_true", help=json_help)
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="nothing on stderr but errors: no progress, notices or warnings (stdout unchanged)")


def add_parallel_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                        help="engine evaluations in parallel on this machine (default: 2 or the core count)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="Dask distributed scheduler (e.g. tcp://host:8786): evaluate there instead of locally")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds before one engine run is stopped")
    parser.add_argument("--verbose", action="store_true",
                        help="every engine run's own log on stderr as it runs (Newton residuals, increments)")
    add_output_arguments(parser)


def parallel_options(args: argparse.Namespace) -> dict:
    """The evaluation options of the pipeline's stages, progress line included (off with --quiet)."""
    return {"workers": args.workers, "scheduler": args.scheduler, "timeout_s": args.timeout,
            "progress": show_progress(args), "verbose": args.verbose and show_progress(args)}


def show_progress(args: argparse.Namespace) -> bool:
    return not getattr(args, "quiet", False)


def notice(args: argparse.Namespace, text: str) -> None:
    """A line for the user on stderr (where a stage went, what was written), unless --quiet."""
    if show_progress(args):
        print(text, file=sys.stderr, flush=True)


def honours_quiet(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """Decorate a command's `run`: under --quiet, the Python warnings and the log records below ERROR that its
    libraries (numpy, scikit-image, Dask) would print on stderr are dropped too; errors still reach it."""

    @functools.wraps(run)
    def quietly(args: argparse.Namespace) -> int:
        if show_progress(args):
            return run(args)
        disabled_before = logging.root.manager.disable
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            logging.disable(logging.WARNING)
            try:
                return run(args)
            finally:
                logging.disable(disabled_before)

    return quietly


def emit(args: argparse.Namespace, result: dict, lines: list[str]) -> None:
    if args.json:
        print(json.dumps(result))
    else:
        print("\n".join(lines))


def fail(message: str, code: int = 2) -> int:
    print(f"calfit: {message}", file=sys.stderr)
    return code
