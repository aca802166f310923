"""Schemas of every input file, validated with `jsonschema`; strict numbers and YAML.

Every document a user gives closedloop is checked here before it is used:

* D-H tables (``*.yaml``, :data:`DH_SCHEMA`), read with :class:`StrictLoader`;
* simulation truth and calibration reports (``*.json``, :data:`TRUTH_SCHEMA`,
  :data:`REPORT_SCHEMA`: the fields ``closedloop check`` reads);
* simulation settings (``--set``, a scenario file's ``settings:``, :data:`SETTINGS_SCHEMA`),
  scenario YAML (:data:`SCENARIO_SCHEMA`); a calibration's options are checked by
  `closedloop.run.options`.

A "number" is a finite int or float, never a boolean (``s: true`` is refused, not read as 1);
booleans are only ``true``/``false`` (YAML 1.1's ``yes``/``no``/``on``/``off`` stay strings and are
refused where a boolean is expected); ``1_000`` is not a number (YAML 1.2 core schema, and
:func:`parse_number` for CSV cells and command-line values).  A failure raises the caller's
`InputError` subclass with one line naming the file, the field and the row.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import yaml

from closedloop.errors import InputError

#: a name usable in parameter names ``<owner>.<field>`` and comma-separated option lists
NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_\-]*$"
#: magnitude of any number in an input file (beyond it Pinocchio's SVDs overflow)
MAX_ABS = 1e6
_NUMBER = re.compile(r"^\s*[-+]?(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?\s*$")
_NONFINITE = re.compile(r"^\s*[-+]?(nan|inf|infinity)\s*$", re.IGNORECASE)


# --------------------------------------------------------------------------- numbers
def parse_number(text: str, what: str, error: type[InputError] = InputError, *, allow_inf: bool = False) -> float:
    """A decimal number (``1``, ``-2.5e-3``, ``.5``), finite; refuses ``1_000``, ``0x10``, ``nan``.

    `what` starts the message, e.g. ``"--snr 1_000"`` or ``"log.csv: row 3, column 'j1'"``.
    """
    if _NUMBER.match(text):
        v = float(text)
        if math.isfinite(v):
            return v
        raise error(f"{what}: {text.strip()} overflows a double")
    if _NONFINITE.match(text):
        if allow_inf and "inf" in text.lower():
            return float(text)
        raise error(f"{what}: value is {text.strip()} (a finite number is needed)")
    raise error(f"{what}: '{text.strip()}' is not a number")


#: the pose-selection methods of `closedloop.design.poses` (D- and A-optimal, greedy and exchange)
POSE_METHODS = ("greedy", "detmax", "greedy-a", "exchange-a")
#: the simulator's draws of the true robot (`closedloop.sims.true_robot`): the identifiable parameters, or all
TRUTH_DRAWS = ("identifiable", "all")


def is_number(x: Any) -> bool:
    """A finite int or float, not a bool."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:  # an int beyond a double
        return False


# --------------------------------------------------------------------------- strict YAML
class StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 core scalars and no duplicate keys.

    Booleans: true/false only; integers: decimal digits (no ``1_000``, no sexagesimal ``1:20``,
    no octal ``010``); floats: ``1.5``, ``1e5``, ``.inf``, ``.nan``.
    """


StrictLoader.yaml_implicit_resolvers = {
    ch: [
        (tag, rx)
        for tag, rx in lst
        if tag not in ("tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float")
    ]
    for ch, lst in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:int", re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+0123456789."),
)


def _int(loader: StrictLoader, node: yaml.ScalarNode) -> int:
    return int(loader.construct_scalar(node))


def _float(loader: StrictLoader, node: yaml.ScalarNode) -> float:
    text = str(loader.construct_scalar(node)).lower()
    return float(text.replace(".inf", "inf").replace(".nan", "nan"))


def _mapping(loader: StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen: set = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            dup = key in seen
        except TypeError:  # an unhashable key (a list)
            raise yaml.constructor.ConstructorError(
                None, None, "a key must be a plain value", key_node.start_mark
            ) from None
        if dup:
            raise yaml.constructor.ConstructorError(None, None, f"duplicate key '{key}'", key_node.start_mark)
        seen.add(key)
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


StrictLoader.add_constructor("tag:yaml.org,2002:int", _int)
StrictLoader.add_constructor("tag:yaml.org,2002:float", _float)
StrictLoader.construct_mapping = _mapping


def read_text(path: str | Path, what: str, error: type[InputError] = InputError) -> str:
    """A file's text (UTF-8, a byte-order mark dropped), noted as an input of the running command
    (`closedloop.io.files.note_input`); unreadable files are `error`."""
    from closedloop.io.files import note_input

    text = _read(path, what, error)
    note_input(path)
    return text


def _read(path: str | Path, what: str, error: type[InputError]) -> str:
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not a {what}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a UTF-8 text file (byte {exc.start})") from None


def load_yaml(
    path: str | Path,
    what: str,
    error: type[InputError] = InputError,
    *,
    schema: dict | None = None,
    rows: str | None = None,
) -> Any:
    """Parse a YAML file with :class:`StrictLoader`; errors name the file and the line.  With `schema`, the
    document is checked against it (`validate`; `rows`: the list of rows it must hold, ``joints``) before
    it is returned.  The file is then noted as an input of the running command (`read_text`)."""
    from closedloop.io.files import note_input

    text = _read(path, what, error)
    try:
        doc = yaml.load(text, Loader=StrictLoader)  # noqa: S506 - StrictLoader is a SafeLoader
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise error(f"{path}: not valid YAML{where} ({problem})") from None
    except (ValueError, OverflowError, RecursionError) as exc:  # a scalar the constructors refuse
        raise error(f"{path}: not valid YAML ({type(exc).__name__}: {exc})") from None
    if schema is not None:
        if rows is not None and (not isinstance(doc, dict) or rows not in doc):
            raise error(f"{path}: a {what} needs a non-empty '{rows}' list")
        validate(doc, schema, path, error, rows=rows)
    note_input(path)
    return doc


def load_json(path: str | Path, what: str, error: type[InputError] = InputError) -> Any:
    """Parse a JSON file; NaN and Infinity are refused (they are not JSON).  The file is noted as an input
    of the running command (`read_text`)."""
    from closedloop.io.files import note_input

    text = _read(path, what, error)

    def refuse(name: str):
        raise ValueError(f"{name} is not a JSON number")

    try:
        doc = json.loads(text, parse_constant=refuse)
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except (ValueError, RecursionError) as exc:
        raise error(f"{path}: not valid JSON ({exc})") from None
    note_input(path)
    return doc


# --------------------------------------------------------------------------- schemas
def _finite_number(_checker, x) -> bool:
    return is_number(x)


def _validator_class():
    """Draft 2020-12 with "number" meaning a finite int or float (jsonschema imported on first use)."""
    if "validator" not in _cache:
        import jsonschema

        base = jsonschema.Draft202012Validator
        _cache["validator"] = jsonschema.validators.extend(
            base, type_checker=base.TYPE_CHECKER.redefine("number", _finite_number)
        )
    return _cache["validator"]


_cache: dict = {}


def num(lo: float = -MAX_ABS, hi: float = MAX_ABS, *, exclusive_lo: bool = False) -> dict:
    """Schema of a finite number in [lo, hi] (or (lo, hi] with `exclusive_lo`)."""
    s: dict = {"type": "number", "maximum": hi}
    s["exclusiveMinimum" if exclusive_lo else "minimum"] = lo
    return s


def integer(lo: int = 0, hi: int = 2**63 - 1) -> dict:
    return {"type": "integer", "minimum": lo, "maximum": hi}


NAME = {"type": "string", "pattern": NAME_PATTERN, "maxLength": 200}

DH_ROW_FIELDS = ("theta_off", "s", "a", "alpha", "k", "lower", "upper")
DH_SCHEMA = {
    "type": "object",
    "properties": {
        "name": NAME,
        "closes": {"type": "boolean"},
        "convention": {"enum": ["dh", "hayati", "modified"]},
        "units": {
            "type": "object",
            "additionalProperties": False,
            "properties": {"length": {"enum": ["m", "mm", "cm", "in"]}, "angle": {"enum": ["rad", "deg"]}},
        },
        "joints": {
            "type": "array",
            "minItems": 1,
            "items": {
                "type": "object",
                "required": ["name"],
                "additionalProperties": False,
                "properties": {
                    "name": NAME,
                    "convention": {"enum": ["dh", "hayati", "modified"]},
                    "parent": NAME,
                    **{f: num() for f in DH_ROW_FIELDS},
                },
            },
        },
    },
    "required": ["joints"],
    "additionalProperties": False,
}

TRUTH_SCHEMA = {
    "type": "object",
    "required": ["parameters"],
    "properties": {
        "parameters": {
            "type": "object",
            "minProperties": 1,
            "additionalProperties": num(),
            "propertyNames": {"minLength": 1, "maxLength": 300},
        },
        "scenario": {"type": "string"},
        "robot": {"type": "string"},
        "seed": integer(),
        "joint_names": {"type": "array", "items": {"type": "string"}},
    },
}

REPORT_PARAMETER = {
    "type": "object",
    "required": ["name", "kind", "unit", "calibrated", "status"],
    "properties": {
        "name": {"type": "string", "minLength": 1, "maxLength": 300},
        "kind": {"type": "string"},
        "unit": {"type": "string"},
        "status": {"type": "string"},
        "calibrated": num(),
        "initial": num(),
        "std_error": {"anyOf": [{"type": "null"}, {"type": "number", "minimum": 0}]},
    },
}
REPORT_SCHEMA = {
    "type": "object",
    "required": ["parameters"],
    "properties": {"parameters": {"type": "array", "items": REPORT_PARAMETER}},
}


def _settings_schema() -> dict:
    """`SimSettings` fields with their ranges (a bad value would hang, explode or be ignored)."""
    p = {
        "timestep": num(1e-5, 0.05),
        "integrator": {"enum": ["implicitfast", "implicit", "Euler", "RK4"]},
        "gravity": {"type": "boolean"},
        "gravcomp": {"type": "boolean"},
        "solref": {
            "type": "array",
            "minItems": 2,
            "maxItems": 2,
            "prefixItems": [num(0, 10, exclusive_lo=True), num(0, 100, exclusive_lo=True)],
        },
        "solimp": {
            "type": "array",
            "minItems": 5,
            "maxItems": 5,
            "prefixItems": [
                num(0, 1, exclusive_lo=True),
                num(0, 1, exclusive_lo=True),
                num(0, 10, exclusive_lo=True),
                num(0, 1, exclusive_lo=True),
                num(1, 100),
            ],
        },
        "armature": num(0, 1e3),
        "kp": num(0, 1e6, exclusive_lo=True),
        "kv": num(0, 1e5),
        "vel_tol": num(0, 10, exclusive_lo=True),
        "move_vel_tol": num(0, 100, exclusive_lo=True),
        "min_steps": integer(0, 10**6),
        "max_steps": integer(1, 10**6),
        "ramp_steps": integer(1, 10**4),
        "step_rad": num(0, 3.2, exclusive_lo=True),
        "target_span": num(0, 10, exclusive_lo=True),
        "retarget_every": integer(1, 10**6),
        "select": {"anyOf": [{"type": "null"}, {"enum": list(POSE_METHODS)}]},
        "select_pool": num(1, 1000),
        "limit_margin": num(0, 1),
        "limit_flag": num(0, 1),
        "drop_flagged": {"type": "boolean"},
        "relax": {"type": "boolean"},
        "relax_passes": integer(0, 50),
        "translation": num(0, 0.1),
        "rotation": num(0, 0.5),
        "offset": num(0, 0.5),
        "scale": num(0, 0.5),
        "truth": {"enum": list(TRUTH_DRAWS)},
        "compliance": num(0, 0.1),
        "noise": num(0, 0.1),
        "quantization": num(0, 0.1),
        "tracker_noise": num(0, 0.1),
        "soft": {"type": "boolean"},
        "stiff": {"type": "boolean"},
    }
    return {"type": "object", "properties": p, "additionalProperties": False}


def settings_schema() -> dict:
    if "settings" not in _cache:
        _cache["settings"] = _settings_schema()
    return _cache["settings"]


def scenario_schema() -> dict:
    """A scenario YAML: robot, loop (a ``--loop`` spec), fixture pose, q0, settings, n, seed."""
    return {
        "type": "object",
        "required": ["robot", "loop"],
        "additionalProperties": False,
        "properties": {
            "name": NAME,
            "robot": {"type": "string", "minLength": 1},
            "loop": {"type": "string", "minLength": 1},
            "fixture": {"type": "array", "minItems": 6, "maxItems": 6, "items": num()},
            "q0": {"type": "array", "minItems": 1, "items": num(-1e3, 1e3)},
            "n": integer(1, 10**7),
            "seed": integer(0),
            "settings": settings_schema(),
            "description": {"type": "string"},
        },
    }


# --------------------------------------------------------------------------- messages
_TYPE_WORDS = {
    "number": "a finite number",
    "integer": "a whole number",
    "string": "a string",
    "boolean": "true or false",
    "object": "a mapping",
    "array": "a list",
    "null": "null",
}


def _show(x: Any) -> str:
    if isinstance(x, bool):
        return "true (a boolean)" if x else "false (a boolean)"
    if isinstance(x, str):
        return repr(x[:60])
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, (dict, list)):
        return "a mapping" if isinstance(x, dict) else "a list"
    text = repr(x)
    return text if len(text) < 60 else text[:57] + "..."


def _where(doc: Any, path: list, rows: str | None) -> str:
    """``joints row 3 ('j2'), field 's'`` from the path ['joints', 2, 's']."""
    parts: list[str] = []
    node = doc
    for key in path:
        try:
            node = node[key]
        except (IndexError, KeyError, TypeError):
            node = None
        if isinstance(key, int):
            label = f"{'row' if rows else 'item'} {key + 1}"
            if isinstance(node, dict) and isinstance(node.get("name"), str):
                label += f" ('{node['name'][:40]}')"
            if parts and parts[-1].startswith("field "):  # "field 'joints'" + "row 3" -> "joints row 3"
                label = f"{parts.pop()[7:-1]} {label}"
            parts.append(label)
        else:
            parts.append(f"field '{key}'")
    return ", ".join(parts) if parts else "document"


def _describe(err) -> str:
    v, inst, val = err.validator, err.instance, err.validator_value
    if v == "type":
        want = " or ".join(_TYPE_WORDS.get(t, t) for t in ([val] if isinstance(val, str) else val))
        return f"expected {want}, got {_show(inst)}"
    if v == "enum":
        return f"expected one of {', '.join(map(str, val))}, got {_show(inst)}"
    if v == "additionalProperties":
        extra = sorted(str(k) for k in inst if k not in err.schema.get("properties", {}))
        return f"unknown field(s) {', '.join(map(repr, extra))} (known: {', '.join(err.schema.get('properties', {}))})"
    if v == "required":
        return f"missing field {err.message.split(' is a required')[0]}"
    if v in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        lo = err.schema.get("minimum", err.schema.get("exclusiveMinimum"))
        op = ">" if "exclusiveMinimum" in err.schema else ">="
        return f"{_show(inst)} is out of range (must be {op} {lo:g} and <= {err.schema.get('maximum', math.inf):g})"
    if v == "pattern":
        return f"{_show(inst)} is not a valid name (letters, digits, '_' and '-', not starting with a digit)"
    if v in ("minItems", "maxItems"):
        return f"expected {val} item(s) {'at least' if v == 'minItems' else 'at most'}, got {len(inst)}"
    if v == "minProperties":
        return "must not be empty"
    if v == "anyOf":
        opts = [str(x) for sub in val for x in sub.get("enum", [])] + [
            _TYPE_WORDS.get(sub["type"], sub["type"]) for sub in val if isinstance(sub.get("type"), str)
        ]
        return f"expected {' or '.join(opts) if opts else 'another value'}, got {_show(inst)}"
    return err.message.splitlines()[0][:200]


def validate(
    doc: Any, schema: dict, source: str | Path, error: type[InputError] = InputError, rows: str | None = None
) -> None:
    """Raise `error` with one line ``source: <where>: <what>`` for the first schema violation.

    `rows` names an array field whose items are rows (``joints``): its indices read "row N ('name')".
    """
    errors = list(_validator_class()(schema).iter_errors(doc))
    if not errors:
        return
    err = min(errors, key=lambda e: (list(map(str, e.absolute_path)), e.validator != "type"))
    raise error(f"{source}: {_where(doc, list(err.absolute_path), rows)}: {_describe(err)}")


def check_settings(values: dict, source: str = "--set", error: type[InputError] = InputError) -> None:
    """Simulation settings: types and ranges, plus ``min_steps <= max_steps`` and solimp ``dmin <= dmax``."""
    validate(values, settings_schema(), source, error)
    if values.get("min_steps", 0) > values.get("max_steps", 10**6):
        raise error(f"{source}: min_steps {values['min_steps']} exceeds max_steps {values['max_steps']}")
    si = values.get("solimp")
    if si is not None and si[0] > si[1]:
        raise error(f"{source}: solimp dmin {si[0]:g} exceeds dmax {si[1]:g}")
