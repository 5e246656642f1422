"""The package's layers, read from its own source: every import (module-level and inside functions) of every module.

Fails if an arrow runs upward (core -> anything outside core but errors; io -> ros/cli/demo/plots/synthetic; ros ->
cli/demo; shift -> cli/demo but the demo's HTML page builder), if the core's stages import each other (fe, method and
scan are siblings; only loop may use them), or if any set of modules imports itself in a circle.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "ros2_ws" / "src" / "hood_decomp" / "hood_decomp"

# What each layer may import, by module prefix (besides itself, the standard library and third-party packages).
ALLOWED = {
    "hood_decomp": (),
    "hood_decomp.errors": (),
    "hood_decomp.core.types": ("hood_decomp.errors",),
    "hood_decomp.core.fe": ("hood_decomp.core.types", "hood_decomp.errors"),
    "hood_decomp.core.method": ("hood_decomp.core.types", "hood_decomp.errors"),
    "hood_decomp.core.scan": ("hood_decomp.core.types", "hood_decomp.errors"),
    "hood_decomp.core.loop": ("hood_decomp.core", "hood_decomp.errors"),
    "hood_decomp.core": ("hood_decomp.core", "hood_decomp.errors"),
    "hood_decomp.io": ("hood_decomp.core", "hood_decomp.errors", "hood_decomp.io"),
    "hood_decomp.synthetic": ("hood_decomp.core", "hood_decomp.errors", "hood_decomp.synthetic"),
    "hood_decomp.plots": ("hood_decomp.core", "hood_decomp.errors", "hood_decomp.plots"),
    "hood_decomp.ros": ("hood_decomp.core", "hood_decomp.errors", "hood_decomp.io", "hood_decomp.ros",
                        "hood_decomp.synthetic"),
    "hood_decomp.shift": ("hood_decomp.core", "hood_decomp.errors", "hood_decomp.io", "hood_decomp.synthetic",
                          "hood_decomp.plots", "hood_decomp.ros", "hood_decomp.shift", "hood_decomp.demo.html"),
    "hood_decomp.demo": ("hood_decomp",),
    "hood_decomp.cli": ("hood_decomp",),
}


def module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_imports() -> dict[str, set[str]]:
    """Module -> hood_decomp modules it imports; ``from a.b import c`` counts as ``a.b.c`` where that is a module."""
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    targets.add(sub if sub in modules else node.module)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def layer_of(module: str) -> str:
    return max((prefix for prefix in ALLOWED if module == prefix or module.startswith(prefix + ".")), key=len)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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


GRAPH = package_imports()


def test_the_walk_sees_the_package():
    """Fails if the walk reads nothing (a moved package root would make every other check here vacuous)."""
    assert "hood_decomp.core.method.bases" in GRAPH
    assert "hood_decomp.core.method.pca" in GRAPH["hood_decomp.core.method.bases"]


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_no_arrow_runs_upward(module):
    """Fails if a module imports a layer its own layer may not import (see ALLOWED)."""
    allowed = ALLOWED[layer_of(module)]
    wrong = sorted(t for t in GRAPH[module]
                   if layer_of(t) != layer_of(module) and not any(t == a or t.startswith(a + ".") for a in allowed))
    assert not wrong, f"{module} imports {wrong}; its layer {layer_of(module)} may import only {allowed}"


def test_no_import_cycle():
    """Fails if any modules import each other in a circle, lazy imports inside functions included."""
    assert cycles(GRAPH) == []


def test_the_check_itself_sees_a_cycle_and_an_upward_arrow():
    """Fails if the checks above could not fail: a planted cycle and a planted core -> ros arrow are found."""
    planted = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}
    assert cycles(planted) == [["a", "b", "c"]]
    assert layer_of("hood_decomp.core.fe.solver") == "hood_decomp.core.fe"
    assert not any("hood_decomp.ros.messages".startswith(a) for a in ALLOWED["hood_decomp.core.fe"])
