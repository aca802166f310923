"""The engines that run jobs outside this process: a local process pool and Ray (see :mod:`closedloop.parallel.executor`).

Objects every job needs (`shared`) are pickled once by the driver and unpickled once per worker
process (a per-process cache keyed by a token of the study); above 256 KiB the pool's jobs carry
only the path of one temporary file holding them (/dev/shm when there is one), Ray's a reference
to its object store, so a large study's data is not sent with every job.
"""

from __future__ import annotations

import logging
import os
import pickle
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from closedloop.parallel.engine import Engine, JobCounts, Outcome, call, limit_threads, register

log = logging.getLogger(__name__)

_CACHE: dict[str, Any] = {}  # per worker process: token -> shared objects (unpickled once)


_INLINE = 1 << 18  # shared objects pickled larger than this (256 KiB) go through a file, read once per worker


def _shared(token: str | None, blob: Any) -> tuple:
    """The study's shared objects in this worker: unpickled once (from the bytes, or the file they were
    written to when large), then cached under the study's token."""
    if token is None:
        return ()
    if token not in _CACHE:
        _CACHE.clear()  # one study at a time per worker
        if isinstance(blob, str):  # a path: the driver wrote the pickle there once
            with open(blob, "rb") as fh:
                blob = fh.read()
        _CACHE[token] = pickle.loads(blob) if isinstance(blob, bytes) else blob
    return _CACHE[token]


def _stage(blob: bytes | None) -> tuple[Any, str | None]:
    """What each job carries for the shared objects: the bytes when small, else the path of a temporary
    file holding them (in /dev/shm when there is one), so a large study's data is not sent with every job."""
    if blob is None or len(blob) <= _INLINE:
        return blob, None
    import tempfile

    folder = "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None
    fd, path = tempfile.mkstemp(prefix="closedloop-shared-", suffix=".pkl", dir=folder)
    with os.fdopen(fd, "wb") as fh:
        fh.write(blob)
    return path, path


def _pool_init() -> None:
    limit_threads()


def _pool_call(fn, index, payload, seed, token, blob, timeout=None) -> Outcome:
    return call(fn, index, payload, seed, _shared(token, blob), timeout, hard=True)


def _start_method() -> str:
    import multiprocessing as mp

    return "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"


@register("local")
class LocalEngine(Engine):
    """A pool of `jobs` worker processes on this machine (forkserver or spawn), reused across studies.

    A worker that dies (killed, out of memory, a crash in native code) breaks the pool: the jobs it had
    not returned are run again on a new pool, then alone, one at a time (`_run_all`).  `timeout`: seconds
    a job may run (`engine.time_limit`)."""

    def __init__(self, jobs: int | None = None, timeout: float | None = None, **_):
        self.workers = max(1, int(jobs or os.cpu_count() or 1))
        self.timeout = timeout
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
        blob, staged = _stage(None if shared is None else pickle.dumps(shared, protocol=pickle.HIGHEST_PROTOCOL))
        args = {
            i: (fn, i, p, None if seeds is None else seeds[i], token, blob, self.timeout)
            for i, p in enumerate(payloads)
        }
        try:
            yield from self._run_all(args, progress)
        finally:
            if staged is not None:
                try:
                    os.unlink(staged)
                except OSError:  # pragma: no cover - already gone
                    pass

    def _run_all(self, args: dict, progress: JobCounts | None):
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

    def _drain(self, todo: list[int], args: dict, progress: JobCounts | None):
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
    """Ray tasks of one CPU each; joins `address` ('auto', 'HOST:6379', 'ray://host:10001') or starts a local
    cluster.

    Small jobs travel several to a task (`chunk_size`): what a task costs the driver and the cluster
    (submitting, scheduling, waiting, receiving) is paid once per chunk, not once per job.  A chunk whose
    worker process or node dies is not run again whole: its jobs are, one per task, each run again by Ray,
    on any node, up to `retries` times (then recorded as crashed); a job that had finished in the lost
    chunk is run again (the batch's jobs find their published folder and are not redone).  `timeout`:
    seconds a job may run (`engine.time_limit`).  The jobs' code must be importable on every node, and
    their files on a file system every node sees."""

    #: most jobs one task carries; fewer as the queue shortens (`chunk_size`)
    max_chunk = 8

    def __init__(
        self,
        jobs: int | None = None,
        address: str | None = None,
        timeout: float | None = None,
        retries: int = 3,
        **_,
    ):
        from closedloop.errors import require

        ray = require("ray", "--ray", "ray")
        self.ray = ray
        self._started = not ray.is_initialized()  # connected here: disconnected by close()
        if self._started:
            # no address: a new cluster on this machine ('local'), never one another program started here
            kw = {"address": address} if address else {"address": "local", **({"num_cpus": jobs} if jobs else {})}
            ray.init(include_dashboard=False, log_to_driver=False, **kw)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.timeout = timeout
        task = ray.remote(num_cpus=1)(_ray_call)
        self._chunk = task.options(max_retries=0)  # a lost chunk's jobs are run again one per task
        self._single = task.options(max_retries=retries)

    def close(self) -> None:
        if self._started and self.ray.is_initialized():
            self.ray.shutdown()
            self._started = False

    def chunk_size(self, queued: int) -> int:
        """Jobs in the next task: as many as keep 4 tasks queued per worker, at most `max_chunk`, down
        to one as the queue empties (so the workers end together)."""
        return max(1, min(self.max_chunk, queued // (4 * self.workers)))

    def imap(self, fn, payloads, seeds, shared, progress=None):
        ray = self.ray
        token = None if shared is None else f"{os.getpid()}-{id(shared)}-{time.monotonic_ns()}"
        ref = None if shared is None else [ray.put(shared)]  # in a list: not resolved per task
        pending: dict = {}  # task -> its jobs' indices
        try:
            yield from self._loop(fn, payloads, seeds, token, ref, pending, progress)
        finally:  # the caller stopped early: cancel what is still queued or running
            for r in pending:
                ray.cancel(r, force=False)

    def _loop(self, fn, payloads, seeds, token, ref, pending, progress):
        ray = self.ray
        queue = list(reversed(range(len(payloads))))
        alone: list[int] = []  # the jobs of a lost chunk: one per task from now on
        limit = 4 * self.workers
        while queue or alone or pending:
            while (queue or alone) and len(pending) < limit:
                if alone:
                    idx, task = [alone.pop()], self._single
                else:
                    idx = [queue.pop() for _ in range(min(self.chunk_size(len(queue)), len(queue)))]
                    task = self._chunk if len(idx) > 1 else self._single
                jobs = [(i, payloads[i], None if seeds is None else seeds[i]) for i in idx]
                pending[task.remote(fn, jobs, token, ref, self.timeout)] = idx
            if progress:
                progress.running = min(sum(map(len, pending.values())), self.workers)
            done, _ = ray.wait(list(pending), num_returns=1)
            for r in done:
                idx = pending.pop(r)
                try:
                    outs = ray.get(r)
                except Exception as exc:  # the worker died (past its retries), or the task could not run
                    if len(idx) > 1:
                        log.warning("a task of %d jobs was lost (%s); its jobs run again one per task", len(idx), exc)
                        alone.extend(reversed(idx))
                        continue
                    text = str(exc).strip().splitlines() or [""]
                    outs = [
                        Outcome(idx[0], error=f"WorkerCrashed: {type(exc).__name__}: {text[-1]}", traceback=str(exc))
                    ]
                yield from outs


def _ray_call(fn, jobs, token, ref, timeout=None) -> list[Outcome]:
    """A Ray task: the jobs ``(index, payload, seed)`` one after the other, their outcomes in a list."""
    limit_threads()
    if token is not None and token not in _CACHE:
        import ray

        _CACHE.clear()
        _CACHE[token] = ray.get(ref[0])
    shared = _CACHE[token] if token is not None else ()
    return [call(fn, i, payload, seed, shared, timeout, hard=True) for i, payload, seed in jobs]
