"""BLAS threads chosen by problem size, for the duration of one call (threadpoolctl).

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
against 33.0 s for the same wall time.  So a problem gets one thread
unless its work, rows * cols^2 (the flops of a QR pass), exceeds
`THREADED_WORK`, and then at most as many as there are idle cores (logical
CPUs minus the one-minute load average), never more than the process's
current setting.

`blas_threads(n, rows, cols)` is a context manager: the user's setting
(environment variables, an outer `threadpool_limits`) is restored on exit,
whatever happens inside.  An explicit `n` (the `--threads` option,
`CalibrationOptions.threads`) overrides the choice.
"""

from __future__ import annotations

import logging
import os
import sys
from contextlib import contextmanager
from typing import Iterator

log = logging.getLogger(__name__)

# rows * cols^2 above which a second thread may pay on idle cores: above the largest problem measured,
# 100,000 Panda configurations (600,000 x 28 = 4.7e8), where two threads still cost 17 % more CPU
# (38.5 s vs 33.0 s) for no shorter wall time.
THREADED_WORK = 6e8

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


def idle_cores() -> int:
    """Logical CPUs this process may use minus the one-minute load average, at least 1."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        load = 0.0
    return max(1, int(cpus - load + 0.5))


def choose_threads(rows: int, cols: int, current: int | None = None) -> int:
    """BLAS threads for a dense pass over a rows x cols matrix: 1 unless the work pays for more."""
    current = current_threads() if current is None else current
    if float(rows) * float(cols) ** 2 < THREADED_WORK:
        return 1
    return max(1, min(current, idle_cores()))


@contextmanager
def blas_threads(n: int | None, rows: int, cols: int) -> Iterator[int]:
    """Limit BLAS threads inside the block; yields the number used.

    n: threads to use (None: `choose_threads(rows, cols)`; 0 or negative: leave
    the current setting alone).  The previous limits are restored on exit.
    """
    if n is not None and n <= 0:
        yield current_threads()
        return
    ctl = _get_controller()
    blas = ctl.select(user_api="blas")
    current = max((lib.num_threads for lib in blas.lib_controllers), default=1)
    k = choose_threads(rows, cols, current) if n is None else int(n)
    if k == current or not blas.lib_controllers:
        yield k
        return
    log.debug("BLAS threads %d -> %d for %d x %d", current, k, rows, cols)
    with ctl.limit(limits=k, user_api="blas"):
        yield k
