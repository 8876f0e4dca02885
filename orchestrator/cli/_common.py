"""Options and output shared by the commands: parallel evaluation (--workers, --scheduler, --timeout, --verbose:
the engines' own logs), --json (one JSON object on stdout, nothing else there; progress and logs on stderr) and
--quiet (nothing on stderr but errors; stdout unchanged).

The type functions refuse a value before the command runs, argparse naming the option (``argument --workers: 0 is
not a whole number of at least 1; give 1 or more``, exit code 2): `whole_number` (counts: workers, draws,
elements, a grid step), `positive_number` (seconds, mm), `tension` (N/mm, in case.toml's range) and `folder` (an output folder: a path that is, or can be
made, a folder; a file there, or under a file, is refused before anything is written)."""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import sys
import warnings
from pathlib import Path
from typing import Callable

from ..case.schema import TENSION_MAX_N_PER_MM, TENSION_TEXT

JSON_HELP = "print one JSON object on stdout (progress and logs go to stderr)"


def whole_number(least: int = 1) -> Callable[[str], int]:
    """argparse type: a whole number of at least `least`."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number; give {least} or more") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"{value} is not a whole number of at least {least}; give {least} or more")
        return value
    parse.__name__ = "whole number"
    return parse


def positive_number(text: str) -> float:
    """argparse type: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a positive number") from None
    if not (value > 0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"{text} is not a positive number; give a number above 0")
    return value


def tension(text: str) -> float:
    """argparse type: a garment tension in N/mm, in the range case.toml accepts (`case.schema`)."""
    value = positive_number(text)
    if value > TENSION_MAX_N_PER_MM:
        raise argparse.ArgumentTypeError(f"{text} N/mm is not {TENSION_TEXT}; give the garment's force per unit width, "
                                         "e.g. 0.16")
    return value


def folder(text: str) -> str:
    """argparse type: a folder to write into, existing or not; not a file, nor a path under a file."""
    path = Path(text)
    for place in (path, *path.parents):
        if place.exists() and not place.is_dir():
            problem = f"{text} is a file, not a folder" if place == path else \
                f"{text} lies under {place}, which is a file, not a folder"
            raise argparse.ArgumentTypeError(f"{problem}; give the path of a folder (a new one is made)")
        if place.exists():
            break
    return text


def add_output_arguments(parser: argparse.ArgumentParser, *, json_help: str | None = JSON_HELP) -> None:
    """--json (unless json_help is None: a command without a JSON result) and --quiet."""
    if json_help is not None:
        parser.add_argument("--json", action="store_true", help=json_help)
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="nothing on stderr but errors: no progress, notices or warnings (stdout unchanged)")


def add_parallel_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=whole_number(1), default=min(2, os.cpu_count() or 1),
                        help="engine evaluations in parallel on this machine (default: 2 or the core count)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="Dask distributed scheduler (e.g. tcp://host:8786): evaluate there instead of locally")
    parser.add_argument("--timeout", type=positive_number, default=120.0, help="seconds before one engine run is stopped")
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
