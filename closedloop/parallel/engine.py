"""The executor's core: job outcomes, the job counts, the worker-side call, the engine base class
and the serial engine (see :mod:`closedloop.parallel.executor` for the whole design; the process-pool and
Ray engines are in :mod:`closedloop.parallel.engines`)."""

from __future__ import annotations

import importlib
import os
import pickle
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from closedloop.parallel import chunks

ENGINES: dict[str, type["Engine"]] = {}


def register(name: str):
    """Class decorator: make an engine available under `name`."""

    def deco(cls):
        cls.name = name
        ENGINES[name] = cls
        return cls

    return deco


@dataclass
class Outcome:
    """What a job gave: its value, or the error that stopped it (type name, message, traceback)."""

    index: int
    value: Any = None
    error: str | None = None  # "Type: message"; None when the job succeeded
    traceback: str = ""
    seconds: float = 0.0  # time inside the job (worker clock)
    cpu: float = 0.0  # CPU seconds of the job's own thread (the worker's other threads not counted)
    worker: str = ""  # host:pid that ran it
    exception: BaseException | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class JobCounts:
    """Where a run of jobs stands: finished (ok or failed) of total, and how many run now (set by the
    engine); the executor reports it to a `closedloop.progress.ProgressReporter`."""

    total: int
    done: int = 0  # finished ok
    failed: int = 0
    running: int = 0

    @property
    def finished(self) -> int:
        return self.done + self.failed

    def note(self) -> str:
        """``4 ok, 1 failed, 2 running``: what a progress display shows beside the count."""
        return f"{self.done} ok, {self.failed} failed, {self.running} running"


# --------------------------------------------------------------------------- worker side
class JobTimeout(BaseException):
    """A job ran past its time limit (an engine's `timeout`).  A BaseException, as KeyboardInterrupt is:
    the job's own ``except Exception`` clauses (a check that may fail without failing the job) must not
    swallow it."""


def hard_grace(seconds: float) -> float:
    """How long past its soft limit a job stuck in native code runs before its worker process is ended."""
    return max(2.0, 0.2 * seconds)


_DEVNULL: list = []  # the file faulthandler writes a stuck job's traceback to (kept open: it needs a live file)


@contextmanager
def time_limit(seconds: float | None, hard: bool = False):
    """Stop the code run inside after `seconds`.

    Soft limit: SIGALRM raises :class:`JobTimeout` in the job (main thread only; Python code, and system
    calls such as a read from a stalled network mount, which Python resumes after running the handler).
    Hard limit (`hard`, in a worker process only): a job still running `hard_grace` later, stuck in native
    code that never returns to Python, ends its process (``faulthandler``'s own thread, which needs no
    Python lock); the engine then sees a dead worker (retried, then recorded as crashed)."""
    if not seconds:
        yield
        return
    import signal
    import threading

    soft = threading.current_thread() is threading.main_thread() and hasattr(signal, "setitimer")
    previous = None
    if soft:

        def expire(signum, frame) -> None:
            signal.setitimer(signal.ITIMER_REAL, 0)
            raise JobTimeout(f"stopped after {seconds:g} s (the per-job time limit)")

        previous = signal.signal(signal.SIGALRM, expire)
        signal.setitimer(signal.ITIMER_REAL, seconds)
    if hard:
        import faulthandler

        if not _DEVNULL:
            _DEVNULL.append(open(os.devnull, "w"))  # noqa: SIM115 - held for the process's life
        faulthandler.dump_traceback_later(seconds + hard_grace(seconds), exit=True, file=_DEVNULL[0])
    try:
        yield
    finally:
        if soft:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
        if hard:
            import faulthandler

            faulthandler.cancel_dump_traceback_later()


_LIMITED = [False]


def limit_threads() -> None:
    """One BLAS / OpenMP thread in this process (env for libraries loaded later, threadpoolctl for loaded ones),
    and one thread for a long log's rows (`chunks.CHUNK_THREADS`): a worker process per core keeps the cores
    busy already."""
    if _LIMITED[0]:
        return
    _LIMITED[0] = True
    chunks.CHUNK_THREADS = 1
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    from threadpoolctl import threadpool_limits  # a dependency

    threadpool_limits(1)


def needs(*modules: str) -> Callable[[Callable], Callable]:
    """Decorator for a job function: the modules it imports as it runs, imported by the process running it
    before its first job's clock and time limit start (`call`).  A worker is then warm for every job, and a
    job's time and time limit are its own, not the imports' (seconds of wall on a loaded machine)."""

    def deco(fn: Callable) -> Callable:
        setattr(fn, "needs", modules)  # noqa: B010 - an attribute of the function, read by `call`
        return fn

    return deco


def warm(fn: Callable) -> bool:
    """Import the modules job function `fn` `needs` that this process has not imported yet; whether
    there were any (the first job in this process)."""
    modules = [m for m in getattr(fn, "needs", ()) if m not in sys.modules]
    for m in modules:
        importlib.import_module(m)
    return bool(modules)


def call(
    fn: Callable,
    index: int,
    payload: Any,
    seed: np.random.SeedSequence | None,
    shared: tuple = (),
    timeout: float | None = None,
    hard: bool = False,
) -> Outcome:
    """Run one job and wrap its value or its error (never raises); stopped after `timeout` seconds
    (`time_limit`; `hard` in a worker process, never in the caller's own)."""
    import socket

    t0, c0 = time.perf_counter(), time.thread_time()
    out = Outcome(index, worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        if warm(fn):  # (the first job in this process: `needs`)
            t0, c0 = time.perf_counter(), time.thread_time()
        kw = {} if seed is None else {"rng": np.random.default_rng(seed)}
        with time_limit(timeout, hard):
            out.value = fn(*shared, payload, **kw)
    except JobTimeout as exc:  # recorded as any failure; its exception does not travel (it is no Exception)
        out.error = f"JobTimeout: {exc}"
        out.traceback = traceback.format_exc()
    except Exception as exc:  # recorded, not fatal
        out.error = f"{type(exc).__name__}: {exc}"
        out.traceback = traceback.format_exc()
        try:
            pickle.dumps(exc)
            out.exception = exc
        except Exception:  # an exception that cannot travel back: its text does
            out.exception = None
    out.seconds, out.cpu = time.perf_counter() - t0, time.thread_time() - c0
    return out


# --------------------------------------------------------------------------- engines
class Engine:
    """Base class: `imap` yields one Outcome per job as jobs finish (any order)."""

    name = "?"
    workers = 1
    timeout: float | None = None  # seconds a job may run before it is stopped (None: no limit)

    def __init__(self, jobs: int | None = None, address: str | None = None, **_) -> None:
        """Engines are made by name (`executor.get_engine`) with the same keywords; each takes what it uses."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release workers (no-op by default)."""

    def imap(
        self, fn: Callable, payloads: list, seeds: list | None, shared: tuple | None, progress: JobCounts | None = None
    ) -> Iterator[Outcome]:
        raise NotImplementedError


@register("serial")
class SerialEngine(Engine):
    """In this process, in job order, on the caller's own objects (no copies).

    threads: BLAS and OpenMP threads while the jobs run (None leaves the process as it is;
    1 as in the workers of the other engines, faster on a shared machine).  The job function's `needs` are
    imported first, so a thread pool they load (OpenMP, with the calibration's modules) is limited too.
    """

    def __init__(self, jobs: int | None = None, threads: int | None = None, timeout: float | None = None, **_):
        self.workers = 1
        self.threads = threads
        self.timeout = timeout  # soft only: a job stuck in native code cannot be stopped in this process

    def imap(self, fn, payloads, seeds, shared, progress=None):
        from contextlib import nullcontext

        if self.threads is None:
            limits = nullcontext()
        else:
            from threadpoolctl import threadpool_limits

            if payloads:
                warm(fn)
            limits = threadpool_limits(self.threads)
        with limits:
            for i, p in enumerate(payloads):
                if progress:
                    progress.running = 1
                yield call(fn, i, p, None if seeds is None else seeds[i], shared or (), self.timeout)


@register("threads")
class ThreadEngine(Engine):
    """In this process on `jobs` threads, on the caller's own objects (no copies), BLAS held to one thread.

    For jobs that share nothing they change and spend their time in numpy on arrays of thousands of rows,
    inside which numpy releases the interpreter lock: the warm refits of a long log's held-out validation
    (`validation.kfold`), each on a problem of its own.  On a machine whose cores other processes hold, a
    process of two such threads gets its share per thread.  No time limit (a thread cannot be stopped).
    """

    def __init__(self, jobs: int | None = None, **_):
        self.workers = max(1, int(jobs or 2))

    def imap(self, fn, payloads, seeds, shared, progress=None):
        from concurrent.futures import ThreadPoolExecutor, as_completed

        from threadpoolctl import threadpool_limits

        if payloads:
            warm(fn)  # imported once, before the threads
        with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(self.workers) as pool:
            futures = [
                pool.submit(call, fn, i, p, None if seeds is None else seeds[i], shared or ())
                for i, p in enumerate(payloads)
            ]
            if progress:
                progress.running = min(self.workers, len(futures))
            for f in as_completed(futures):
                yield f.result()
