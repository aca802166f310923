"""Point, plane and measured loops: Jacobians, noise-free recovery, identifiability, noise."""

from __future__ import annotations

import site

import numpy as np
import pinocchio as pin
import pytest
from support import relative_fk_error

from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate
from closedloop.errors import LoopError
from closedloop.io.logs import JointLog
from closedloop.loops.common import relative_point
from closedloop.loops.measured import MeasuredPointLoop, MeasuredPoseLoop
from closedloop.loops.plane import PlaneLoop
from closedloop.loops.point import PointLoop
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import vec_of
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.studies.identifiable import identifiable_names
from closedloop.studies.synthetic import self_motion
from closedloop.studies.truth import draw_truth

ERD = site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/"
UR5 = ERD + "ur_description/urdf/ur5_robot.urdf"
PANDA = ERD + "panda_description/urdf/panda.urdf"
BAXTER = ERD + "baxter_description/urdf/baxter.urdf"
UR5_Q0 = [0.3, -1.2, 1.4, -1.0, 1.2, 0.4]
PANDA_Q0 = [0.2, 0.3, -0.2, -2.0, 0.1, 2.0, 0.5]
BAXTER_Q0 = [0.3, -0.5, -0.5, 1.5, 0.3, 0.8, 0.2, -0.3, -0.5, 0.5, 1.5, -0.3, 0.8, -0.2]
COLS = ("x", "y", "z", "rx", "ry", "rz")

_robots: dict[str, RobotModel] = {}


def robot_of(path: str) -> RobotModel:
    if path not in _robots:
        _robots[path] = RobotModel.from_file(path)
    return _robots[path]


def loop_joints(robot: RobotModel, loop) -> list[str]:
    js = {j for f in (loop.frame_a, loop.frame_b) for j in robot.supporting_joints(f)}
    return sorted(js, key=robot.joint_names.index)


def closed_experiment(path, make, theta0, own, n=40, seed=0, noise=None, options=None):
    """Truth in the identifiable parameterisation, self-motion data, calibration from nominal."""
    robot = robot_of(path)
    joints = loop_joints(robot, make())
    theta0 = np.atleast_2d(theta0)
    names = identifiable_names(robot, [make()], theta0, n=n)
    rng = np.random.default_rng(seed)
    prob = CalibrationProblem(robot, joints, [LoopBlock(make(), theta0, np.arange(1))])
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    TA, TB = prob.loop_poses(truth, 0, theta0)
    truth[prob.loop_slices[0]] = prob.blocks[0].loop.initialize(TA, TB)
    for k, v in own.items():
        truth[prob.index[k]] = v
    th = self_motion(prob, truth, theta0, n, rng)
    if noise:
        th = th + rng.normal(scale=noise, size=th.shape)
    res = calibrate(robot, JointLog(joints, th), [make()], options or CalibrationOptions(noise=noise))
    truth_by_name = dict(zip(prob.names, truth))
    return res, truth_by_name


def estimated_errors(res, truth_by_name):
    est = [i for i, s in enumerate(res.fit.status) if s == "estimated"]
    err = np.array([res.fit.values[i] - truth_by_name[res.fit.names[i]] for i in est])
    return est, err


def dropped_names(res) -> set[str]:
    return {d.name for d in res.identifiability.dropped}


# ---------------------------------------------------------------- Jacobians
def _fd_problem(loop, frame="tool0", seed=0, N=4):
    robot = robot_of(UR5)
    joints = robot.supporting_joints(frame)
    rng = np.random.default_rng(seed)
    th = rng.uniform(-1, 1, (N, len(joints)))
    extra = {f"{loop.name}:{c}": rng.normal(size=N) for c in COLS}
    prob = build_problem(robot, JointLog(joints, th, None, None, extra), [loop])
    x = prob.nominal + rng.normal(scale=0.05, size=len(prob.names))
    sc = prob.rp.scale_index()
    x[sc] = 1 + rng.normal(scale=0.05, size=sc.size)
    return prob, x


JAC_CASES = {
    "point": lambda: PointLoop("c", "tool0"),
    "point_known_tip": lambda: PointLoop("c", "tool0", tip=[0.0, 0.01, 0.1]),
    "point_known_point": lambda: PointLoop("c", "tool0", point=[0.3, 0.2, 0.1]),
    "point_two_branches": lambda: PointLoop("c", "tool0", "upper_arm_link"),
    "plane": lambda: PlaneLoop("c", "tool0", normal=[1.0, 1.0, 0.2]),
    "plane_known_tip": lambda: PlaneLoop("c", "tool0", tip=[0.0, 0.0, 0.1]),
    "measured_pose": lambda: MeasuredPoseLoop("c", "tool0", sigma_t=1e-4, sigma_r=1e-4),
    "measured_pose_known_tool": lambda: MeasuredPoseLoop("c", "tool0", tool=pin.SE3.Identity()),
    "measured_point": lambda: MeasuredPointLoop("c", "tool0", sigma_t=1e-4),
    "measured_point_to_link": lambda: MeasuredPointLoop("c", "tool0", "shoulder_link"),
}


@pytest.mark.parametrize("case", sorted(JAC_CASES))
def test_jacobian_matches_central_differences(case):
    prob, x = _fd_problem(JAC_CASES[case]())
    ev = prob.evaluate(x)[0]
    J = ev.J.reshape(-1, x.size)
    Jn = np.zeros_like(J)
    h = 1e-6
    for k in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (prob.evaluate(xp, False)[0].r.ravel() - prob.evaluate(xm, False)[0].r.ravel()) / (2 * h)
    assert np.abs(J - Jn).max() <= 1e-6 * np.abs(J).max()


def test_point_jq_matches_central_differences():
    """d r / d reading (used for whitening and self-motion) on a two-branch point loop."""
    prob, x = _fd_problem(PointLoop("c", "tool0", "upper_arm_link"))
    b = prob.blocks[0]
    Jq = prob.evaluate(x)[0].Jq
    h = 1e-6
    for j in range(b.theta.shape[1]):
        tp, tm = b.theta.copy(), b.theta.copy()
        tp[:, j] += h
        tm[:, j] -= h
        d = (prob.evaluate(x, False, [tp])[0].r - prob.evaluate(x, False, [tm])[0].r) / (2 * h)
        assert np.allclose(Jq[:, :, j], d, atol=1e-7)


# ---------------------------------------------------------------- point contact (3.4.1)
def test_point_contact_ur5_theorem4():
    """6R arm under point contact: noise-free recovery and the Theorem 4 redundancies."""
    res, truth = closed_experiment(
        UR5, lambda: PointLoop("ball", "tool0"), UR5_Q0, {"ball.tip_x": 0.01, "ball.tip_y": -0.02, "ball.tip_z": 0.12}
    )
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    # 17 robot + tip (3) + contact point (3).  The tip starts from the data (a pivot fit), off the last
    # axis as the real one is: that axis's position and tilt are identified (a start at the flange origin,
    # on the axis, used to drop them as "no effect", and exact data then fitted only to 8 um).
    assert len(est) == 23
    dropped = dropped_names(res)
    # base orientation about the contact point and base position (theta_0^off, alpha_0 of 3.4.1):
    assert {f"shoulder_pan_joint.{f}" for f in COLS} | {"shoulder_pan_joint.offset"} <= dropped
    # tool orientation is free (alpha_n): the tip's angle about the last axis absorbs its offset
    assert {"wrist_3_joint.offset", "wrist_3_joint.rz"} <= dropped
    assert {"wrist_3_joint.x", "wrist_3_joint.rx"} <= {res.fit.names[i] for i in est}
    assert res.fit.residuals_after[0].rms_m < 1e-10
    assert res.verdict.status == "ok"
    # one length fixed (a_0 = -1 in the theorem)
    assert any("length scale" in n for n in res.notes)
    assert all(
        res.fit.status[res.fit.names.index(f"ball.{f}")] == "estimated"
        for f in ("tip_x", "tip_y", "tip_z", "px", "py", "pz")
    )


def test_point_contact_panda():
    res, truth = closed_experiment(
        PANDA,
        lambda: PointLoop("ball", "panda_hand"),
        PANDA_Q0,
        {"ball.tip_x": 0.01, "ball.tip_y": -0.02, "ball.tip_z": 0.12},
    )
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    # 21 robot + 6 loop: the tip (12 cm out) starts from the data, off the last axis, whose position and
    # tilt are then identified (a start on the axis dropped them)
    assert len(est) == 27
    dropped = dropped_names(res)
    assert {f"panda_joint1.{f}" for f in COLS} | {"panda_joint1.offset"} <= dropped
    assert {"panda_joint7.offset", "panda_joint7.rz"} <= dropped
    assert res.fit.residuals_after[0].rms_m < 1e-10 and res.verdict.status == "ok"


def test_point_two_arms_baxter():
    """Baxter's grippers joined point-wise: two branches of one model, 14 joints."""
    res, truth = closed_experiment(
        BAXTER, lambda: PointLoop("touch", "left_gripper", "right_gripper"), BAXTER_Q0, {"touch.tip_z": 0.02}, n=40
    )
    # judged by what the arms do: the touching point in the right gripper, up to the length scale
    pos, _, _ = relative_fk_error(res, [truth[n] for n in res.fit.names], "left_gripper", "right_gripper", tip="touch")
    assert pos < 1e-8
    dropped = dropped_names(res)
    # only the relative pose of the two arm bases matters: one base is the gauge
    assert {f"left_s0.{f}" for f in COLS} <= dropped | {res.scale.gauge}
    # the size is held by a named length, or the verdict says that none alone holds it (never silently)
    assert any("length scale" in n for n in res.notes) or (
        res.verdict.status == "suspect" and any("scale is not determined" in r for r in res.verdict.reasons)
    )


def test_point_contact_noise_within_four_sigma():
    noise = 1e-4
    res, truth = closed_experiment(
        UR5,
        lambda: PointLoop("ball", "tool0"),
        UR5_Q0,
        {"ball.tip_x": 0.01, "ball.tip_y": -0.02, "ball.tip_z": 0.12},
        n=80,
        seed=3,
        noise=noise,
    )
    assert res.converged
    est, err = estimated_errors(res, truth)
    std = res.fit.std[est]
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.abs(err / std).max() < 4.0
    assert 0.5 < res.noise.chi2 / res.noise.dof < 1.5


def test_point_initialize_is_mean_contact_point():
    robot = robot_of(UR5)
    loop = PointLoop("ball", "tool0", tip=[0.0, 0.0, 0.1])
    prob = CalibrationProblem(
        robot, robot.supporting_joints("tool0"), [LoopBlock(loop, np.atleast_2d(UR5_Q0), np.arange(1))]
    )
    th = np.array(UR5_Q0) + np.random.default_rng(0).normal(scale=0.1, size=(5, 6))
    TA, TB = prob.loop_poses(prob.nominal, 0, th)
    p = loop.initialize(TA, TB)
    ref = np.mean([TA[i, :3, :3] @ [0, 0, 0.1] + TA[i, :3, 3] for i in range(5)], axis=0)
    assert np.allclose(p, ref)


# ---------------------------------------------------------------- plane
def test_plane_ur5_recovery():
    own = {"floor.tip_x": 0.01, "floor.tip_y": -0.02, "floor.tip_z": 0.12, "floor.nrx": 0.2, "floor.nry": -0.15}
    res, truth = closed_experiment(UR5, lambda: PlaneLoop("floor", "tool0"), UR5_Q0, own, n=120)
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    dropped = dropped_names(res)
    assert {f"shoulder_pan_joint.{f}" for f in COLS} <= dropped
    for f in ("tip_x", "tip_y", "tip_z", "nrx", "nry", "d"):
        assert res.fit.status[res.fit.names.index(f"floor.{f}")] == "estimated"


def test_plane_parameterisation():
    loop = PlaneLoop("p", "tool0", normal=[0.0, 1.0, 0.0])
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        assert np.allclose(loop.normal(loop.angles(n)), n)
    # the far hemisphere is flipped back: same plane, |w| <= pi/2
    w = loop.angles(np.array([0.3, -0.9, 0.2]) / np.linalg.norm([0.3, -0.9, 0.2]))
    p = np.concatenate([[0.0, 0.0, 0.1], w, [0.4]])
    q = loop.normalize(p)
    assert np.linalg.norm(q[3:5]) <= np.pi / 2
    assert np.allclose(loop.normal(q[3:5]), -loop.normal(p[3:5])) and q[5] == -0.4
    # a data fit picks the normal towards the reference
    pts = rng.normal(size=(10, 3)) * [1, 0, 1] + [0, -0.5, 0]
    TA = np.tile(np.eye(4), (10, 1, 1))
    TA[:, :3, 3] = pts
    fit = loop.initialize(TA, np.tile(np.eye(4), (10, 1, 1)))
    assert np.allclose(loop.normal(fit[3:5]), [0, 1, 0]) and np.isclose(fit[5], -0.5)


# ---------------------------------------------------------------- measured (open loop, 3.2)
X_TRUE = pin.SE3(pin.exp3(np.array([0.1, -0.2, 2.0])), np.array([1.5, 0.3, 0.2]))
Y_TRUE = pin.SE3(pin.exp3(np.array([0.05, 0.02, -0.1])), np.array([0.01, -0.02, 0.1]))
TIP_TRUE = np.array([0.01, -0.02, 0.1])
GUESS = X_TRUE * pin.SE3(pin.exp3(np.array([0.2, -0.3, 0.25])), np.array([0.1, -0.2, 0.15]))


def _measurements(prob, values, th, kind, name="m"):
    TA, TB = prob.loop_poses(values, 0, th)
    out = {f"{name}:{c}": np.empty(len(th)) for c in (COLS if kind == "pose" else COLS[:3])}
    for i in range(len(th)):
        W = pin.SE3(TB[i]).actInv(pin.SE3(TA[i]))
        v = vec_of(X_TRUE.inverse() * W * Y_TRUE) if kind == "pose" else X_TRUE.actInv(W.act(TIP_TRUE))
        for k, c in enumerate(COLS[: len(v)]):
            out[f"{name}:{c}"][i] = v[k]
    return out


def measured_experiment(kind, noise_q=None, sigma_t=None, sigma_r=None, N=30, seed=1):
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    rng = np.random.default_rng(seed)
    th = rng.uniform(-1.5, 1.5, (N, 6))

    def make():
        if kind == "pose":
            return MeasuredPoseLoop("m", "tool0", initial_base=GUESS, sigma_t=sigma_t, sigma_r=sigma_r)
        return MeasuredPointLoop("m", "tool0", initial_base=GUESS, sigma_t=sigma_t)

    zeros = {f"m:{c}": np.zeros(N) for c in COLS}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [make()])
    x = prob.nominal
    # the identifiable parameterisation: what calibrate estimates on nominal data
    res0 = calibrate(robot, JointLog(joints, th, None, None, _measurements(prob, x, th, kind)), [make()])
    names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("m.")]
    truth = x.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    ex = _measurements(prob, truth, th, kind)
    if sigma_t:
        ex = {
            k: v + rng.normal(scale=sigma_t if k[-1] in "xyz" and ":r" not in k else sigma_r, size=N)
            for k, v in ex.items()
        }
    thr = th + rng.normal(scale=noise_q, size=th.shape) if noise_q else th
    res = calibrate(robot, JointLog(joints, thr, None, None, ex), [make()], CalibrationOptions(noise=noise_q))
    truth[prob.loop_slices[0]] = np.concatenate([vec_of(X_TRUE), vec_of(Y_TRUE) if kind == "pose" else TIP_TRUE])
    return res, dict(zip(prob.names, truth))


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_measured_recovery(kind):
    res, truth = measured_experiment(kind)
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    assert not any("length scale" in n for n in res.notes)  # the sensor fixes the length
    dropped = dropped_names(res)
    assert {f"shoulder_pan_joint.{f}" for f in COLS} <= dropped  # absorbed by the sensor base
    # point: the tip (off the wrist_3 axis) is fitted before the identifiability analysis, so
    # the tilt of that axis is kept (27, as with the full pose minus the 3 orientation-only ones)
    assert len(est) == (30 if kind == "pose" else 27)


def test_measured_point_noise_within_four_sigma():
    res, truth = measured_experiment("point", noise_q=1e-5, sigma_t=1e-5, N=60, seed=2)
    est, err = estimated_errors(res, truth)
    assert np.abs(err / res.fit.std[est]).max() < 4.0


def test_measured_point_initialize_rigid_fit():
    """With every configuration, the sensor base is fitted exactly (Kabsch) from the nominal model."""
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    th = np.random.default_rng(0).uniform(-1.5, 1.5, (8, 6))
    loop = MeasuredPointLoop("m", "tool0", tip=TIP_TRUE)
    prob = build_problem(robot, JointLog(joints, th, None, None, {f"m:{c}": np.zeros(8) for c in COLS}), [loop])
    meas = loop.measurements(_measurements(prob, prob.nominal, th, "point"), np.arange(len(th)))
    TA, TB = prob.loop_poses(prob.nominal, 0)
    assert np.allclose(loop.initialize(TA, TB, meas), vec_of(X_TRUE), atol=1e-10)


UR10 = ERD + "ur_description/urdf/ur10_robot.urdf"
UR10_TIP = np.array([0.03, -0.02, 0.15])  # off the wrist_3 axis (tool0's origin is on it)


def _ur10_point_data(values, prob, th, tip=UR10_TIP):
    TA, TB = prob.loop_poses(values, 0, th)
    y, *_ = relative_point(TA, TB, tip)
    z = np.array([X_TRUE.actInv(v) for v in y])
    return {f"m:{c}": z[:, k].copy() for k, c in enumerate("xyz")}


def test_measured_point_default_tip_fit_ur10():
    """Default options, unknown tip: the tip is fitted before the identifiability analysis.

    With the tip left at tool0's origin (on the wrist_3 axis), the tilt of that
    axis (wrist_3_joint.rx; .rz is redundant with wrist_2_joint.offset anyway)
    would look redundant and be dropped.  The initializer fits the sensor base
    and the tip to all configurations at the nominal robot, so every
    identifiable robot parameter is estimated (the same set as with the true
    tip given as initial_tip) and recovered.
    """
    robot = robot_of(UR10)
    joints = robot.supporting_joints("tool0")
    rng = np.random.default_rng(3)
    N = 60
    th = rng.uniform(-np.pi, np.pi, (N, 6))
    zeros = {f"m:{c}": np.zeros(N) for c in COLS[:3]}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    opts = CalibrationOptions(noise=1e-9)  # the (known) joint noise: none
    # the identifiable set, from nominal data with the true tip given as the starting value
    ref = calibrate(
        robot,
        JointLog(joints, th, None, None, _ur10_point_data(prob.nominal, prob, th)),
        [MeasuredPointLoop("m", "tool0", initial_tip=UR10_TIP, sigma_t=1e-5)],
        opts,
    )
    names = [n for n, s in zip(ref.fit.names, ref.fit.status) if s == "estimated" and not n.startswith("m.")]
    assert "wrist_3_joint.rx" in names and len(names) == 18  # + 9 (base, tip) = 27
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    data = _ur10_point_data(truth, prob, th)
    res = calibrate(
        robot, JointLog(joints, th, None, None, data), [MeasuredPointLoop("m", "tool0", sigma_t=1e-5)], opts
    )
    truth[prob.loop_slices[0]] = np.concatenate([vec_of(X_TRUE), UR10_TIP])
    est, err = estimated_errors(res, dict(zip(prob.names, truth)))
    estimated = {res.fit.names[i] for i in est}
    assert set(names) <= estimated and "wrist_3_joint.rx" in estimated
    assert "wrist_3_joint.rx" not in dropped_names(res)
    assert {"m.tip_x", "m.tip_y", "m.tip_z"} <= estimated
    assert np.abs(err).max() < 1e-8


def test_measured_initialize_fits_base_and_tool():
    """At the nominal robot, initialize() recovers the unknown base and tip / tool frame exactly
    from all configurations; an explicit initial_tip / initial_tool is kept as given."""
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    th = np.random.default_rng(4).uniform(-1.5, 1.5, (12, 6))
    for kind in ("point", "pose"):
        cols = COLS if kind == "pose" else COLS[:3]
        zeros = {f"m:{c}": np.zeros(12) for c in cols}
        cls = MeasuredPoseLoop if kind == "pose" else MeasuredPointLoop
        prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [cls("m", "tool0")])
        TA, TB = prob.loop_poses(prob.nominal, 0)
        own = vec_of(Y_TRUE) if kind == "pose" else TIP_TRUE
        loop = cls("m", "tool0")
        meas = loop.measurements(_measurements(prob, prob.nominal, th, kind), np.arange(len(th)))
        p = loop.initialize(TA, TB, meas)
        assert np.allclose(p, np.concatenate([vec_of(X_TRUE), own]), atol=1e-9)
        assert np.array_equal(p, loop.initialize(TA, TB, meas))  # deterministic
        # known base: only the tip / tool
        loop = cls("m", "tool0", base=X_TRUE)
        assert np.allclose(loop.initialize(TA, TB, meas), own, atol=1e-9)
        # explicit initial value: kept, only the base is fitted
        guess = pin.SE3.Identity() if kind == "pose" else np.zeros(3)
        loop = (
            MeasuredPoseLoop("m", "tool0", initial_tool=guess)
            if kind == "pose"
            else MeasuredPointLoop("m", "tool0", initial_tip=guess)
        )
        p = loop.initialize(TA, TB, meas)
        assert np.allclose(p[6:], 0.0) and not np.allclose(p[:6], vec_of(X_TRUE), atol=1e-4)


def test_measured_missing_column_is_an_error():
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    lg = JointLog(joints, np.zeros((3, 6)), None, None, {"m:x": np.zeros(3), "m:y": np.zeros(3)})
    with pytest.raises(LoopError, match="m:z"):
        build_problem(robot, lg, [MeasuredPointLoop("m", "tool0")])


# ---------------------------------------------------------------- CLI specs
def test_specs():
    robot = robot_of(UR5)
    lp = parse_loop('point:frame=tool0,tip="0 0 0.1",name=ball', robot)
    assert isinstance(lp, PointLoop) and np.allclose(lp.tip, [0, 0, 0.1]) and lp.point is None
    assert [p.name for p in lp.parameters()] == ["ball.px", "ball.py", "ball.pz"]
    lp = parse_loop("point:frame=tool0,to=upper_arm_link", robot)
    assert lp.frame_b == "upper_arm_link" and len(lp.parameters()) == 6
    lp = parse_loop('plane:frame=tool0,normal="1 0 0",name=wall', robot)
    assert isinstance(lp, PlaneLoop) and np.allclose(lp.n_ref, [1, 0, 0])
    assert [p.name for p in lp.parameters()][-3:] == ["wall.nrx", "wall.nry", "wall.d"]
    lp = parse_loop("measured_pose:frame=tool0,sigma_t=1e-4,sigma_r=2e-4,name=trk", robot)
    assert isinstance(lp, MeasuredPoseLoop) and lp.scale_free is False
    assert np.allclose(np.diag(lp.measurement_cov), [1e-8] * 3 + [4e-8] * 3)
    assert lp.columns() == [f"trk:{c}" for c in COLS]
    lp = parse_loop('measured_point:frame=tool0,tip="0 0 0.1",base=identity', robot)
    assert isinstance(lp, MeasuredPointLoop) and lp.parameters() == []
    with pytest.raises(LoopError):
        parse_loop("plane:frame=tool0,tip=1 2", robot)


@pytest.mark.slow
def test_two_planes_sessions_by_loop_column():
    """Two planes (floor, wall) touched by one known tip; rows assigned by the log's `loop` column."""
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    tip = [0.0, 0.0, 0.1]

    def make():
        return [PlaneLoop("floor", "tool0", tip=tip), PlaneLoop("wall", "tool0", tip=tip, normal=[1.0, 0.0, 0.0])]

    q0 = np.atleast_2d(UR5_Q0)
    names = identifiable_names(robot, make(), q0, n=60)
    rng = np.random.default_rng(5)
    prob = CalibrationProblem(robot, joints, [LoopBlock(lp, q0, np.arange(1)) for lp in make()])
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    for bi, (b, sl) in enumerate(zip(prob.blocks, prob.loop_slices)):
        TA, TB = prob.loop_poses(truth, bi, q0)
        truth[sl] = b.loop.initialize(TA, TB)
    truth[prob.index["floor.nrx"]], truth[prob.index["floor.nry"]] = 0.05, -0.08
    truth[prob.index["wall.nrx"]], truth[prob.index["wall.nry"]] = -0.1, 0.07
    blocks = [self_motion(prob, truth, q0, 60, rng, block=bi) for bi in range(2)]
    log_ = JointLog(joints, np.vstack(blocks), None, np.repeat(["floor", "wall"], [len(b) for b in blocks]))
    res = calibrate(robot, log_, make())
    est, err = estimated_errors(res, dict(zip(prob.names, truth)))
    assert np.abs(err).max() < 1e-8
    for f in ("floor", "wall"):
        for g in ("nrx", "nry", "d"):
            assert res.fit.status[res.fit.names.index(f"{f}.{g}")] == "estimated"


def _ur10_tracker_experiment(noise_q: float, sigma_t: float, seed: int, N: int = 150, N_held: int = 100):
    """UR10 + true errors, tracker at X_TRUE measuring UR10_TIP; calibrations with default options
    (joint noise unknown, tracker noise given) and with plain least squares; held-out prediction
    error against the noise-free truth."""
    from closedloop.validation.kfold import closure_residuals

    robot = robot_of(UR10)
    joints = robot.supporting_joints("tool0")
    rng = np.random.default_rng(seed)
    th = rng.uniform(-np.pi, np.pi, (N + N_held, 6))
    zeros = {f"m:{c}": np.zeros(len(th)) for c in COLS[:3]}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    names = [n for n in prob.names if not n.startswith("m.") and n.split(".")[1] in COLS + ("offset",)]
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    data = _ur10_point_data(truth, prob, th)
    train = {k: v[:N] + rng.normal(0.0, sigma_t, N) for k, v in data.items()}
    held = {k: v[N:] for k, v in data.items()}
    readings = th[:N] + (rng.normal(0.0, noise_q, (N, 6)) if noise_q else 0.0)
    out = {}
    for label, opts in (("default", CalibrationOptions()), ("plain", CalibrationOptions(weighting="none"))):
        loop = MeasuredPointLoop("m", "tool0", sigma_t=sigma_t)
        res = calibrate(robot, JointLog(joints, readings, None, None, train), [loop], opts)
        pred = closure_residuals(res, robot, JointLog(joints, th[N:], None, None, held), [loop])
        out[label] = (res, pred["loops"][0]["rms_m"])
    return out


def test_tracker_noise_given_joint_noise_estimated_noise_free_joints():
    """Joints noise free, tracker noise given: the joint level is estimated near zero (variance
    components, closedloop.estimate.noise), so the weighting is the tracker's own and the default fit predicts
    held-out configurations as well as plain least squares (it used to read the tracker noise as joint
    noise and predict 4x worse)."""
    out = _ur10_tracker_experiment(0.0, 1e-5, seed=5)
    res, held = out["default"]
    _, held_plain = out["plain"]
    # joint noise adds at most ~ (5 urad x ~1 m)^2, a quarter of the tracker variance: at 450 residual rows
    # the variance estimate itself scatters by ~7 % of the tracker variance
    assert res.noise.sigma_estimated and res.noise.sigma < 5e-6
    assert held <= 1.1 * held_plain, (held, held_plain)
    assert held < 1e-5  # below the tracker noise itself: 150 configurations average it down
    assert abs(res.noise.chi2 / res.noise.dof - 1.0) < 0.2  # the tracker noise explains the residual


def test_tracker_and_joint_noise_both_present():
    """1e-4 rad joint noise beside a 1e-5 m tracker: the joint level is recovered (within 25 %) and the
    errors-in-variables fit predicts better than plain least squares."""
    out = _ur10_tracker_experiment(1e-4, 1e-5, seed=6)
    res, held = out["default"]
    _, held_plain = out["plain"]
    assert res.noise.sigma == pytest.approx(1e-4, rel=0.25)
    assert held < held_plain, (held, held_plain)
