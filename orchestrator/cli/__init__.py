"""The `calfit` command line: one module per subcommand, each with `add_arguments`
and `run` (returns the exit code). Progress and logs go to stderr (--quiet: errors only);
with --json a command prints one JSON object on stdout and nothing else there. The
options of every command are documented in docs/cli.md (tests/test_docs.py keeps them equal).
"""

from __future__ import annotations

import argparse

from . import (
    _demo,
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
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="calfit",
        description="Identify calf soft-tissue properties from MRI under a compression garment, "
        "and compute the pressure it transmits (finite-element engine calfit-fe).",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module in COMMANDS.items():
        sub = commands.add_parser(name, help=module.HELP, description=module.__doc__,
                                  formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_arguments(sub)
        sub.set_defaults(handler=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.handler(args) or 0)
