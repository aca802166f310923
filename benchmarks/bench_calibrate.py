"""Benchmark: weld-loop calibration of the 7-DOF Panda (issue 2; issue 5 for the sizes).

Prints, per dataset size, the whole calibration time (analysis + solve), the
solve time, the number of LM iterations and the time per iteration.  Data:
exact self-motion configurations of a random true Panda (1,000 distinct ones,
tiled with fresh 1e-4 rad noise for larger sizes).

    python benchmarks/bench_calibrate.py                    # 1,000 configurations
    python benchmarks/bench_calibrate.py --sizes 1000 10000 100000
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from closedloop.calibration import calibrate
from closedloop.data import JointLog
from closedloop.loops import WeldLoop
from closedloop.models import ROBOTS
from closedloop.robot import RobotModel
from closedloop.truth import make_dataset

from machine import machine  # benchmarks/machine.py


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000])
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs")
    args = ap.parse_args()
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    ds = make_dataset(robot, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 1000, rng,
                      stride=1)
    print(f"machine: {machine()}")
    print(f"data: 1,000 exact self-motion configurations in {time.perf_counter() - t:.1f} s; noise 1e-4 rad")
    print(f"{'configs':>9} {'total [s]':>10} {'solve [s]':>10} {'iters':>6} {'s/iter':>8} {'params':>7}")
    for n in args.sizes:
        reps = int(np.ceil(n / 1000))
        th = np.tile(ds.readings, (reps, 1))[:n]
        th = th + rng.normal(0.0, 1e-4, th.shape)
        log = JointLog(ds.joints, th)
        best = None
        for _ in range(args.repeat):
            stages: dict[str, float] = {}

            def progress(stage, it, cost, stages=stages):
                stages.setdefault(stage, time.perf_counter())

            t0 = time.perf_counter()
            res = calibrate(robot, log, [WeldLoop("fixture", "panda_hand")], progress=progress)
            total = time.perf_counter() - t0
            solve = total - (stages.get("solving", t0) - t0)
            if best is None or total < best[0]:
                best = (total, solve, res.iterations, len(res.estimated))
        total, solve, iters, npar = best
        print(f"{n:>9,} {total:>10.3f} {solve:>10.3f} {iters:>6d} {solve / max(iters, 1):>8.4f} {npar:>7d}")


if __name__ == "__main__":
    main()
