"""The `calfit` command line: one module per subcommand, each with `add_arguments`
and `run` (returns the exit code). Progress and logs go to stderr (--quiet: errors only);
with --json a command prints one JSON object on stdout and nothing else there. The
options of every command are documented in docs/cli.md (tests/house/test_docs.py keeps them equal).

Every error a user can mend is a `CalfitError` (`core.errors`), caught here once: its message, one sentence
naming the file or option and the fix, goes to stderr as ``calfit: <message>`` with exit code 2, never a
traceback. A bad option value is refused by argparse before anything runs (`_common`'s type functions), also
with exit code 2. An interrupted command (Ctrl-C) keeps what it finished and says how to resume.
"""

from __future__ import annotations

import argparse
import sys

from ..core.errors import CalfitError
from ..run.blas import single_blas_thread
from . import (
    _demo,
    _design,
    _diagnose,
    _identify,
    _measure,
    _montecarlo,
    _paraview,
    _phantom,
    _pressures,
    _report,
    _solve,
    _study,
)
from ._common import fail

COMMANDS = {
    "demo": _demo,
    "phantom": _phantom,
    "solve": _solve,
    "measure": _measure,
    "identify": _identify,
    "montecarlo": _montecarlo,
    "pressures": _pressures,
    "diagnose": _diagnose,
    "report": _report,
    "paraview": _paraview,
    "study": _study,
    "design": _design,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="calfit",
        description="Identify calf soft-tissue properties from MRI under a compression garment, "
        "and compute the pressure it transmits (finite-element engine calfit-fe).",
    )
    parser.add_argument("--version", action="version", version=f"calfit {version()}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module in COMMANDS.items():
        sub = commands.add_parser(name, help=module.HELP, description=module.__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub)
        sub.set_defaults(handler=module.run)
    return parser


def version() -> str:
    """The installed package's version, else (a source tree on the path) pyproject.toml's."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("calfit")
    except PackageNotFoundError:
        from pathlib import Path

        import tomllib

        pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
        try:
            return tomllib.loads(pyproject.read_text(encoding="utf-8"))["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    single_blas_thread()   # beside the engine's and the DIC's processes (`run.blas`)
    try:
        return int(args.handler(args) or 0)
    except CalfitError as error:
        return fail(str(error))
    except KeyboardInterrupt:
        print("calfit: interrupted; what was finished is kept: run the same command again to resume",
              file=sys.stderr)
        return 130
