"""The documentation is the repository's own and says what the code does:
- every relative link of the README, of solver_cpp/README.md and of every page under docs/ resolves to a file or
  folder of the repository, and a link to `page.md#anchor` to one of that page's headings;
- every `--option` that README.md or a page under docs/ gives a `calfit` command is an option of that command in
  the parser (`orchestrator.cli.build_parser`); an option named without its command is an option of a command, or
  of the script the same paragraph names (`benchmarks/x.py --only ...`);
- every command of the CLI has its section in docs/cli.md, whose options are exactly those of the command (and
  `python -m orchestrator.cli COMMAND --help` names each of them);
- every key case.toml accepts is documented in docs/case-folder.md;
- the README stays a page for users: at most 150 lines;
- docs/design.md describes the layout as it is: every path it cites exists, every stage package of pyproject.toml's
  contract is in it, and each module it names in a package's row is in that package;
- docs/python.md's example imports only names that exist, and runs: a small phantom case prepared, measured,
  identified, given its intervals and its pressures, from a script."""

from __future__ import annotations

import ast
import functools
import importlib
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from orchestrator.case.folder import _TOML_SCHEMA
from orchestrator.cli import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]      # the user's pages
DOCUMENTS = [*PAGES, ROOT / "solver_cpp" / "README.md"]
LINK = re.compile(r"\]\(([^)\s]+)\)")
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z-]*|-[a-z])(?![\w-])")
LONG_OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*(?![\w-])")
FENCE = re.compile(r"^```(\w*)\s*$")
SCRIPT = re.compile(r"(?<![\w/.-])((?:benchmarks|tests)/[\w/]+\.py)\b")
CALFIT = re.compile(r"(?<![\w/.-])calfit(?:\s+([a-z][a-z-]*))?(?![\w-])")
OTHER_PROGRAMS = ("calfit-fe", "dask", "pip", "pytest", "make", "cmake", "ctest", "paraview", "ccx")
README_LINES = 150
ANY_COMMAND = "any calfit command"


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


@functools.cache
def _parser():
    return build_parser()


def _subparsers():
    parser = _parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices


def _options(parser) -> set[str]:
    return {s for action in parser._actions for s in action.option_strings}


def _cli_sections() -> dict[str, str]:
    text = (ROOT / "docs" / "cli.md").read_text()
    parts = re.split(r"^## calfit (\S+)\s*$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))


def _blocks(text: str):
    """The page as (kind, text) blocks: ("prose", a paragraph, table rows included) and ("code:<language>", a
    fenced block)."""
    blocks, lines, fence = [], [], None
    for line in text.split("\n"):
        match = FENCE.match(line)
        if fence is None and match:
            if lines:
                blocks.append(("prose", "\n".join(lines)))
            lines, fence = [], match.group(1) or "sh"
        elif fence is not None and line.startswith("```"):
            blocks.append((f"code:{fence}", "\n".join(lines)))
            lines, fence = [], None
        elif fence is None and not line.strip():
            if lines:
                blocks.append(("prose", "\n".join(lines)))
            lines = []
        else:
            lines.append(line)
    if lines:
        blocks.append(("prose" if fence is None else f"code:{fence}", "\n".join(lines)))
    return blocks


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    anchors, seen = set(), {}
    for kind, block in _blocks(page.read_text()):
        if kind != "prose":
            continue
        for line in block.split("\n"):
            heading = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
            if heading:
                slug = _slug(heading.group(1))
                anchors.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
                seen[slug] = seen.get(slug, 0) + 1
    return anchors


@pytest.mark.parametrize("document", DOCUMENTS, ids=_rel)
def test_links_resolve_inside_the_repository(document):
    for kind, block in _blocks(document.read_text()):
        if kind != "prose":
            continue
        for target in LINK.findall(block):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            resolved = (document.parent / path).resolve() if path else document
            assert resolved.is_relative_to(ROOT), f"{_rel(document)} links outside the repository: {target}"
            assert resolved.exists(), f"{_rel(document)} links to a missing file: {target}"
            if anchor and resolved.suffix == ".md":
                assert anchor in _anchors(resolved), f"{_rel(document)} links to a missing heading: {target}"


# --- options -----------------------------------------------------------------------------------------------

def _spans(kind: str, block: str) -> list[str]:
    """What a block shows as commands: its code spans (prose, a span may wrap over lines), or each line of a
    shell block. Python and TOML blocks show none."""
    if kind == "prose":
        return re.findall(r"`([^`]+)`", block.replace("\n", " "))
    if kind in ("code:sh", "code:bash", "code:console", "code:text"):
        return block.split("\n")
    return []


def _programs(text: str) -> list[tuple[int, str]]:
    """(position, program) of every program a text names: `calfit CMD` (or `calfit` alone), a script of
    benchmarks/ or tests/, another program."""
    found = [(m.start(), f"calfit {m.group(1)}" if m.group(1) in COMMANDS else "calfit") for m in CALFIT.finditer(text)]
    found += [(m.start(), m.group(1)) for m in SCRIPT.finditer(text)]
    for name in OTHER_PROGRAMS:
        found += [(m.start(), name) for m in re.finditer(rf"(?<![\w/.-]){re.escape(name)}(?![\w.-])", text)]
    # `calfit-fe` is not `calfit`: drop a `calfit` found at the start of `calfit-fe`
    engine = {position for position, name in found if name == "calfit-fe"}
    return sorted((p, n) for p, n in found if not (n == "calfit" and p in engine))


def _has_option(program: str, option: str) -> bool | None:
    """Whether the program has the option; None for a program outside the repository's parsers and scripts."""
    commands = _subparsers()
    if program == ANY_COMMAND:
        return any(option in _options(parser) for parser in commands.values()) or option in _options(_parser())
    if program == "calfit":
        return option in _options(_parser())
    if program.startswith("calfit "):
        return option in _options(commands[program.split()[1]]) | _options(_parser())
    if program.endswith(".py"):
        script = ROOT / program
        return script.is_file() and f'"{option}"' in script.read_text()
    return None


def _option_uses():
    """(page, option, programs it may belong to, context) for every long option the user's pages show. An option
    after a program in its span is that program's; one named alone is the page section's command's (docs/cli.md),
    a script's that its paragraph names, or any command's."""
    uses = []
    for page in PAGES:
        section = None
        for kind, block in _blocks(page.read_text()):
            heading = re.search(r"^## calfit (\S+)\s*$", block, flags=re.M) if page.name == "cli.md" else None
            if heading or (kind == "prose" and re.match(r"^#{1,2} ", block)):
                section = f"calfit {heading.group(1)}" if heading else None
            scripts = sorted({program for _, program in _programs(block) if program.endswith(".py")})
            for span in _spans(kind, block):
                programs = _programs(span)
                for match in LONG_OPTION.finditer(span):
                    before = [program for position, program in programs if position < match.start()]
                    candidates = [before[-1]] if before else [*([section] if section else []), *scripts, ANY_COMMAND]
                    uses.append((page, match.group(0), candidates, span.strip()))
    return uses


def test_every_option_the_pages_give_a_command_exists():
    missing = []
    for page, option, candidates, span in _option_uses():
        answers = [_has_option(program, option) for program in candidates]
        if not (any(answers) or all(answer is None for answer in answers)):
            missing.append(f"{_rel(page)}: {option} is not an option of {' or '.join(candidates)} (in `{span}`)")
    assert not missing, "\n".join(missing)


def test_the_option_check_sees_what_it_checks():
    uses = {(_rel(page), option, tuple(candidates)) for page, option, candidates, _ in _option_uses()}
    assert ("docs/cli.md", "--respect-outline", ("calfit measure",)) in uses
    assert ("docs/validation/error-model.md", "--splice", ("benchmarks/error_budget.py",)) in uses
    assert any(page == "README.md" and option == "--scheduler" for page, option, _ in uses)
    assert not _has_option("calfit identify", "--no-such-option")
    assert _has_option("benchmarks/error_budget.py", "--sampling")


def test_every_command_has_its_section():
    assert set(_cli_sections()) == set(COMMANDS)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_documented_options_are_the_commands_options(command):
    parser = _subparsers()[command]
    options = _options(parser) - {"-h", "--help"}
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


def test_the_readme_is_a_page_for_users():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_LINES, f"README.md has {len(lines)} lines; move the detail to docs/"
    first = next(block for kind, block in _blocks("\n".join(lines)) if kind.startswith("code:"))
    assert first.startswith("make demo") and first.split("\n")[1].startswith("make test"), "the two commands first"


# --- docs/design.md ----------------------------------------------------------------------------------------

REPOSITORY_PATH = re.compile(r"`((?:orchestrator|solver_cpp|tests|templates|benchmarks|docs)/[\w./-]*)`")


@pytest.mark.parametrize("page", [ROOT / "docs" / "design.md", ROOT / "README.md"], ids=_rel)
def test_every_path_a_page_cites_exists(page):
    missing = [path for path in REPOSITORY_PATH.findall(page.read_text()) if not (ROOT / path).exists()]
    assert not missing, f"{_rel(page)} cites paths that are not in the repository: {missing}"


def test_the_design_holds_every_stage_package_and_the_modules_it_names():
    text = (ROOT / "docs" / "design.md").read_text()
    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    stages = {stage.strip() for layer in contract[0]["layers"] for stage in layer.split("|")}
    packages = {f"orchestrator.{p.name}" for p in (ROOT / "orchestrator").iterdir() if (p / "__init__.py").is_file()}
    assert stages == packages, "pyproject.toml's stage contract and orchestrator's packages differ"
    for stage in sorted(stages):
        folder = stage.replace(".", "/") + "/"
        assert f"`{folder}`" in text, f"docs/design.md does not describe {folder}"
    for line in text.splitlines():
        row = re.search(r"`(orchestrator/\w+/)`", line) if line.startswith("|") else None
        for name in re.findall(r"`(\w+\.py|\w+/)`", line[row.end():]) if row else ():
            assert (ROOT / row.group(1) / name).exists(), f"docs/design.md names {row.group(1)}{name}, which is not there"
    assert "tests/house/test_layering.py" in text and "[tool.importlinter]" in text


# --- docs/python.md ----------------------------------------------------------------------------------------

def _python_example() -> str:
    blocks = [block for kind, block in _blocks((ROOT / "docs" / "python.md").read_text()) if kind == "code:python"]
    assert len(blocks) == 1, "docs/python.md holds one Python example"
    return blocks[0]


def test_every_name_the_python_example_imports_exists():
    for node in ast.walk(ast.parse(_python_example())):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(module, alias.name), f"docs/python.md imports {alias.name} from {node.module}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                importlib.import_module(alias.name)


def test_the_python_example_runs_the_pipeline(tmp_path):
    script = tmp_path / "example.py"
    script.write_text(_python_example())
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    run = tmp_path / "calfit-example" / "run"
    identification = json.loads((run / "identification.json").read_text())
    truth = json.loads((tmp_path / "calfit-example" / "case.truth" / "parameters.json").read_text())["parameters_kPa"]
    for name, value in zip(identification["parameters"], identification["best"]["theta"]):
        assert value == pytest.approx(truth[name], rel=0.1), name
    pressures = json.loads((run / "pressures.json").read_text())
    assert pressures["landmarks"] and all(0.5 < p < 10 for p in pressures["mean_kPa"])     # kPa, about 20 mmHg
    assert "misfit" in done.stdout and "deep_veins" in done.stdout
