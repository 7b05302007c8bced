"""No import cycle inside hybridqcm: the graph of every `import` / `from` statement between its modules.

The graph is read from the source (AST), not from a running interpreter, so imports inside
functions (deferred for start-up time) count too: a cycle hidden behind a lazy import is still a
cycle in the design. Imports under `if TYPE_CHECKING:` are left out (they never run).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE_ROOT = Path(__file__).resolve().parents[1] / "src" / "hybridqcm"


def module_names(root: Path = PACKAGE_ROOT) -> dict[str, Path]:
    """Dotted name -> file, for every module of the package (a package is its __init__.py)."""
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_nodes(tree: ast.AST):
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules that module ``name`` (file ``path``) imports, anywhere in its body."""
    is_package = path.name == "__init__.py"
    targets = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        else:
            if node.level:  # relative: resolve against the importing module's package
                base = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # `from a.b import c` imports a.b, and a.b.c too when c is a module
            candidates = [source] + [f"{source}.{alias.name}" for alias in node.names]
        for candidate in candidates:
            if candidate in modules and candidate != name:
                targets.add(candidate)
    return targets


def import_graph(root: Path = PACKAGE_ROOT) -> dict[str, set[str]]:
    modules = module_names(root)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a -> b -> ... -> a) per strongly connected component with more than one module (Tarjan)."""
    index, low, on_stack, stack, components = {}, {}, set(), [], []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                components.append(set(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    cycles = []
    for component in components:  # a shortest path back to the start, inside the component
        start = min(component)
        paths = {start: [start]}
        frontier = [start]
        cycle = None
        while frontier and cycle is None:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & component):
                    if w == start:
                        cycle = paths[v] + [start]
                        break
                    if w not in paths:
                        paths[w] = paths[v] + [w]
                        nxt.append(w)
                if cycle:
                    break
            frontier = nxt
        cycles.append(cycle)
    return sorted(cycles)


def test_cycle_finder_names_a_known_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"e2"}, "e2": set()}
    assert find_cycles(graph) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_graph_reads_lazy_relative_and_from_imports(tmp_path):
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("from .leaf import x\n")
    (package / "sub" / "leaf.py").write_text("def f():\n    from pkg import top\nx = 1\n")
    (package / "top.py").write_text(
        "from typing import TYPE_CHECKING\nfrom pkg.sub import leaf\nif TYPE_CHECKING:\n    import pkg.other\n"
    )
    (package / "other.py").write_text("import pkg.top\n")
    graph = import_graph(package)
    assert graph["pkg.sub"] == {"pkg.sub.leaf"}
    assert graph["pkg.sub.leaf"] == {"pkg", "pkg.top"}  # `from pkg import top` runs pkg/__init__ first
    assert graph["pkg.top"] == {"pkg.sub", "pkg.sub.leaf"}
    assert graph["pkg.other"] == {"pkg.top"}
    assert find_cycles(graph) == [["pkg.sub", "pkg.sub.leaf", "pkg.top", "pkg.sub"]]


def test_hybridqcm_has_no_import_cycle():
    graph = import_graph()
    assert "hybridqcm.apps.pipeline" in graph and "hybridqcm.physics" in graph
    cycles = find_cycles(graph)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize(
    "lower, upper",
    [
        ("hybridqcm.pipelines.catalog", "hybridqcm.pipelines.runner"),
        ("hybridqcm.reports.results", "hybridqcm.pipelines.runner"),
        ("hybridqcm.reports.manifest", "hybridqcm.reports.results"),
        ("hybridqcm.pipelines.runner", "hybridqcm.apps.pipeline"),
        ("hybridqcm.reports.results", "hybridqcm.apps.results"),
    ],
)
def test_pipeline_modules_point_one_way(lower, upper):
    graph = import_graph()
    assert lower in graph[upper] and upper not in graph[lower]


# models/: one concept a module, imports pointing down (issue 8). Each module may import only
# the models modules listed here (and anything outside models/).
MODELS_LAYERS = {
    "hybridqcm.models.networks": set(),
    "hybridqcm.models.uncertainty": set(),
    "hybridqcm.models.physics_losses": set(),
    "hybridqcm.models.schedule": set(),
    "hybridqcm.models.untrusted": {"hybridqcm.models.networks"},
    "hybridqcm.models.base": {
        "hybridqcm.models.networks",
        "hybridqcm.models.physics_losses",
        "hybridqcm.models.schedule",
        "hybridqcm.models.untrusted",
    },
    "hybridqcm.models.signal_models": {"hybridqcm.models.base"},
    "hybridqcm.models.estimators": {
        "hybridqcm.models.base",
        "hybridqcm.models.physics_losses",
    },
    "hybridqcm.models.gaussian_estimator": {
        "hybridqcm.models.base",
        "hybridqcm.models.estimators",
        "hybridqcm.models.uncertainty",
    },
    "hybridqcm.models.checkpoint": {
        "hybridqcm.models.estimators",
        "hybridqcm.models.gaussian_estimator",
        "hybridqcm.models.signal_models",
        "hybridqcm.models.untrusted",
    },
}


@pytest.mark.parametrize("module", sorted(MODELS_LAYERS))
def test_models_modules_import_only_the_layers_below(module):
    graph = import_graph()
    inside = {m for m in graph[module] if m.startswith("hybridqcm.models")}
    assert inside <= MODELS_LAYERS[module], sorted(inside - MODELS_LAYERS[module])


# The package's layers (issue 29): a module imports only its own layer and those below. Top-level helper
# modules (errors, atomic, config, console, metrics, plots, ...) sit below everything except `training`
# (qcm-train's work) and `testing` (fixtures for tests and bench), which build on models and estimation.
PACKAGE_LAYERS = ("physics", "data", "models", "estimation", "reports", "pipelines", "apps")


def _layer(module: str) -> int:
    part = module.split(".")[1] if module.count(".") >= 1 else ""
    if part in PACKAGE_LAYERS:
        return PACKAGE_LAYERS.index(part)
    return PACKAGE_LAYERS.index("reports") if part in ("training", "testing") else -1  # helpers: below all


def test_package_layers_point_down():
    graph = import_graph()
    upward = sorted(
        f"{module} -> {target}"
        for module, targets in graph.items()
        for target in targets
        if _layer(target) > max(_layer(module), -1) and not (_layer(module) == -1 and _layer(target) == -1)
    )
    assert not upward, upward


def test_layer_check_sees_an_upward_import():
    assert _layer("hybridqcm.estimation.runner") < _layer("hybridqcm.reports.vehicle")
    assert _layer("hybridqcm.config") < _layer("hybridqcm.physics.road") < _layer("hybridqcm.apps.estimate")
