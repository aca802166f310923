"""The executor's core: job outcomes, the job counts, the worker-side call, the engine base class
and the serial engine (see :mod:`closedloop.parallel.executor` for the whole design; the process-pool and
Ray engines are in :mod:`closedloop.parallel.engines`)."""

from __future__ import annotations

import os
import pickle
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

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
_LIMITED = [False]


def limit_threads() -> None:
    """One BLAS / OpenMP thread in this process (env for libraries loaded later, threadpoolctl for loaded ones)."""
    if _LIMITED[0]:
        return
    _LIMITED[0] = True
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    from threadpoolctl import threadpool_limits  # a dependency

    threadpool_limits(1)


def call(fn: Callable, index: int, payload: Any, seed: np.random.SeedSequence | None, shared: tuple = ()) -> Outcome:
    """Run one job and wrap its value or its error (never raises)."""
    import socket

    t0 = time.perf_counter()
    out = Outcome(index, worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        kw = {} if seed is None else {"rng": np.random.default_rng(seed)}
        out.value = fn(*shared, payload, **kw)
    except Exception as exc:  # recorded, not fatal
        out.error = f"{type(exc).__name__}: {exc}"
        out.traceback = traceback.format_exc()
        try:
            pickle.dumps(exc)
            out.exception = exc
        except Exception:  # an exception that cannot travel back: its text does
            out.exception = None
    out.seconds = time.perf_counter() - t0
    return out


# --------------------------------------------------------------------------- engines
class Engine:
    """Base class: `imap` yields one Outcome per job as jobs finish (any order)."""

    name = "?"
    workers = 1

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

    threads: BLAS threads while the jobs run (None leaves the process as it is;
    1 as in the workers of the other engines, faster on a shared machine).
    """

    def __init__(self, jobs: int | None = None, threads: int | None = None, **_):
        self.workers = 1
        self.threads = threads

    def imap(self, fn, payloads, seeds, shared, progress=None):
        from contextlib import nullcontext

        if self.threads is None:
            limits = nullcontext()
        else:
            from threadpoolctl import threadpool_limits

            limits = threadpool_limits(self.threads)
        with limits:
            for i, p in enumerate(payloads):
                if progress:
                    progress.running = 1
                yield call(fn, i, p, None if seeds is None else seeds[i], shared or ())
