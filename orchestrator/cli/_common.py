"""Options and output shared by the loop commands: parallel evaluation (--workers, --scheduler,
--timeout), --json (one JSON object on stdout, nothing else there; progress and logs on stderr)."""

from __future__ import annotations

import argparse
import json
import os
import sys


def add_parallel_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1),
                        help="engine evaluations in parallel on this machine (default: 2 or the core count)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="Dask distributed scheduler (e.g. tcp://host:8786): evaluate there instead of locally")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds before one engine run is stopped")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout (logs go to stderr)")


def parallel_options(args: argparse.Namespace) -> dict:
    return {"workers": args.workers, "scheduler": args.scheduler, "timeout_s": args.timeout}


def emit(args: argparse.Namespace, result: dict, lines: list[str]) -> None:
    if args.json:
        print(json.dumps(result))
    else:
        print("\n".join(lines))


def fail(message: str, code: int = 2) -> int:
    print(f"calfit: {message}", file=sys.stderr)
    return code
