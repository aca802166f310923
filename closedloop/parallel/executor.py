"""One executor for every many-job command: in process, a local process pool, or a Ray cluster.

A study (Monte Carlo draws, k-fold refits, a batch of calibrations) is a list
of independent jobs ``fn(*shared, payload, rng=...)``.  An engine runs them and
yields an :class:`Outcome` per job as it finishes; :func:`run` collects them in
job order.  Engines are registered by name, as qpsolvers registers solvers:

* ``serial``: in this process, one job after the other (today's loops);
* ``threads``: in this process on ``jobs`` threads, for jobs that share nothing they change and spend
  their time in numpy (a long log's warm held-out refits, `validation.kfold`);
* ``local``: a ``concurrent.futures.ProcessPoolExecutor`` of ``jobs`` workers
  started with *forkserver* (POSIX) or *spawn*, never fork;
* ``ray``: Ray tasks of one CPU each, on the cluster at ``address``
  ('auto' joins a running cluster; None starts a local one), imported lazily
  (``pip install "closedloop[ray]"``; from a checkout ``pip install ".[ray]"``).

The results do not depend on the engine: randomness comes from a
``numpy.random.SeedSequence(seed).spawn(n)`` child per *job* (never per
worker), every worker limits BLAS to one thread (threadpoolctl; no
oversubscription, no thread-count dependent rounding) and results are returned
in job order.  A job that raises is recorded in its outcome and never stops the
others; a job that kills its worker process (a crash in native code) is
retried (local pool: once on a new pool, then alone; Ray, where small jobs
travel several to a task: the lost task's jobs one per task, each up to 3
times, on any node, also when its node died) and recorded as failed.  An
engine's `timeout` stops a job that runs longer (`engine.time_limit`:
`JobTimeout`); the modules a job function `needs` are imported before its
clock and limit start.

Layout: :mod:`closedloop.parallel.engine` (outcomes, progress, the worker-side
call, the engine base class, the serial engine), :mod:`closedloop.parallel.engines`
(the process pool and Ray); this module is the front end (`imap`, `run`,
`get_engine`, the ``--jobs`` / ``--ray`` options) and re-exports them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from closedloop.parallel.engine import (
    ENGINES,
    Engine,
    JobCounts,
    JobTimeout,
    Outcome,
    SerialEngine,
    call,
    limit_threads,
    needs,
    register,
)
from closedloop.parallel.engines import LocalEngine, RayEngine
from closedloop.progress import ProgressReporter

__all__ = [
    "ENGINES",
    "Engine",
    "JobTimeout",
    "Outcome",
    "JobCounts",
    "SerialEngine",
    "LocalEngine",
    "RayEngine",
    "call",
    "limit_threads",
    "needs",
    "register",
    "get_engine",
    "job_seeds",
    "imap",
    "run",
    "add_arguments",
    "engine_from_args",
]

log = logging.getLogger(__name__)

_NO_SHARED = object()


# --------------------------------------------------------------------------- front end
def get_engine(
    engine: "str | Engine | None" = None,
    jobs: int | None = None,
    address: str | None = None,
    timeout: float | None = None,
) -> Engine:
    """An engine by name ('serial', 'threads', 'local', 'ray'), or the instance given (None: serial); `timeout`:
    seconds a job may run before it is stopped and recorded as failed (`JobTimeout`)."""
    if isinstance(engine, Engine):
        return engine
    name = engine or "serial"
    if name not in ENGINES:
        from closedloop.errors import InputError

        raise InputError(f"unknown engine '{name}' (known: {', '.join(sorted(ENGINES))})")
    return ENGINES[name](jobs=jobs, address=address, timeout=timeout)


def job_seeds(seed: int | np.random.SeedSequence | None, n: int) -> list[np.random.SeedSequence] | None:
    """One child SeedSequence per job (the same whichever engine or worker count)."""
    if seed is None:
        return None
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    return ss.spawn(n)


def imap(
    fn: Callable,
    payloads: Iterable,
    engine: "str | Engine | None" = None,
    *,
    shared: Any = _NO_SHARED,
    seed: int | np.random.SeedSequence | None = None,
    jobs: int | None = None,
    address: str | None = None,
    progress: ProgressReporter | None = None,
    task: str = "jobs",
) -> Iterator[Outcome]:
    """Run ``fn(*shared, payload[, rng=...])`` for every payload; yield Outcomes as jobs finish.

    `shared` is a tuple of objects every job needs (a robot model, loops,
    options): sent once per worker, not once per job.  With `seed`, each job
    gets ``rng = default_rng(SeedSequence(seed).spawn(n)[i])``.  As each job ends, `progress` is told
    ``(task, finished, total, "4 ok, 1 failed, 2 running")``.
    """
    payloads = list(payloads)
    own = not isinstance(engine, Engine)
    eng = get_engine(engine, jobs, address)
    shared_t = None if shared is _NO_SHARED else tuple(shared)
    state = JobCounts(len(payloads))
    try:
        for out in eng.imap(fn, payloads, job_seeds(seed, len(payloads)), shared_t, state):
            if out.ok:
                state.done += 1
            else:
                state.failed += 1
            state.running = min(state.running, state.total - state.done - state.failed)
            if progress:
                progress(task, state.finished, state.total, state.note())
            yield out
    finally:
        if own:
            eng.close()


def run(fn: Callable, payloads: Iterable, engine: "str | Engine | None" = None, *, errors: str = "raise", **kw) -> list:
    """The values of all jobs in job order.  errors='raise' re-raises the first failure (in job
    order) after all jobs ran; errors='record' returns the Outcome of a failed job in its place."""
    outs = sorted(imap(fn, payloads, engine, **kw), key=lambda o: o.index)
    if errors == "raise":
        for o in outs:
            if not o.ok:
                if o.exception is not None:
                    raise o.exception
                from closedloop.errors import ClosedLoopError

                raise ClosedLoopError(f"job {o.index} failed: {o.error}")
        return [o.value for o in outs]
    return [o.value if o.ok else o for o in outs]


def add_arguments(parser, timeout: bool = False) -> None:
    """--jobs / --ray for a many-job command (and --job-timeout with `timeout`)."""
    parser.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="local worker processes (default: all cores; 1 runs in this process)",
    )
    parser.add_argument(
        "--ray",
        metavar="auto|local|ADDRESS",
        default=None,
        help="run on a Ray cluster: 'auto' joins the running one, an address (ray://HOST:10001) another, "
        "'local' starts one here with --jobs CPUs (needs Ray: pip install \"closedloop[ray]\", "
        'from a checkout pip install ".[ray]")',
    )
    if timeout:
        parser.add_argument(
            "--job-timeout",
            metavar="SECONDS",
            default=None,
            help="stop a job that runs longer and record it as failed (JobTimeout); the others go on",
        )


def engine_from_args(args) -> Engine:
    """The engine `--jobs` / `--ray` (and `--job-timeout`, when the command has it: seconds, checked by
    the command) ask for."""
    timeout = getattr(args, "job_timeout", None)
    timeout = None if timeout is None else float(timeout)
    if getattr(args, "ray", None):
        return get_engine("ray", args.jobs, None if args.ray == "local" else args.ray, timeout)
    if args.jobs is not None and args.jobs < 1:
        from closedloop.errors import InputError

        raise InputError("--jobs must be at least 1")
    if args.jobs == 1:
        return SerialEngine(threads=1, timeout=timeout)
    return get_engine("local", args.jobs, timeout=timeout)
