"""Baxter's two grippers rigidly grasping each other: the thesis's 12-DOF Example 2 (3.5), on 14 joints.

The left gripper holds the right one with an unknown grasp transform (a weld
loop between two branches of one model, six unknown closure parameters).  The
closed chain has 14 - 6 = 8 degrees of self-motion.  Pure-kinematic data are
generated on the TRUE loop (nominal URDF + random errors in the identifiable
parameters, `closedloop.studies.truth.make_dataset`), the nominal model is calibrated
from the joint readings alone, and truth is printed against calibration with the
summary of what was dropped (structural redundancies, and what absorbed them).

    python examples/dual_arm_baxter.py [N] [SEED]
"""

from __future__ import annotations

import site
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.truth import make_dataset

URDF = (
    Path(site.getsitepackages()[0]) / "cmeel.prefix/share/example-robot-data/robots/baxter_description/urdf/baxter.urdf"
)
# A configuration with the grippers in front of the torso (left arm, then right arm).
Q0 = {
    "left_s0": 0.3,
    "left_s1": -0.4,
    "left_e0": -0.3,
    "left_e1": 1.3,
    "left_w0": 0.2,
    "left_w1": 0.6,
    "left_w2": 0.1,
    "right_s0": -0.3,
    "right_s1": -0.4,
    "right_e0": 0.3,
    "right_e1": 1.3,
    "right_w0": -0.2,
    "right_w1": 0.6,
    "right_w2": -0.1,
}


def run(n: int = 60, seed: int = 0, verbose: bool = True) -> dict:
    robot = RobotModel.from_file(URDF)
    loop = WeldLoop("grasp", "left_gripper", "right_gripper")
    rng = np.random.default_rng(seed)
    joints = [j for j in robot.joint_names if j in Q0]
    t0 = time.time()
    ds = make_dataset(robot, loop, np.array([Q0[j] for j in joints]), n, rng, step=0.05)
    t_data = time.time() - t0
    t0 = time.time()
    res = calibrate(
        robot, ds.log(noisy=False), [WeldLoop("grasp", "left_gripper", "right_gripper")], CalibrationOptions()
    )
    t_cal = time.time() - t0
    truth = ds.truth_dict()
    est = [k for k, s in enumerate(res.fit.status) if s == "estimated"]
    errs = {res.fit.names[k]: abs(res.fit.values[k] - truth[res.fit.names[k]]) for k in est}
    out = {
        "n": n,
        "estimated": len(est),
        "dropped": len(res.identifiability.dropped),
        "weak": len(res.identifiability.weak),
        "max_error": max(errs.values()),
        "before": res.fit.residuals_before[0],
        "after": res.fit.residuals_after[0],
        "converged": res.converged,
        "notes": res.notes,
        "seconds_data": t_data,
        "seconds_cal": t_cal,
        "result": res,
        "dataset": ds,
    }
    if verbose:
        b, a = res.fit.residuals_before[0], res.fit.residuals_after[0]
        print(
            f"Baxter dual-arm grasp: {len(ds.joints)} joints, {n} configurations "
            f"(data {t_data:.1f} s, calibration {t_cal:.1f} s, {res.fit.iterations} iterations, {res.fit.solver_status})"
        )
        print(
            f"  closure RMS {b.rms_m * 1e3:.3f} mm -> {a.rms_m * 1e3:.2e} mm, "
            f"{b.rms_rad * 1e3:.3f} mrad -> {a.rms_rad * 1e3:.2e} mrad"
        )
        print(f"\n  {'parameter':24s} {'nominal':>12s} {'truth':>12s} {'calibrated':>12s} {'error':>9s}")
        for k in est:
            nme = res.fit.names[k]
            print(
                f"  {nme:24s} {res.fit.initial[k]:+12.6f} {truth[nme]:+12.6f} {res.fit.values[k]:+12.6f} {errs[nme]:9.1e}"
            )
        print(
            f"\n  {len(est)} estimated, max |error| {out['max_error']:.2e}; {len(res.identifiability.dropped)} dropped, "
            f"{len(res.identifiability.weak)} weak directions"
        )
        kinds = Counter(d.name.rsplit(".", 1)[1] for d in res.identifiability.dropped)
        print("  dropped by field:", dict(sorted(kinds.items())))
        for d in res.identifiability.dropped:
            if d.name.startswith(("left_s0.", "right_s0.", "left_e1.")):  # a representative sample
                print("   ", d.describe())
        for note in res.notes:
            print("  note:", note)
    return out


if __name__ == "__main__":
    N = int(sys.argv[1]) if len(sys.argv) > 1 else 60
    SEED = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    run(N, SEED)
