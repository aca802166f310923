"""What an evaluation of a loop block returns, and the memory it is formed in.

`BlockEval` is one block's residuals and Jacobians over its configurations.
A long log is evaluated a chunk of configurations at a time
(`problem.CHUNK`); the chunks are written into arrays allocated once
(`stack_chunks`), and the large temporaries of each chunk (kinematic
regressors, their products) live in a `Workspace` that the next chunk and
the next evaluation reuse.  Freed and allocated again, arrays of that size
go back to the kernel (glibc returns them) and come back as page faults: at
100,000 configurations that was a fifth of the calibration's time.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np


@dataclass
class BlockEval:
    r: np.ndarray  # (N, m)
    J: np.ndarray | None  # (N, m, C) d r / d parameters, over the requested columns (default: all P)
    Jq: np.ndarray | None  # (N, m, n_joints) d r / d reading
    valid: np.ndarray | None = None  # (N, m) False: a row with no observation (LoopEval.valid); None: all
    cov: np.ndarray | None = None  # (N, m, m) per-configuration measurement covariance (LoopEval.cov)
    #: (N,) the log rows of the configurations (LoopBlock.rows): blocks that read the same row share its
    #: joint noise and are whitened together (`noise.whiten`); None for a block without configurations
    rows: np.ndarray | None = None

    def take(self, idx: np.ndarray) -> "BlockEval":
        """The evaluation of the configurations `idx` (indices or a mask over its N) alone."""

        def cut(a):
            return None if a is None else a[idx]

        return BlockEval(self.r[idx], cut(self.J), cut(self.Jq), cut(self.valid), cut(self.cov), cut(self.rows))

    def jacobian(self) -> np.ndarray:
        """`J`, which an evaluation with Jacobians holds (a ValueError if this one was made without)."""
        if self.J is None:
            raise ValueError("this block was evaluated without its parameter Jacobian")
        return self.J


class Workspace:
    """Named scratch arrays reused from one chunk (and one evaluation) to the next.

    `get(name, shape)` returns an uninitialised array of that shape, a view of
    the named buffer, grown when too small.  Whatever a caller keeps beyond the
    chunk must be copied out (`stack_chunks` does) before the next `get` of the
    same name.
    """

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        size = int(np.prod(shape))
        buf = self._buffers.get(name)
        if buf is None or buf.size < size:
            buf = self._buffers[name] = np.empty(size)
        return buf[:size].reshape(shape)


class ChunkStack:
    """One block's evaluation of N configurations, written a chunk at a time into arrays allocated once.

    No list of chunks is kept and no concatenation copies them again (at 100,000 configurations J alone is
    ~130 MB, and a fresh array of that size costs its page faults on every pass).  A field is allocated
    at the first chunk that has it; a chunk without `valid` (all valid) or `cov` (none) beside one with it
    is written as all True / zeros.  `put` may be called from several threads, for disjoint chunks, in any
    order once the first chunk is in.
    """

    _FILL = {"valid": True, "cov": 0.0}  # what a chunk without the field stands for

    def __init__(self, N: int) -> None:
        self.N = N
        self._out: dict[str, np.ndarray | None] = dict.fromkeys(("r", "J", "Jq", "valid", "cov", "rows"))
        self._lock = threading.Lock()

    def put(self, a: int, part: BlockEval) -> None:
        """Write the chunk `part` of the configurations from `a` on."""
        n = part.r.shape[0]
        for name in self._out:
            v = getattr(part, name)
            dest = self._out[name]
            if v is None and (name not in self._FILL or dest is None):
                continue
            if dest is None:
                with self._lock:
                    dest = self._out[name]
                    if dest is None:
                        dest = np.empty((self.N,) + v.shape[1:], dtype=v.dtype)
                        if name in self._FILL:
                            dest[...] = self._FILL[name]  # the chunks without it
                        self._out[name] = dest
            dest[a : a + n] = self._FILL[name] if v is None else v

    def result(self) -> BlockEval:
        out = dict(self._out)
        r = out.pop("r")
        assert r is not None  # every chunk has r, and a block is chunked only when it has configurations
        return BlockEval(r=r, **out)


def read_only(e: BlockEval) -> BlockEval:
    """`e` with its arrays made read-only, to be shared as it is (a long log's kept evaluation: a copy of its
    Jacobian costs a quarter of the pass that made it); a caller that would write into one makes its own."""
    for a in (e.r, e.J, e.Jq, e.valid, e.cov):
        if a is not None:
            a.flags.writeable = False
    return e


def copy_eval(e: BlockEval, jacobian: bool, no_columns: bool) -> BlockEval:
    """A copy of a kept evaluation: r only, or with the Jacobians (none of J's columns with `no_columns`)."""

    def cp(a):
        return None if a is None else a.copy()

    if not jacobian:
        return BlockEval(e.r.copy(), None, None, cp(e.valid), cp(e.cov), e.rows)
    J = e.J[:, :, :0].copy() if no_columns and e.J is not None else cp(e.J)
    return BlockEval(e.r.copy(), J, cp(e.Jq), cp(e.valid), cp(e.cov), e.rows)
