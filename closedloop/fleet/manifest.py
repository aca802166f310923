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
    try:
        cv = int(d.get("cv") if d.get("cv") not in (None, "") else 5)
    except (TypeError, ValueError):
        raise InputError(f"{where}: cv '{d.get('cv')}' is not a whole number") from None
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


def read_manifest(path: str | Path) -> list[BatchJob]:
    """Jobs of a YAML manifest (``jobs:`` list, optional ``defaults:``) or a CSV one (a row per job;
    ``loops`` separated by ';'; options as columns or a JSON ``options`` column)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(f"{path}: cannot read manifest ({exc.strerror})") from None
    base = path.resolve().parent
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        defaults, rows = (
            ({}, doc) if isinstance(doc, list) else ((doc or {}).get("defaults") or {}, (doc or {}).get("jobs"))
        )
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise InputError(f"{path}: expected a list of jobs under 'jobs:'")
        rows = [{**defaults, **r} for r in rows]
        first = 1
    elif path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        rows = []
        for r in reader:
            if None in r:  # more cells than the header names: an unquoted comma
                raise InputError(
                    f"{path}: line {reader.line_num}: {len(reader.fieldnames) + len(r[None])} cells, the "
                    f'header has {len(reader.fieldnames)} (quote a cell that holds commas, "..."; '
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
    seen: dict[Path, str] = {}
    for j in jobs:
        if j.out in seen:
            raise InputError(f"{path}: jobs '{seen[j.out]}' and '{j.name}' write the same folder {j.out}")
        seen[j.out] = j.name
    if not jobs:
        raise InputError(f"{path}: no jobs")
    return jobs
