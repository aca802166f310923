"""Speed on a large real-sized problem: a humanoid upper body, two hand markers, 1,000 poses.

TALOS (example-robot-data `talos_full_v2.urdf`, cut to the torso and both arms: 16 joints) with two
markers measured by a tracker (`measured_point` loops on both grippers), 1,000 random postures.  The
truth is the nominal model with placement and offset errors (2 mm / 2 mrad / 0.02 rad); the readings
carry 1e-5 rad of noise and an elastic deflection of the shoulders (a model error, so that the
calibration goes the way it goes on a real robot: the errors-in-variables fit, the noise hypothesis
rejected, the plain fit).  Measured: `calibrate` with the defaults, and with 5-fold validation
(`cross_validate`, serial); the floor is what Pinocchio alone takes for the forward kinematics and
frame Jacobians of the same poses, once (`pin.computeJointJacobians` + `getFrameJacobian` per pose).

    nice python benchmarks/bench_real.py               # 1,000 poses, profile -> stdout
    python benchmarks/bench_real.py --poses 500 --no-validation --profile
    python benchmarks/bench_real.py --recordings       # the public recordings of real TALOS and TIAGo

`--recordings` times closedloop's defaults on the real recordings of docs/validation/real-robots.md, read
from ../shared/real-data/ beside the repository (it stops, naming the folder, where one is absent): the
fit on all rows and the held-out protocol of tests/test_real_robots.py, against the same floor.

Not part of the test suite.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))  # real_data: where the recordings live
from machine import header  # noqa: E402
from real_data import RECORDINGS, chain_urdf, figaroh_log  # noqa: E402

from closedloop.assets.catalog import example_robot_data_dir  # noqa: E402
from closedloop.calibration.pipeline import build_problem, calibrate  # noqa: E402
from closedloop.io.logs import JointLog  # noqa: E402
from closedloop.loops.measured import MeasuredPointLoop  # noqa: E402
from closedloop.model.robot import RobotModel  # noqa: E402
from closedloop.records import CalibrationOptions  # noqa: E402
from closedloop.studies.truth import draw_truth  # noqa: E402
from closedloop.validation.kfold import cross_validate, holdout, subset  # noqa: E402

TIPS = ("gripper_left_base_link", "gripper_right_base_link")
X_TRUE = pin.SE3(pin.exp3(np.array([0.05, -0.1, 1.0])), np.array([1.2, 0.3, -0.4]))
MARK = np.array([0.02, -0.01, -0.08])


def dataset(robot: RobotModel, n: int, seed: int, bend: float) -> JointLog:
    rng = np.random.default_rng(seed)
    joints = sorted({j for t in TIPS for j in robot.supporting_joints(t)}, key=lambda j: robot.joint_names.index(j))
    lo = np.array([robot.model.lowerPositionLimit[robot.model.idx_qs[robot.model.getJointId(j)]] for j in joints])
    hi = np.array([robot.model.upperPositionLimit[robot.model.idx_qs[robot.model.getJointId(j)]] for j in joints])
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    th = mid + 0.7 * half * rng.uniform(-1, 1, (n, len(joints)))
    zeros = {f"{lp}:{c}": np.zeros(n) for lp in ("left", "right") for c in "xyz"}
    loops = [MeasuredPointLoop("left", TIPS[0]), MeasuredPointLoop("right", TIPS[1])]
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), loops)
    names = [p.name for p in prob.params if p.kind in ("placement", "offset")]
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    bent = th.copy()
    for j, name in enumerate(joints):
        if name.endswith("_2_joint") and name.startswith("arm"):  # shoulders bent by the arm's weight
            bent[:, j] += bend * np.sin(th[:, j])
    extra = {}
    for bi, lp in enumerate(("left", "right")):
        TA, TB = prob.loop_poses(truth, bi, bent)
        m = np.array([X_TRUE.actInv(pin.SE3(TB[i]).actInv(pin.SE3(TA[i])).act(MARK)) for i in range(n)])
        extra |= {f"{lp}:{c}": m[:, k] + rng.normal(scale=1e-5, size=n) for k, c in enumerate("xyz")}
    readings = th + rng.normal(scale=1e-5, size=th.shape)
    return JointLog(joints, readings, None, None, extra)


def floor(robot: RobotModel, log_: JointLog, tips: tuple[str, ...] = TIPS) -> float:
    """Pinocchio alone: forward kinematics and the frames' Jacobians at every pose, once (seconds, best of 5)."""
    model = robot.model
    data = model.createData()
    fids = [model.getFrameId(t) for t in tips]
    qs = []
    for row in log_.angles:
        q = pin.neutral(model)
        for j, name in enumerate(log_.joints):
            q[model.idx_qs[model.getJointId(name)]] = row[j]
        qs.append(q)
    best = np.inf
    for _ in range(5):  # the best of 5: the machine is shared
        t = time.perf_counter()
        for q in qs:
            pin.computeJointJacobians(model, data, q)
            pin.updateFramePlacements(model, data)
            for f in fids:
                pin.getFrameJacobian(model, data, f, pin.LOCAL)
        best = min(best, time.perf_counter() - t)
    return best


def recordings() -> None:
    """The real recordings (module doc): fit on all rows, then the held-out protocol (every fifth row held out)."""
    for name, rec in RECORDINGS.items():
        log_ = figaroh_log(name, skip=False)
        with tempfile.TemporaryDirectory() as tmp:
            robot = RobotModel.from_file(
                chain_urdf(example_robot_data_dir() / rec.urdf, rec.frame, Path(tmp) / "chain.urdf")
            )
        loops = [MeasuredPointLoop("m", rec.frame)]
        fl = floor(robot, log_, (rec.frame,))
        t, c = time.perf_counter(), time.process_time()
        res = calibrate(robot, log_, loops, CalibrationOptions())
        fit, cpu = time.perf_counter() - t, time.process_time() - c
        idx = np.arange(len(log_))
        test = idx % 5 == 0
        t = time.perf_counter()
        h = holdout(robot, subset(log_, idx[~test]), subset(log_, idx[test]), loops, CalibrationOptions())
        held = time.perf_counter() - t
        print(
            f"{name} ({rec.folder}): {len(log_)} postures, {len(log_.joints)} joints; floor {fl * 1e3:.2f} ms; "
            f"calibrate (defaults, all rows) {fit:.2f} s wall, {cpu:.2f} s cpu, {len(res.fit.estimated)} parameters, "
            f"verdict {res.verdict.status}; held-out protocol {held:.2f} s wall, held-out RMS "
            f"{h['test']['loops'][0]['rms_m'] * 1e3:.3f} mm"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--bend", type=float, default=5e-3, help="shoulder deflection amplitude (rad), the model error")
    ap.add_argument("--no-validation", action="store_true")
    ap.add_argument("--profile", action="store_true", help="cProfile of the fit, top 25 by cumulative time")
    ap.add_argument("--recordings", action="store_true", help="the real TALOS and TIAGo recordings instead")
    args = ap.parse_args()
    print(header())
    if args.recordings:
        recordings()
        print(header())
        return
    src = example_robot_data_dir() / "talos_data/robots/talos_full_v2.urdf"
    with tempfile.TemporaryDirectory() as tmp:
        robot = RobotModel.from_file(chain_urdf(src, TIPS, Path(tmp) / "upper.urdf"))
    log_ = dataset(robot, args.poses, args.seed, args.bend)
    loops = [MeasuredPointLoop("left", TIPS[0]), MeasuredPointLoop("right", TIPS[1])]
    fl = floor(robot, log_)
    print(f"poses {len(log_)}, joints {len(log_.joints)}, markers 2, shoulder deflection {args.bend:g} rad")
    print(f"floor (Pinocchio FK + 2 frame Jacobians per pose, once): {fl * 1e3:.1f} ms")
    prof = cProfile.Profile() if args.profile else None
    t, c = time.perf_counter(), time.process_time()
    if prof:
        prof.enable()
    res = calibrate(robot, log_, loops, CalibrationOptions())
    if prof:
        prof.disable()
    fit, cpu = time.perf_counter() - t, time.process_time() - c
    print(
        f"calibrate (defaults): {fit:.2f} s wall, {cpu:.2f} s cpu, {len(res.fit.estimated)} parameters, "
        f"{res.fit.iterations} iterations, "
        f"estimator {res.noise.estimator}, verdict {res.verdict.status}; {fit / fl:.0f}x the floor"
    )
    print(f"  {res.notes[0]}")
    if prof:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(25)
        print(s.getvalue())
    if not args.no_validation:
        t, c = time.perf_counter(), time.process_time()
        cv = cross_validate(robot, log_, loops, CalibrationOptions(), k=5)
        val, vcpu = time.perf_counter() - t, time.process_time() - c
        test = ", ".join(f"{x['loop']} {x['rms_m'] * 1e3:.3f} mm" for x in cv["test"])
        print(
            f"5-fold validation (serial): {val:.2f} s wall, {vcpu:.2f} s cpu; fit + validation "
            f"{fit + val:.2f} s wall, {cpu + vcpu:.2f} s cpu; held-out {test}"
        )
    print(header())


if __name__ == "__main__":
    main()
