"""The orchestrator's rooms import one way (DESIGN.md: data flows one way through the pipeline): no module imports,
even inside a function, one that imports it back; every template in one folder."""

import ast
from pathlib import Path

import orchestrator
from orchestrator.engine.decks import template_dir

PACKAGE = Path(orchestrator.__file__).parent


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
