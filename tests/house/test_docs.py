"""The documentation is the repository's own and says what the code does: every link of the README and of docs/
resolves to a file of the repository; every command of the CLI has its section in docs/cli.md, whose options
are exactly those of the command (and `python -m orchestrator.cli COMMAND --help` names each of them); every
key case.toml accepts is documented in docs/case-folder.md."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.case.folder import _TOML_SCHEMA
from orchestrator.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[2]
DOCUMENTS = [ROOT / "README.md", ROOT / "solver_cpp" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z-]*|-[a-z])(?![\w-])")


def _subparsers():
    parser = build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


def _cli_sections() -> dict[str, str]:
    text = (ROOT / "docs" / "cli.md").read_text()
    parts = re.split(r"^## calfit (\S+)\s*$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve_inside_the_repository(document):
    for target in LINK.findall(document.read_text()):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path = target.split("#")[0]
        if not path:
            continue
        resolved = (document.parent / path).resolve()
        assert resolved.is_relative_to(ROOT), f"{document.name} links outside the repository: {target}"
        assert resolved.exists(), f"{document.name} links to a missing file: {target}"


def test_every_command_has_its_section():
    assert set(_cli_sections()) == set(COMMANDS)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_documented_options_are_the_commands_options(command):
    parser = _subparsers()[command]
    options = {s for action in parser._actions for s in action.option_strings} - {"-h", "--help"}
    section = re.sub(rf"`calfit (?!{command}\b)[^`]*`", "", _cli_sections()[command])   # other commands' options
    documented = set(OPTION.findall(section))
    assert documented == options, (f"docs/cli.md, calfit {command}: documented but not an option "
                                   f"{sorted(documented - options)}; an option not documented {sorted(options - documented)}")
    shown = parser.format_help()         # what `python -m orchestrator.cli COMMAND --help` prints
    assert all(option in shown for option in documented)


def test_the_help_lists_every_command_and_each_commands_help_its_options():
    shown = subprocess.run([sys.executable, "-m", "orchestrator.cli", "--help"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)
    assert shown.returncode == 0 and all(command in shown.stdout for command in COMMANDS)
    report = subprocess.run([sys.executable, "-m", "orchestrator.cli", "report", "--help"], capture_output=True,
                            text=True, timeout=60, cwd=ROOT)
    assert report.returncode == 0 and "--truth" in report.stdout and "--quiet" in report.stdout


def test_every_case_toml_key_is_documented():
    text = (ROOT / "docs" / "case-folder.md").read_text()
    for table, keys in _TOML_SCHEMA.items():
        assert f"[{table}]" in text
        for key in keys or ():
            assert f"`{key}`" in text, f"case.toml key [{table}] {key} is not in docs/case-folder.md"
