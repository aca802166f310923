"""The package's layout (issue 15): no private name imported across modules, no import cycle, small modules.

Every module of ``closedloop/`` is parsed with `ast` (nothing is imported):

* a name starting with one underscore (not a dunder) imported from another closedloop module, at
  any depth of the file (a function's local import counts), is an error;
* the graph of module-level imports among closedloop modules (``import a.b``, ``from . import x``
  where x is a submodule, ``from .m import name``; imports inside functions, under ``if
  TYPE_CHECKING`` or PEP 562 ``__getattr__`` excluded) has no cycle; a package's ``__init__``
  importing its own submodules is not an edge back from them;
* no module is over `MAX_LINES` lines, except those in `LONG_MODULES` (each with its reason).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "closedloop"
MAX_LINES = 450

# Modules allowed over MAX_LINES lines, each with its reason.
LONG_MODULES: dict[str, str] = {}

# Private names of other packages that may be imported, each with its reason.
FOREIGN_PRIVATE_ALLOWED: dict[tuple[str, str], str] = {}


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


def _module_level_nodes(tree: ast.Module):
    """Import nodes executed when the module is imported (not in functions, TYPE_CHECKING blocks)."""
    stack = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            test = ast.unparse(node.test)
            if "TYPE_CHECKING" not in test:
                stack.extend(node.body + node.orelse)
        elif isinstance(node, ast.Try):
            stack.extend(node.body + node.orelse + node.finalbody + [h for x in node.handlers for h in x.body])
        elif isinstance(node, (ast.With,)):
            stack.extend(node.body)


def _parsed() -> dict[str, tuple[Path, ast.Module]]:
    return {m: (p, ast.parse(p.read_text(), filename=str(p))) for m, p in MODULES.items()}


PARSED = _parsed()


def test_every_module_is_found():
    assert "closedloop" in MODULES and "closedloop.cli.main" in MODULES and "closedloop.sims.dataset" in MODULES
    assert len(MODULES) > 60


def test_no_private_name_imported_across_modules():
    bad = []
    for module, (path, tree) in PARSED.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                source = _resolve(module, path, node)
                for alias in node.names:
                    if not _is_private(alias.name):
                        continue
                    if source.split(".")[0] == "closedloop":
                        if f"{source}.{alias.name}" in MODULES:
                            continue  # a private submodule of a package (none today, allowed by name)
                        bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {alias.name} from {source}")
                    elif (source, alias.name) not in FOREIGN_PRIVATE_ALLOWED:
                        bad.append(
                            f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {alias.name} from {source} "
                            "(another package's private name)"
                        )
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if (
                        any(_is_private(part) for part in alias.name.split("."))
                        and (alias.name, "") not in FOREIGN_PRIVATE_ALLOWED
                    ):
                        bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: import {alias.name}")
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def _edges() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module, (path, tree) in PARSED.items():
        for node in _module_level_nodes(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                source = _resolve(module, path, node)
                targets = [source]
                targets += [f"{source}.{a.name}" for a in node.names if f"{source}.{a.name}" in MODULES]
            for t in targets:
                while t and t not in MODULES:  # `import closedloop.x.y` reaches the deepest known module
                    t = t.rpartition(".")[0]
                if not t or t == module:
                    continue
                # a submodule importing a name from its own package's __init__ while the __init__ imports it
                graph[module].add(t)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
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
        for w in sorted(graph[v]):
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


def _without_package_inits(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Drop edges from a module to a package containing it (importing ``closedloop.x`` runs ``closedloop``'s
    __init__ first anyway: such an edge is never a cycle of its own making)."""
    return {m: {t for t in ts if not m.startswith(t + ".")} for m, ts in graph.items()}


def test_no_import_cycle():
    cycles = _cycles(_without_package_inits(_edges()))
    assert not cycles, "import cycles among closedloop modules: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_cycle_detector_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_modules_are_small():
    long = {m: len(p.read_text().splitlines()) for m, p in MODULES.items()}
    over = {m: n for m, n in long.items() if n > MAX_LINES and m not in LONG_MODULES}
    assert not over, f"modules over {MAX_LINES} lines: {over}"


def test_functions_are_short():
    """No function over 80 lines (decorators and docstring included) anywhere in the package."""
    import ast

    over = {}
    for m, p in MODULES.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                over[f"{m}.{node.name}"] = node.end_lineno - node.lineno + 1
    assert not over, f"functions over 80 lines: {over}"
