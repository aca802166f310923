"""A two-arm rig at scale: 16 contact loops, ~1,000 configurations; fit and validation times, against the truth.

Baxter (example-robot-data: two 7-joint arms on a torso) whose hands touch each other and their
surroundings, every contact a loop of its own:

* each hand: a stylus point on a wall and on two tables (`plane`, the stylus shared by the hand's three
  planes) and its flat pad on the same wall and tables (`face`): 6 loops per hand;
* the hands: spherical ends pressed together (`sphere`, radii sum unknown), a ball bar of known length
  between them (`sphere` with the distance given: it sets the robot's size), the pads pressed together
  (`face`), and the wrists' spheres (`sphere`): 4 loops.

The truth perturbs every parameter the loops identify (`closedloop.studies.truth.draw_truth`: joint
origins 2 mm / 2 mrad, offsets 0.02 rad); each loop's configurations walk along its self-motion in the
true robot (`closedloop.studies.synthetic.self_motion`), with Gaussian joint noise.  The script then
times the calibration (`calibrate`), leave-one-fixture-out (`validation.fixtures`) and region validation
(`validation.regions`, 4 regions), reports the iterations, whether the fit converged and whether its
profile check (`analysis.linearity`) found a minimum, and compares the calibrated robot with the truth by
what the rig does: the left hand's pose in the right hand's frame and each hand's tool point in the world
(position and rotation, at readings drawn within the joint ranges, the world's base pose removed).

    python benchmarks/dual_arm_rig.py                       # 16 loops, 62 configurations each
    python benchmarks/dual_arm_rig.py --per-loop 6          # a tenth of the rows
    python benchmarks/dual_arm_rig.py --data /tmp/rig.npz   # keep the simulated rows (reused when present)
"""

from __future__ import annotations

import argparse
import os
import site
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import header  # noqa: E402  benchmarks/machine.py

ERD = site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/"
BAXTER = ERD + "baxter_description/urdf/baxter.urdf"
LEFT = [f"left_{j}" for j in ("s0", "s1", "e0", "e1", "w0", "w1", "w2")]
RIGHT = [f"right_{j}" for j in ("s0", "s1", "e0", "e1", "w0", "w1", "w2")]
#: a start of the two arms (left, then right) with the grippers in front of the torso, near each other
Q_HANDS = np.array([0.3, -0.5, -0.5, 1.5, 0.3, 0.8, 0.2, -0.3, -0.5, 0.5, 1.5, -0.3, 0.8, -0.2])


def rig_loops(robot, bar: float | None = None):
    """The 16 loops and, per loop, the start configuration its walk begins at (14 readings); `bar`: the ball
    bar's length when known (m; None: a parameter)."""
    from closedloop.loops.face import FaceLoop
    from closedloop.loops.plane import PlaneLoop
    from closedloop.loops.settings import share
    from closedloop.loops.sphere import SphereLoop

    loops, starts = [], []
    rng = np.random.default_rng(7)
    for side, frame, sign in (("l", "left_gripper", 1.0), ("r", "right_gripper", -1.0)):
        for k, (place, normal) in enumerate(
            (("wall", [0.0, -sign, 0.0]), ("table1", [0.0, 0.0, 1.0]), ("table2", [0.2, 0.0, 1.0]))
        ):
            q = Q_HANDS + rng.normal(0.0, 0.15, 14)
            lp = PlaneLoop(f"{side}_{place}", frame, tip=None, normal=np.array(normal))
            share(lp, "tip", f"{side}_stylus")
            loops.append(lp)
            starts.append(q)
            q = Q_HANDS + rng.normal(0.0, 0.15, 14)
            loops.append(FaceLoop(f"{side}_{place}_pad", frame, normal=np.array(normal)))
            starts.append(q)
    loops.append(SphereLoop("hands", "left_gripper", "right_gripper", tip=[0.0, 0.0, 0.03], point=[0.0, 0.0, 0.03]))
    starts.append(Q_HANDS)
    loops.append(
        SphereLoop("bar", "left_gripper", "right_gripper", tip=[0.0, 0.0, 0.0], point=[0.0, 0.0, 0.0], distance=bar)
    )
    starts.append(Q_HANDS + rng.normal(0.0, 0.1, 14))
    loops.append(FaceLoop("pads", "left_gripper", "right_gripper"))
    starts.append(Q_HANDS + rng.normal(0.0, 0.1, 14))
    loops.append(SphereLoop("wrists", "left_wrist", "right_wrist", tip=[0.0, 0.0, 0.0], point=[0.0, 0.0, 0.0]))
    starts.append(Q_HANDS + rng.normal(0.0, 0.1, 14))
    return loops, np.array(starts)


def simulate(robot, per_loop: int, noise: float, seed: int):
    """(readings (n, 14), loop name per row, the truth by parameter name: the robot's and every loop's own)."""
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.io.logs import JointLog
    from closedloop.problem.problem import CalibrationProblem, LoopBlock
    from closedloop.studies.synthetic import self_motion
    from closedloop.studies.truth import draw_truth

    joints = LEFT + RIGHT
    loops, starts = rig_loops(robot)
    rng = np.random.default_rng(seed)
    # the identifiable set: what a calibration of the nominal robot on nominal walks estimates
    walks = []
    for lp, q in zip(loops, starts):
        prob = CalibrationProblem(robot, joints, [LoopBlock(lp, q[None], np.arange(1))])
        x = prob.nominal.copy()
        x[prob.loop_slices[0]] = lp.initialize(*prob.loop_poses(x, 0, q[None]))
        walks.append(self_motion(prob, x, q[None], 8, np.random.default_rng(seed + 1), step=0.1))
    rows = np.vstack(walks)
    names = np.repeat([lp.name for lp in loops], [len(w) for w in walks])
    res0 = calibrate(robot, JointLog(joints, rows, None, names), loops, CalibrationOptions())
    robot_names = [
        n
        for n, s in zip(res0.fit.names, res0.fit.status)
        if s == "estimated" and "." in n and n.split(".")[0] in robot.joint_names
    ]
    true_robot = draw_truth(robot, robot_names, rng)
    truth: dict[str, float] = dict(true_robot)
    out, labels = [], []
    for lp, q in zip(loops, starts):
        prob = CalibrationProblem(robot, joints, [LoopBlock(lp, q[None], np.arange(1))])
        x = prob.nominal.copy()
        for k, v in true_robot.items():
            x[prob.index[k]] = v
        x[prob.loop_slices[0]] = lp.initialize(*prob.loop_poses(x, 0, q[None]))
        if lp.name == "hands":  # two 3 cm spheres: a distance of 6 cm between the centres
            x[prob.loop_slices[0]] = [0.06]
        th = self_motion(prob, x, q[None], per_loop, rng, step=0.08, stride=1)
        out.append(th + rng.normal(0.0, noise, th.shape))
        labels += [lp.name] * len(th)
        truth.update({n: float(v) for n, v in zip(prob.names[prob.loop_slices[0]], x[prob.loop_slices[0]])})
    return np.vstack(out), np.array(labels), truth


def compare(res, truth: dict[str, float], robot, n: int = 200, seed: int = 0) -> dict[str, float]:
    """What the rig does, calibrated against true: the left gripper's pose in the right gripper's frame over
    `n` readings within the joint ranges (max position error, m; max rotation error, rad)."""
    import pinocchio as pin

    prob = res.problem
    x_true = prob.nominal.copy()
    for k, v in truth.items():
        if k in prob.index:
            x_true[prob.index[k]] = v
    joints = prob.joints
    lo = np.array([robot.joint(j).lower for j in joints])
    hi = np.array([robot.joint(j).upper for j in joints])
    th = np.random.default_rng(seed).uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), (n, len(joints)))
    ids = [robot.frame_id("left_gripper"), robot.frame_id("right_gripper")]
    out = {}
    poses = []
    for x in (res.fit.values, x_true):
        kin = prob.frame_kinematics(prob.rp.apply(x[: prob.n_robot]), th, ids, False)
        poses.append(kin)
    a = [np.linalg.solve(kin[ids[1]][0], kin[ids[0]][0]) for kin in poses]  # T_R^-1 T_L
    dp = np.linalg.norm(a[0][:, :3, 3] - a[1][:, :3, 3], axis=1)
    dr = np.array([np.linalg.norm(pin.log3(r0.T @ r1)) for r0, r1 in zip(a[0][:, :3, :3], a[1][:, :3, :3])])
    out["hand_in_hand_m"] = float(dp.max())
    out["hand_in_hand_rad"] = float(dr.max())
    return out


def pinocchio_floor(robot, th: np.ndarray) -> float:
    """CPU seconds Pinocchio alone takes for the forward kinematics of both grippers at every reading."""
    import pinocchio as pin

    model = robot.model
    data = model.createData()
    q = robot.configurations(th, LEFT + RIGHT)
    ids = [model.getFrameId("left_gripper"), model.getFrameId("right_gripper")]
    t = time.process_time()
    for qi in q:
        pin.forwardKinematics(model, data, qi)
        for f in ids:
            pin.updateFramePlacement(model, data, f)
    return time.process_time() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-loop", type=int, default=62, help="configurations per loop (16 loops)")
    ap.add_argument("--noise", type=float, default=2e-5, help="joint noise, rad")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", help="an .npz of simulated rows: read when present, else written")
    ap.add_argument("--no-validate", action="store_true", help="time the fit only")
    a = ap.parse_args()
    print(header())
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.errors import ClosedLoopError
    from closedloop.io.logs import JointLog
    from closedloop.model.robot import RobotModel
    from closedloop.validation.fixtures import leave_one_fixture_out
    from closedloop.validation.regions import region_validate

    robot = RobotModel.from_file(BAXTER)
    t0 = time.perf_counter()
    if a.data and Path(a.data).exists():
        z = np.load(a.data, allow_pickle=False)
        th, labels = z["th"], z["labels"]
        truth = dict(zip(z["truth_names"].tolist(), z["truth_values"].tolist()))
        print(f"read {len(th)} rows from {a.data}")
    else:
        th, labels, truth = simulate(robot, a.per_loop, a.noise, a.seed)
        print(f"simulated {len(th)} rows of {len(set(labels))} loops in {time.perf_counter() - t0:.1f} s")
        if a.data:
            np.savez(
                a.data,
                th=th,
                labels=labels,
                truth_names=np.array(list(truth)),
                truth_values=np.array(list(truth.values())),
            )
    log = JointLog(LEFT + RIGHT, th, None, labels)
    loops, _ = rig_loops(robot, bar=truth["bar.d"])  # the ball bar's length known: it sets the size
    opts = CalibrationOptions(noise=a.noise)
    t = time.perf_counter()
    c0 = time.process_time()
    res = calibrate(robot, log, loops, opts)
    fit_s, fit_cpu = time.perf_counter() - t, time.process_time() - c0
    profiles = res.noise.profiles
    minimum = not any(p.falls for p in profiles) if profiles else None
    print(
        f"fit: {len(res.fit.estimated)} parameters, {len(th)} configurations, {len(loops)} loops: "
        f"{fit_s:.1f} s wall, {fit_cpu:.1f} s CPU, {res.fit.iterations} iterations, {res.fit.solver_status}; "
        f"profile check: {'not run' if minimum is None else ('a minimum' if minimum else 'NOT a minimum')} "
        f"({len(res.noise.profiles)} directions); verdict {res.verdict.status}"
    )
    floor = pinocchio_floor(robot, th)
    t = time.process_time()
    res.problem.evaluate(res.fit.values, True)
    jac = time.process_time() - t
    print(
        f"  for scale: Pinocchio's forward kinematics of the {len(th)} configurations (both grippers) alone "
        f"{floor * 1e3:.0f} ms CPU; one residual + Jacobian of the problem {jac * 1e3:.0f} ms CPU"
    )
    for p in res.noise.profiles:
        print(f"  profile {p.describe()}")
    for w in res.verdict.reasons:
        print(f"  verdict: {w}")
    print(f"  against the truth: {compare(res, truth, robot)}")
    if a.no_validate:
        return
    t, c0 = time.perf_counter(), time.process_time()
    lofo = leave_one_fixture_out(robot, log, loops, opts, result=res)
    lofo_s, lofo_cpu = time.perf_counter() - t, time.process_time() - c0
    rows = (lofo or {}).get("fixtures", [])
    worse = [f["fixture"] for f in rows if f.get("worse")]
    print(
        f"leave-one-fixture-out: {len(rows)} "
        f"fixtures in {lofo_s:.1f} s wall, {lofo_cpu:.1f} s CPU; worse than nominal: {worse or 'none'}; "
        f"refits converged: {sum(bool(f.get('converged')) for f in rows)}/{len(rows)}"
    )
    print(
        "  refits: iterations "
        + ", ".join(f"{f['fixture']} {f.get('iterations')}{'' if f.get('warm') else ' (cold)'}" for f in rows)
    )
    cal = [f["calibrated_rms_m"] for f in rows if f.get("calibrated_rms_m") is not None]
    nom = [f["nominal_rms_m"] for f in rows if f.get("nominal_rms_m") is not None]
    if cal:
        print(
            f"  held-out closure RMS (m): calibrated median {np.median(cal):.3g}, nominal median {np.median(nom):.3g}"
        )
    t, c0 = time.perf_counter(), time.process_time()
    try:
        rv = region_validate(robot, log, loops, res.problem.joints, opts, k=4)
    except ClosedLoopError as exc:  # a tenth of the rows: too few per loop for 4 regions
        print(f"regions: not run ({exc})")
        rv = None
    reg_s, reg_cpu = time.perf_counter() - t, time.process_time() - c0
    if rv is not None:
        print(f"regions: {rv['k']} held out in {reg_s:.1f} s wall, {reg_cpu:.1f} s CPU")
    print(
        f"validation total {lofo_s + reg_s:.1f} s wall, {lofo_cpu + reg_cpu:.1f} s CPU; "
        f"load average after: {os.getloadavg()[0]:.2f}"
    )


if __name__ == "__main__":
    main()
