"""Time per evaluation of the loops that eliminate passive joints.

`HingeLoop` (the door of thesis 3.4.2, one eliminated angle) and `PassiveChainLoop` (3.4.3, the
two-joint door task model `assets/tasks/door.urdf`) evaluated with their Jacobians on N synthetic
configurations: tool poses on the true closure manifold, moved off it by a random twist of
`--off` (so that the Gauss-Newton elimination takes a few iterations, as it does during a
calibration), and evaluated at parameters a little off the truth (new ones at every repetition,
as a solver's iterations are).  Prints the machine line and, per loop, N and thread mode, the
median wall and CPU time of one evaluation (on a shared machine the CPU time is the comparable one).

    python benchmarks/bench_loops.py                       # N = 40 and 1000, BLAS 1 and default
    python benchmarks/bench_loops.py --sizes 40 --threads 1 --repeat 21
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import add_arguments, condition, conditions, header, threads_mode  # noqa: E402

TASKS = Path(__file__).resolve().parents[1] / "closedloop" / "assets" / "tasks"


def _rz(a: float) -> pin.SE3:
    return pin.SE3(pin.exp3(np.array([0.0, 0.0, a])), np.zeros(3))


def hinge_case(n: int, off: float, rng: np.random.Generator):
    """A HingeLoop, poses (TA, TB) and a parameter sampler."""
    from closedloop.loops.hinge import HingeLoop

    lp = HingeLoop("door", "tool", axis=(np.array([0.5, 0.4, 0.6]), np.array([0.0, 0.0, 1.0])))
    p = np.array([0.01, -0.02, 0.07, -0.07, 0.45, 0.1, 0.05, -0.1, 0.2])
    H, G = lp.hinge(p), lp.grasp(p)
    TA = np.array([(H * _rz(a) * G * pin.exp6(rng.normal(0.0, off, 6))).homogeneous for a in rng.uniform(-1.2, 1.2, n)])
    TB = np.repeat(np.eye(4)[None], n, axis=0)
    return lp, TA, TB, lambda: p + rng.normal(0.0, 0.01, p.size)


def passive_case(n: int, off: float, rng: np.random.Generator):
    """A PassiveChainLoop on the door task model, poses (TA, TB) and a parameter sampler."""
    from closedloop.loops.passive import PassiveChainLoop

    P0 = pin.SE3(pin.exp3(np.array([0.1, -0.2, 0.3])), np.array([0.6, 0.2, 0.3]))
    lp = PassiveChainLoop("door", "tool", TASKS / "door.urdf", "grip", q0=np.array([0.3, 0.1]), pose=P0)
    data = lp.model.createData()
    TA = []
    for _ in range(n):
        q = np.array([rng.uniform(0.0, 1.0), rng.uniform(-0.4, 0.4)])
        pin.forwardKinematics(lp.model, data, q)
        TF = pin.updateFramePlacement(lp.model, data, lp.fid)
        TA.append((P0 * TF * pin.exp6(rng.normal(0.0, off, 6))).homogeneous)
    TA = np.array(TA)
    TB = np.repeat(np.eye(4)[None], n, axis=0)
    size = 12 + 6 * lp.nj
    return lp, TA, TB, lambda: rng.normal(0.0, 0.003, size)


def time_eval(case, n: int, off: float, repeat: int) -> tuple[float, float]:
    """Median wall and CPU seconds of one `evaluate` (with Jacobians) over `repeat` parameter draws."""
    rng = np.random.default_rng(0)
    lp, TA, TB, draw = case(n, off, rng)
    lp.evaluate(TA, TB, draw())  # warm-up (and the passive loop's warm-start cache)
    ts, cs = [], []
    for _ in range(repeat):
        p = draw()
        t, c = time.perf_counter(), time.process_time()
        lp.evaluate(TA, TB, p)
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    return statistics.median(ts), statistics.median(cs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[40, 1000])
    ap.add_argument("--repeat", type=int, default=11)
    ap.add_argument("--off", type=float, default=1e-3, help="std of the twist moving each pose off the manifold")
    add_arguments(ap)
    args = ap.parse_args(argv)
    print(header(), flush=True)
    cases = {"hinge": hinge_case, "passive (door.urdf, 2 DOF)": passive_case}
    for cond in conditions(args.loaded):
        with condition(cond) as label:
            print(f"\n## {label}")
            print("| loop | N | BLAS threads | wall ms / evaluation | CPU ms / evaluation | CPU us / configuration |")
            print("|---|---|---|---|---|---|")
            for name, case in cases.items():
                for n in args.sizes:
                    for mode in args.threads:
                        with threads_mode(mode) as tm:
                            t, c = time_eval(case, n, args.off, max(1, args.repeat if n <= 100 else args.repeat // 2))
                        print(
                            f"| {name} | {n} | {tm} | {1e3 * t:.2f} | {1e3 * c:.2f} | {1e6 * c / n:.1f} |", flush=True
                        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
