"""The package's layout: layers by concept, every import counted, no circle, no private name across modules.

Every module of ``closedloop/`` is parsed with `ast` (nothing is imported).  An *edge* is any import of
a closedloop module, at any depth of the file: a function's local import counts as much as one at the
top.  Only imports under ``if TYPE_CHECKING:`` are left out (they are never executed: annotations).

* **Layers** (`LAYERS`, top to bottom): a module may import its own unit (subpackage or top-level
  module) and any unit of a lower layer, never one of its own layer or above.  The root ``closedloop``
  package is the public façade: it imports, nothing imports it.
* **No circle** among modules inside a unit either (a package's ``__init__`` importing its own
  submodules is not an edge back from them).
* **The simulator never runs the calibrator**: nothing that ``closedloop.sims`` imports, directly or
  through other modules, is in `CALIBRATOR` (the ground-truth generator must not depend on the code it
  is meant to check).
* **No private name** (one leading underscore) imported from another closedloop module.

Module and function sizes are judged by cohesion in review, not by a cap here.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "closedloop"

#: top to bottom; a unit is a subpackage of closedloop or a top-level module
LAYERS: list[tuple[str, ...]] = [
    ("cli",),  # the command line: parses, prints, exits
    ("sims",),  # MuJoCo datasets with their ground truth
    ("fleet",),  # batch manifests, drift across a fleet
    ("run",),  # one calibration run from files to files, and its options
    ("impedance",),  # Part II: time-varying joint impedance
    ("validation",),  # k-fold, fixtures, evaluate, check against a truth
    ("studies",),  # Monte Carlo, thesis hand, truth drawing
    ("design",),  # pose selection
    ("output",),  # URDF, MJCF, D-H, report, HTML
    ("calibration",),  # the pipeline, staged solves, verdict
    ("analysis",),  # identifiability, gauge, scale, observability, linearity
    ("estimate",),  # solver, QR, stages, robust losses, outliers, noise, variance components
    ("records",),  # options and results, built by keyword
    ("problem",),  # the stacked calibration problem, shared parameters, lengths, distances
    ("loops",),  # one module per loop type, the loop registry, cameras
    ("model",),  # robot, D-H, parameters, SE(3)
    ("assets",),  # the robot, task and scene files shipped with the package, and their catalogue
    ("io",),  # logs, bags, camera info, schemas and option values, files written whole
    ("parallel",),  # executor and engines (serial, local processes, Ray)
    ("version", "errors", "progress"),
]

#: what the simulator must not reach, even through other modules: the pipeline and the solver's stages
#: (the simulator may use kinematics, the problem's Jacobians and linear algebra such as `estimate.qr`)
CALIBRATOR = (
    "closedloop.calibration",
    "closedloop.estimate.lm",
    "closedloop.estimate.residual",
    "closedloop.estimate.outliers",
    "closedloop.estimate.robust",
    "closedloop.validation",
)


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


# Parsed when a test asks (conftest's session fixture, shared with test_one_way), not at import: every xdist
# worker imports this file to collect it.
@pytest.fixture(scope="module")
def parsed(package_trees) -> dict[str, tuple[Path, ast.Module]]:
    return {m: (p, package_trees[p]) for m, p in MODULES.items()}


def _package_of(module: str, path: Path) -> str:
    return module if path.name == "__init__.py" else module.rsplit(".", 1)[0]


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module name of a ``from X import ...``."""
    if not node.level:
        return node.module or ""
    base = _package_of(module, path).split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _imports(tree: ast.Module):
    """Every import node of the file except those under ``if TYPE_CHECKING:``."""
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def _deepest(name: str) -> str:
    while name and name not in MODULES:  # `import closedloop.x.y` reaches the deepest known module
        name = name.rpartition(".")[0]
    return name


def edges(parsed: dict[str, tuple[Path, ast.Module]], modules=MODULES) -> dict[str, dict[str, int]]:
    """module -> {imported closedloop module: line of the first such import}."""
    graph: dict[str, dict[str, int]] = {m: {} for m in modules}
    for module, (path, tree) in parsed.items():
        for node in _imports(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                source = _resolve(module, path, node)
                targets = [source] + [f"{source}.{a.name}" for a in node.names if f"{source}.{a.name}" in modules]
            for t in targets:
                if not t.startswith("closedloop"):
                    continue
                t = _deepest(t)
                if t and t != module:
                    graph[module].setdefault(t, node.lineno)
    return graph


def unit(module: str) -> str:
    """The unit of a module: its subpackage or top-level module under closedloop ('' for the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer_violations(graph: dict[str, dict[str, int]], layers=LAYERS) -> list[str]:
    """Edges that go up, sideways to another unit of the same layer, or into the root façade."""
    rank = {u: k for k, layer in enumerate(layers) for u in layer}
    bad = []
    for module, targets in graph.items():
        a = unit(module)
        for target, line in targets.items():
            b = unit(target)
            if a == b:
                continue
            if b == "" and a != "":
                bad.append(f"{module}:{line} imports the root package (the public façade): import the module itself")
            elif a == "":
                continue
            elif a not in rank or b not in rank:
                bad.append(f"{module}:{line} -> {target}: unit '{a if a not in rank else b}' has no layer in LAYERS")
            elif rank[b] <= rank[a]:
                where = "the same layer" if rank[b] == rank[a] else "a higher layer"
                bad.append(f"{module}:{line} -> {target}: '{b}' is {where} than '{a}'")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _without_own_packages(graph: dict[str, dict[str, int]]) -> dict[str, set[str]]:
    """Drop edges from a module to a package containing it (a package's __init__ runs before any of its
    modules anyway: such an edge is never a circle of its own making)."""
    return {m: {t for t in ts if not m.startswith(t + ".")} for m, ts in graph.items()}


def reach(graph: dict[str, set[str]], start: list[str]) -> dict[str, str]:
    """Every module reachable from `start`, each with the module it was first reached from."""
    seen = {s: "" for s in start}
    todo = list(start)
    while todo:
        m = todo.pop()
        for t in sorted(graph.get(m, ())):
            if t not in seen:
                seen[t] = m
                todo.append(t)
    return seen


@pytest.fixture(scope="module")
def graph(parsed) -> dict[str, dict[str, int]]:
    return edges(parsed)


def test_every_module_is_found():
    assert "closedloop" in MODULES and "closedloop.cli.main" in MODULES and "closedloop.sims.dataset" in MODULES
    assert len(MODULES) > 60
    assert {unit(m) for m in MODULES} - {""} <= {u for layer in LAYERS for u in layer}


def test_function_level_imports_are_counted(graph):
    """The graph holds an import made inside a function (the CLI loads its commands that way)."""
    assert any("closedloop.cli.calibrate" in t for t in [graph["closedloop.cli.main"]])
    tree = ast.parse("def f():\n    from closedloop.errors import InputError\n")
    g = edges({"closedloop.io.logs": (PACKAGE / "io" / "logs.py", tree)}, MODULES)
    assert "closedloop.errors" in g["closedloop.io.logs"]


def test_layers(graph):
    bad = layer_violations(graph)
    assert not bad, "imports against the layers (tests/test_layout.py LAYERS):\n" + "\n".join(bad)


def test_a_wrong_way_import_fails():
    """The checker itself: an upward, a sideways and a root import are each reported."""
    graph = {
        "closedloop.model.robot": {"closedloop.calibration.pipeline": 7},  # up
        "closedloop.version": {"closedloop.errors": 3},  # sideways, same layer
        "closedloop.io.logs": {"closedloop": 5},  # the façade
        "closedloop.cli.main": {"closedloop.io.logs": 9},  # down: fine
    }
    bad = layer_violations(graph)
    assert len(bad) == 3
    assert any("closedloop.model.robot:7" in b and "higher layer" in b for b in bad)
    assert any("closedloop.version:3" in b and "same layer" in b for b in bad)
    assert any("closedloop.io.logs:5" in b and "façade" in b for b in bad)


def test_no_import_cycle(graph):
    found = cycles(_without_own_packages(graph))
    assert not found, "import cycles among closedloop modules: " + "; ".join(" <-> ".join(c) for c in found)


def test_cycle_detector_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_simulator_never_runs_the_calibrator(graph):
    sims = [m for m in MODULES if m.startswith("closedloop.sims")]
    seen = reach(_without_own_packages(graph), sims)
    bad = []
    for m in sorted(seen):
        if m.startswith(CALIBRATOR):
            chain, k = [m], m
            while seen[k]:
                k = seen[k]
                chain.append(k)
            bad.append(" <- ".join(chain))
    assert not bad, "the simulator reaches the calibrator:\n" + "\n".join(bad)


def test_no_private_name_imported_across_modules(parsed):
    bad = []
    for module, (path, tree) in parsed.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                source = _resolve(module, path, node)
                for alias in node.names:
                    if _is_private(alias.name) and source.split(".")[0] == "closedloop":
                        if f"{source}.{alias.name}" not in MODULES:
                            bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {alias.name} from {source}")
                    elif _is_private(alias.name):
                        bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {alias.name} from {source}")
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if any(_is_private(part) for part in alias.name.split(".")):
                        bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: import {alias.name}")
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)
