"""BLAS threads for the duration of one call (threadpoolctl): one, unless the user asks for more.

The calibration's dense algebra is tall and thin: a few thousand to a few
hundred thousand rows, a few dozen columns (the Jacobian of 6 residual rows
per configuration in the estimated parameters), factored a chunk of rows at
a time (`qr.r_factor`) and batched 6 x 6 products.  OpenBLAS's threads
gain nothing there and cost a lot when other processes hold the cores: its
worker threads spin-wait for a core the scheduler has given to someone else.
Measured on a 2-core AMD EPYC (`benchmarks/bench_calibrate.py`, thread modes
1 / default / auto), the Panda weld costs 0.13 s CPU at 1,000 configurations
single-threaded and 0.38-0.40 s with OpenBLAS's two threads (wall, both cores
kept busy: 1.2 s vs 3.3 s); at 10,000, 1.3 s vs 3.1 s CPU; on a nearly idle
machine (load 1.6) two threads were never faster from 1,000 to 30,000
configurations (180,000 rows x 28 columns); at 100,000 they cost 38.5 s CPU
against 33.0 s for the same wall time.  What parallel work a long log has is
its rows' (kinematics, whitening), and that runs on threads of its own, a chunk
of rows each (`parallel.chunks`), which OpenBLAS's spinning threads would only
slow: the main job at 100,000 rows took 20 s wall and 21.7 s CPU with both,
10.2-10.7 s and 13.5-13.8 s with the chunk threads and one BLAS thread (idle).
So a problem gets one BLAS thread.

`blas_threads(n)` is a context manager: the user's setting (environment
variables, an outer `threadpool_limits`) is restored on exit, whatever happens
inside.  An explicit `n` (the `--threads` option, `CalibrationOptions.threads`)
sets the BLAS threads and caps the chunk threads (`parallel.chunks.limited`).
"""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from typing import Iterator

from closedloop.parallel.chunks import limited

log = logging.getLogger(__name__)

_controller = None
_modules_seen = -1


def _get_controller():
    """A cached threadpoolctl controller, rebuilt when new modules (maybe a BLAS) were imported."""
    global _controller, _modules_seen
    from threadpoolctl import ThreadpoolController

    if _controller is None or len(sys.modules) != _modules_seen:
        _controller = ThreadpoolController()
        _modules_seen = len(sys.modules)
    return _controller


def current_threads() -> int:
    """The largest BLAS thread count currently set in this process (1 if no BLAS is loaded)."""
    blas = _get_controller().select(user_api="blas")
    return max((lib.num_threads for lib in blas.lib_controllers), default=1)


@contextmanager
def blas_threads(n: int | None) -> Iterator[int]:
    """Limit BLAS threads inside the block; yields the number used.

    n: threads to use, which also caps the chunk threads (None: one BLAS thread, the chunk threads
    `parallel.chunks` chooses; 0 or negative: leave the current setting alone).  The previous limits are
    restored on exit.
    """
    if n is not None and n <= 0:
        yield current_threads()
        return
    ctl = _get_controller()
    blas = ctl.select(user_api="blas")
    current = max((lib.num_threads for lib in blas.lib_controllers), default=1)
    k = 1 if n is None else int(n)
    with limited(n):
        if k == current or not blas.lib_controllers:
            yield k
            return
        log.debug("BLAS threads %d -> %d", current, k)
        with ctl.limit(limits=k, user_api="blas"):
            yield k
