"""Benchmark of the MuJoCo dataset generator: settled configurations per second.

Usage::

    python benchmarks/bench_simulate.py [--n 500] [--jobs 2] [--repeat 1] [--scenario NAME ...]

For every scenario it reports

* ``loop/s``: recorded (settled) configurations per second of the simulation
  loop (planning QP + MuJoCo stepping + recording), one process;
* ``total/s``: the same including model loading, truth draw, scene building and
  writing the outputs;
* ``steps/cfg``: simulation steps per recorded configuration;
* with ``--jobs J > 1``: aggregate configurations per second of J independent
  datasets (different seeds) generated concurrently in J processes (all
  recorded configurations / the slowest simulation loop; process start-up excluded).

With ``--repeat R`` every figure is the best of R runs (on a shared machine the
other jobs only ever slow a run down).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from closedloop.sims import SCENARIOS, simulate


def _run(args: tuple[str, int, int, str]) -> tuple[int, float]:
    name, n, seed, out = args
    res = simulate(name, n, seed, Path(out))
    return len(res.readings), res.elapsed_s


def _cpu_name() -> str:
    """CPU model (``platform.processor()``, else ``/proc/cpuinfo``)."""
    name = platform.processor()
    if name and name != platform.machine():
        return name
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return name or "unknown CPU"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=500, help="configurations per dataset")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel processes for the aggregate")
    parser.add_argument("--repeat", type=int, default=1, help="runs per figure (best reported)")
    parser.add_argument("--scenario", nargs="*", default=sorted(SCENARIOS))
    args = parser.parse_args()

    print(f"machine: {platform.machine()} {_cpu_name()}; cpus: {os.cpu_count()}; "
          f"python {platform.python_version()}")
    print(f"{'scenario':<12} {'n':>6} {'loop/s':>9} {'total/s':>9} {'steps/cfg':>10} {'viol max [m]':>13}"
          + (f" {'agg/s (' + str(args.jobs) + ' jobs)':>16}" if args.jobs > 1 else ""))
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenario:
            simulate(name, 5, 0, Path(tmp) / "warmup")  # imports, caches
            loop_rate = total_rate = 0.0
            for _ in range(max(1, args.repeat)):
                t0 = time.perf_counter()
                res = simulate(name, args.n, 0, Path(tmp) / name)
                total = time.perf_counter() - t0
                n = len(res.readings)
                loop_rate = max(loop_rate, res.configs_per_second)
                total_rate = max(total_rate, n / total)
            line = (f"{name:<12} {n:>6} {loop_rate:>9.0f} {total_rate:>9.0f} "
                    f"{res.n_steps / max(n, 1):>10.1f} {res.violation_m.max():>13.2e}")
            if args.jobs > 1:
                jobs = [(name, args.n, seed, str(Path(tmp) / f"{name}_{seed}")) for seed in range(1, args.jobs + 1)]
                agg = 0.0
                for _ in range(max(1, args.repeat)):
                    with ProcessPoolExecutor(args.jobs) as pool:
                        runs = list(pool.map(_run, jobs))
                    # simulation loops run concurrently: aggregate = all configurations / slowest loop
                    agg = max(agg, sum(c for c, _ in runs) / max(t for _, t in runs))
                line += f" {agg:>16.0f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
