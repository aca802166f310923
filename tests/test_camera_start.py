"""The camera loop's start from rays (loops.camera_start.ray_start): one unknown point, one hand camera."""

from __future__ import annotations

import site

import numpy as np
import pinocchio as pin
import pytest

from closedloop.calibration.pipeline import build_problem
from closedloop.io.logs import JointLog
from closedloop.loops.camera import start as camera_start
from closedloop.loops.camera.loop import CameraLoop
from closedloop.model.robot import RobotModel

UR5 = site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
K = np.array([600.0, 600.0, 319.5, 239.5])
X = pin.SE3(pin.exp3(np.array([0.02, -0.03, 0.01])), np.array([0.03, -0.05, 0.04]))  # camera in tool0
Q_DOWN = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.from_file(UR5)


def board_point_loop(robot: RobotModel, seed: int, n: int = 30):
    """A camera loop of one world point on the table seen by a camera on tool0 (exact pixels), its poses, truth."""
    rng = np.random.default_rng(seed)
    P = np.array([0.55, 0.05, 0.0]) + rng.uniform(-0.1, 0.1, 3) * [1.0, 1.0, 0.0]
    th = Q_DOWN + rng.uniform(-0.35, 0.35, (8 * n, 6))
    joints = robot.supporting_joints("tool0")
    zeros = np.zeros(len(th))
    probe = build_problem(
        robot,
        JointLog(joints, th, None, None, {"b:u1": zeros, "b:v1": zeros}),
        [CameraLoop("b", "universe", "tool0", K=[K])],
    )
    Tc = probe.loop_frame_poses(probe.nominal, 0)[1] @ X.homogeneous
    pc = np.einsum("nji,nj->ni", Tc[:, :3, :3], P - Tc[:, :3, 3])
    uv = K[:2] * pc[:, :2] / pc[:, 2:] + K[2:]
    keep = np.flatnonzero((pc[:, 2] > 0.15) & np.all((uv > 0) & (uv < [640, 480]), axis=1))[:n]
    assert keep.size == n
    prob = build_problem(
        robot,
        JointLog(joints, th[keep], None, None, {"b:u1": uv[keep, 0], "b:v1": uv[keep, 1]}),
        [CameraLoop("b", "universe", "tool0", K=[K])],
    )
    return prob.blocks[0].loop, prob.loop_frame_poses(prob.nominal, 0), P, prob.blocks[0].meas


def test_ray_fit_exact_at_the_true_rotation(robot):
    """At the true camera rotation the marker and the camera position follow exactly (zero ray distance)."""
    loop, Ts, P, uv = board_point_loop(robot, 0)
    y0, RFA, *_ = camera_start.relative_point(Ts[0], Ts[1], np.zeros(3))
    m = np.column_stack([(uv[:, 0] - K[2]) / K[0], (uv[:, 1] - K[3]) / K[1], np.ones(len(y0))])
    cost, t, tX, front = camera_start.ray_fit(X.rotation[None], RFA, y0, m)
    assert cost[0] < 1e-20 and front[0] == 1.0
    np.testing.assert_allclose(t[0], P, atol=1e-9)
    np.testing.assert_allclose(tX[0], X.translation, atol=1e-9)


@pytest.mark.parametrize("seed", [*range(6), 14])  # 5 and 14: the DLT-only start ran off (camera km away)
def test_start_recovers_point_and_camera_without_a_guess(robot, seed):
    loop, Ts, P, uv = board_point_loop(robot, seed)
    p = loop.initialize_frames(Ts, uv)
    np.testing.assert_allclose(loop.tip_point(p), P, atol=1e-8)
    Xs = loop.camera_pose(p, 0)
    np.testing.assert_allclose(Xs.translation, X.translation, atol=1e-8)
    assert np.linalg.norm(pin.log3(Xs.rotation @ X.rotation.T)) < 1e-8
