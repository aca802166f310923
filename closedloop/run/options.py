"""The options of one calibration run, defined once: name, type, bounds, default and help text.

`CalibrateOptions` is the record `closedloop.run.calibrate_files` takes.  Every entry point is derived
from its fields (the metadata each field carries, `option`):

* the command line's ``calibrate`` arguments (`closedloop.cli.main`, through `OPTIONS`),
* a ``--config`` file (its keys are the same options; values go through the parser's conversions),
* a batch manifest's job (`closedloop.fleet.manifest`: the same keys, `MANIFEST_ALIASES` for the
  older spellings ``loops`` and ``bounds``),
* the Python API (``CalibrateOptions(model=..., log=..., loop=[...], snr=2.0)``),
* the command-line reference page (generated from the parser),
* the JSON schema of a config or a job (`json_schema`).

Values are checked once, by `checked` (called by `CalibrateOptions` itself): a bad one is one
`InputError` line ``<option> <value>: <what is wrong>``, the option spelled as its entry point spells
it (``--snr`` on the command line, ``snr`` in a manifest and in Python).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

from closedloop.errors import InputError

if TYPE_CHECKING:
    from closedloop.records import VerdictRules

#: the largest joint-reading noise std (rad or m) an option accepts: 0.1 rad is 5.7 degrees, no encoder's
MAX_JOINT_NOISE = 0.1
_NOISE_RANGE = (
    f"the joint noise must be > 0 and <= {MAX_JOINT_NOISE} (a reading's std in rad or m; 0.1 rad is 5.7 degrees)"
)

#: where an option is taken: the command line (and so a --config file), a batch manifest's job
CLI, MANIFEST = "cli", "manifest"


def option(
    default: Any,
    help: str,
    *,
    kind: str,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    choices: tuple = (),
    metavar: str | None = None,
    positional: bool = False,
    where: tuple[str, ...] = (CLI, MANIFEST),
) -> Any:
    """A field of `CalibrateOptions` with what every entry point derives from it.

    `kind` is how a value is read: ``float``, ``int``, ``bool``, ``text``, ``choice``, ``texts`` (repeatable
    text), ``patterns`` (comma-separated names), ``noise``, ``bounds``, ``fix``, ``args`` (a repeatable
    option of several words)."""
    meta = {
        "kind": kind,
        "help": help,
        "lo": lo,
        "hi": hi,
        "lo_open": lo_open,
        "choices": choices,
        "metavar": metavar,
        "positional": positional,
        "where": where,
    }
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class CalibrateOptions:
    """One calibration run: its inputs, what to identify and how, its validation and its outputs.

    Built by keyword; every value is checked (and text forms parsed) on construction (module doc).
    `rules` (the verdict's thresholds, `closedloop.records.VerdictRules`; its defaults unless given) is for the
    Python API only.
    """

    model: str = option(None, "URDF, MJCF (.xml) or D-H table (.yaml)", kind="text", positional=True, metavar="model")
    log: str | None = option(
        None,
        "CSV: header of joint names, one row per configuration; or a ROS bag "
        "(.bag, ROS 2 bag directory, .mcap, .db3) of sensor_msgs/JointState; "
        "omitted when each loop names its file (--loop ...,log=FILE)",
        kind="text",
        positional=True,
        metavar="log",
    )
    loop: list[str] = option(
        [],
        "loop closure TYPE:key=value,..., e.g. weld:frame=panda_hand (repeatable; types below)",
        kind="texts",
        metavar="SPEC",
    )
    html: str | None = option(None, "self-contained HTML report with figures", kind="text", where=(CLI,))
    plots: str | None = option(
        None, "write the report's figures as PNG files in DIR", kind="text", metavar="DIR", where=(CLI,)
    )
    out: str | None = option(
        None,
        "calibrated model, in the input's format: URDF (.urdf), MJCF (.xml) or D-H table (.yaml)",
        kind="text",
        where=(CLI,),
    )
    report: str | None = option(None, "JSON report", kind="text", where=(CLI,))
    identify: list[str] | None = option(
        None, "comma-separated parameter patterns (placement, offset, scale, loop, globs)", kind="patterns"
    )
    fix: list[str] = option([], "hold a parameter fixed", kind="fix", metavar="NAME[=VALUE]")
    noise: float | dict[str, float] | None = option(
        None, "joint reading std (rad), one number or joint=value,...; default: estimated", kind="noise"
    )
    weighting: str | None = option(
        None,
        "noise: errors-in-variables weighting (default; none for --readings commanded); "
        "none: plain loop residual (thesis)",
        kind="choice",
        choices=("noise", "none"),
    )
    bound: dict[str, tuple[float, float]] = option({}, "bound a parameter", kind="bounds", metavar="NAME=LOW:HIGH")
    snr: float = option(
        1.0, "SVD truncation: keep directions above snr * noise", kind="float", lo=0.0, hi=1e6, lo_open=True
    )
    robust: str = option(
        "auto",
        "outliers: auto (default) rejects configurations the noise cannot explain, after a robust "
        "refit; huber/cauchy keep a robust loss in the final fit; off trusts every row",
        kind="choice",
        choices=("auto", "huber", "cauchy", "off"),
    )
    force: bool = option(
        False, "write the calibrated model even when the verdict is 'failed'", kind="bool", where=(CLI,)
    )
    cv: int | None = option(
        None,
        "K-fold held-out validation in the report (default 5, fewer on a shorter log; 0 disables)",
        kind="int",
        lo=0,
        hi=10**6,
        metavar="K",
    )
    max_iter: int = option(100, "solver iterations at most (default 100)", kind="int", lo=1, hi=10**6, metavar="N")
    threads: int | None = option(
        None,
        "threads for the fit: BLAS threads, and at most as many for a long log's rows (default: one BLAS "
        "thread, two for the rows; 0: keep the environment's BLAS setting)",
        kind="int",
        lo=0,
        hi=4096,
        metavar="N",
    )
    degrees: bool = option(False, "the log is in degrees", kind="bool")
    distance: list[list[str]] = option(
        [],
        "a known distance between two loop points: A.point B.point METRES [SIGMA] "
        "(e.g. front_a.point front_b.point 0.050); it sets the scale",
        kind="args",
        metavar="ARG",
    )
    length: list[list[str]] = option(
        [],
        "a known length between two frames of the robot a fixed distance apart: FRAME_A FRAME_B "
        "METRES [SIGMA] (e.g. a link measured with calipers); the report says how far it sets the scale",
        kind="args",
        metavar="ARG",
    )
    block: list[list[str]] = option(
        [],
        "points of one rigid block at known positions in its own frame: NAME A.point=X,Y,Z "
        "B.point=X,Y,Z ... [sigma=S] (metres); its pairwise distances set the scale",
        kind="args",
        metavar="ARG",
    )
    joints: list[str] | None = option(
        None,
        "the column order of header-less CSV logs (the first row is then data)",
        kind="patterns",
        metavar="J1,J2,...",
    )
    readings: str = option(
        "measured",
        "what the log's joint values are: measured by encoders (default) or the controller's commanded "
        "setpoints; commanded readings make the residual model and servo error, not reading noise: the fit "
        "is plain least squares unless --weighting is given, and the report records it",
        kind="choice",
        choices=("measured", "commanded"),
    )
    lofo: str = option(
        "auto",
        "leave-one-fixture-out validation when the loops form several fixtures (default: auto)",
        kind="choice",
        choices=("auto", "off"),
    )
    regions: int = option(
        4,
        "held-out validation by region: K regions of joint space left out in turn (default 4; 0 disables)",
        kind="int",
        lo=0,
        hi=10**4,
        metavar="K",
    )
    workspace: str | None = option(
        None,
        "where the accuracy is predicted: a log of joint readings, or joint ranges joint=lo:hi,... "
        "(default: 200 random readings within the joint limits)",
        kind="text",
        metavar="LOG|RANGES",
    )
    accuracy: str | None = option(
        None,
        "accuracy target over the workspace, e.g. 0.2mm, 1mrad or 0.2mm,1mrad: the verdict is ok only "
        "where the predicted largest error meets it",
        kind="text",
        metavar="TARGET",
    )
    prior_tolerance: str | None = option(
        None,
        "the nominal model's tolerance (one std), the prior of what the data cannot see: "
        "length=1mm,angle=1mrad,offset=10mrad,scale=0.001 (the defaults; give any of them)",
        kind="text",
        metavar="TOLERANCES",
    )
    suggest: str | None = option(
        None,
        "write the configurations to record next (CSV of joint readings at the loop's place) that most "
        "reduce the predicted error over the workspace",
        kind="text",
        metavar="FILE",
        where=(CLI,),
    )
    suggest_n: int = option(
        10, "how many configurations --suggest writes (default 10)", kind="int", lo=1, hi=10**4, metavar="N"
    )
    rules: VerdictRules = field(default_factory=lambda: _verdict_rules(), metadata={"kind": "rules", "where": ()})

    def __post_init__(self) -> None:
        for name, value in checked(self).items():
            object.__setattr__(self, name, value)

    @property
    def folds(self) -> int:
        """The k-fold count asked for: `cv`, or 5 when not given (`calibrate_files` takes fewer on a short log)."""
        return 5 if self.cv is None else self.cv

    def with_values(self, **values: Any) -> CalibrateOptions:
        """A copy with `values` replaced (checked again)."""
        return replace(self, **values)


#: every option an entry point takes, in the command line's order (the `rules` of the API excluded)
OPTIONS = tuple(f for f in fields(CalibrateOptions) if f.metadata.get("where"))
#: older spellings of a manifest's keys: the key read -> the option
MANIFEST_ALIASES = {"loops": "loop", "bounds": "bound"}


def flag(name: str) -> str:
    """The command line's spelling of an option: ``max_iter`` -> ``--max-iter``."""
    return "--" + name.replace("_", "-")


def _verdict_rules() -> VerdictRules:
    """The default rules, `VerdictRules()`: the records are imported when an options record is made, not
    with the command line's parser."""
    from closedloop.records import VerdictRules

    return VerdictRules()


def default(f) -> Any:
    """An option's default value."""
    return f.default_factory() if f.default is MISSING else f.default


# --------------------------------------------------------------------------- the one validation
def checked(opts: CalibrateOptions, spell=lambda name: name) -> dict[str, Any]:
    """Every option's value checked and in its canonical form (a text form parsed), by name; raises one
    `InputError` line ``<spell(name)> <value>: <what is wrong>`` for the first bad one."""
    out = {}
    for f in OPTIONS:
        value = getattr(opts, f.name)
        out[f.name] = check_value(f.name, value, spell(f.name))
    if out["model"] in (None, ""):
        raise InputError(f"{spell('model')}: the robot model is required")
    if out["regions"] == 1:
        raise InputError(f"{spell('regions')} 1: region validation needs 2 regions or more (or 0 to disable)")
    if out["accuracy"] is not None:
        from closedloop.run.accuracy import parse_accuracy

        parse_accuracy(str(out["accuracy"]))  # refused now, not after the fit
    if out["log"] in (None, "") and not (out["loop"] and all("log=" in s for s in out["loop"])):
        raise InputError(
            "calibrate: the following arguments are required: log (or give every loop its own "
            "file: --loop ...,log=FILE)"
        )
    return out


def check_value(name: str, value: Any, label: str | None = None) -> Any:
    """One option's value checked and parsed (`checked`); `label` names it in the message."""
    f = _FIELDS[name]
    m = f.metadata
    label = label or name
    kind = m["kind"]
    if value is None:
        if kind in ("texts", "fix", "args", "bounds", "bool"):
            return default(f)
        return None
    if kind == "float" or kind == "int":
        return _number(label, value, m, integer=kind == "int")
    if kind == "bool":
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            value = value.strip().lower() == "true"
        if not isinstance(value, bool):
            raise InputError(f"{label} {_shown(value)}: expected true or false")
        return value
    if kind == "choice":
        if not isinstance(value, str) or value not in m["choices"]:
            raise InputError(f"{label} {_shown(value)}: expected one of {', '.join(m['choices'])}")
        return value
    if kind == "text":
        if isinstance(value, bool) or not isinstance(value, (str, int, float)) or not str(value):
            raise InputError(f"{label} {_shown(value)}: expected a text value (a path, a name)")
        if name == "prior_tolerance":  # refused now, not after the fit
            from closedloop.run.accuracy import parse_prior

            parse_prior(str(value), label)
        return str(value)
    if kind == "texts":
        items = _texts(label, value)
        for spec in items if name == "loop" else ():
            check_loop_numbers(spec)
        return items
    if kind == "patterns":
        items = [value] if isinstance(value, str) else _texts(label, value)
        out = [p.strip() for item in items for p in item.split(",") if p.strip()]
        return out or None
    if kind == "fix":
        return _fix(label, value)
    if kind == "noise":
        return parse_noise(value, label)
    if kind == "bounds":
        return parse_bounds(value, label)
    if kind == "args":
        if isinstance(value, (str, bool)) or not isinstance(value, (list, tuple)):
            raise InputError(f"{label} {_shown(value)}: expected a list of argument lists")
        return [_texts(label, [v] if isinstance(v, str) else v) for v in value]
    raise AssertionError(kind)


def _number(label: str, value: Any, m: Mapping, integer: bool) -> int | float:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(f"{label} {_shown(value)}: expected {'a whole number' if integer else 'a finite number'}")
    v = check_number(label, value, m["lo"], m["hi"], integer=integer, lo_open=m["lo_open"])
    if label.lstrip("-").replace("-", "_") == "cv" and v == 1:
        raise InputError(f"{label} 1: K-fold validation needs K >= 2 (or 0 to disable)")
    return v


def check_number(opt: str, value, lo: float, hi: float, *, integer: bool = False, lo_open: bool = False):
    """A numeric option in range (``lo < v`` when `lo_open`, else ``lo <= v``; ``v <= hi``), as float/int;
    one line ``<opt> <value>: <what is wrong>`` otherwise (every command's numeric options, and `checked`)."""
    from closedloop.io.schemas import is_number, parse_number

    v = parse_number(value, f"{opt} {value}") if isinstance(value, str) else value
    if not is_number(v) or (integer and float(v) != int(v)):
        raise InputError(f"{opt} {value}: expected {'a whole number' if integer else 'a finite number'}")
    if v < lo or (lo_open and v == lo) or v > hi:
        raise InputError(f"{opt} {value}: must be {'>' if lo_open else '>='} {lo:g} and <= {hi:g}")
    return int(v) if integer else float(v)


def check_loop_numbers(spec: str) -> None:
    """Numbers inside a ``--loop`` spec (closure, axis, point, ...) are decimal, finite and within 1e6."""
    import re

    from closedloop.io.schemas import MAX_ABS, parse_number

    for token in re.split(r"[\s,=:\"']+", spec):
        if re.fullmatch(
            r"[-+]?(\d[\d_]*\.?[\d_]*|\.\d[\d_]*)([eE][-+]?\d+)?|[-+]?(nan|inf|infinity)", token, re.IGNORECASE
        ):
            v = parse_number(token, f"--loop {spec}")
            if abs(v) > MAX_ABS:
                raise InputError(f"--loop {spec}: {token} is out of range (|value| <= {MAX_ABS:g})")


def _texts(label: str, value: Any) -> list[str]:
    if isinstance(value, str):
        return [value]
    if isinstance(value, (list, tuple)) and all(
        isinstance(x, (str, int, float)) and not isinstance(x, bool) for x in value
    ):
        return [str(x) for x in value]
    raise InputError(f"{label} {_shown(value)}: expected text or a list of text")


def _fix(label: str, value: Any) -> list[str]:
    """``NAME[=VALUE]`` items (a mapping name -> value or null too); a value is a finite number."""
    from closedloop.io.schemas import parse_number

    if isinstance(value, Mapping):
        value = [str(k) if v is None else f"{k}={v!r}" for k, v in value.items()]
    items = _texts(label, value)
    for item in items:
        for part in item.split(","):
            name, eq, num = part.partition("=")
            if eq:
                parse_number(num, f"{label} {part.strip()}")
    return items


def parse_noise(value: Any, label: str = "--noise") -> float | dict[str, float] | None:
    """``1e-4`` or ``j1=1e-4,j2=2e-4`` (or a number, or a mapping joint -> number): every value a finite
    number > 0 (rad or m) and at most `MAX_JOINT_NOISE`."""
    from closedloop.io.schemas import parse_number

    if value is None:
        return None
    if isinstance(value, Mapping):
        value = ",".join(f"{k}={v!r}" if not isinstance(v, str) else f"{k}={v}" for k, v in value.items())
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise InputError(f"{label} {_shown(value)}: expected a number or joint=value,...")
    text = value if isinstance(value, str) else repr(value)
    if "=" not in text:
        v = parse_number(text, f"{label} {text}")
        if not 0 < v <= MAX_JOINT_NOISE:
            raise InputError(f"{label} {text}: {_NOISE_RANGE}")
        return v
    out: dict[str, float] = {}
    for part in text.split(","):
        k, _, number = (t.strip() for t in part.partition("="))
        if not k:
            raise InputError(f"{label} {part}: expected joint=value")
        out[k] = parse_number(number, f"{label} {part}")
        if not 0 < out[k] <= MAX_JOINT_NOISE:
            raise InputError(f"{label} {part}: {_NOISE_RANGE}")
    return out


def parse_bounds(value: Any, label: str = "--bound") -> dict[str, tuple[float, float]]:
    """``NAME=LOW:HIGH`` items (an empty side is unbounded; ``;`` separates items in one text), or a
    mapping NAME -> [LOW, HIGH] (null unbounded); LOW <= HIGH."""
    from closedloop.io.schemas import parse_number

    if isinstance(value, Mapping):
        items = []
        for name, rng in value.items():
            if not (isinstance(rng, (list, tuple)) and len(rng) == 2):
                raise InputError(f"{label} {name}: expected [LOW, HIGH], got {_shown(rng)}")
            items.append(f"{name}={'' if rng[0] is None else rng[0]}:{'' if rng[1] is None else rng[1]}")
    elif isinstance(value, str):
        items = [s.strip() for s in value.split(";") if s.strip()]
    else:
        items = _texts(label, value)
    out = {}
    for item in items:
        name, eq, rng = item.partition("=")
        lo, colon, hi = rng.partition(":")
        if not eq or not colon or not name.strip():
            raise InputError(f"{label} {item}: expected NAME=LOW:HIGH")
        lo_v = parse_number(lo, f"{label} {item}", allow_inf=True) if lo.strip() else -math.inf
        hi_v = parse_number(hi, f"{label} {item}", allow_inf=True) if hi.strip() else math.inf
        if lo_v > hi_v:
            raise InputError(f"{label} {item}: the lower bound {lo.strip()} exceeds the upper bound {hi.strip()}")
        out[name.strip()] = (lo_v, hi_v)
    return out


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    return repr(value) if not isinstance(value, (int, float)) else f"{value}"


_FIELDS = {f.name: f for f in fields(CalibrateOptions)}


# --------------------------------------------------------------------------- derived forms
def from_mapping(values: Mapping[str, Any], where: str, entry: str = MANIFEST) -> CalibrateOptions:
    """Options from a mapping of option names (a manifest's job, `MANIFEST_ALIASES` read as their option):
    an unknown key is one line naming `where`; a bad value ``<where>: option '<key>': <key> <value>: ...``."""
    known = {f.name for f in OPTIONS if entry in f.metadata["where"]}
    values = {MANIFEST_ALIASES.get(k, k) if entry == MANIFEST else k: v for k, v in values.items()}
    for k, v in values.items():  # a CSV cell: several loops, fixes or bounds separated by ';'
        if isinstance(v, str) and k in _FIELDS and _FIELDS[k].metadata["kind"] in ("texts", "fix", "bounds"):
            values[k] = [s.strip() for s in v.split(";") if s.strip()]
    spelled = {MANIFEST_ALIASES.get(k, k): k for k in values} | {v: k for k, v in MANIFEST_ALIASES.items()}
    unknown = sorted(set(values) - known)
    if unknown:
        raise InputError(f"{where}: unknown option(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    for k, v in values.items():
        key = spelled.get(k, k)
        try:
            check_value(k, v, key)
        except InputError as exc:
            raise InputError(f"{where}: option '{key}': {exc}") from None
    try:
        return CalibrateOptions(**{k: v for k, v in values.items() if v is not None and v != ""})
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def json_schema(entry: str = MANIFEST) -> dict:
    """The JSON schema of the options an entry point takes (`entry`: ``cli`` for a config file,
    ``manifest`` for a job), from the fields: types, bounds, choices, defaults, help."""
    props: dict[str, dict] = {}
    for f in OPTIONS:
        if entry not in f.metadata["where"]:
            continue
        m = f.metadata
        s: dict[str, Any] = {"description": m["help"]}
        kind = m["kind"]
        if kind in ("float", "int"):
            s["type"] = "number" if kind == "float" else "integer"
            s["exclusiveMinimum" if m["lo_open"] else "minimum"] = m["lo"]
            s["maximum"] = m["hi"]
        elif kind == "bool":
            s["type"] = "boolean"
        elif kind == "choice":
            s["enum"] = list(m["choices"])
        elif kind == "text":
            s["type"] = "string"
        elif kind in ("texts", "fix", "patterns"):
            s["anyOf"] = [{"type": "string"}, {"type": "array", "items": {"type": "string"}}]
        elif kind == "noise":
            limit = {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_JOINT_NOISE}
            s["anyOf"] = [limit, {"type": "string"}, {"type": "object", "additionalProperties": limit}]
        elif kind == "bounds":
            s["anyOf"] = [{"type": "array", "items": {"type": "string"}}, {"type": "object"}]
        elif kind == "args":
            s["type"] = "array"
            s["items"] = {"type": "array", "items": {"type": "string"}}
        value = default(f)
        if value is not None:
            s["default"] = value
        props[f.name] = s
    return {"type": "object", "additionalProperties": False, "properties": props}
