"""The thesis's hand-eye system without MuJoCo: a UR5 and a two-camera head (each camera on its pan joint).

Exact pixels of the true robot + true cameras, truth in the identifiable
parameterisation (only the robot parameters a calibration on nominal data
estimates are perturbed), as in tests/test_loops_camera.py.  Shared by
tests/test_loops_camera_head.py and benchmarks/camera_head_mc.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scratch import scratch_dir

from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate
from closedloop.io.logs import JointLog
from closedloop.loops.camera.loop import CameraLoop
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import vec_of
from closedloop.sims.camera_scene import MARKER, head_urdf, mujoco_intrinsics, pan_towards
from closedloop.studies.truth import draw_truth

FRAMES = ["cam_left_optical", "cam_right_optical"]
ARM = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
Q0 = np.array([0.0, -1.3, 1.6, -1.9, -1.57, 0.0])
K_TRUE = [
    mujoco_intrinsics() + np.array([3.0, -2.0, 4.0, -3.0]),
    mujoco_intrinsics() + np.array([-2.0, 1.0, -5.0, 2.0]),
]
MOUNT = [
    pin.SE3(pin.exp3(np.array([0.01, -0.02, 0.015])), np.array([0.004, -0.003, 0.005])),
    pin.SE3(pin.exp3(np.array([-0.012, 0.01, -0.02])), np.array([-0.003, 0.002, -0.004])),
]
_robots: dict[float, RobotModel] = {}


def head_robot(verge: float = 0.0) -> RobotModel:
    if verge not in _robots:
        path = scratch_dir("head_") / "head.urdf"
        path.write_text(head_urdf(verge))
        _robots[verge] = RobotModel.from_file(path)
    return _robots[verge]


def head_readings(robot: RobotModel, N: int, seed: int, jitter: float = 0.12) -> np.ndarray:
    """(N, 8) readings in robot.joint_names order: random arm poses, each pan towards the nominal marker
    (+ U(-jitter, jitter) rad), keeping poses with the marker in front of both cameras."""
    rng = np.random.default_rng(seed)
    m = robot.model
    d = m.createData()
    names = robot.joint_names
    out = []
    while len(out) < N:
        th = np.zeros(len(names))
        th[[names.index(j) for j in ARM]] = Q0 + rng.uniform(-0.6, 0.6, 6)
        q = robot.configurations(th[None], names)[0]
        pin.framesForwardKinematics(m, d, q)
        x = d.oMf[m.getFrameId("tool0")].act(MARKER)
        ok = True
        for side in ("left", "right"):
            th[names.index(f"cam_{side}_pan")] = pan_towards(robot, q, names, x, side) + rng.uniform(-jitter, jitter)
        q = robot.configurations(th[None], names)[0]
        pin.framesForwardKinematics(m, d, q)
        for f in FRAMES:
            pc = d.oMf[m.getFrameId(f)].actInv(x)
            ok &= pc[2] > 0.3 and abs(pc[1] / pc[2]) < 0.45
        if ok:
            out.append(th)
    return np.array(out)


def truth_pixels(problem, values: np.ndarray, theta: np.ndarray, loop_name: str = "cam", D=None) -> dict:
    """Exact pixel columns of the true cameras (MOUNT, K_TRUE, distortion D) at robot `values`."""
    truth = CameraLoop(loop_name, "tool0", camera_frames=FRAMES, K=K_TRUE, poses=MOUNT, tip=MARKER, D=D)
    cols = truth.columns()
    Ts = problem.loop_frame_poses(values, 0, theta)
    uv = truth.residual_frames(Ts, np.zeros(0), np.zeros((len(theta), len(cols))))  # the residual at zero pixels
    return {c: uv[:, k].copy() for k, c in enumerate(cols)}


def true_own(loop_name: str = "cam", D=None, dist=()) -> dict[str, float]:
    out = {f"{loop_name}.{f}": float(v) for f, v in zip(("tip_x", "tip_y", "tip_z"), MARKER)}
    for c in range(2):
        out |= {
            f"{loop_name}.cam{c + 1}.{f}": float(v) for f, v in zip(("x", "y", "z", "rx", "ry", "rz"), vec_of(MOUNT[c]))
        }
        out |= {f"{loop_name}.cam{c + 1}.{f}": float(v) for f, v in zip(("fx", "fy", "cx", "cy"), K_TRUE[c])}
        for i, f in enumerate(("k1", "k2", "p1", "p2", "k3")):
            if f in dist:
                out[f"{loop_name}.cam{c + 1}.{f}"] = float(D[c][i])
    return out


@dataclass
class HeadCase:
    robot: RobotModel
    theta: np.ndarray
    truth: dict  # name -> true value (identifiable parameterisation)
    truth_values: np.ndarray  # the robot at the truth (problem order)
    gauge: str | None = None  # the length the nominal-data calibration held (unperturbed in the truth)


def head_case(
    make,
    N: int = 60,
    seed: int = 1,
    verge: float = 0.0,
    D=None,
    dist=(),
    jitter: float = 0.12,
    options: CalibrationOptions | None = None,
) -> HeadCase:
    """Readings and the truth: robot parameters that a nominal-data calibration estimates are perturbed."""
    robot = head_robot(verge)
    th = head_readings(robot, N, seed, jitter)
    names = robot.joint_names
    zeros = {c: np.zeros(N) for c in make().columns()}
    prob = build_problem(robot, JointLog(names, th, None, None, zeros), [make()])
    x = prob.nominal
    res0 = calibrate(
        robot,
        JointLog(names, th, None, None, truth_pixels(prob, x, th, D=D)),
        [make()],
        options or CalibrationOptions(robust=None),
    )
    robot_names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("cam.")]
    truth = x.copy()
    for k, v in draw_truth(robot, robot_names, np.random.default_rng(seed + 1000)).items():
        truth[prob.index[k]] = v
    by_name = dict(zip(prob.names, truth)) | {k: v for k, v in true_own(D=D, dist=dist).items() if k in prob.index}
    return HeadCase(robot, th, by_name, truth, res0.scale.gauge)


def run_head(
    case: HeadCase,
    make,
    sigma_px: float | None = None,
    noise_q: float | None = None,
    seed: int = 0,
    D=None,
    options: CalibrationOptions | None = None,
):
    """Calibrate from noisy readings/pixels of `case`; returns the result and (estimated index, errors)."""
    rng = np.random.default_rng(seed)
    names = case.robot.joint_names
    zeros = {c: np.zeros(len(case.theta)) for c in make().columns()}
    prob = build_problem(case.robot, JointLog(names, case.theta, None, None, zeros), [make()])
    data = truth_pixels(prob, case.truth_values, case.theta, D=D)
    if sigma_px:
        data = {k: v + rng.normal(scale=sigma_px, size=v.size) for k, v in data.items()}
    th = case.theta + rng.normal(scale=noise_q, size=case.theta.shape) if noise_q else case.theta
    res = calibrate(
        case.robot,
        JointLog(names, th, None, None, data),
        [make()],
        options or CalibrationOptions(noise=noise_q, robust=None),
    )
    est = [i for i, s in enumerate(res.fit.status) if s == "estimated"]
    err = np.array([res.fit.values[i] - case.truth[res.fit.names[i]] for i in est])
    return res, est, err
