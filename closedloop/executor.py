"""One executor for every many-job command: in process, a local process pool, or a Ray cluster.

A study (Monte Carlo draws, k-fold refits, a batch of calibrations) is a list
of independent jobs ``fn(*shared, payload, rng=...)``.  An engine runs them and
yields an :class:`Outcome` per job as it finishes; :func:`run` collects them in
job order.  Engines are registered by name, as qpsolvers registers solvers:

* ``serial``: in this process, one job after the other (today's loops);
* ``local``: a ``concurrent.futures.ProcessPoolExecutor`` of ``jobs`` workers
  started with *forkserver* (POSIX) or *spawn*, never fork;
* ``ray``: Ray tasks of one CPU each, on the cluster at ``address``
  ('auto' joins a running cluster; None starts a local one), imported lazily
  (``pip install "closedloop[ray]"``).

The results do not depend on the engine: randomness comes from a
``numpy.random.SeedSequence(seed).spawn(n)`` child per *job* (never per
worker), every worker limits BLAS to one thread (threadpoolctl; no
oversubscription, no thread-count dependent rounding) and results are returned
in job order.  A job that raises is recorded in its outcome and never stops the
others; a job that kills its worker process (a crash in native code) is
retried once, then alone, and recorded as failed.
"""

from __future__ import annotations

import logging
import os
import pickle
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

ENGINES: dict[str, type["Engine"]] = {}
_NO_SHARED = object()


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
class Progress:
    """One line for the whole batch: done, failed, running, rate, time left."""

    total: int
    done: int = 0
    failed: int = 0
    running: int = 0
    t0: float = field(default_factory=time.perf_counter)

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    @property
    def rate(self) -> float:
        return (self.done + self.failed) / self.elapsed if self.elapsed > 0 else 0.0

    @property
    def eta(self) -> float | None:
        left = self.total - self.done - self.failed
        return left / self.rate if self.rate > 0 else None

    def line(self) -> str:
        eta = "?" if self.eta is None else f"{self.eta:.0f} s"
        return (f"{self.done + self.failed}/{self.total} finished ({self.done} ok, {self.failed} failed), "
                f"{self.running} running, {self.rate:.2g} jobs/s, {eta} left")


# --------------------------------------------------------------------------- worker side
_CACHE: dict[str, Any] = {}  # per worker process: token -> shared objects (unpickled once)


_LIMITED = [False]


def limit_threads() -> None:
    """One BLAS / OpenMP thread in this process (env for libraries loaded later, threadpoolctl for loaded ones)."""
    if _LIMITED[0]:
        return
    _LIMITED[0] = True
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    try:
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        pass


def _shared(token: str | None, blob: Any) -> tuple:
    if token is None:
        return ()
    if token not in _CACHE:
        _CACHE.clear()  # one study at a time per worker
        _CACHE[token] = pickle.loads(blob) if isinstance(blob, bytes) else blob
    return _CACHE[token]


def call(fn: Callable, index: int, payload: Any, seed: np.random.SeedSequence | None,
         shared: tuple = ()) -> Outcome:
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


def _pool_init() -> None:
    limit_threads()


def _pool_call(fn, index, payload, seed, token, blob) -> Outcome:
    return call(fn, index, payload, seed, _shared(token, blob))


# --------------------------------------------------------------------------- engines
class Engine:
    """Base class: `imap` yields one Outcome per job as jobs finish (any order)."""

    name = "?"
    workers = 1

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release workers (no-op by default)."""

    def imap(self, fn: Callable, payloads: list, seeds: list | None, shared: tuple | None,
             progress: Progress | None = None) -> Iterator[Outcome]:
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


def _start_method() -> str:
    import multiprocessing as mp

    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


@register("local")
class LocalEngine(Engine):
    """A pool of `jobs` worker processes on this machine (forkserver or spawn), reused across studies."""

    def __init__(self, jobs: int | None = None, **_):
        self.workers = max(1, int(jobs or os.cpu_count() or 1))
        self._pool: ProcessPoolExecutor | None = None

    def _new_pool(self, workers: int) -> ProcessPoolExecutor:
        import multiprocessing as mp

        return ProcessPoolExecutor(workers, mp_context=mp.get_context(_start_method()), initializer=_pool_init)

    @property
    def pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = self._new_pool(self.workers)
        return self._pool

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def imap(self, fn, payloads, seeds, shared, progress=None):
        token = None if shared is None else f"{os.getpid()}-{id(shared)}-{time.monotonic_ns()}"
        blob = None if shared is None else pickle.dumps(shared, protocol=pickle.HIGHEST_PROTOCOL)
        args = {i: (fn, i, p, None if seeds is None else seeds[i], token, blob) for i, p in enumerate(payloads)}
        todo = list(args)
        for _attempt in range(2):  # the whole pool, then once more after a worker died
            broken = yield from self._drain(todo, args, progress)
            if not broken:
                return
            log.warning("a worker process died; %d unfinished job(s) resubmitted", len(broken))
            self.close()
            todo = broken
        for i in todo:  # alone, one at a time: a job that kills its worker is the one that failed
            pool = self._new_pool(1)
            try:
                yield pool.submit(_pool_call, *args[i]).result()
            except BrokenProcessPool:
                yield Outcome(i, error="WorkerCrashed: the worker process died while running this job")
            finally:
                pool.shutdown(wait=True)

    def _drain(self, todo: list[int], args: dict, progress: Progress | None):
        """Submit `todo` with back-pressure; yield outcomes; return the jobs lost to a broken pool."""
        pending: dict[Future, int] = {}
        queue = list(reversed(todo))
        limit = 4 * self.workers
        broken: list[int] = []
        try:
            return (yield from self._loop(queue, pending, broken, args, limit, progress))
        finally:  # the caller stopped early (an error, a break): queued jobs are not run
            for f in pending:
                f.cancel()

    def _loop(self, queue, pending, broken, args, limit, progress):
        while queue or pending:
            try:
                while queue and len(pending) < limit:
                    i = queue.pop()
                    pending[self.pool.submit(_pool_call, *args[i])] = i
            except BrokenProcessPool:
                broken.extend(pending.values())
                broken.extend(reversed(queue))
                return broken
            if progress:
                progress.running = min(len(pending), self.workers)
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                i = pending.pop(f)
                try:
                    yield f.result()
                except BrokenProcessPool:
                    broken.append(i)
            if broken:
                broken.extend(pending.values())
                broken.extend(reversed(queue))
                return sorted(set(broken))
        return broken


@register("ray")
class RayEngine(Engine):
    """Ray tasks of one CPU each; joins `address` ('auto', 'ray://host:10001', ...) or starts a local cluster."""

    def __init__(self, jobs: int | None = None, address: str | None = None, **_):
        try:
            import ray
        except ImportError:
            from .errors import InputError
            raise InputError('--ray needs Ray: pip install "closedloop[ray]"') from None
        self.ray = ray
        self._started = not ray.is_initialized()  # connected here: disconnected by close()
        if self._started:
            kw = {"address": address} if address else {"num_cpus": jobs} if jobs else {}
            ray.init(include_dashboard=False, log_to_driver=False, **kw)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self._task = ray.remote(num_cpus=1, max_retries=1)(_ray_call)

    def close(self) -> None:
        if self._started and self.ray.is_initialized():
            self.ray.shutdown()
            self._started = False

    def imap(self, fn, payloads, seeds, shared, progress=None):
        ray = self.ray
        token = None if shared is None else f"{os.getpid()}-{id(shared)}-{time.monotonic_ns()}"
        ref = None if shared is None else [ray.put(shared)]  # in a list: not resolved per task
        pending: dict = {}
        queue = list(reversed(range(len(payloads))))
        limit = 4 * self.workers
        try:
            yield from self._loop(fn, payloads, seeds, token, ref, queue, pending, limit, progress)
        finally:  # the caller stopped early: cancel what is still queued or running
            for r in pending:
                ray.cancel(r, force=False)

    def _loop(self, fn, payloads, seeds, token, ref, queue, pending, limit, progress):
        ray = self.ray
        while queue or pending:
            while queue and len(pending) < limit:
                i = queue.pop()
                seed = None if seeds is None else seeds[i]
                pending[self._task.remote(fn, i, payloads[i], seed, token, ref)] = i
            if progress:
                progress.running = min(len(pending), self.workers)
            done, _ = ray.wait(list(pending), num_returns=1)
            for r in done:
                i = pending.pop(r)
                try:
                    yield ray.get(r)
                except Exception as exc:  # the worker died (twice), or the task could not run: recorded
                    text = str(exc).strip().splitlines() or [""]
                    yield Outcome(i, error=f"WorkerCrashed: {type(exc).__name__}: {text[-1]}", traceback=str(exc))


def _ray_call(fn, index, payload, seed, token, ref) -> Outcome:
    limit_threads()
    if token is not None and token not in _CACHE:
        import ray
        _CACHE.clear()
        _CACHE[token] = ray.get(ref[0])
    return call(fn, index, payload, seed, _CACHE[token] if token is not None else ())


# --------------------------------------------------------------------------- front end
def get_engine(engine: "str | Engine | None" = None, jobs: int | None = None, address: str | None = None) -> Engine:
    """An engine by name ('serial', 'local', 'ray'), or the instance given (None: serial)."""
    if isinstance(engine, Engine):
        return engine
    name = engine or "serial"
    if name not in ENGINES:
        from .errors import InputError
        raise InputError(f"unknown engine '{name}' (known: {', '.join(sorted(ENGINES))})")
    return ENGINES[name](jobs=jobs, address=address)


def job_seeds(seed: int | np.random.SeedSequence | None, n: int) -> list[np.random.SeedSequence] | None:
    """One child SeedSequence per job (the same whichever engine or worker count)."""
    if seed is None:
        return None
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    return ss.spawn(n)


def imap(fn: Callable, payloads: Iterable, engine: "str | Engine | None" = None, *, shared: Any = _NO_SHARED,
         seed: int | np.random.SeedSequence | None = None, jobs: int | None = None, address: str | None = None,
         progress: Callable[[Progress], None] | None = None) -> Iterator[Outcome]:
    """Run ``fn(*shared, payload[, rng=...])`` for every payload; yield Outcomes as jobs finish.

    `shared` is a tuple of objects every job needs (a robot model, loops,
    options): sent once per worker, not once per job.  With `seed`, each job
    gets ``rng = default_rng(SeedSequence(seed).spawn(n)[i])``.
    """
    payloads = list(payloads)
    own = not isinstance(engine, Engine)
    eng = get_engine(engine, jobs, address)
    shared_t = None if shared is _NO_SHARED else tuple(shared)
    state = Progress(len(payloads))
    try:
        for out in eng.imap(fn, payloads, job_seeds(seed, len(payloads)), shared_t, state):
            if out.ok:
                state.done += 1
            else:
                state.failed += 1
            state.running = min(state.running, state.total - state.done - state.failed)
            if progress:
                progress(state)
            yield out
    finally:
        if own:
            eng.close()


def run(fn: Callable, payloads: Iterable, engine: "str | Engine | None" = None, *, errors: str = "raise",
        **kw) -> list:
    """The values of all jobs in job order.  errors='raise' re-raises the first failure (in job
    order) after all jobs ran; errors='record' returns the Outcome of a failed job in its place."""
    outs = sorted(imap(fn, payloads, engine, **kw), key=lambda o: o.index)
    if errors == "raise":
        for o in outs:
            if not o.ok:
                if o.exception is not None:
                    raise o.exception
                from .errors import ClosedLoopError
                raise ClosedLoopError(f"job {o.index} failed: {o.error}")
        return [o.value for o in outs]
    return [o.value if o.ok else o for o in outs]


def add_arguments(parser) -> None:
    """--jobs / --ray for a many-job command."""
    parser.add_argument("--jobs", type=int, default=None, metavar="N",
                        help="local worker processes (default: all cores; 1 runs in this process)")
    parser.add_argument("--ray", metavar="auto|ADDRESS", default=None,
                        help="run on a Ray cluster: 'auto' joins the running one, an address another, 'local' "
                             "starts one here with --jobs CPUs (needs closedloop[ray])")


def engine_from_args(args) -> Engine:
    if getattr(args, "ray", None):
        return get_engine("ray", args.jobs, None if args.ray == "local" else args.ray)
    if args.jobs is not None and args.jobs < 1:
        from .errors import InputError
        raise InputError("--jobs must be at least 1")
    if args.jobs == 1:
        return SerialEngine(threads=1)
    return get_engine("local", args.jobs)


def progress_printer(prefix: str = "", quiet: bool = False) -> Callable[[Progress], None]:
    """A progress callback printing one line on stderr (rewritten in place on a terminal; once a second in logs)."""
    tty = sys.stderr.isatty()
    last = [-1.0]

    def show(p: Progress) -> None:
        if quiet:
            return
        now = time.perf_counter()
        finished = p.done + p.failed == p.total
        if tty:
            print("\r" + (prefix + p.line()).ljust(90), end="\n" if finished else "", file=sys.stderr, flush=True)
        elif finished or now - last[0] > 1.0:
            print(prefix + p.line(), file=sys.stderr, flush=True)
            last[0] = now
    return show
