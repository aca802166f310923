"""Is the size's standard error right?  Simulated ball-and-socket rigs, one seed per draw.

Each seed draws a true Panda (every joint origin 1 mm / 1 mrad, offsets 5 mrad), 30 configurations per
socket of a two-socket block (50 mm) at three places, 0.2 mm play in the sockets and 2e-5 rad joint
noise (`examples/ball_socket_rig.py`), calibrates it with the three known distances, and compares the
calibrated robot's size with the truth (ball positions at random readings after the best rigid motion)
against the reported standard error (`CalibrationResult.scale_std`).  Also the per-loop play estimate.

    python benchmarks/rig_scale_mc.py --draws 20
    python benchmarks/rig_scale_mc.py --draws 20 --block     # a three-socket block (--block) instead
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from machine import header  # noqa: E402  benchmarks/machine.py


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--block", action="store_true", help="a three-socket block (tests/test_rigs.py BLOCK)")
    a = ap.parse_args()
    print(header())
    import test_rigs as tr  # the rig helpers and the truth comparison of tests/test_rigs.py

    from closedloop import CalibrationOptions, calibrate
    from closedloop.problem.distances import parse_blocks

    z, task, t0 = [], [], time.perf_counter()
    for seed in range(a.draws):
        with tempfile.TemporaryDirectory() as tmp:
            rig, robot, log = tr._setup(
                Path(tmp),
                seed=seed,
                n=20 if a.block else 30,
                places=3,
                sigma_task=tr.SIGMA_TASK,
                sigma_q=2e-5,
                block=tr.BLOCK if a.block else None,
            )
            loops = tr._loops(robot, rig.loop_names())
            if a.block:
                known = parse_blocks(
                    [
                        [f"b{p}"] + [f"place{p}_{s}.point={x},{y},{z}" for s, (x, y, z) in zip("abc", tr.BLOCK)]
                        for p in (1, 2, 3)
                    ],
                    loops,
                )
            else:
                known = tr._distances(loops, (1, 2, 3))
            res = calibrate(robot, log, loops + known, CalibrationOptions())
            err = tr.scale_error(res, rig)
        z.append(err / res.scale.scale_std)
        task += [d["task_sigma_m"] / tr.SIGMA_TASK for d in res.noise.noise_model]
        print(
            f"seed {seed:3d}: size error {err:+.4%}, standard error {res.scale.scale_std:.4%}, z {z[-1]:+.2f}, "
            f"verdict {res.verdict.status}"
        )
    z = np.array(z)
    print(
        f"{a.draws} draws in {time.perf_counter() - t0:.0f} s: mean z^2 {np.mean(z**2):.2f}, "
        f"|z| < 1 in {np.mean(np.abs(z) < 1):.0%}, < 2 in {np.mean(np.abs(z) < 2):.0%}; "
        f"play estimate / truth {np.mean(task):.3f} +- {np.std(task):.3f} (range {min(task):.2f}-{max(task):.2f})"
    )


if __name__ == "__main__":
    main()
