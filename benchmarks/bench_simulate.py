"""Benchmark of the MuJoCo dataset generator: settled configurations per second, and the floor.

Usage::

    python benchmarks/bench_simulate.py [--n 300] [--repeat 3] [--scenario NAME ...] [--loaded] [--jobs 2]

For every scenario, load condition and BLAS thread mode it reports

* ``loop/s``: recorded (settled) configurations per second of the simulation
  loop (planning + MuJoCo stepping + recording), one process, wall time;
* ``steps/cfg``: simulation steps per recorded configuration;
* ``bound/s``: MuJoCo's own stepping rate on the scenario's scene
  (`floor.mujoco_rate`, measured in the same conditions) / steps per
  configuration, and ``%bound`` = loop/s / bound/s;
* ``mj ms/cfg``, ``other ms/cfg``: CPU time per configuration inside
  ``mujoco.mj_step`` (the calls the loop makes, timed one by one) and outside
  it (planner, servo ramp, settle checks, recording); ``plan ms/cfg``: the
  part of ``other`` spent in the nominal planner's ``step`` (its waypoints).
  The timers' own cost (two CPU-clock reads per call, ~1 us; measured on a
  no-op by `timer_cost`) is subtracted: ``mj`` loses the part inside the
  timed interval, ``other`` the rest;
* with ``--jobs J > 1``: aggregate configurations per second of J datasets
  simulated concurrently in J processes.

Every figure is the best of ``--repeat`` runs (on a shared machine other jobs
only ever slow a run down).  ``--loaded`` repeats everything while one busy
process per CPU keeps the cores busy (bounded in time, killed afterwards).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path

from floor import mujoco_rate, scenario_scene  # benchmarks/floor.py
from machine import add_arguments, condition, conditions, header, threads_mode  # benchmarks/machine.py

import closedloop.sims.dataset
import closedloop.sims.tracking  # noqa: F401  (the stepping loop; patched below with the dataset module)
from closedloop.sims import SCENARIOS, simulate


def _run(args: tuple[str, int, int, str]) -> tuple[int, float]:
    name, n, seed, out = args
    res = simulate(name, n, seed, Path(out))
    return len(res.readings), res.elapsed_s


def timer_cost(calls: int = 20000) -> tuple[float, float]:
    """CPU seconds per call that the `mj_step_timer` wrapper adds, (inside the timed interval, outside it)."""
    acc, clock = [0.0], time.process_time

    def noop(m, d, nstep=1) -> None:
        return None

    def timed(m, d, nstep=1):
        t = clock()
        noop(m, d, nstep)
        acc[0] += clock() - t

    best = (float("inf"), 0.0)
    for _ in range(5):
        acc[0] = 0.0
        t0 = clock()
        for _ in range(calls):
            timed(None, None, 1)
        total = clock() - t0
        t0 = clock()
        for _ in range(calls):
            noop(None, None, 1)
        total -= clock() - t0  # the call itself is not the timer's
        if total < best[0] + best[1]:
            best = (acc[0] / calls, max(total - acc[0], 0.0) / calls)
    return best


@contextmanager
def mj_step_timer():
    """Count the CPU time of every `mujoco.mj_step` call the dataset loop makes (yields [seconds, calls])."""
    import mujoco

    acc = [0.0, 0]
    step, clock = mujoco.mj_step, time.process_time

    def timed_step(m, d, nstep=1):
        t = clock()
        step(m, d, nstep)
        acc[0] += clock() - t
        acc[1] += 1

    shim = type("mujoco", (), {name: getattr(mujoco, name) for name in dir(mujoco) if not name.startswith("__")})
    shim.mj_step = staticmethod(timed_step)
    with _patched("mujoco", shim):
        yield acc


@contextmanager
def _patched(attr: str, value):
    """Replace module attribute `attr` (the `mujoco` or `time` module) in every closedloop.sims module holding it."""
    import sys

    mods = [
        m
        for name, m in list(sys.modules.items())
        if name.startswith("closedloop.sims.") and m is not None and hasattr(m, attr)
    ]
    saved = [(m, getattr(m, attr)) for m in mods]
    for m in mods:
        setattr(m, attr, value)
    try:
        yield
    finally:
        for m, v in saved:
            setattr(m, attr, v)


def measure(name: str, n: int, repeat: int, tmp: Path) -> tuple[int, float, float]:
    """(configurations, best loop rate [cfg/s, wall], steps per configuration) of `repeat` runs."""
    best = (0, 0.0, 0.0)
    for _ in range(max(1, repeat)):
        res = simulate(name, n, 0, tmp / name)
        k = len(res.readings)
        if res.configs_per_second > best[1]:
            best = (k, res.configs_per_second, res.n_steps / max(k, 1))
    return best


@contextmanager
def planner_timer():
    """Count the CPU time of the planners' `step` (yields [seconds])."""
    from closedloop.sims.driver import NominalLoopPlanner, RandomConfigurations

    acc, clock = [0.0], time.process_time
    saved = [(cls, cls.step) for cls in (NominalLoopPlanner, RandomConfigurations)]

    def timed(step):
        def wrapper(self):
            t = clock()
            try:
                return step(self)
            finally:
                acc[0] += clock() - t

        return wrapper

    for cls, step in saved:
        cls.step = timed(step)
    try:
        yield acc
    finally:
        for cls, step in saved:
            cls.step = step


def split_cpu(name: str, n: int, tmp: Path) -> tuple[float, float, float]:
    """CPU seconds per configuration of the simulation loop inside `mj_step`, outside it, and in the planner.

    The loop's own clock (``elapsed_s``) is read on the CPU clock for this run.
    """
    cpu_clock = type("time", (), {"perf_counter": staticmethod(time.process_time)})
    inside, outside = timer_cost()
    with _patched("time", cpu_clock), mj_step_timer() as acc, planner_timer() as plan:
        res = simulate(name, n, 0, tmp / f"{name}-cpu")
    k = max(len(res.readings), 1)
    mj = acc[0] - acc[1] * inside
    return mj / k, (res.elapsed_s - mj - acc[1] * (inside + outside)) / k, plan[0] / k


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=300, help="configurations per dataset")
    parser.add_argument("--jobs", type=int, default=1, help="parallel processes for the aggregate")
    parser.add_argument("--repeat", type=int, default=3, help="runs per figure (best reported)")
    parser.add_argument("--scenario", nargs="*", default=sorted(SCENARIOS))
    add_arguments(parser)
    args = parser.parse_args()

    print(header())
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        scenes = {name: scenario_scene(name, tmp / "scenes") for name in args.scenario}
        for name in args.scenario:
            simulate(name, 5, 0, tmp / "warmup")  # imports, caches
        for cond in conditions(args.loaded):
            for mode in args.threads:
                with condition(cond) as cdesc, threads_mode(mode) as tdesc:
                    print(f"\n[{cdesc}; BLAS threads {tdesc}]")
                    print(
                        f"{'scenario':<12} {'n':>5} {'loop/s':>7} {'steps/cfg':>9} {'bound/s':>8} {'%bound':>7} "
                        f"{'mj ms/cfg':>9} {'other ms/cfg':>12} {'plan ms/cfg':>11} {'%mj':>5}"
                        + (f" {'agg/s (' + str(args.jobs) + ' jobs)':>16}" if args.jobs > 1 else "")
                    )
                    for name in args.scenario:
                        k, rate, steps = measure(name, args.n, args.repeat, tmp)
                        bound = mujoco_rate(scenes[name])[0] / steps
                        splits = [split_cpu(name, args.n, tmp) for _ in range(max(1, args.repeat))]
                        mj, other, plan = (min(sp[i] for sp in splits) for i in range(3))
                        line = (
                            f"{name:<12} {k:>5} {rate:>7.0f} {steps:>9.1f} {bound:>8.0f} "
                            f"{100 * rate / bound:>6.0f}% {1e3 * mj:>9.3f} {1e3 * other:>12.3f} "
                            f"{1e3 * plan:>11.3f} {100 * mj / (mj + other):>4.0f}%"
                        )
                        if args.jobs > 1:
                            jobs = [
                                (name, args.n, seed, str(tmp / f"{name}_{seed}")) for seed in range(1, args.jobs + 1)
                            ]
                            with ProcessPoolExecutor(args.jobs) as pool:
                                runs = list(pool.map(_run, jobs))
                            line += f" {sum(c for c, _ in runs) / max(t for _, t in runs):>16.0f}"
                        print(line, flush=True)


if __name__ == "__main__":
    main()
