"""`closedloop batch MANIFEST`: many calibrations, each independent, resumable, on any executor.

A manifest (YAML or CSV) lists jobs: model, log (CSV or ROS bag), loops,
options, output folder, and optionally the robot's id and the date of the log.
Every job is one calibration run, as ``closedloop calibrate`` runs it (`closedloop.run.calibrate_files`:
k-fold and leave-one-fixture-out validation, the verdict, the report of the same shape), on one of the
engines of ``closedloop.parallel.executor``.

* A job that raises is recorded (summary row ``status=failed``, the error) and
  the others go on; a failed job is tried again by the next run.
* Outputs are written whole (`closedloop.io.files.OutputSet` with a folder): into a temporary folder
  beside the output folder, the completion marker ``done.json`` last, then one rename.  A killed batch
  leaves finished folders and hidden ``.NAME.tmp-*`` folders (removed by the
  next run), never a half job; a folder with its marker is not redone.
* The summary CSV gets a row as each job finishes (republished at most once
  a second), and is rewritten in manifest order at the end with the drift
  columns filled.
* Faults: a job past ``--job-timeout`` is stopped and recorded (`JobTimeout`);
  a job whose worker process or cluster node died is run again by the engine
  (`run_once`: a job that had already published its folder is not calibrated
  again); a worker sends back the job's summary row only (`run_row`): the batch holds the summary
  rows only, each job's record is read back from its folder for the drift.

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
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from closedloop.errors import InputError
from closedloop.fleet.drift import Drift, drift, drift_columns, gauge_record
from closedloop.fleet.manifest import BatchJob, read_manifest
from closedloop.io.files import is_special
from closedloop.parallel.engine import needs
from closedloop.progress import ProgressReporter
from closedloop.run.calibrate import DONE

__all__ = [
    "BatchJob",
    "BatchResult",
    "Drift",
    "drift",
    "read_manifest",
    "run_batch",
    "run_job",
    "finished",
]

log = logging.getLogger(__name__)

MARKER = DONE  # a finished job's folder holds it (`closedloop.run.calibrate_files`)
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
    "cpu_seconds",
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
    """Calibrate, validate and judge one job as `calibrate` does (`closedloop.run.calibrate_files`), its
    folder published whole with the completion marker last; return the marker (summary row, parameters,
    gauge)."""
    import time

    from closedloop.run import calibrate_files

    die_with_batch(job.batch_pid)
    t0, c0 = time.perf_counter(), time.thread_time()

    def marker(run) -> dict:
        res, report, lg = run.result, run.report, run.log
        test = (report.get("validation") or {}).get("test")
        row = {
            "name": job.name,
            "robot": job.robot,
            "date": job.date,
            "status": "ok" if res.converged else "not converged",
            "verdict": run.verdict.status,
            "verdict_reasons": "; ".join(run.verdict.reasons),
            "configurations": len(lg),
            "estimated": len(res.fit.estimated),
            "rms_before_mm": _pooled(res.fit.residuals_before, "rms_m"),
            "rms_after_mm": _pooled(res.fit.residuals_after, "rms_m"),
            "rms_before_mrad": _pooled(res.fit.residuals_before, "rms_rad"),
            "rms_after_mrad": _pooled(res.fit.residuals_after, "rms_rad"),
            "cv_test_mm": _pooled_dicts(test, "rms_m") if test else None,
            "cv_test_mrad": _pooled_dicts(test, "rms_rad") if test else None,
            "top_changes": _top_changes(report),
            "seconds": round(time.perf_counter() - t0, 3),
            "cpu_seconds": round(time.thread_time() - c0, 3),
            "out": str(job.out),
        }
        params = {
            p["name"]: [p["calibrated"], p["std_error"], p["kind"]]
            for p in report["parameters"]
            if p["status"] == "estimated"
        }
        return {"row": row, "parameters": params, "gauge": _gauge(res)}

    made: list[dict] = []  # the record written to the folder, returned as made (not read back)

    def record(run) -> dict:
        made.append(marker(run))
        return made[-1]

    run = calibrate_files(job.run_options(), folder=job.out, done=record)
    return made[-1] if made else finished(job) or marker(run)


def _gauge(res) -> dict | None:
    """The calibration's gauge record for drift (batch_drift.gauge_record), None when it cannot be made."""
    try:
        return gauge_record(res)
    except Exception as exc:  # drift then falls back to plain differences; the job itself is fine
        log.warning("no gauge record (%s: %s): drift compares plain parameter differences", type(exc).__name__, exc)
        return None


def _pooled_dicts(loops: list[dict], key: str) -> float | None:
    vals = [(d["n"], d[key]) for d in loops if d.get(key) is not None]
    if not vals:
        return None
    n, x = np.array(vals, float).T
    return float(np.sqrt(np.sum(n * x**2) / n.sum()) * 1e3)


def finished(job: BatchJob) -> dict | None:
    """The marker of a job finished by an earlier run, or None."""
    try:
        return json.loads((job.out / MARKER).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _clean_temporaries(jobs: list[BatchJob]) -> int:
    from closedloop.io.files import remove_temporaries

    return sum(remove_temporaries(j.out) for j in jobs)


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


@needs(  # what a job imports as it runs (`run.calibrate_files`): imported before the first job's time limit
    "closedloop.analysis.accuracy",
    "closedloop.analysis.observability",
    "closedloop.calibration.pipeline",
    "closedloop.calibration.verdict",
    "closedloop.estimate.threads",
    "closedloop.fleet.guard",
    "closedloop.io.joint_log",
    "closedloop.io.marker",
    "closedloop.io.robot_files",
    "closedloop.loops.common",
    "closedloop.loops.geometry",
    "closedloop.loops.spec",
    "closedloop.model.axes",
    "closedloop.output.report",
    "closedloop.output.urdf",
    "closedloop.parallel.executor",
    "closedloop.problem.unwrap",
    "closedloop.records",
    "closedloop.run.accuracy",
    "closedloop.run.inputs",
    "closedloop.validation.fixtures",
    "closedloop.validation.kfold",
    "closedloop.validation.regions",
    "numpy.random",
)
def run_row(job: BatchJob) -> dict:
    """What a worker sends back to the batch: the job's summary row (`run_once`; the rest of its record
    stays in its folder, read from there for the drift)."""
    return run_once(job)["row"]


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


def run_batch(
    jobs: list[BatchJob], summary: str | Path, engine=None, progress: ProgressReporter | None = None, z_max: float = 3.0
) -> BatchResult:
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
    for out in imap(run_row, todo, engine, progress=progress, task="batch"):
        j = todo[out.index]
        cost = {"seconds": round(out.seconds, 3), "cpu_seconds": round(out.cpu, 3), "resumed": "no"}
        if out.ok:  # seconds, cpu_seconds: the whole job in its worker, its inputs' reading and its folder's writing
            rows[j.name] = {**out.value, **cost}
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
                **cost,
                "out": str(j.out),
            }
        sink.add(rows[j.name])
    # a worker killed while it wrote a job's folder (a node lost) left its temporary beside the folder the job's
    # run elsewhere published
    n_tmp = _clean_temporaries([j for j in todo if finished(j) is not None])
    if n_tmp:
        log.info("removed %d temporary folder(s) of a worker lost while it wrote", n_tmp)
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
    from closedloop.io.files import check_outputs, identity

    inputs = list(dict.fromkeys([Path(manifest)] + [p for j in jobs for p in (j.model, j.log)]))
    outputs = {"--summary": summary}
    if not is_special(summary):
        outputs["--summary (its drift table)"] = drift_path(summary)
    check_outputs(outputs, inputs)
    # each input file once, by inode: one look-up per job, not one per job and input
    by_inode: dict[tuple[int, int] | None, Path] = {}
    for i in inputs:
        by_inode.setdefault(identity(i), i)
    by_inode.pop(None, None)
    for j in jobs:
        if j.out.exists() and not j.out.is_dir():
            raise InputError(f"job {j.name}: out {j.out}: is a file; give a folder")
        same = by_inode.get(identity(j.out))
        if same is not None:
            raise InputError(f"job {j.name}: out {j.out}: is an input of the batch ({same})")
