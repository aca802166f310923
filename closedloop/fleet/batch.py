"""`closedloop batch MANIFEST`: many calibrations, each independent, resumable, on any executor.

A manifest (YAML or CSV) lists jobs: model, log (CSV or ROS bag), loops,
options, output folder, and optionally the robot's id and the date of the log.
Every job is calibrated and k-fold validated on its own (``closedloop.calibrate``,
``validation.cross_validate``) by one of the engines of ``closedloop.parallel.executor``.

* A job that raises is recorded (summary row ``status=failed``, the error) and
  the others go on; a failed job is tried again by the next run.
* Outputs are written whole: into a temporary folder beside the output folder,
  the completion marker ``done.json`` last, then one rename.  A killed batch
  leaves finished folders and hidden ``.NAME.tmp-*`` folders (removed by the
  next run), never a half job; a folder with its marker is not redone.
* The summary CSV gets a row as each job finishes (republished at most once
  a second), and is rewritten in manifest order at the end with the drift
  columns filled.
* Faults: a job past ``--job-timeout`` is stopped and recorded (`JobTimeout`);
  a job whose worker process or cluster node died is run again by the engine
  (`run_once`: a job that had already published its folder is not calibrated
  again); the batch holds the summary rows only, each job's record is read
  back from its folder for the drift.

Drift (:mod:`closedloop.fleet.drift`): for jobs of the same robot ordered by date, every robot
parameter of two consecutive calibrations, expressed in one gauge (the earlier calibration's: the
later one is moved along its gauge directions, so another fixed length or another reduction is not
a change), gets z = change / its standard error (both covariances, eq. 3.17 whitened, propagated
through the gauge map); the change is flagged when |z| > 3: larger than the two calibrations'
noise can explain.  The manifest is read by :mod:`closedloop.fleet.manifest`.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import uuid
from collections import Counter
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from closedloop.errors import EXIT_FAILED, InputError
from closedloop.fleet.drift import Drift, drift, drift_columns, gauge_record
from closedloop.fleet.manifest import BatchJob, as_list, read_manifest
from closedloop.io.files import is_special
from closedloop.io.schemas import check_number

__all__ = [
    "BatchJob",
    "BatchResult",
    "Drift",
    "drift",
    "read_manifest",
    "run_batch",
    "run_job",
    "finished",
    "cmd_batch",
    "add_parser",
]

log = logging.getLogger(__name__)

MARKER = "done.json"
COLUMNS = [
    "name",
    "robot",
    "date",
    "status",
    "verdict",
    "verdict_reasons",
    "configurations",
    "estimated",
    "rms_before_mm",
    "rms_after_mm",
    "rms_before_mrad",
    "rms_after_mrad",
    "cv_test_mm",
    "cv_test_mrad",
    "top_changes",
    "drift_from",
    "drift_max_z",
    "drift_flagged",
    "seconds",
    "resumed",
    "error",
    "out",
]


# --------------------------------------------------------------------------- workers end with the batch
def die_with_batch(pid: int) -> None:
    """In a worker process: end it the moment the batch process `pid` dies (`closedloop.fleet.guard`).
    SIGINT and SIGTERM are ignored here: Ctrl-C reaches the whole process group, and the batch ends its
    workers itself (`end_workers`)."""
    import signal
    import threading

    from closedloop.fleet.guard import watch

    if pid <= 0 or pid == os.getpid():
        return
    watch(pid)
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)


def descendants(pid: int | None = None) -> list[int]:
    """Every live process below `pid` (default: this one), each before its own children, from ``/proc``."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [os.getpid() if pid is None else pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def start_worker_server() -> None:
    """Start the fork server that local pools fork their workers from, for this batch: with SIGINT
    ignored (its workers inherit that from birth, so Ctrl-C, sent to the whole process group, reaches
    the batch alone even while a worker is still starting; the batch ends its workers itself,
    `end_workers`), and with `closedloop.fleet.guard` preloaded (each worker it forks ends when the
    batch process dies, SIGKILL included)."""
    import multiprocessing as mp
    import signal
    import threading

    from closedloop.fleet.guard import BATCH_PID

    if "forkserver" not in mp.get_all_start_methods() or threading.current_thread() is not threading.main_thread():
        return
    from multiprocessing import forkserver

    os.environ[BATCH_PID] = str(os.getpid())
    preload = list(getattr(forkserver._forkserver, "_preload_modules", ["__main__"]))
    forkserver.set_forkserver_preload(preload + ["closedloop.fleet.guard"])
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGINT, previous)


def end_workers() -> None:
    """Kill (SIGKILL) the pool processes this batch started: the fork server and every worker below it,
    and spawned workers (children running ``multiprocessing.spawn``); the resource tracker then ends by
    itself, and no other process is touched.  Called when the batch is interrupted, before the engine's
    shutdown would wait for the running jobs."""
    import signal
    import threading
    from concurrent.futures import InvalidStateError
    from multiprocessing import resource_tracker

    previous = threading.excepthook

    def quiet(args) -> None:  # the pool's manager thread, finding its workers killed, fails a cancelled future
        if args.exc_type is not InvalidStateError:
            previous(args)

    threading.excepthook = quiet

    from multiprocessing import forkserver

    tracker = getattr(resource_tracker._resource_tracker, "_pid", None)  # it ends by itself, its leases settled
    server = getattr(forkserver._forkserver, "_forkserver_pid", None)
    pool = [server, *descendants(server)] if server else []
    for child in descendants(os.getpid()):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"multiprocessing.spawn" in cmd and child != tracker:
            pool += [child, *descendants(child)]
    for pid in pool:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


# --------------------------------------------------------------------------- one job (in a worker)
def _options(opts: dict, names: list[str]):
    from closedloop.calibration.pipeline import CalibrationOptions
    from closedloop.model.parameters import parse_fix

    noise = opts.get("noise")
    if isinstance(noise, str):
        from closedloop.io.schemas import parse_noise as _parse_noise

        noise = _parse_noise(noise)
    bounds = opts.get("bounds") or {}
    if isinstance(bounds, (list, str)):
        from closedloop.io.schemas import parse_bounds as _parse_bounds

        bounds = _parse_bounds(as_list(bounds))
    ident = opts.get("identify")
    return CalibrationOptions(
        identify=ident.split(",") if isinstance(ident, str) else ident,
        fix=parse_fix(as_list(opts.get("fix")), names),
        noise=noise,
        weighting=opts.get("weighting", "noise"),
        snr=float(opts.get("snr", 1.0)),
        max_iter=int(opts.get("max_iter", 100)),
        bounds={k: tuple(v) for k, v in bounds.items()},
        robust=None if opts.get("robust") == "off" else opts.get("robust"),
    )


def _read(job: BatchJob, robot):
    """The job's log (a CSV or a bag), refused as `calibrate` refuses it (`data.check_angle_units`)."""
    from closedloop.io.logs import check_angle_units, read_log

    degrees = job.options.get("degrees", False)
    degrees = degrees.strip().lower() in ("1", "true", "yes") if isinstance(degrees, str) else bool(degrees)
    lg = None
    try:
        from closedloop.io.bags import extract, is_bag

        if is_bag(job.log):
            lg = extract(job.log, robot.joint_names)[0]
    except ImportError:  # pragma: no cover - bag support not installed
        pass
    if lg is None:
        lg = read_log(
            job.log,
            robot.joint_names,
            degrees=degrees,
            linear=[j for j, info in robot.joints.items() if info.kind == "prismatic"],
        )
    check_angle_units(lg, robot, degrees)
    return lg


def _pooled(res_list, key: str) -> float | None:
    """RMS over loops (weighted by configurations) of one residual statistic, in mm or mrad."""
    vals = [(r.n, getattr(r, key)) for r in res_list if getattr(r, key, None) is not None]
    if not vals:
        return None
    n = np.array([v[0] for v in vals], float)
    x = np.array([v[1] for v in vals], float)
    return float(np.sqrt(np.sum(n * x**2) / n.sum()) * 1e3)


def _top_changes(report: dict, k: int = 3) -> str:
    """The k estimated parameters that moved most from their initial value (mm, mrad, 1e-3)."""
    unit = {"m": "mm", "rad": "mrad"}
    est = [
        (p["name"], (p["calibrated"] - p["initial"]) * 1e3, unit.get(p["unit"], "e-3"))
        for p in report["parameters"]
        if p["status"] == "estimated" and p["kind"] != "loop"
    ]
    est.sort(key=lambda t: -abs(t[1]))
    return "; ".join(f"{n}={d:+.3g}{u}" for n, d, u in est[:k])


def run_job(job: BatchJob) -> dict:
    """Calibrate and validate one job, write its folder whole; return its summary row (+ parameters)."""
    import time

    from closedloop.calibration.pipeline import build_problem, calibrate
    from closedloop.loops.spec import default_loops, parse_loop
    from closedloop.model.robot import RobotModel
    from closedloop.output.report import build_report, write_report
    from closedloop.output.urdf import write_model

    die_with_batch(job.batch_pid)
    t0 = time.perf_counter()
    robot = RobotModel.from_file(job.model)
    loops = [parse_loop(s, robot) for s in job.loops] or default_loops(robot)
    if not loops:
        raise InputError(f"job {job.name}: no loops given")
    lg = _read(job, robot)
    opts = _options(job.options, build_problem(robot, lg, loops).names)
    res = calibrate(robot, lg, loops, opts)
    report = build_report(res, job.model, job.log)
    cv_t: tuple[float | None, float | None] = (None, None)
    cv = None
    if job.cv and res.converged:
        from closedloop.validation.kfold import cross_validate

        try:
            cv = cross_validate(robot, lg, loops, opts, k=job.cv, exclude=[rj.row - 1 for rj in res.rejected])
            report["validation"] = {
                "k": job.cv,
                "excluded_rows": [i + 1 for i in cv["excluded"]],
                "test": cv["test"],
                "train": cv["train"],
                "test_whitened_rms": cv["test_whitened_rms"],
                "parameter_spread": cv["parameter_spread"],
            }
            t = cv["test"]
            cv_t = (_pooled_dicts(t, "rms_m"), _pooled_dicts(t, "rms_rad"))
        except Exception as exc:  # validation is a check, not the job
            report["validation"] = {"error": f"{type(exc).__name__}: {exc}"}
    verdict = _judge(res, cv, report)
    row = {
        "name": job.name,
        "robot": job.robot,
        "date": job.date,
        "status": "ok" if res.converged else "not converged",
        "verdict": getattr(verdict, "status", "n/a"),
        "verdict_reasons": "; ".join(getattr(verdict, "reasons", [])),
        "configurations": len(lg),
        "estimated": len(res.estimated),
        "rms_before_mm": _pooled(res.residuals_before, "rms_m"),
        "rms_after_mm": _pooled(res.residuals_after, "rms_m"),
        "rms_before_mrad": _pooled(res.residuals_before, "rms_rad"),
        "rms_after_mrad": _pooled(res.residuals_after, "rms_rad"),
        "cv_test_mm": cv_t[0],
        "cv_test_mrad": cv_t[1],
        "top_changes": _top_changes(report),
        "seconds": round(time.perf_counter() - t0, 3),
        "out": str(job.out),
    }
    params = {
        p["name"]: [p["calibrated"], p["std_error"], p["kind"]]
        for p in report["parameters"]
        if p["status"] == "estimated"
    }
    files = {"report.json": lambda p: write_report(report, p)}
    if res.converged and getattr(verdict, "status", "") != "failed" and robot.kind in ("urdf", "dh"):
        files["calibrated" + (".yaml" if robot.kind == "dh" else ".urdf")] = lambda p: write_model(
            robot, res.as_dict(), p
        )
    marker = {"row": row, "parameters": params, "gauge": _gauge(res)}
    _write_whole(job.out, files, marker)
    return marker


def _gauge(res) -> dict | None:
    """The calibration's gauge record for drift (batch_drift.gauge_record), None when it cannot be made."""
    try:
        return gauge_record(res)
    except Exception as exc:  # drift then falls back to plain differences; the job itself is fine
        log.warning("no gauge record (%s: %s): drift compares plain parameter differences", type(exc).__name__, exc)
        return None


def _judge(res, cv: dict | None, report: dict):
    """The calibration's verdict, judged again with the held-out folds as `closedloop calibrate` does."""
    try:
        from closedloop.calibration.verdict import judge
        from closedloop.output.report import verdict_record
    except ImportError:  # a core without verdicts: 'n/a' in the summary
        return getattr(res, "verdict", None)
    verdict = judge(res, cv)
    report["verdict"] = verdict_record(verdict)
    return verdict


def _pooled_dicts(loops: list[dict], key: str) -> float | None:
    vals = [(d["n"], d[key]) for d in loops if d.get(key) is not None]
    if not vals:
        return None
    n, x = np.array(vals, float).T
    return float(np.sqrt(np.sum(n * x**2) / n.sum()) * 1e3)


def _write_whole(out: Path, files: dict, marker: dict) -> None:
    """Write `files` (name -> writer(path)) and the marker last into a temporary folder, then rename it to `out`."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        for name, writer in files.items():
            writer(tmp / name)
        (tmp / MARKER).write_text(json.dumps(marker, indent=1) + "\n")
        if out.exists():
            if (out / MARKER).exists():  # finished meanwhile by another run: keep that one
                shutil.rmtree(tmp)
                return
            if any(out.iterdir()):
                raise InputError(f"{out}: exists and is not a finished batch job; remove it or choose another 'out'")
            out.rmdir()
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def finished(job: BatchJob) -> dict | None:
    """The marker of a job finished by an earlier run, or None."""
    try:
        return json.loads((job.out / MARKER).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _clean_temporaries(jobs: list[BatchJob]) -> int:
    n = 0
    for j in jobs:
        if j.out.parent.is_dir():
            for t in j.out.parent.glob(f".{j.out.name}.tmp-*"):
                shutil.rmtree(t, ignore_errors=True)
                n += 1
    return n


# --------------------------------------------------------------------------- the batch
@dataclass
class BatchResult:
    rows: list[dict]  # summary rows, manifest order
    drift: list[Drift]
    ran: list[str]  # jobs run by this call
    resumed: list[str]  # finished earlier, not redone
    failed: list[str]


class _Summary:
    """The summary CSV: published whole as jobs finish (the rows so far, in finishing order; a reader
    never sees a torn file), then in manifest order at the end.  Rewriting a long table after every job
    would cost O(jobs^2): it is published after the first job, then again once `interval` seconds have
    passed, and never so often that writing it takes more than 5 % of the batch's time.  A device or
    named pipe (``--summary /dev/stdout``) gets the final table only."""

    def __init__(self, path: Path, interval: float = 1.0):
        from closedloop.io.files import is_special

        self.path = path
        self.rows: list[dict] = []
        self.stream = not is_special(path)
        self.interval = interval
        self.last = -float("inf")  # when it was last published (perf_counter)
        self.cost = 0.0  # how long that took

    def add(self, row: dict, publish: bool = True) -> None:
        import time

        self.rows.append(row)
        now = time.perf_counter()
        if self.stream and publish and now - self.last >= max(self.interval, 20.0 * self.cost):
            self._write(self.rows)
            self.last = time.perf_counter()
            self.cost = self.last - now

    def finish(self, rows) -> None:
        self._write(rows)

    def _write(self, rows) -> None:
        import io

        from closedloop.io.files import atomic_write_text

        buf = io.StringIO()
        w = csv.DictWriter(buf, COLUMNS, extrasaction="ignore", lineterminator="\r\n")
        w.writeheader()
        w.writerows(_fmt(r) for r in rows)
        atomic_write_text(self.path, buf.getvalue())


def _fmt(row: dict) -> dict:
    return {k: (f"{v:.6g}" if isinstance(v, float) else "" if v is None else v) for k, v in row.items()}


def run_once(job: BatchJob) -> dict:
    """A job's record: the one on disk when its folder is finished, else `run_job`'s.  A job is run again
    when the worker or node running it died (the executor retries it); when that happened after its
    folder was published, the retry returns that folder's record instead of calibrating again."""
    return finished(job) or run_job(job)


class _Markers(Mapping):
    """The finished jobs' records (``done.json``) by name, read from disk when asked (the last two kept):
    the batch holds the summary rows, never every job's parameters and matrices."""

    def __init__(self, jobs: list[BatchJob], names: set[str]):
        self.jobs = {j.name: j for j in jobs if j.name in names}
        self.cache: dict[str, dict] = {}

    def __getitem__(self, name: str) -> dict:
        if name not in self.cache:
            marker = finished(self.jobs[name]) if name in self.jobs else None
            if marker is None:
                raise KeyError(name)
            if len(self.cache) >= 2:
                self.cache.pop(next(iter(self.cache)))
            self.cache[name] = marker
        return self.cache[name]

    def __iter__(self):
        return iter(self.jobs)

    def __len__(self) -> int:
        return len(self.jobs)


def run_batch(jobs: list[BatchJob], summary: str | Path, engine=None, progress=None, z_max: float = 3.0) -> BatchResult:
    """Run every job not finished before on `engine` (see closedloop.parallel.executor); write the summary.

    What the batch holds while it runs is each job's summary row: every job's record (parameters,
    covariance, information matrix) is written to its folder and read back from there, two at a time,
    for the drift."""
    from closedloop.parallel.executor import imap

    n_tmp = _clean_temporaries(jobs)
    if n_tmp:
        log.info("removed %d unfinished temporary folder(s) of an interrupted run", n_tmp)
    sink = _Summary(Path(summary))
    rows: dict[str, dict] = {}
    todo = []
    # a local pool's workers end with this process (`die_with_batch`); a cluster's nodes may be other
    # machines, where this process id means nothing: Ray ends a dead driver's tasks itself
    local = getattr(engine, "name", engine) == "local"
    for j in jobs:
        done = finished(j)
        if done is None:
            j.batch_pid = os.getpid() if local else 0
            todo.append(j)
        else:
            rows[j.name] = {**done["row"], "resumed": "yes"}
            sink.add(rows[j.name], publish=False)  # (published with the first job that finishes)
    failed = []
    for out in imap(run_once, todo, engine, progress=progress):
        j = todo[out.index]
        if out.ok:  # seconds: the whole job in its worker, its folder's writing included
            rows[j.name] = {**out.value["row"], "seconds": round(out.seconds, 3), "resumed": "no"}
        else:
            failed.append(j.name)
            log.warning("job %s failed: %s", j.name, out.error)
            rows[j.name] = {
                "name": j.name,
                "robot": j.robot,
                "date": j.date,
                "status": "failed",
                "verdict": "n/a",
                "error": out.error,
                "seconds": round(out.seconds, 3),
                "resumed": "no",
                "out": str(j.out),
            }
        sink.add(rows[j.name])
    markers = _Markers(jobs, {n for n, r in rows.items() if r["status"] != "failed"})
    drifts = drift(jobs, markers, z_max, rows=rows)
    drift_columns(rows, drifts)
    ordered = [rows[j.name] for j in jobs]
    sink.finish(ordered)
    if drifts and not is_special(summary):  # (a summary on a device or pipe: the drift is printed only)
        _write_drift(Path(summary), drifts)
    ran = {j.name for j in todo}
    return BatchResult(ordered, drifts, [j.name for j in todo], [j.name for j in jobs if j.name not in ran], failed)


def drift_path(summary: Path) -> Path:
    """The drift table written beside the summary: ``SUMMARY.drift.csv``."""
    return summary.with_name(summary.stem + ".drift.csv")


def _write_drift(summary: Path, drifts: list[Drift]) -> None:
    import io

    from closedloop.io.files import atomic_write_text

    buf = io.StringIO()
    w = csv.DictWriter(buf, list(asdict(drifts[0])), lineterminator="\r\n")
    w.writeheader()
    w.writerows(_fmt(asdict(d)) for d in drifts)
    atomic_write_text(drift_path(summary), buf.getvalue())


def check_batch_outputs(manifest: str | Path, jobs: list[BatchJob], summary: Path) -> None:
    """Before any job runs: the summary (and its drift table) and every job's folder may be written,
    and none of them is an input (the manifest, a model, a log) -- by inode, links resolved."""
    from closedloop.io.files import check_outputs, same_file

    inputs = [manifest] + [p for j in jobs for p in (j.model, j.log)]
    outputs = {"--summary": summary}
    if not is_special(summary):
        outputs["--summary (its drift table)"] = drift_path(summary)
    check_outputs(outputs, inputs)
    for j in jobs:
        if j.out.exists() and not j.out.is_dir():
            raise InputError(f"job {j.name}: out {j.out}: is a file; give a folder")
        for i in inputs:
            if same_file(j.out, i):
                raise InputError(f"job {j.name}: out {j.out}: is an input of the batch ({i})")


def cmd_batch(args) -> int:
    """CLI: closedloop batch MANIFEST [--jobs N | --ray auto|ADDRESS] [--job-timeout S] [--summary CSV]."""
    import sys

    from closedloop.parallel.executor import engine_from_args, progress_printer

    jobs = read_manifest(args.manifest)
    summary = (
        Path(args.summary) if args.summary else Path(args.manifest).with_name(Path(args.manifest).stem + ".summary.csv")
    )
    args.drift_z = check_number("--drift-z", args.drift_z, 0.0, 1e6, lo_open=True)
    if args.job_timeout is not None:
        args.job_timeout = check_number("--job-timeout", args.job_timeout, 0.0, 1e7, lo_open=True)
    check_batch_outputs(args.manifest, jobs, summary)
    with engine_from_args(args) as eng:
        if eng.name == "local":
            start_worker_server()
        try:
            res = run_batch(jobs, summary, eng, progress_printer("batch: ", args.quiet), args.drift_z)
        except KeyboardInterrupt:  # Ctrl-C, SIGTERM: no worker may run on (the shutdown would wait for them)
            end_workers()
            raise
    flagged = [d for d in res.drift if d.flagged]
    verdicts = Counter(str(r.get("verdict", "")) for r in res.rows if r["name"] not in res.failed)
    print(
        f"{len(res.ran)} job(s) run on {eng.name} ({eng.workers} worker(s)), {len(res.resumed)} finished "
        f"earlier (not redone), {len(res.failed)} failed -> {summary}"
    )
    if +verdicts:
        print("  verdicts: " + ", ".join(f"{verdicts[v]} {v}" for v in ("ok", "suspect", "failed") if verdicts[v]))
    for name in res.failed:
        print(f"  failed: {name}: {next(r['error'] for r in res.rows if r['name'] == name)}", file=sys.stderr)
    for r in res.rows:
        if r.get("verdict") == "failed" and r["name"] not in res.failed:
            print(f"  verdict failed: {r['name']}: {r.get('verdict_reasons', '')}", file=sys.stderr)
    if res.drift:
        print(
            f"  drift: {len(flagged)} of {sum(not d.note for d in res.drift)} parameter changes exceed "
            f"{args.drift_z:g} standard errors" + ("" if is_special(summary) else f" -> {drift_path(summary)}")
        )
    for d in res.drift:
        if d.note:
            print(f"    {d.robot} {d.before} -> {d.after}: {d.note}")
    for d in flagged:
        print(f"    {d.robot} {d.before} -> {d.after}: {d.parameter} {d.change:+.3g} (z = {d.z:+.1f})")
    # a job that could not run: 1; every job ran but a calibration's verdict is failed: 3, as calibrate's
    return 1 if res.failed else EXIT_FAILED if verdicts["failed"] else 0


def add_parser(sub) -> None:
    """The `batch` subcommand."""
    from closedloop.parallel.executor import add_arguments

    b = sub.add_parser("batch", help="calibrate many robots/logs from a manifest (YAML or CSV), resumable")
    b.add_argument("manifest", help="YAML (jobs: [...]) or CSV: model, log, loops, options, out[, robot, date, cv]")
    b.add_argument("--summary", help="summary CSV (default: MANIFEST.summary.csv beside the manifest)")
    b.add_argument("--drift-z", default=3.0, help="flag a parameter change above this many std. errors")
    add_arguments(b, timeout=True)
    b.add_argument("--quiet", action="store_true", help="no progress lines (the summary is still printed)")
    b.set_defaults(func=cmd_batch)
