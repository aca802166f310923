"""Every analytic Jacobian column against central finite differences (1e-6 relative)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import yaml

from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem, LoopBlock


def fd_check(robot, loop, joints, rng, h=1e-5):
    theta = rng.uniform(-1.0, 1.0, (4, len(joints)))
    prob = CalibrationProblem(robot, joints, [LoopBlock(loop, theta, np.arange(4))])
    x = prob.nominal + rng.normal(0.0, 0.05, len(prob.nominal))  # away from nominal: exercises Jexp6 etc.
    sl = prob.loop_slices[0]
    if sl.stop > sl.start:  # closure near the data, as `calibrate` starts it (log6 is ill-conditioned near pi)
        TA, TB = prob.loop_poses(x, 0, theta[:1])
        x[sl] = loop.initialize(TA, TB) + rng.normal(0.0, 0.05, sl.stop - sl.start)
    ev = prob.evaluate(x)[0]
    J = ev.J.reshape(-1, x.size)
    num = np.zeros_like(J)
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = h
        num[:, k] = ((prob.evaluate(x + e, False)[0].r - prob.evaluate(x - e, False)[0].r) / (2 * h)).ravel()
    scale = np.abs(num).max()
    err = np.abs(J - num).max(axis=0) / np.maximum(np.abs(num).max(axis=0), 1e-2 * scale)
    Jq = ev.Jq.reshape(-1, len(joints))
    numq = np.zeros_like(Jq)
    for j in range(len(joints)):
        e = np.zeros_like(theta)
        e[:, j] = h
        numq[:, j] = (
            (prob.evaluate(x, False, [theta + e])[0].r - prob.evaluate(x, False, [theta - e])[0].r) / (2 * h)
        ).ravel()
    return prob.names, err, np.abs(Jq - numq).max() / np.abs(numq).max()


@pytest.mark.parametrize("frame_b", ["universe", "panda_link3"])
def test_urdf_weld_columns(panda, frame_b):
    """Placement (x..rz), offset, scale and closure columns; world and branch-to-branch welds."""
    names, err, errq = fd_check(
        panda, WeldLoop("w", "panda_hand", frame_b), panda.supporting_joints("panda_hand"), np.random.default_rng(0)
    )
    kinds = {n.split(".")[-1] for n in names}
    assert {"x", "y", "z", "rx", "ry", "rz", "offset", "scale"} <= kinds
    bad = {n: e for n, e in zip(names, err) if e > 1e-6}
    assert not bad, bad
    assert errq < 1e-6


def test_dh_and_hayati_columns(tmp_path):
    """D-H (eq. 4.1) and Hayati (eq. 4.2) rows, theta_off and k, including the last row's end frame."""
    rng = np.random.default_rng(1)
    rows = [
        {
            "name": f"j{i}",
            "s": float(rng.uniform(-0.3, 0.3)),
            "a": float(rng.uniform(-0.3, 0.3)),
            "alpha": float(rng.uniform(-2, 2)),
            "theta_off": float(rng.uniform(-1, 1)),
            "convention": "hayati" if i % 2 else "dh",
        }
        for i in range(1, 8)
    ]
    path = tmp_path / "chain.yaml"
    path.write_text(yaml.safe_dump({"name": "c", "closes": True, "joints": rows}))
    robot = RobotModel.from_file(path)
    loop = WeldLoop("closure", robot.dh.end_frame, closure=pin.SE3.Identity())
    names, err, errq = fd_check(robot, loop, robot.joint_names, rng)
    assert {"j7.s", "j7.a", "j7.alpha", "j2.k", "j3.theta_off"} <= set(names)
    bad = {n: e for n, e in zip(names, err) if e > 1e-6}
    assert not bad, bad
    assert errq < 1e-6


def test_half_turn_is_not_zero(panda):
    """The exact SE(3) log: a closure error of a half turn reads pi, not 0 (no small-angle vee)."""
    loop = WeldLoop("w", "panda_hand", closure=pin.SE3.Identity())
    T = np.eye(4)
    T[:3, :3] = pin.exp3(np.array([np.pi, 0.0, 0.0]))
    r = loop.evaluate(T[None], np.eye(4)[None], np.zeros(0)).r[0]
    assert abs(np.linalg.norm(r[3:]) - np.pi) < 1e-9
