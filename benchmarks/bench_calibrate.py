"""Benchmark: weld-loop calibration of the 7-DOF Panda.

Per dataset size, BLAS thread mode and load condition: the whole calibration
time (analysis + solve), the solve time, the LM iterations, the CPU time, and
the ratios to the floor (`floor.pinocchio_floor`: forward kinematics + frame
Jacobian of the same number of configurations, measured in the same
conditions): `total / floor` and `solve / (floor x iterations)`.  Data: exact
self-motion configurations of a random true Panda (1,000 distinct ones, tiled
with fresh 1e-4 rad noise for larger sizes).

Thread modes: `1` (single-threaded), `default` (the BLAS libraries' own
setting), `auto` (`closedloop.estimate.threads.blas_threads(None)`, what the
library chooses: one BLAS thread, the rows on `parallel.chunks`' threads).  `--loaded` repeats everything while one busy process per
CPU keeps the cores busy (bounded in time, killed afterwards).  `kernel`: the
median kernel CPU of a run (page faults), part of `cpu tot`; `--reuse-memory`
keeps glibc from unmapping freed arrays (what grows superlinearly at 100,000).
`--corrupt F` corrupts a fraction F of the rows (one reading off by 0.05-0.2
rad): the outlier screen's robust refit and the final fit on the rows kept
(`rejected`: rows rejected, and how many of them were corrupted).

    python benchmarks/bench_calibrate.py                              # 1,000 configurations
    python benchmarks/bench_calibrate.py --sizes 1000 10000 100000 --loaded
    python benchmarks/bench_calibrate.py --sizes 1000 10000 100000 --corrupt 0.05 --threads 1
"""

from __future__ import annotations

import argparse

import numpy as np
from floor import pinocchio_floor  # benchmarks/floor.py
from machine import add_arguments, condition, conditions, header, threads_mode, timed  # benchmarks/machine.py

from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import calibrate
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.truth import make_dataset


def _log(ds, n: int, rng: np.random.Generator, corrupt: float = 0.0) -> tuple[JointLog, np.ndarray]:
    """n configurations (the 1,000 tiled, fresh noise) and the rows corrupted: a fraction `corrupt` of them
    with one reading off by 0.05-0.2 rad (a glitch: closures of centimetres)."""
    reps = int(np.ceil(n / 1000))
    th = np.tile(ds.readings, (reps, 1))[:n] + rng.normal(0.0, 1e-4, (n, ds.readings.shape[1]))
    bad = np.zeros(0, dtype=int)
    if corrupt > 0:
        bad = rng.choice(n, int(round(corrupt * n)), replace=False)
        th[bad, rng.integers(0, th.shape[1], bad.size)] += rng.choice([-1.0, 1.0], bad.size) * rng.uniform(
            0.05, 0.2, bad.size
        )
    return JointLog(ds.joints, th), bad


def run_once(robot, log: JointLog, mode: str) -> tuple[float, float, float, float, int, int, float, list[int]]:
    """(total wall, solve wall, total CPU, solve CPU, iterations, estimated parameters, kernel CPU, rejected
    rows) of one calibration.  The kernel's share (page faults: arrays above glibc's mmap threshold, 32 MB at most, are
    mapped and zeroed afresh on every allocation) is what grows faster than the data."""
    import resource
    import time

    stages: dict[str, tuple[float, float]] = {}

    def progress(stage, it, total=None, note=""):
        stages.setdefault(stage, (time.perf_counter(), time.process_time()))

    loops = [WeldLoop("fixture", "panda_hand")]
    if mode == "auto":
        from closedloop.estimate.threads import blas_threads

        def call():
            with blas_threads(None):
                return calibrate(robot, log, loops, progress=progress)
    else:

        def call():
            with threads_mode(mode):
                return calibrate(robot, log, loops, progress=progress)

    t0, c0 = time.perf_counter(), time.process_time()
    k0 = resource.getrusage(resource.RUSAGE_SELF).ru_stime
    res, total, cpu = timed(call)
    kernel = resource.getrusage(resource.RUSAGE_SELF).ru_stime - k0
    s0, sc0 = stages.get("solving", (t0, c0))
    return (
        total,
        total - (s0 - t0),
        cpu,
        cpu - (sc0 - c0),
        res.fit.iterations,
        len(res.fit.estimated),
        kernel,
        [rj.row - 1 for rj in res.outliers.rejected],
    )


def reuse_freed_memory() -> bool:
    """glibc only: keep freed arrays in the heap for reuse (no mmap, no trimming), for this process.

    The same as MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=2147483647 MALLOC_TOP_PAD_=1073741824 in the
    environment.  Returns whether the C library took it.
    """
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_top_pad, m_mmap_max = -1, -2, -4
    return all(libc.mallopt(k, v) == 1 for k, v in ((m_mmap_max, 0), (m_trim_threshold, 2**31 - 1), (m_top_pad, 2**30)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000])
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure (median and best reported)")
    ap.add_argument(
        "--reuse-memory",
        action="store_true",
        help="glibc: keep freed arrays for reuse (mallopt; see reuse_freed_memory)",
    )
    ap.add_argument(
        "--corrupt",
        type=float,
        default=0.0,
        metavar="F",
        help="fraction of rows with one reading off by 0.05-0.2 rad (outlier screen)",
    )
    add_arguments(ap)
    ap.set_defaults(threads=["1", "default", "auto"])
    args = ap.parse_args()
    if args.reuse_memory:
        print(f"malloc: freed memory kept for reuse: {reuse_freed_memory()}")
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(0)
    ds, t_data, _ = timed(
        make_dataset,
        robot,
        WeldLoop("fixture", "panda_hand"),
        [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8],
        1000,
        rng,
        stride=1,
    )
    print(header())
    print(
        f"data: 1,000 exact self-motion configurations in {t_data:.1f} s; noise 1e-4 rad"
        + (f"; {100 * args.corrupt:g} % of the rows corrupted" if args.corrupt else "")
    )
    logs = {n: _log(ds, n, rng, args.corrupt) for n in args.sizes}
    calibrate(robot, logs[args.sizes[0]][0], [WeldLoop("fixture", "panda_hand")])  # warm-up (imports, caches)
    for cond in conditions(args.loaded):
        with condition(cond) as cdesc:
            print(f"\n[{cdesc}]")
            print(
                "wall: median and best of the runs; cpu: medians; floor: Pinocchio FK + frame Jacobian of the\n"
                "same configurations (benchmarks/floor.py), best of 3, wall and CPU; ratios on the CPU clock\n"
                "(on a shared machine the wall clock measures the scheduler)"
            )
            print(
                f"{'threads':>8} {'configs':>9} {'total med':>10} {'best':>7} {'solve med':>10} {'best':>7} "
                f"{'cpu tot':>8} {'cpu solve':>9} {'iters':>5} {'floor ms':>9} {'cpu':>6} "
                f"{'tot/fl':>7} {'solve/(fl*it)':>14} {'kernel':>7}"
            )
            for mode in args.threads:
                for n in args.sizes:
                    reps = args.repeat if n <= 10000 else max(1, args.repeat // 3)
                    runs = [run_once(robot, logs[n][0], mode) for _ in range(reps)]
                    tot = np.array([r[0] for r in runs])
                    sol = np.array([r[1] for r in runs])
                    cpu = float(np.median([r[2] for r in runs]))
                    cpu_s = float(np.median([r[3] for r in runs]))
                    iters = runs[0][4]
                    kernel = float(np.median([r[6] for r in runs]))
                    with threads_mode("1"):
                        fl, fl_cpu = pinocchio_floor("panda", n=n, repeat=3)
                    print(
                        f"{mode:>8} {n:>9,} {np.median(tot):>10.3f} {tot.min():>7.3f} {np.median(sol):>10.3f} "
                        f"{sol.min():>7.3f} {cpu:>8.3f} {cpu_s:>9.3f} {iters:>5d} {1e3 * fl:>9.2f} "
                        f"{1e3 * fl_cpu:>6.2f} {cpu / fl_cpu:>7.0f} {cpu_s / (fl_cpu * max(iters, 1)):>14.1f} {kernel:>7.2f}"
                        + (
                            f"  rejected {len(runs[0][7])} ({np.isin(runs[0][7], logs[n][1]).sum()} corrupted of "
                            f"{logs[n][1].size})"
                            if args.corrupt
                            else ""
                        ),
                        flush=True,
                    )


if __name__ == "__main__":
    main()
