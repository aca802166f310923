"""Chunks of a long array worked on by threads of this process.

A long log is evaluated a chunk of configurations at a time (`problem.problem.CHUNK`, `estimate.noise`):
each chunk is a few dozen numpy operations on arrays of thousands of rows, inside which numpy releases the
interpreter lock.  Two threads then keep two cores busy on disjoint chunks, with no copy of the data and no
process to start; on a machine whose cores other processes hold, the process still gets its share per
thread.  Each thread holds one *slot* at a time (the scratch memory its chunk is formed in,
`problem.blocks.Workspace`), so that no two chunks write the same buffers.

BLAS is held to one thread meanwhile: OpenBLAS's own threads inside each chunk's products would only wait
for the cores the chunk threads hold (`estimate.threads`).
"""

from __future__ import annotations

import os
import queue
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator, Sequence, TypeVar

T = TypeVar("T")

#: threads at most for the chunks of one pass
CHUNK_THREADS = 2
_LIMIT: ContextVar[int | None] = ContextVar("chunk_threads_limit", default=None)


@contextmanager
def limited(n: int | None) -> Iterator[None]:
    """At most `n` chunk threads inside the block (None: no cap beyond `chunk_threads`' own)."""
    token = _LIMIT.set(n if n is None else max(1, int(n)))
    try:
        yield
    finally:
        _LIMIT.reset(token)


def cpus() -> int:
    """Logical CPUs this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def chunk_threads(n_chunks: int) -> int:
    """Threads for `n_chunks` chunks: `CHUNK_THREADS`, no more than the chunks, the CPUs this process may use
    or the cap of an enclosing `limited`.  Not fewer on a loaded machine: the threads wait for the
    interpreter, not in a spin, and each gets its share of the cores."""
    cap = _LIMIT.get()
    return max(1, min(CHUNK_THREADS, n_chunks, cpus(), cap if cap is not None else CHUNK_THREADS))


def for_each_chunk(work: Callable[[int, T], None], starts: Sequence[int], slots: Sequence[T]) -> None:
    """``work(start, slot)`` for every start, on as many threads as `slots`, each call with a slot no other
    running call holds.  Exceptions propagate (the first one raised, after the running calls end)."""
    if len(slots) <= 1 or len(starts) <= 1:
        for a in starts:
            work(a, slots[0])
        return
    from threadpoolctl import threadpool_limits

    free: queue.SimpleQueue = queue.SimpleQueue()
    for s in slots:
        free.put(s)

    def task(a: int) -> None:
        slot = free.get()
        try:
            work(a, slot)
        finally:
            free.put(slot)

    with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(len(slots)) as pool:
        for _ in pool.map(task, starts):
            pass
