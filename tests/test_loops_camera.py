"""Camera loop (a tool marker in one or two pinhole cameras): Jacobians, recovery, identifiability, noise."""

from __future__ import annotations

import site

import numpy as np
import pinocchio as pin
import pytest

from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate
from closedloop.errors import LoopError
from closedloop.io.logs import JointLog
from closedloop.loops.camera.loop import CameraLoop, camera_from_dlt, project
from closedloop.loops.common import relative_point
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import vec_of
from closedloop.studies.truth import draw_truth

ERD = site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/"
UR5 = ERD + "ur_description/urdf/ur5_robot.urdf"
BAXTER = ERD + "baxter_description/urdf/baxter.urdf"
COLS = ("x", "y", "z", "rx", "ry", "rz")

_robots: dict[str, RobotModel] = {}


def robot_of(path: str) -> RobotModel:
    if path not in _robots:
        _robots[path] = RobotModel.from_file(path)
    return _robots[path]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> pin.SE3:
    """A camera pose at `eye` with its optical axis (z) towards `target`."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return pin.SE3(np.column_stack([x, np.cross(z, x), z]), np.asarray(eye, float))


# true cameras around the UR5 (world frame), about 2 m from the base
X1 = look_at([2.0, 0.3, 0.8], [0.2, 0.0, 0.3])
X2 = look_at([1.9, -0.5, 1.0], [0.2, 0.0, 0.3])
K1 = np.array([800.0, 780.0, 320.0, 240.0])
K2 = np.array([900.0, 900.0, 330.0, 250.0])
TIP = np.array([0.02, -0.03, 0.12])  # the marker, off tool0's (wrist_3) axis


def pixels(prob, values, th, Xs, Ks, name="cam", tip=TIP) -> dict[str, np.ndarray]:
    """Exact pixel columns of the marker at the robot `values` (readings th), cameras Xs in B."""
    TA, TB = prob.loop_poses(values, 0, th)
    y, *_ = relative_point(TA, TB, tip)
    out = {}
    for c, (X, k) in enumerate(zip(Xs, Ks)):
        pc = (y - X.translation) @ X.rotation
        assert pc[:, 2].min() > 0.3  # every marker position in front of every camera
        uv, _, _ = project(pc, k, jacobian=False)
        out[f"{name}:u{c + 1}"], out[f"{name}:v{c + 1}"] = uv[:, 0].copy(), uv[:, 1].copy()
    return out


def true_own(Xs, Ks, name="cam", rig=False) -> dict[str, float]:
    out = {f"{name}.{f}": float(v) for f, v in zip(("tip_x", "tip_y", "tip_z"), TIP)}
    for c, (X, k) in enumerate(zip(Xs, Ks)):
        if not (rig and c == 1):
            out |= {f"{name}.cam{c + 1}.{f}": float(v) for f, v in zip(COLS, vec_of(X))}
        out |= {f"{name}.cam{c + 1}.{f}": float(v) for f, v in zip(("fx", "fy", "cx", "cy"), k)}
    return out


def camera_experiment(make, Xs, Ks, th, path=UR5, sigma_px=None, noise_q=None, seed=1, rig=False):
    """Truth in the identifiable parameterisation (what calibrate estimates on nominal data),
    pixels from the true robot and cameras, calibration from nominal with default starts."""
    robot = robot_of(path)
    loop = make()
    joints = sorted(
        {j for f in (loop.frame_a, loop.frame_b) for j in robot.supporting_joints(f)}, key=robot.joint_names.index
    )
    rng = np.random.default_rng(seed)
    zeros = {c: np.zeros(len(th)) for c in loop.columns()}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [make()])
    x = prob.nominal
    res0 = calibrate(robot, JointLog(joints, th, None, None, pixels(prob, x, th, Xs, Ks)), [make()])
    names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("cam.")]
    truth = x.copy()
    for k, v in draw_truth(robot, names, rng).items():
        truth[prob.index[k]] = v
    data = pixels(prob, truth, th, Xs, Ks)
    if sigma_px:
        data = {k: v + rng.normal(scale=sigma_px, size=v.size) for k, v in data.items()}
    thr = th + rng.normal(scale=noise_q, size=th.shape) if noise_q else th
    res = calibrate(robot, JointLog(joints, thr, None, None, data), [make()], CalibrationOptions(noise=noise_q))
    truth_by_name = dict(zip(prob.names, truth))
    truth_by_name |= {k: v for k, v in true_own(Xs, Ks, rig=rig).items() if k in truth_by_name}
    return res, truth_by_name


def estimated_errors(res, truth_by_name):
    est = [i for i, s in enumerate(res.fit.status) if s == "estimated"]
    return est, np.array([res.fit.values[i] - truth_by_name[res.fit.names[i]] for i in est])


def dropped_names(res) -> set[str]:
    return {d.name for d in res.identifiability.dropped}


def ur5_readings(N: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.5, 1.5, (N, 6))


# ---------------------------------------------------------------- Jacobians
JAC_CASES = {
    "mono_unknown_K": lambda: CameraLoop("c", "tool0", initial_poses=[X1]),
    "mono_known_K": lambda: CameraLoop("c", "tool0", K=[K1], initial_poses=[X1], sigma_px=0.3),
    "mono_known_tip": lambda: CameraLoop("c", "tool0", initial_poses=[X1], tip=TIP),
    "stereo": lambda: CameraLoop("c", "tool0", cameras=2, initial_poses=[X1, X2], initial_K=[K1, K2]),
    "stereo_rig": lambda: CameraLoop(
        "c", "tool0", cameras=2, K=[K1, None], initial_poses=[X1, None], rig=X1.inverse() * X2
    ),
    "stereo_known_pose": lambda: CameraLoop("c", "tool0", cameras=2, poses=[X1, None], initial_poses=[None, X2]),
    "stereo_on_link": lambda: CameraLoop(
        "c", "tool0", "upper_arm_link", cameras=2, initial_poses=[X1, X2], K=[K1, None]
    ),
}


@pytest.mark.parametrize("case", sorted(JAC_CASES))
def test_jacobian_matches_central_differences(case):
    """Every column (robot geometry, offsets, scales, camera poses, intrinsics, marker) to 1e-6 relative."""
    loop = JAC_CASES[case]()
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    rng = np.random.default_rng(0)
    N = 4
    th = rng.uniform(-1, 1, (N, 6))
    extra = {c: rng.normal(scale=100.0, size=N) for c in loop.columns()}
    prob = build_problem(robot, JointLog(joints, th, None, None, extra), [loop])
    x = prob.nominal + rng.normal(scale=0.05, size=len(prob.names))
    sc = prob.rp.scale_index()
    x[sc] = 1 + rng.normal(scale=0.05, size=sc.size)
    ev = prob.evaluate(x)[0]
    assert np.array_equal(ev.r, prob.evaluate(x, False)[0].r)  # the residual-only path agrees
    J = ev.J.reshape(-1, x.size)
    Jn = np.zeros_like(J)
    h = 1e-6
    for k in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (prob.evaluate(xp, False)[0].r.ravel() - prob.evaluate(xm, False)[0].r.ravel()) / (2 * h)
    # per column, relative to the column (a floor of 1 px per unit for columns that vanish)
    err = np.abs(J - Jn).max(axis=0) / np.maximum(np.abs(J).max(axis=0), 1.0)
    assert err.max() <= 1e-6, prob.names[int(np.argmax(err))]


# ---------------------------------------------------------------- noise-free recovery (UR5, world cameras)
def test_stereo_known_intrinsics_recovery():
    """(a) A stereo pair with known intrinsics, unknown poses: every estimated parameter to 1e-8.

    The pinhole projection is invariant under scaling, so the length scale is
    not fixed by the cameras (thesis 5.4, eq. 5.27): one robot length is fixed.
    """
    make = lambda: parse_loop(
        f'camera:frame=tool0,name=cam,cameras=2,K1="{" ".join(map(str, K1))}",'  # noqa: E731
        f'K2="{" ".join(map(str, K2))}",sigma_px=0.3',
        robot_of(UR5),
    )
    res, truth = camera_experiment(make, [X1, X2], [K1, K2], ur5_readings(40))
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    assert any("length scale" in n for n in res.notes)
    assert {f"shoulder_pan_joint.{f}" for f in COLS} <= dropped_names(res)  # absorbed by the camera poses
    own = [f"cam.cam{c}.{f}" for c in (1, 2) for f in COLS] + ["cam.tip_x", "cam.tip_y", "cam.tip_z"]
    assert all(res.fit.status[res.fit.names.index(n)] == "estimated" for n in own)
    assert len(est) == 32  # 17 robot (18 of the measured point, less the length scale) + 12 poses + 3 marker


def test_mono_unknown_intrinsics_recovery():
    """(b) One camera, unknown intrinsics and pose (started from the DLT): every parameter to 1e-8."""
    res, truth = camera_experiment(lambda: CameraLoop("cam", "tool0"), [X1], [K1], ur5_readings(40))
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    assert any("length scale" in n for n in res.notes)
    assert all(res.fit.status[res.fit.names.index(f"cam.cam1.{f}")] == "estimated" for f in ("fx", "fy", "cx", "cy"))
    assert len(est) == 30  # 17 robot + 6 pose + 4 intrinsics + 3 marker


def test_stereo_rig_fixes_length_scale():
    """A calibrated stereo head (known intrinsics and baseline) fixes the length scale: nothing is fixed."""
    loop = CameraLoop("cam", "tool0", cameras=2, K=[K1, K2], rig=X1.inverse() * X2)
    assert loop.scale_free is False
    assert CameraLoop("cam", "tool0", cameras=2, K=[K1, K2]).scale_free is True
    res, truth = camera_experiment(
        lambda: CameraLoop("cam", "tool0", cameras=2, K=[K1, K2], rig=X1.inverse() * X2),
        [X1, X2],
        [K1, K2],
        ur5_readings(40),
        rig=True,
    )
    est, err = estimated_errors(res, truth)
    assert np.abs(err).max() < 1e-8
    assert not any("length scale" in n for n in res.notes)
    assert len(est) == 27  # 18 robot + 6 rig pose + 3 marker
    assert "cam.cam2.x" not in res.fit.names


# ---------------------------------------------------------------- pixel noise
@pytest.mark.parametrize("cameras", [1, 2])
def test_pixel_noise_within_four_sigma(cameras):
    """0.3 px pixel noise (+1e-5 rad joint noise): every estimated parameter within 4 standard errors."""
    if cameras == 1:
        make, Xs, Ks = (lambda: CameraLoop("cam", "tool0", sigma_px=0.3)), [X1], [K1]
    else:
        make, Xs, Ks = (lambda: CameraLoop("cam", "tool0", cameras=2, K=[K1, K2], sigma_px=0.3)), [X1, X2], [K1, K2]
    res, truth = camera_experiment(make, Xs, Ks, ur5_readings(80, seed=2), sigma_px=0.3, noise_q=1e-5, seed=2)
    assert res.converged
    est, err = estimated_errors(res, truth)
    std = res.fit.std[est]
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.abs(err / std).max() < 4.0
    assert 0.7 < res.noise.chi2 / res.noise.dof < 1.3
    assert len(est) >= 25


# ---------------------------------------------------------------- a camera on a robot frame
def test_stereo_head_on_baxter():
    """A stereo pair on Baxter's head (frame B = head, moved by head_pan) tracking the left gripper."""
    rng = np.random.default_rng(4)
    N = 60
    th = np.column_stack(
        [
            rng.uniform(-0.3, 0.3, N),  # head_pan
            np.array([0.3, -0.5, -0.5, 1.5, 0.3, 0.8, 0.2]) + rng.uniform(-0.4, 0.4, (N, 7)),
        ]
    )
    # cameras in the head frame, 6 cm either side of its x axis, looking ahead and down at the workspace
    Xs = [look_at([0.12, 0.06, 0.08], [0.8, 0.35, -0.5]), look_at([0.12, -0.06, 0.08], [0.8, 0.35, -0.5])]
    make = lambda: CameraLoop("cam", "left_gripper", "head", cameras=2, K=[K1, K2])  # noqa: E731
    res, truth = camera_experiment(make, Xs, [K1, K2], th, path=BAXTER)
    est, err = estimated_errors(res, truth)
    # exact data: what is left is round-off amplified by this rig's conditioning: 2e-10 with the frame poses
    # of the very Pinocchio calls that made the data, 2.3e-8 with 1e-15 rad added to the readings or with
    # the poses read off the kinematic regressors (1e-15 m from Pinocchio's)
    assert np.abs(err).max() < 1e-7
    assert res.problem.joints == [
        "head_pan",
        "left_s0",
        "left_s1",
        "left_e0",
        "left_e1",
        "left_w0",
        "left_w1",
        "left_w2",
    ]
    # only the arm base relative to the head pan axis is seen: the head_pan placement and offset are absorbed
    # (by left_s0's placement and the cameras), one length sets the scale
    assert {f"head_pan.{f}" for f in ("x", "y", "rx", "ry", "rz", "offset")} <= dropped_names(res) | {res.scale.gauge}
    assert any("length scale" in n for n in res.notes)
    estimated = {res.fit.names[i] for i in est}
    assert {f"cam.cam{c}.{f}" for c in (1, 2) for f in COLS} <= estimated
    assert len(est) == 40  # 25 arm + 12 camera poses + 3 marker


# ---------------------------------------------------------------- the linear start
def test_initialize_recovers_cameras_at_the_nominal_robot():
    """With exact pixels of the nominal robot, initialize() returns the true cameras and marker
    (DLT / PnP + Gauss-Newton); with fewer than six configurations it falls back to the pose guess."""
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    th = ur5_readings(12, seed=5)
    for K, init_K in (([None], None), ([K1], None), ([None], [K1 * 1.1])):
        loop = CameraLoop("cam", "tool0", K=K, initial_K=init_K)
        prob = build_problem(robot, JointLog(joints, th, None, None, {c: np.zeros(12) for c in loop.columns()}), [loop])
        uv = loop.measurements(pixels(prob, prob.nominal, th, [X1], [K1]), np.arange(len(th)))
        TA, TB = prob.loop_poses(prob.nominal, 0)
        p = loop.initialize(TA, TB, uv)
        ref = np.concatenate([vec_of(X1)] + ([K1] if K[0] is None else []) + [TIP])
        assert np.allclose(p, ref, atol=1e-7), (K, init_K)
        assert np.array_equal(p, loop.initialize(TA, TB, uv))  # deterministic
    # a stereo head with a known rig and unknown intrinsics of camera 2: its K from the DLT as well
    loop = CameraLoop("cam", "tool0", cameras=2, K=[K1, None], rig=X1.inverse() * X2)
    prob = build_problem(robot, JointLog(joints, th, None, None, {c: np.zeros(12) for c in loop.columns()}), [loop])
    uv = loop.measurements(pixels(prob, prob.nominal, th, [X1, X2], [K1, K2]), np.arange(len(th)))
    TA, TB = prob.loop_poses(prob.nominal, 0)
    assert np.allclose(loop.initialize(TA, TB, uv), np.concatenate([vec_of(X1), K2, TIP]), atol=1e-7)
    # the DLT alone: exact on exact data
    TA, TB = prob.loop_poses(prob.nominal, 0)
    y, *_ = relative_point(TA, TB, TIP)
    uv = np.column_stack([v for k, v in pixels(prob, prob.nominal, th, [X1], [K1]).items()])
    Xf, kf = camera_from_dlt(y, uv, None)
    assert np.allclose(vec_of(Xf), vec_of(X1), atol=1e-9) and np.allclose(kf, K1, atol=1e-6)
    assert camera_from_dlt(y[:5], uv[:5], None) is None  # fewer than six points
    # five configurations: no DLT, the given guess is the start
    guess = X1 * pin.SE3(pin.exp3(np.array([0.02, -0.01, 0.03])), np.array([0.03, 0.02, -0.05]))
    loop = CameraLoop("cam", "tool0", K=[K1], initial_poses=[guess], initial_tip=TIP)
    prob = build_problem(robot, JointLog(joints, th[:5], None, None, {c: np.zeros(5) for c in loop.columns()}), [loop])
    uv = loop.measurements(pixels(prob, prob.nominal, th[:5], [X1], [K1]), np.arange(5))
    TA, TB = prob.loop_poses(prob.nominal, 0)
    p = loop.initialize(TA, TB, uv)
    assert np.allclose(p[:6], vec_of(X1), atol=1e-8) and np.array_equal(p[6:], TIP)  # given tip kept


# ---------------------------------------------------------------- specs, errors, reporting
def test_spec():
    robot = robot_of(UR5)
    lp = parse_loop(
        'camera:frame=tool0,name=eye,cameras=2,K1="800 780 320 240",K2_0="900 900 330 250",'
        'pose1="2 0.3 0.8 0 0 0",sigma_px=0.5',
        robot,
    )
    assert isinstance(lp, CameraLoop) and lp.cameras == 2 and lp.dim == 4
    assert lp.columns() == ["eye:u1", "eye:v1", "eye:u2", "eye:v2"]
    names = [p.name for p in lp.parameters()]
    assert names[:6] == [f"eye.cam1.{f}" for f in COLS] and names[6:12] == [f"eye.cam2.{f}" for f in COLS]
    assert names[12:] == [
        "eye.cam2.fx",
        "eye.cam2.fy",
        "eye.cam2.cx",
        "eye.cam2.cy",
        "eye.tip_x",
        "eye.tip_y",
        "eye.tip_z",
    ]
    assert [p.unit for p in lp.parameters()][12:16] == ["px"] * 4
    assert np.allclose(lp.measurement_cov, 0.25 * np.eye(4))
    assert lp.translation_rows == () and lp.rotation_rows == () and lp.pixel_rows == (0, 1, 2, 3)
    assert lp.scale_free
    lp = parse_loop('camera:frame=tool0,to=upper_arm_link,tip="0 0 0.1",K1="800 800 320 240"', robot)
    assert lp.frame_b == "upper_arm_link" and [p.name for p in lp.parameters()] == [f"camera.cam1.{f}" for f in COLS]
    lp = parse_loop('camera:frame=tool0,cameras=2,rig="0.1 0 0 0 0 0",K1="800 800 320 240",K2="800 800 320 240"', robot)
    assert not lp.scale_free and len(lp.parameters()) == 9


@pytest.mark.parametrize(
    "spec, key",
    [
        ("camera:to=tool0", "frame"),
        ("camera:frame=tool0,cameras=3", "cameras"),
        ('camera:frame=tool0,K1="800 800 320"', "K1"),
        ('camera:frame=tool0,K1="-800 800 320 240"', "K1"),
        ('camera:frame=tool0,K2="800 800 320 240"', "K2"),
        ('camera:frame=tool0,K1="800 800 320 240",K1_0="800 800 320 240"', "K1_0"),
        ('camera:frame=tool0,pose1="1 2 3"', "pose1"),
        ('camera:frame=tool0,rig="0 0 0 0 0 0"', "rig"),
        ('camera:frame=tool0,cameras=2,rig="0.1 0 0 0 0 0",pose2="1 0 0 0 0 0"', "pose"),
        ("camera:frame=tool0,sigma_px=-1", "sigma_px"),
        ("camera:frame=tool0,sigma_px=abc", "sigma_px"),
        ("camera:frame=tool0,focal=800", "focal"),
    ],
)
def test_bad_spec_one_line_error(spec, key):
    with pytest.raises(LoopError) as exc:
        parse_loop(spec, robot_of(UR5))
    msg = str(exc.value)
    assert "\n" not in msg and key in msg and ("camera" in msg)


def test_missing_column_is_a_one_line_error():
    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    lg = JointLog(joints, np.zeros((3, 6)), None, None, {f"cam:{c}": np.zeros(3) for c in ("u1", "v1", "u2")})
    with pytest.raises(LoopError) as exc:
        build_problem(robot, lg, [CameraLoop("cam", "tool0", cameras=2)])
    assert "cam:v2" in str(exc.value) and "cam:u1" not in str(exc.value) and "\n" not in str(exc.value)
    lg.extra["cam:v2"] = np.array([1.0, np.nan, 2.0])
    with pytest.raises(LoopError, match="row.s. 2"):
        build_problem(robot, lg, [CameraLoop("cam", "tool0", cameras=2)])


def test_residual_stats_in_pixels():
    """The report's closure statistics for a camera loop are image-point errors in pixels."""
    from types import SimpleNamespace

    from closedloop.calibration.pipeline import residual_stats
    from closedloop.problem.problem import BlockEval

    loop = CameraLoop("cam", "tool0", cameras=2)
    r = np.array([[3.0, 4.0, 0.0, 0.0], [0.0, 0.0, 6.0, 8.0]])
    (s,) = residual_stats(SimpleNamespace(blocks=[SimpleNamespace(loop=loop)]), [BlockEval(r, None, None)])
    assert np.isclose(s.max_px, 10.0) and np.isclose(s.rms_px, np.sqrt((25 + 100) / 4))
    assert s.rms_m is None and s.rms_rad is None
    assert loop.describe()["residual_unit"] == "px"
