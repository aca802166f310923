"""Default weighting against the unweighted fit on held-out places, over seeds (contact noise).

tests/test_rigs.py `test_contact_default_no_worse_than_unweighted_heldout` (seed 0) compares the default
(task noise estimated beside the joint noise, pooled when the loops agree, `closedloop.estimate.variance`) with
``--weighting none`` on held-out places.  Over seeds: noise or a bias?  Each seed draws a rig as the test's
(three places, two sockets 50 mm apart, 0.2 mm play, 2e-5 rad joint noise, the three distances known),
runs leave-one-place-out with both weightings (and with the true noise model given, sigma_task=0.2mm)
and reports the mean held-out RMS difference with its standard error over seeds.

    python benchmarks/rig_contact_weighting.py --seeds 20
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
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--n", type=int, default=30, help="configurations per socket and place")
    a = ap.parse_args()
    print(header())
    import test_rigs as tr

    from closedloop import CalibrationOptions, calibrate
    from closedloop.validation.fixtures import leave_one_fixture_out

    cases = (
        ("default", "", CalibrationOptions()),
        ("unweighted", "", CalibrationOptions(weighting="none")),
        ("true noise", ",sigma_task=0.2mm", CalibrationOptions()),
    )
    rel, t0 = {k: [] for k, _, _ in cases[1:]}, time.perf_counter()
    sizes, poss = {k: [] for k, _, _ in cases}, {k: [] for k, _, _ in cases}
    for seed in range(a.seeds):
        held, size, pos = {}, {}, {}
        with tempfile.TemporaryDirectory() as tmp:
            rig, robot, log = tr._setup(Path(tmp), seed=seed, n=a.n, places=3, sigma_task=tr.SIGMA_TASK, sigma_q=2e-5)
            for label, extra, opt in cases:
                loops = tr._loops(robot, rig.loop_names(), extra)
                out = leave_one_fixture_out(robot, log, loops + tr._distances(loops, (1, 2, 3)), opt)
                held[label] = np.mean([r["calibrated_rms_m"] for r in out["fixtures"]])
                res = calibrate(robot, log, loops + tr._distances(loops, (1, 2, 3)), opt)  # all places
                P, Q = tr.ball_positions(res, rig)
                size[label], pos[label] = tr.scale_error(res, rig), tr.rigid_rms(P, Q)
        for k in rel:
            rel[k].append(held["default"] / held[k] - 1.0)
        for k in sizes:
            sizes[k].append(size[k])
            poss[k].append(pos[k])
        print(
            f"seed {seed:3d}: held-out RMS (mm) "
            + ", ".join(f"{k} {v * 1e3:.4f}" for k, v in held.items())
            + f"; default vs unweighted {rel['unweighted'][-1]:+.2%}; size error "
            + ", ".join(f"{k} {v:+.3%}" for k, v in size.items())
            + "; position error vs truth (mm) "
            + ", ".join(f"{k} {v * 1e3:.4f}" for k, v in pos.items()),
            flush=True,
        )
    print(f"{a.seeds} seeds in {time.perf_counter() - t0:.0f} s")
    for k, v in rel.items():
        v = np.array(v)
        print(
            f"held-out RMS, default / {k} - 1: mean {v.mean():+.3%} +- {v.std(ddof=1) / np.sqrt(v.size):.3%} "
            f"(standard error), range {v.min():+.2%} .. {v.max():+.2%}, default better in {np.mean(v < 0):.0%}"
        )
    for k in sizes:
        sz, ps = np.array(sizes[k]), np.array(poss[k]) * 1e3
        print(
            f"{k}: size error mean {sz.mean():+.3%} +- {sz.std(ddof=1) / np.sqrt(sz.size):.3%}; position error "
            f"vs truth {ps.mean():.4f} +- {ps.std(ddof=1) / np.sqrt(ps.size):.4f} mm"
        )


if __name__ == "__main__":
    main()
