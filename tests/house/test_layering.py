"""The orchestrator's stages import one way (docs/design.md: data flows one way through the pipeline): import-linter
holds pyproject.toml's stage contract (a stage imports only from the stages below it) and is shown to break on an
upward import; no module imports, even inside a function, one that imports it back; every template in one folder."""

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import orchestrator
from orchestrator.engine.decks import template_dir

PACKAGE = Path(orchestrator.__file__).parent
PYPROJECT = PACKAGE.parent / "pyproject.toml"
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _lint_imports(config: Path, package_parent: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", str(config)], capture_output=True, text=True,
                          cwd=package_parent, env={"PYTHONPATH": str(package_parent), "PATH": ""}, timeout=120)


def test_every_stage_imports_only_from_the_stages_below_it():
    result = _lint_imports(PYPROJECT, PACKAGE.parent)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 kept, 0 broken" in result.stdout


def test_the_stage_contract_breaks_on_an_import_from_a_lower_stage_to_a_higher_one(tmp_path):
    # under another name: the editable install would find the real package first
    copy = tmp_path / "stages_copy"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    units = copy / "core" / "units.py"
    units.write_text(units.read_text() + "\nfrom ..report import run_report  # upward\n")
    config = tmp_path / "pyproject.toml"
    config.write_text(PYPROJECT.read_text().replace('"orchestrator"', '"stages_copy"').replace('orchestrator.', 'stages_copy.'))
    result = _lint_imports(config, tmp_path)
    assert result.returncode == 1 and "0 kept, 1 broken" in result.stdout, result.stdout
    assert "stages_copy.core.units -> stages_copy.report.run_report" in result.stdout


def _module_name(path: Path) -> str:
    parts = ("orchestrator",) + path.relative_to(PACKAGE).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the orchestrator modules it imports (relative imports, at any depth of the module's code)."""
    files = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph = {name: set() for name in files}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
                for candidate in [target] + [f"{target}.{alias.name}" for alias in node.names]:
                    if candidate in files and candidate != name:
                        graph[name].add(candidate)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                other = stack.pop()
                on_stack.discard(other)
                component.append(other)
                if other == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return found


def test_the_cycle_finder_finds_a_circle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_module_of_the_orchestrator_imports_one_that_imports_it_back():
    graph = import_graph()
    assert len(graph) > 50 and "orchestrator.measure.measurements" in graph["orchestrator.run.setup"]
    assert cycles(graph) == []


def test_every_template_lives_in_templates():
    assert {"leg_slice.inp.j2", "leg_laplace.inp.j2", "report.html.j2"} <= {p.name for p in template_dir().glob("*.j2")}
    assert not list(PACKAGE.rglob("*.j2")), "a template inside the package: put it in templates/"
