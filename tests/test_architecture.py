"""The import graph of socnav: no module imports one that imports it back, and data flows one way, from the simulator
up to the command line (a module never imports -- not even lazily inside a function -- one of a higher layer).

The graph is read from the source with `ast` (nothing is imported): every ``import socnav...`` and ``from socnav...
import ...`` of every module under src/socnav, at module level, inside functions and under ``if TYPE_CHECKING:``,
resolved to the socnav module it names (``from socnav.x import y``: the module socnav.x.y if there is one, else
socnav.x).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "socnav"

#: The layers, lowest first: a module may import modules of its own layer and of lower ones only. A module belongs to
#: the layer of its longest prefix listed here. The order is the data flow: the simulator, its configuration, the
#: environments built on them, controllers acting in them, learned policies (rl), their uncertainty, the safety layer
#: using both, the deployable navigator (export/runtime), the experiment engine, the paper's experiments run on it,
#: and the command line. docs/api/index.md states this list (test_the_docs_state_the_layers).
LAYERS: list[tuple[str, ...]] = [
    ("socnav.io", "socnav.extras", "socnav.validation"),  # utilities: files, install hints, what settings share
    ("socnav.sim",),  # the simulator: kernels, scenarios, its configuration (socnav.sim.config), the batched world
    ("socnav.config",),  # the configuration as users import it: re-exports socnav.sim.config and socnav.validation
    ("socnav.viz",),  # draws the scenes an environment renders
    ("socnav.envs", "socnav"),  # `socnav` itself: the package root re-exports make_env and load_config
    ("socnav.controllers",),
    ("socnav.rl",),
    ("socnav.uncertainty",),
    ("socnav.safety",),
    ("socnav.export", "socnav.runtime"),
    ("socnav.ros2",),  # the navigator and the simulator as ROS 2 nodes (the `ros2` extra)
    ("socnav.experiments",),  # the experiment engine: files, units, run directory, backends, statistics, reports
    ("socnav.paper",),  # the paper's experiment kinds (found by name: socnav.experiments.registry.KIND_MODULES)
    ("socnav.cli", "socnav._console", "socnav.__main__"),  # the command line, by group, and its workflows
]

#: Imports that break the layering; each would say why. None today: keep it that way.
KNOWN_VIOLATIONS: set[tuple[str, str]] = set()


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    line: int
    where: str  # "module" (runs when `source` is imported), "function" or "TYPE_CHECKING"

    @property
    def module_level(self) -> bool:
        return self.where == "module"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, where: str = "module"):
    """(import node, where) for every import in `tree`, looking inside functions and type-only blocks too."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, where
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            yield from _imports(node, "function")
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                yield from _imports(ast.Module(body=[child], type_ignores=[]), "TYPE_CHECKING")
            for child in node.orelse:
                yield from _imports(ast.Module(body=[child], type_ignores=[]), where)
        else:
            yield from _imports(node, where)


def _resolve(name: str, modules: set[str]) -> str | None:
    """The socnav module `name` refers to (itself, or the closest enclosing module), None outside socnav."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def build_graph() -> tuple[set[str], list[Edge]]:
    files = sorted((SRC / PACKAGE).rglob("*.py"))
    modules = {module_name(path) for path in files}
    edges = []
    for path in files:
        source = module_name(path)
        is_package = path.name == "__init__.py"
        for node, where in _imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the package of `source`
                    anchor = source.split(".")[: len(source.split(".")) - node.level + is_package]
                    base = ".".join(anchor + ([base] if base else []))
                # `from socnav.x import y`: the submodule socnav.x.y if there is one, else socnav.x itself
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                           for alias in node.names]
            for target in targets:
                resolved = _resolve(target, modules) if target.split(".")[0] == PACKAGE else None
                if resolved is not None and resolved != source:
                    edges.append(Edge(source, resolved, node.lineno, where))
    return modules, list(dict.fromkeys(edges))  # `from m import a, b`: one edge


def find_cycle(edges: list[Edge]) -> list[str] | None:
    """A cycle of the directed graph as [a, b, ..., a], or None."""
    graph: dict[str, set[str]] = {}
    for edge in edges:
        graph.setdefault(edge.source, set()).add(edge.target)
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for target in sorted(graph.get(node, ())):
            if state.get(target) == 1:
                return [*path[path.index(target):], target]
            if target not in state and (cycle := visit(target)) is not None:
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)) is not None:
            return cycle
    return None


def layer_of(module: str) -> int:
    matches = [(len(prefix), index) for index, prefixes in enumerate(LAYERS) for prefix in prefixes
               # the package root `socnav` is a layer of its own module only, not a catch-all for new modules
               if module == prefix or (prefix != PACKAGE and module.startswith(prefix + "."))]
    assert matches, f"{module} is in no layer of LAYERS: add it where it belongs"
    return max(matches)[1]


@pytest.fixture(scope="module")
def graph() -> tuple[set[str], list[Edge]]:
    return build_graph()


def test_the_graph_is_read(graph):
    # guards the reader itself: a resolver that lost every edge would pass the tests below
    modules, edges = graph
    assert {"socnav", "socnav.cli", "socnav.sim.world", "socnav.experiments.runner"} <= modules
    found = {(edge.source, edge.target) for edge in edges}
    assert ("socnav.sim.world", "socnav.sim.orca") in found  # module level
    assert ("socnav.cli.train", "socnav.rl.training") in found  # inside a command


def test_no_import_cycle_at_module_level(graph):
    _, edges = graph
    cycle = find_cycle([edge for edge in edges if edge.module_level])
    assert cycle is None, "import cycle at module level: " + " -> ".join(cycle)


def test_no_import_cycle_at_all(graph):
    # also through imports inside functions: no module imports (ever) a module that imports it back
    _, edges = graph
    allowed = [edge for edge in edges if (edge.source, edge.target) not in KNOWN_VIOLATIONS]
    cycle = find_cycle(allowed)
    assert cycle is None, "import cycle (lazy imports included): " + " -> ".join(cycle)


def test_every_module_is_in_a_layer(graph):
    modules, _ = graph
    for module in modules:
        layer_of(module)


def test_no_module_imports_a_higher_layer(graph):
    _, edges = graph
    upward = sorted(f"{edge.source} (line {edge.line}, {edge.where}) imports {edge.target}: layer "
                    f"{LAYERS[layer_of(edge.source)][0]} < {LAYERS[layer_of(edge.target)][0]}"
                    for edge in edges
                    if layer_of(edge.target) > layer_of(edge.source)
                    and (edge.source, edge.target) not in KNOWN_VIOLATIONS)
    assert not upward, "imports against the data flow:\n" + "\n".join(upward)


#: The most lines a module of src/ may have: past it a module holds more than one concern.
MODULE_LINES = 700
#: Modules allowed past it, each with its reason (orca.py stays whole on purpose).
LONG_MODULES = {
    "socnav.sim.orca": "RVO2's agent and obstacle kernels call one another, and numba invalidates a cached kernel only "
                       "when its own file changes (numba's 'Notes on caching': changes in another file are not seen)",
}


def test_no_module_is_longer_than_the_limit():
    lengths = {module_name(path): len(path.read_text().splitlines()) for path in (SRC / PACKAGE).rglob("*.py")}
    long = sorted(f"{module}: {lines} lines" for module, lines in lengths.items()
                  if lines > MODULE_LINES and module not in LONG_MODULES)
    assert not long, f"modules over {MODULE_LINES} lines (split by concern):\n" + "\n".join(long)
    assert set(LONG_MODULES) <= set(lengths), "an allowed long module no longer exists: drop it from LONG_MODULES"
    fitting = sorted(module for module in LONG_MODULES if lengths[module] <= MODULE_LINES)
    assert not fitting, f"no longer over the limit, drop them from LONG_MODULES: {fitting}"


def test_the_docs_state_the_layers():
    # docs/api/index.md's table of layers is this file's LAYERS, in order: the page cannot drift from the test
    page = (SRC.parent / "docs" / "api" / "index.md").read_text()
    section = page.split("## Layers", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and line[2:3].isdigit()]
    documented = [tuple(name.strip(" `") for name in row.split("|")[2].split(",")) for row in rows]
    assert documented == LAYERS, "docs/api/index.md's table of layers differs from LAYERS: update the page"


def test_the_engine_finds_every_kind_of_the_paper_by_name():
    # the one way up (socnav.experiments -> socnav.paper) is a name in KIND_MODULES, never an import statement
    from socnav.experiments.registry import KIND_MODULES

    modules, _ = build_graph()
    kinds = {module for module in modules if module.count(".") == 2 and module.startswith("socnav.paper.")
             and (SRC / Path(*module.split("."))).is_dir()}
    assert set(KIND_MODULES.values()) == kinds
