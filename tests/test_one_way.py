"""Things the package does one way, checked on its source with `ast` (nothing is imported):

* **printing only in** ``closedloop/cli/``: no ``print()`` and no ``sys.stdout`` / ``sys.stderr`` (nor
  their ``__stdout__`` / ``__stderr__``) elsewhere; the library returns values, logs (`logging`) or
  reports progress through `closedloop.progress.ProgressReporter`.  Flushing stderr before C++ code
  writes to its file descriptor (`model.robot`) is not a write;
* **an optional package is refused one way**: `closedloop.errors.require`; no other ``except
  ImportError`` in the package but the one reading numpy's optional LAPACK binding (`estimate.qr`);
* **scipy**: its signal processing (``scipy.signal``, ``scipy.ndimage``) and distributions
  (``scipy.stats``, ``scipy.special``) are never imported: `impedance.filters` and `estimate.robust.stats`
  stand for them (their import costs more than the work, module docstrings); the rest of scipy
  (``linalg``, ``optimize``, ``sparse``) is imported inside the function that uses it, except by the
  simulator's planner (`sims.qp`, which calls LAPACK on every step).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "closedloop"


# Parsed when a test asks (conftest's session fixture, shared with test_layout), not at import: every xdist
# worker imports this file to collect it.
@pytest.fixture(scope="module")
def sources(package_trees) -> dict[str, ast.Module]:
    return {p.relative_to(PACKAGE.parent).as_posix(): tree for p, tree in package_trees.items()}


STREAMS = {"stdout", "stderr", "__stdout__", "__stderr__"}
NOT_WRITES = {"flush", "fileno", "isatty"}  # a stream's method that writes nothing
IMPORT_ERROR_ALLOWED = {"closedloop/errors.py", "closedloop/estimate/qr.py"}
SCIPY_NEVER = ("scipy.signal", "scipy.ndimage", "scipy.stats", "scipy.special")
SCIPY_AT_TOP_ALLOWED = {"closedloop/sims/qp.py"}


def _parents(tree: ast.AST) -> dict[ast.AST, ast.AST]:
    return {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}


def printing(tree: ast.AST) -> list[int]:
    """Lines that print or touch sys.stdout / sys.stderr other than to flush them."""
    up = _parents(tree)
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
            lines.append(node.lineno)
        elif isinstance(node, ast.Attribute) and node.attr in STREAMS:
            if isinstance(node.value, ast.Name) and node.value.id == "sys":
                parent = up.get(node)
                if not (isinstance(parent, ast.Attribute) and parent.attr in NOT_WRITES):
                    lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.module == "sys":
            if any(a.name in STREAMS for a in node.names):
                lines.append(node.lineno)
    return sorted(set(lines))


def test_printing_only_in_cli(sources):
    found = [
        f"{path}:{line}"
        for path, tree in sources.items()
        if not path.startswith("closedloop/cli/")
        for line in printing(tree)
    ]
    assert found == [], "printing outside closedloop/cli/: " + ", ".join(found)


def test_the_scan_sees_every_way_of_printing():
    text = (
        "import sys\nfrom sys import stderr\nprint('x')\nsys.stdout.write('x')\nprint('x', file=sys.stderr)\n"
        "w = sys.__stderr__\nsys.stderr.flush()\n"
    )
    assert printing(ast.parse(text)) == [2, 3, 4, 5, 6]


def test_a_missing_optional_package_is_refused_one_way(sources):
    found = []
    for path, tree in sources.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.ExceptHandler) and node.type is not None:
                names = {n.id for n in ast.walk(node.type) if isinstance(n, ast.Name)}
                if names & {"ImportError", "ModuleNotFoundError"} and path not in IMPORT_ERROR_ALLOWED:
                    found.append(f"{path}:{node.lineno}")
    assert found == [], "except ImportError outside closedloop.errors.require: " + ", ".join(found)


def _scipy_imports(tree: ast.Module):
    """(module imported, line, at the top of the file?) for every scipy import."""
    top = set(tree.body)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            if name == "scipy" or name.startswith("scipy."):
                yield name, node.lineno, node in top


def test_scipy_signal_and_stats_kept_out_the_rest_imported_where_used(sources):
    never, eager = [], []
    for path, tree in sources.items():
        for name, line, at_top in _scipy_imports(tree):
            if name.startswith(SCIPY_NEVER):
                never.append(f"{path}:{line} {name}")
            elif at_top and path not in SCIPY_AT_TOP_ALLOWED:
                eager.append(f"{path}:{line} {name}")
    assert never == [], "use impedance.filters / estimate.robust.stats instead: " + ", ".join(never)
    assert eager == [], "import scipy inside the function that uses it: " + ", ".join(eager)
