"""The machine a benchmark ran on, for the figures in the README.

Every benchmark prints `header()` (CPU, load average, BLAS threads) beside its
figures, runs its measurements single-threaded and with the default BLAS
threads (`THREAD_MODES`, `threads_mode`), and can measure under load
(`busy_cores`: processes that keep the cores busy, bounded in time and killed
afterwards), as a laptop running a simulator or a shared CI runner is.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from contextlib import contextmanager
from typing import Iterator

THREAD_MODES = ("1", "default")  # BLAS threads: single-threaded, and the libraries' own default


def machine() -> str:
    """CPU model, logical CPU count and Python version."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}; {os.cpu_count()} logical cpus; python {platform.python_version()}"


def load() -> str:
    """The 1, 5 and 15-minute load averages."""
    try:
        a, b, c = os.getloadavg()
    except OSError:
        return "load n/a"
    return f"load {a:.2f} {b:.2f} {c:.2f}"


def blas() -> str:
    """The BLAS libraries loaded in this process and their current thread counts (threadpoolctl)."""
    import numpy  # noqa: F401  (loads numpy's BLAS)
    from threadpoolctl import threadpool_info

    libs = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    if not libs:
        return "BLAS: none loaded"
    return "BLAS threads: " + ", ".join(f"{i['internal_api']} {i.get('version')} x{i['num_threads']}" for i in libs)


def header() -> str:
    """Machine, load average and BLAS threads, one line each."""
    env = [
        f"{k}={os.environ[k]}"
        for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
        if k in os.environ
    ]
    return f"machine: {machine()}\n{load()}\n{blas()}" + (f" ({' '.join(env)})" if env else "")


@contextmanager
def threads_mode(mode: str) -> Iterator[str]:
    """BLAS threads for the block: '1' single-threaded, 'default' the libraries' own setting."""
    if mode == "default":
        yield f"default ({blas().split(': ', 1)[-1]})"
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(int(mode), user_api="blas"):
        yield mode


@contextmanager
def busy_cores(n: int | None = None, seconds: float = 600.0) -> Iterator[list[int]]:
    """`n` processes spinning in a loop (default: one per logical CPU) for the block.

    Each stops by itself after `seconds` and is killed by its own pid on exit,
    whatever happens inside.
    """
    n = (os.cpu_count() or 1) if n is None else n
    # the busy loop bounds itself (no wrapper process: killing a `timeout` wrapper would orphan its child)
    code = f"import time\nend = time.time() + {float(seconds)}\nwhile time.time() < end: pass"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        for _ in range(n)
    ]
    time.sleep(1.0)  # let them reach the scheduler
    try:
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            p.kill()
            p.wait()


def timed(fn, *args, **kwargs):
    """(result, wall seconds, CPU seconds of this process) of one call: on a shared machine the
    wall time is what a user waits, the CPU time what the work itself costs."""
    t, c = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t, time.process_time() - c


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """--threads (modes) and --loaded, for every benchmark script."""
    ap.add_argument(
        "--threads",
        nargs="+",
        default=list(THREAD_MODES),
        choices=["1", "2", "4", "default", "auto"],
        help="BLAS thread modes to run (default: 1 and default; auto: closedloop.estimate.threads chooses)",
    )
    ap.add_argument(
        "--loaded",
        action="store_true",
        help="also run while one busy process per CPU keeps the cores busy (bounded, killed after)",
    )


def conditions(loaded: bool) -> list[str]:
    """The load conditions to run: idle, and 'loaded' when asked."""
    return ["idle", "loaded"] if loaded else ["idle"]


@contextmanager
def condition(name: str, seconds: float = 1800.0) -> Iterator[str]:
    """'idle': nothing added; 'loaded': `busy_cores()` for the block."""
    if name == "loaded":
        with busy_cores(seconds=seconds) as pids:
            yield f"loaded (+{len(pids)} busy processes; {load()})"
    else:
        yield f"no added load ({load()})"


def tests_zoo():
    """tests/zoo.py, the robot zoo, as the module `zoo` (benchmarks/zoo.py has the same name, so it is
    loaded from its path); tests/ is appended to sys.path for the modules it imports (zoo_judge)."""
    import importlib.util
    import sys
    from pathlib import Path

    tests = Path(__file__).resolve().parents[1] / "tests"
    if str(tests) not in sys.path:
        sys.path.append(str(tests))
    spec = importlib.util.spec_from_file_location("zoo", tests / "zoo.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["zoo"] = mod
    spec.loader.exec_module(mod)
    return mod
