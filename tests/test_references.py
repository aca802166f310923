"""Every backticked module, function or file path in the docs, the README and the package's docstrings and
comments names something that exists.

What counts as a path (inside single or double backticks, reST roles included):

* a dotted name starting with ``closedloop.`` (`closedloop.loops.spec.parse_loop`): its module must exist,
  and the name after it must be defined at the module's top level (a class's attribute after that, in the
  class or a base class of the package);
* a dotted name whose first part is a module of the package named short (`spec.parse_loop`,
  `estimate.outliers`, `verdict._minimum`): one module whose dotted name ends so must define the rest;
* a dotted name whose first part is a class of the package (`CalibrationResult.reducible`): the attribute
  must be the class's (or a base's);
* a dotted name whose first part names no module or class of the package but whose second part is a
  function or class defined at the top level of one (`fit.weighted_stage`, `staging.solve_staged`):
  a reference to a module that does not exist;
* a file path ending in ``.py`` (``estimate/residual.py``, ``weld.py``, ``cli/calibrate.py:cmd_calibrate``):
  a file of the repository or of the package ending so must exist (and define the function after ``:``).

Paths are read from the code with `ast`, not imported.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "closedloop"

SPAN = re.compile(r"(?<!`)``?([^`\n]+?)``?(?!`)")
DOTTED = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)+$")
FILE = re.compile(r"^([\w./-]*\w\.py)(?::(\w+))?$")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
#: what a backticked name ending so is: a file's name, not a module path
EXTENSIONS = {"json", "csv", "xml", "h5", "yaml", "yml", "urdf", "txt", "html", "md", "png", "npz", "npy", "bag", "db3"}
#: objects the prose names by their usual variable (`parser.parse_args`, an estimate `est`), not modules
VARIABLES = {"parser", "est", "args", "self", "res", "result", "opt", "np", "pin"}
#: third-party packages the prose names by their own module paths (`scipy.stats`)
THIRD_PARTY = {"scipy", "numpy", "pinocchio", "mujoco", "matplotlib", "ray", "tqdm", "rosbags", "yourdfpy", "h5py"}
#: keys of the JSON report and of truth.json that read like code paths
KEYS = {"identifiability.moved_not_identifiable", "report.fixture_validation", "loop.calibrate"}


class Module:
    def __init__(self, path: Path):
        self.path = path
        tree = ast.parse(path.read_text(encoding="utf-8"))
        self.names: set[str] = set()
        self.classes: dict[str, ast.ClassDef] = {}
        self.nested: set[str] = set()  # every function defined anywhere in the file
        self.strings: set[str] = set()  # string constants: the names a lazy `__getattr__` (PEP 562) serves
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                self.nested.add(node.name)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                self.strings.add(node.value)
        for node in tree.body:
            for n in _bound(node):
                self.names.add(n)
            if isinstance(node, ast.ClassDef):
                self.classes[node.name] = node
            if isinstance(node, ast.If):  # `if TYPE_CHECKING:` imports and conditional definitions
                for sub in node.body + node.orelse:
                    self.names.update(_bound(sub))


def _bound(node: ast.stmt) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name]
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return [(a.asname or a.name).split(".")[0] for a in node.names]
    if isinstance(node, ast.Assign):
        return [n.id for t in node.targets for n in ast.walk(t) if isinstance(n, ast.Name)]
    if isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


@cache  # a class is asked for each attribute the prose names of it (and of its subclasses)
def _class_attributes(cls: ast.ClassDef) -> frozenset[str]:
    out = set()
    for node in cls.body:
        out.update(_bound(node))
    for node in ast.walk(cls):  # self.x = ... in its methods
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
            out.add(node.attr)
    return frozenset(out)


@cache
def modules() -> dict[str, Module]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(not p.isidentifier() for p in parts):
            continue
        out[".".join(parts)] = Module(path)
    return out


@cache
def classes() -> dict[str, list[ast.ClassDef]]:
    out: dict[str, list[ast.ClassDef]] = {}
    for m in modules().values():
        for name, cls in m.classes.items():
            out.setdefault(name, []).append(cls)
    return out


@cache
def top_level_definitions() -> set[str]:
    """Functions and classes defined at the top level of some module (not imported, not constants)."""
    out = set()
    for m in modules().values():
        out.update(m.classes)
        out.update(n for n in m.names if n in m.nested)
    return out


def _has_attribute(cls_name: str, attr: str, seen: frozenset = frozenset()) -> bool:
    for cls in classes().get(cls_name, []):
        if attr in _class_attributes(cls):
            return True
        for base in cls.bases:
            name = base.id if isinstance(base, ast.Name) else getattr(base, "attr", None)
            if name and name not in seen and name in classes() and _has_attribute(name, attr, seen | {cls_name}):
                return True
        if any(not (isinstance(b, ast.Name) and b.id in classes()) for b in cls.bases):
            if cls.bases and not all(isinstance(b, ast.Name) and b.id in ("object",) for b in cls.bases):
                return True  # a base outside the package (str, Enum, ...): its attributes are not checked
    return False


def _resolve_in(module: str, rest: list[str]) -> bool:
    m = modules()[module]
    if not rest:
        return True
    if module + "." + rest[0] in modules():  # a submodule
        return _resolve_in(module + "." + rest[0], rest[1:])
    if rest[0] not in m.names and not ("__getattr__" in m.names and rest[0] in m.strings):
        return False
    if len(rest) >= 2 and rest[0] in m.classes:
        return _has_attribute(rest[0], rest[1])
    return True


def dotted_problem(ref: str) -> str | None:
    """Why the dotted reference names nothing, or None."""
    parts = ref.split(".")
    mods = modules()
    if parts[0] == "closedloop":
        for k in range(len(parts), 0, -1):
            if ".".join(parts[:k]) in mods:
                return None if _resolve_in(".".join(parts[:k]), parts[k:]) else f"no {'.'.join(parts[k:])} in it"
        return "no such module"
    if parts[-1] in EXTENSIONS or parts[0] in VARIABLES or parts[0] in THIRD_PARTY or ref in KEYS:
        return None
    for k in range(len(parts), 0, -1):  # a module named by its last parts
        suffix = "." + ".".join(parts[:k])
        found = [name for name in mods if name.endswith(suffix)]
        if found:
            if any(_resolve_in(name, parts[k:]) for name in found):
                return None
            if parts[k] in top_level_definitions() or f"closedloop.{'.'.join(parts[: k + 1])}" in mods:
                return f"no {'.'.join(parts[k:])} in {' or '.join(found)}"
            return None  # an object's attribute (`loop.own_cov`, a report key `verdict.size_measured`)
    if parts[0] in classes():
        return None if _has_attribute(parts[0], parts[1]) else f"{parts[0]} has no attribute {parts[1]}"
    if parts[0].islower() and parts[1] in top_level_definitions():
        return f"no module '{parts[0]}' (and '{parts[1]}' is defined elsewhere)"
    return None


def file_problem(path: str, func: str | None) -> str | None:
    """Why a backticked file path (and function) names nothing, or None."""
    if "/" not in path and not path.startswith(("test_", "bench")):
        candidates = [p for p in ROOT.rglob(path) if ".git" not in p.parts and "site" not in p.parts]
    else:
        candidates = [
            p for p in (ROOT / path, PACKAGE / path, ROOT / "tests" / path, ROOT / "benchmarks" / path) if p.is_file()
        ] or [p for p in PACKAGE.rglob(Path(path).name) if p.as_posix().endswith("/" + path)]
    if not candidates:
        return "no such file"
    if func and not any(func in Module(p).nested or func in Module(p).names for p in candidates):
        return f"no {func} in it"
    return None


def references(text: str) -> list[str]:
    return [m.group(1).strip() for m in SPAN.finditer(text)]


def problems_in(text: str) -> list[str]:
    out = []
    for ref in references(text):
        ref = re.sub(r"^:\w+:", "", ref).rstrip("()")
        if ref.startswith(("closedloop ", "$", "-")) or " " in ref:
            continue
        f = FILE.match(ref)
        if f:
            why = file_problem(f.group(1), f.group(2))
        elif DOTTED.match(ref):
            why = dotted_problem(ref)
        else:
            continue
        if why:
            out.append(f"`{ref}`: {why}")
    return out


def _sources() -> list[Path]:
    docs = sorted((ROOT / "docs").rglob("*.md"))
    return [ROOT / "README.md", *docs, *sorted(PACKAGE.rglob("*.py"))]


def test_every_backticked_path_exists():
    bad = []
    for path in _sources():
        text = path.read_text(encoding="utf-8")
        if path.suffix == ".md":
            text = FENCE.sub("", text)  # code blocks are run by the docs tests, not read here
        bad += [f"{path.relative_to(ROOT)}: {p}" for p in problems_in(text)]
    assert not bad, "\n".join(bad)


def test_the_check_sees_a_missing_module_function_and_file():
    assert dotted_problem("closedloop.loops.spec.parse_loop") is None
    assert dotted_problem("spec.parse_loop") is None
    assert dotted_problem("closedloop.calibration.staging") == "no such module" or dotted_problem(
        "closedloop.calibration.staging"
    )
    assert dotted_problem("closedloop.loops.spec.no_such_function")
    assert dotted_problem("fit.weighted_stage")  # `fit` was renamed: weighted_stage lives elsewhere
    assert dotted_problem("CalibrationOptions.nothing_like_this")
    assert dotted_problem("res.values") is None  # a variable's attribute is not a path
    assert dotted_problem("estimate.qr") is None and dotted_problem("closedloop.calibrate") is None
    assert dotted_problem("calibration.build_problem")  # defined in calibration.pipeline, not exported
    assert file_problem("estimate/residual.py", "weighted_stage") is None
    assert file_problem("estimate/stages.py", None) == "no such file"
    assert file_problem("cli/calibrate.py", "no_such_command")
    assert problems_in("see `closedloop.estimate.lm.levenberg_marquardt` and ``loops/weld.py``") == []
