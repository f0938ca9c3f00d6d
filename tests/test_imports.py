"""The package's import graph, read from every module's source: no circle, and the rooms'
arrows point one way (docs/architecture.md)."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "flowins"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The flowins modules ``path`` imports, at its top or inside a function (a lazy import
    closes a circle as surely as any other)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for target in targets:
            if target in modules and target != name:
                found.add(target)
    return found


def import_graph() -> dict[str, set[str]]:
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    return {module_name(p): imports_of(p, modules) for p in paths}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_circle_finder_finds_a_circle_and_only_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert circles(graph) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_top_level_lazy_and_relative_imports():
    graph = import_graph()
    assert "flowins.filter.ekf" in graph["flowins.filter.runner"] | graph.get("flowins.filter.chain", set())
    assert "flowins.training.parameters" in graph["flowins.settings"]
    assert all(target.startswith("flowins") for targets in graph.values() for target in targets)


def test_no_module_of_flowins_imports_itself_back_through_others():
    assert circles(import_graph()) == []


def test_the_filter_core_knows_no_measurement_model_and_the_rooms_point_one_way():
    graph = import_graph()
    later = {
        "flowins.filter": ("flowins.measurements", "flowins.navigation", "flowins.training", "flowins.jobs",
                           "flowins.settings", "flowins.evaluation", "flowins.flow"),
        "flowins.measurements": ("flowins.navigation", "flowins.training", "flowins.jobs", "flowins.settings"),
        "flowins.navigation": ("flowins.training", "flowins.jobs", "flowins.settings", "flowins.evaluation"),
        "flowins.evaluation": ("flowins.navigation", "flowins.training", "flowins.jobs", "flowins.settings"),
        "flowins.training": ("flowins.jobs", "flowins.settings"),
        "flowins.settings": ("flowins.jobs",),
    }
    wrong = [(module, target) for module, targets in graph.items() for room, banned in later.items()
             if module == room or module.startswith(room + ".") for target in targets if target.startswith(banned)]
    assert wrong == []
