"""The manifest of `closedloop batch`: a YAML or CSV list of calibration jobs (see :mod:`closedloop.fleet.batch`).

A job names its output folder (``out``), its ``name``, ``robot`` and ``date``; every other key is an
option of the run, as `calibrate` takes it (`closedloop.run.options`: ``model``, ``log``, ``loop`` (or
``loops``), ``cv``, ``noise``, ``bound`` (or ``bounds``), ``threads``, ...), given as a key of the job or in
its ``options`` mapping (a JSON object in a CSV cell).  A CSV cell separates several loops, fixes or
bounds with ``;``.
"""

from __future__ import annotations

import csv
import datetime
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from closedloop.errors import InputError
from closedloop.run.options import MANIFEST, MANIFEST_ALIASES, OPTIONS, CalibrateOptions, from_mapping

#: a job's own keys; every other key is an option of the run (`closedloop.run.options`, as `calibrate`'s)
JOB_KEYS = {"name", "robot", "date", "out", "options"}


@dataclass
class BatchJob:
    """One calibration of a manifest (paths resolved against the manifest's folder); `options` holds the
    run's options the job gives besides its model, log, loops and folds, checked and parsed."""

    name: str
    model: Path
    log: Path
    out: Path
    loops: list[str] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)
    robot: str = ""
    date: str = ""
    cv: int | None = None  # folds; None: 5, fewer on a shorter log (as `calibrate --cv`)
    batch_pid: int = 0  # the process running the batch: a worker ends with it

    def model_file(self) -> Path:
        """The calibrated model in the job's folder, in the input's format."""
        suffix = self.model.suffix.lower()
        return self.out / (
            "calibrated"
            + (".yaml" if suffix in (".yaml", ".yml") else ".xml" if suffix in (".xml", ".mjcf") else ".urdf")
        )

    def run_options(self) -> CalibrateOptions:
        """The run's options: the job's model, log, loops and options, its folder's model and report."""
        return CalibrateOptions(
            model=str(self.model),
            log=str(self.log),
            loop=list(self.loops),
            cv=self.cv,
            out=str(self.model_file()),
            report=str(self.out / "report.json"),
            **self.options,
        )


# --------------------------------------------------------------------------- manifest
def as_list(v) -> list[str]:
    if v is None or v == "":
        return []
    if isinstance(v, str):
        return [s.strip() for s in v.split(";") if s.strip()]
    return [str(s) for s in v]


def _job(d: dict, base: Path, where: str) -> BatchJob:
    known = {f.name for f in OPTIONS if MANIFEST in f.metadata["where"]} | set(MANIFEST_ALIASES)
    unknown = set(d) - JOB_KEYS - known
    if unknown:
        raise InputError(
            f"{where}: unknown key(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(JOB_KEYS | known))})"
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
    values = {**opts, **{k: d[k] for k in known if d.get(k) not in (None, "")}}
    if isinstance(d.get("date"), (datetime.date, datetime.datetime)):  # YAML reads 2026-03-02 as a date
        d = {**d, "date": d["date"].isoformat()}
    for key in ("model", "log", "out", "name", "robot", "date"):
        if d.get(key) is not None and not isinstance(d[key], (str, int, float)) or isinstance(d.get(key), bool):
            raise InputError(f"{where}: '{key}' must be a text value, got {_kind(d[key])}")
    values["model"], values["log"] = str(base / str(d["model"])), str(base / str(d["log"]))
    run = from_mapping(values, where)
    given = {MANIFEST_ALIASES.get(k, k) for k, v in values.items() if v is not None and v != ""}
    options = {k: getattr(run, k) for k in given - {"model", "log", "loop", "cv"}}
    out = base / str(d["out"])
    return BatchJob(
        str(d.get("name") or out.name),
        Path(run.model),
        Path(str(run.log)),
        out,
        list(run.loop),
        options,
        str(d.get("robot") or ""),
        str(d.get("date") or ""),
        run.cv,
    )


def _kind(v: Any) -> str:
    return {bool: "true/false", list: "a list", dict: "a mapping"}.get(type(v), repr(v))


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
