"""The manifest of `closedloop batch`: a YAML or CSV list of calibration jobs (see :mod:`closedloop.fleet.batch`)."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from closedloop.errors import InputError

JOB_KEYS = {"name", "robot", "date", "model", "log", "loops", "options", "out", "cv"}
OPTION_KEYS = {"identify", "fix", "noise", "weighting", "snr", "max_iter", "bounds", "robust", "degrees"}


@dataclass
class BatchJob:
    """One calibration of a manifest (paths resolved against the manifest's folder)."""

    name: str
    model: Path
    log: Path
    out: Path
    loops: list[str] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)
    robot: str = ""
    date: str = ""
    cv: int = 5
    batch_pid: int = 0  # the process running the batch: a worker ends with it


# --------------------------------------------------------------------------- manifest
def as_list(v) -> list[str]:
    if v is None or v == "":
        return []
    if isinstance(v, str):
        return [s.strip() for s in v.split(";") if s.strip()]
    return [str(s) for s in v]


def _job(d: dict, base: Path, where: str) -> BatchJob:
    unknown = set(d) - JOB_KEYS - OPTION_KEYS
    if unknown:
        raise InputError(
            f"{where}: unknown key(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(JOB_KEYS | OPTION_KEYS))})"
        )
    for key in ("model", "log", "out"):
        if not d.get(key):
            raise InputError(f"{where}: no '{key}'")
    opts = d.get("options") or {}
    if isinstance(opts, str):
        try:
            opts = json.loads(opts)
        except json.JSONDecodeError:
            raise InputError(f"{where}: options '{opts}' is not a JSON object") from None
    if not isinstance(opts, dict):
        raise InputError(f"{where}: options must be a mapping")
    opts = {**opts, **{k: d[k] for k in OPTION_KEYS if d.get(k) not in (None, "")}}
    bad = set(opts) - OPTION_KEYS
    if bad:
        raise InputError(
            f"{where}: unknown option(s) {', '.join(sorted(bad))} (known: {', '.join(sorted(OPTION_KEYS))})"
        )
    loops = d.get("loops")
    if loops is not None and not (
        isinstance(loops, str) or (isinstance(loops, list) and all(isinstance(x, str) for x in loops))
    ):
        raise InputError(f"{where}: 'loops' must be a loop spec or a list of them, got {_kind(loops)}")
    opts = check_options(opts, where)
    cv = _cv(d.get("cv"), where)
    for key in ("model", "log", "out", "name", "robot", "date"):
        if d.get(key) is not None and not isinstance(d[key], (str, int, float)) or isinstance(d.get(key), bool):
            raise InputError(f"{where}: '{key}' must be a text value, got {_kind(d[key])}")
    out = base / str(d["out"])
    return BatchJob(
        str(d.get("name") or out.name),
        base / str(d["model"]),
        base / str(d["log"]),
        out,
        as_list(d.get("loops")),
        opts,
        str(d.get("robot") or ""),
        str(d.get("date") or ""),
        cv,
    )


def _kind(v: Any) -> str:
    return {bool: "true/false", list: "a list", dict: "a mapping"}.get(type(v), repr(v))


def _cv(value: Any, where: str) -> int:
    """The job's K-fold count, as ``calibrate --cv`` takes it: a whole number >= 0, not 1 (default 5)."""
    from closedloop.io.schemas import check_number

    if value is None or value == "":
        return 5
    if isinstance(value, bool):
        raise InputError(f"{where}: cv {value}: expected a whole number")
    try:
        k = check_number("cv", value if isinstance(value, (int, float)) else str(value), 0, 10**6, integer=True)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    if k == 1:
        raise InputError(f"{where}: cv 1: K-fold validation needs K >= 2 (or 0 to disable)")
    return k


_ENUMS = {"weighting": ("noise", "none"), "robust": ("auto", "huber", "cauchy", "off")}


def check_options(opts: dict, where: str) -> dict:
    """A job's calibration options checked as ``closedloop calibrate`` checks its own (types, ranges,
    enums; one line naming the job and the option).  YAML gives typed values, a CSV cell text: both
    are accepted where they mean a valid value.  Returns the options with their values parsed."""
    from closedloop.io.schemas import check_number, parse_bounds, parse_noise, parse_number

    out: dict = {}
    for key, value in opts.items():
        what = f"{where}: option '{key}'"
        if value is None:
            continue
        try:
            if key in ("snr", "max_iter"):
                if isinstance(value, bool):
                    raise InputError(f"{key} {value}: expected a number")
                v = value if isinstance(value, (int, float)) else str(value)
                lo, integer = (1, True) if key == "max_iter" else (0.0, False)
                out[key] = check_number(key, v, lo, 10**6, integer=integer, lo_open=not integer)
            elif key in _ENUMS:
                if not isinstance(value, str) or value not in _ENUMS[key]:
                    raise InputError(f"expected one of {', '.join(_ENUMS[key])}, got {_kind(value)}")
                out[key] = value
            elif key == "degrees":
                if isinstance(value, str) and value.strip().lower() in ("true", "false"):
                    value = value.strip().lower() == "true"
                if not isinstance(value, bool):
                    raise InputError(f"expected true or false, got {_kind(value)}")
                out[key] = value
            elif key == "noise":
                if isinstance(value, dict):
                    value = ",".join(f"{k}={v!r}" if not isinstance(v, str) else f"{k}={v}" for k, v in value.items())
                if isinstance(value, bool) or not isinstance(value, (str, int, float)):
                    raise InputError(f"expected a number or joint=value,..., got {_kind(value)}")
                out[key] = parse_noise(value if isinstance(value, str) else repr(value))
            elif key in ("identify", "fix"):
                if not isinstance(value, (str, list)) or (
                    isinstance(value, list) and not all(isinstance(x, str) for x in value)
                ):
                    raise InputError(f"expected text or a list of text, got {_kind(value)}")
                items = as_list(value) if not isinstance(value, str) or key == "fix" else [value]
                if key == "fix":
                    for item in items:
                        for part in item.split(","):
                            name, eq, num = part.partition("=")
                            if eq:
                                parse_number(num, f"fix {part.strip()}")
                out[key] = value
            elif key == "bounds":
                if isinstance(value, dict):
                    pairs = []
                    for name, rng in value.items():
                        if not (isinstance(rng, list) and len(rng) == 2):
                            raise InputError(f"{name}: expected [LOW, HIGH], got {_kind(rng)}")
                        pairs.append(f"{name}={'' if rng[0] is None else rng[0]}:{'' if rng[1] is None else rng[1]}")
                    value = pairs
                if isinstance(value, (bool, int, float)):
                    raise InputError(f"expected NAME=LOW:HIGH items, got {_kind(value)}")
                out[key] = parse_bounds(as_list(value))
            else:
                out[key] = value
        except InputError as exc:
            raise InputError(f"{what}: {exc}") from None
    return out


def read_manifest(path: str | Path) -> list[BatchJob]:
    """Jobs of a YAML manifest (``jobs:`` list, optional ``defaults:``) or a CSV one (a row per job;
    ``loops`` separated by ';'; options as columns or a JSON ``options`` column)."""
    from closedloop.io.files import note_input

    path = Path(path)
    note_input(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read manifest ({exc.strerror})") from None
    base = path.resolve().parent
    if path.suffix.lower() in (".yaml", ".yml"):
        from closedloop.io.schemas import load_yaml  # strict: only true/false are booleans, no 1_000

        doc = load_yaml(path, "manifest")
        if isinstance(doc, dict) and set(doc) - {"defaults", "jobs"}:
            extra = ", ".join(sorted(map(str, set(doc) - {"defaults", "jobs"})))
            raise InputError(f"{path}: unknown top-level key(s) {extra} (known: defaults, jobs)")
        defaults: Any = {}  # checked below: a mapping
        rows: Any = doc if isinstance(doc, list) else None  # checked below: a list of mappings
        if isinstance(doc, dict):
            defaults, rows = doc.get("defaults") or {}, doc.get("jobs")
        if not isinstance(defaults, dict):
            raise InputError(f"{path}: 'defaults' must be a mapping of job keys")
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise InputError(f"{path}: expected a list of jobs under 'jobs:'")
        rows = [{**defaults, **r} for r in rows]
        first = 1
    elif path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        rows = []
        for r in reader:
            if None in r:  # more cells than the header names: an unquoted comma
                header = len(reader.fieldnames or ())
                raise InputError(
                    f"{path}: line {reader.line_num}: {header + len(r[None])} cells, the "
                    f'header has {header} (quote a cell that holds commas, "..."; '
                    "separate loops with ';')"
                )
            if any((v or "").strip() for v in r.values() if isinstance(v, str)):
                rows.append(r)
        first = 2  # the header is line 1
    else:
        raise InputError(f"{path}: manifest must be .yaml, .yml or .csv")
    jobs = [
        _job(r, base, f"{path}: job {i} ({'line ' + str(i + first - 1) if first == 2 else 'entry ' + str(i)})")
        for i, r in enumerate(rows, start=1)
    ]
    names: dict[str, int] = {}
    for i, j in enumerate(jobs, start=1):
        if j.name in names:
            row = lambda k: f"line {k + first - 1}" if first == 2 else f"entry {k}"
            raise InputError(
                f"{path}: job {names[j.name]} ({row(names[j.name])}) and job {i} ({row(i)}) have the same name "
                f"'{j.name}'; give each job its own name"
            )
        names[j.name] = i
    seen: dict[Path, str] = {}
    for j in jobs:
        if j.out in seen:
            raise InputError(f"{path}: jobs '{seen[j.out]}' and '{j.name}' write the same folder {j.out}")
        seen[j.out] = j.name
    if not jobs:
        raise InputError(f"{path}: no jobs")
    return jobs
