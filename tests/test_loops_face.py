"""The face loop (a flat face sliding on a flat face, 3 equations): Jacobians, recovery, charts, refusals."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from support import central_difference_jacobian
from test_loops_point_plane_measured import (
    BAXTER,
    BAXTER_Q0,
    PANDA,
    PANDA_Q0,
    UR5,
    UR5_Q0,
    _fd_problem,
    estimated_errors,
    loop_joints,
    robot_of,
)

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.errors import LoopError
from closedloop.io.logs import JointLog
from closedloop.loops.face import FaceLoop
from closedloop.loops.plane import PlaneLoop
from closedloop.loops.spec import parse_loop
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.studies.identifiable import identifiable_names
from closedloop.studies.synthetic import self_motion
from closedloop.studies.truth import draw_truth

JAC_CASES = {
    "table": lambda: FaceLoop("f", "tool0"),
    "references": lambda: FaceLoop("f", "tool0", tip=[0.01, 0.02, 0.1], face=[0.2, 1.0, 0.3], normal=[1.0, 0.0, 1.0]),
    "two_branches": lambda: FaceLoop("f", "tool0", "upper_arm_link", face=[0.0, 0.0, -1.0]),
}
#: the palm's face and the table in the truth, off their nominal references
PALM = {"palm.mrx": 0.05, "palm.mry": -0.03, "palm.nrx": 0.02, "palm.nry": 0.01}


@pytest.mark.parametrize("case", sorted(JAC_CASES))
def test_jacobian_matches_central_differences(case):
    J, Jn = central_difference_jacobian(*_fd_problem(JAC_CASES[case]()))
    assert np.abs(J - Jn).max() <= 1e-6 * np.abs(J).max()


def _contact(loop: FaceLoop, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the contact is, by any parameterisation: A's face normal seen in B (N, 3) and the height of A's
    face point over B's plane (N,), each model with its own faces."""
    m, n, d = loop.face_normal(p[:2]), loop.normal(p[2:4]), p[4]
    RBA = np.swapaxes(TB[:, :3, :3], 1, 2) @ TA[:, :3, :3]
    y = np.einsum("nji,nj->ni", TB[:, :3, :3], TA[:, :3, :3] @ loop.tip + TA[:, :3, 3] - TB[:, :3, 3])
    return RBA @ m, y @ n - d


def _experiment(path, make, theta0, own, n, noise=None, seed=0, names_n=12, stride=1):
    """`closed_experiment` on a shorter walk: the truth in the identifiable parameterisation (read off a walk
    of `names_n` nominal configurations), `n` configurations along the true loop's self-motion, with joint
    noise; the calibration result, the truth by name, the readings and the true loop (its chart)."""
    robot = robot_of(path)
    joints = loop_joints(robot, make())
    theta0 = np.atleast_2d(theta0)
    rng = np.random.default_rng(seed)
    prob = CalibrationProblem(robot, joints, [LoopBlock(make(), theta0, np.arange(1))])
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, identifiable_names(robot, [make()], theta0, n=names_n), rng).items():
        truth[prob.index[k]] = v
    truth[prob.loop_slices[0]] = prob.blocks[0].loop.initialize(*prob.loop_poses(truth, 0, theta0))
    for k, v in own.items():
        truth[prob.index[k]] = v
    th = self_motion(prob, truth, theta0, n, rng, step=0.1, stride=stride)
    if noise:
        th = th + rng.normal(scale=noise, size=th.shape)
    res = calibrate(robot, JointLog(joints, th), [make()], CalibrationOptions(noise=noise))
    return res, dict(zip(prob.names, truth)), prob


def _contact_error(res, truth: dict[str, float], true_prob, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The calibrated contact minus the true one at readings `th` (A's face normal in B, 3 rows, and the
    height of A's face point over B's face, 1 row, per reading; (n, 4)), and the standard error of each
    from the fit's covariance (the calibrated contact's derivatives by central differences)."""
    prob = res.problem
    sl = prob.loop_slices[0]

    def contact(x: np.ndarray, problem, loop) -> np.ndarray:
        v, h = _contact(loop, *problem.loop_poses(x, 0, th), x[problem.loop_slices[0]])
        return np.c_[v, h]

    x_true = np.array([truth[n] for n in true_prob.names])
    c_true = contact(x_true, true_prob, true_prob.blocks[0].loop)
    c_cal = contact(res.fit.values, prob, prob.blocks[0].loop)
    sign = 1.0 if np.sum(c_cal[:, :3] * c_true[:, :3]) > 0 else -1.0  # (m, n, d) and (-m, -n, -d): one contact
    J = []
    for i in res.fit.estimated:
        h = 1e-6
        xp, xm = res.fit.values.copy(), res.fit.values.copy()
        xp[i] += h
        xm[i] -= h
        J.append(((contact(xp, prob, prob.blocks[0].loop) - contact(xm, prob, prob.blocks[0].loop)) / (2 * h)).ravel())
    Jm = np.array(J).T
    sd = np.sqrt(np.einsum("ij,jk,ik->i", Jm, res.fit.covariance, Jm)).reshape(c_cal.shape)
    assert sl.stop - sl.start == 5
    return c_cal - sign * c_true, sd


def test_palm_on_a_table_recovered_within_the_noise():
    """The Panda's hand pressed flat on a table (7 joints + 3 passive DOF: mobility 4), 1e-5 rad of joint
    noise: every estimated parameter within 4 standard errors of the truth, chi-square/dof near 1, and the
    contact itself (the face's normal in the world and its height over the table, at readings the fit never
    saw) as the truth's to within 4 of its standard errors propagated from the fit's covariance."""
    noise = 1e-5
    res, truth, true_prob = _experiment(PANDA, lambda: FaceLoop("palm", "panda_hand"), PANDA_Q0, PALM, 60, noise)
    assert res.converged and res.verdict.status != "failed", res.verdict.describe()
    est, err = estimated_errors(res, truth)
    names = [res.fit.names[i] for i in est]
    assert {f"palm.{f}" for f in ("mrx", "mry", "nrx", "nry", "d")} <= set(names)
    std = res.fit.std[est]
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.abs(err / std).max() < 4.0, max(zip(np.abs(err / std), names))
    assert 0.5 < res.noise.chi2 / res.noise.dof < 1.5
    th = np.array(PANDA_Q0) + np.random.default_rng(5).uniform(-0.3, 0.3, (20, 7))
    diff, sd = _contact_error(res, truth, true_prob, th)
    assert np.all(sd > 0) and np.abs(diff / sd).max() < 4.0, np.abs(diff / sd).max()
    assert np.abs(diff).max() < 1e-3  # and small: under 1 mm, 1 mrad


@pytest.mark.slow
def test_two_hands_face_to_face_baxter():
    """Baxter's grippers held pad to pad (a moving face: B is the other arm), exact data: the pads' contact
    recovered to the length scale (A's face normal in B and its height over B's face, over new readings)."""
    res, truth, true_prob = _experiment(
        BAXTER,
        lambda: FaceLoop("pads", "left_gripper", "right_gripper"),
        BAXTER_Q0,
        {"pads.mrx": 0.03, "pads.nry": -0.02},
        60,
        names_n=30,
    )
    assert res.fit.residuals_after[0].rms_m < 1e-9 and res.fit.residuals_after[0].rms_rad < 1e-9
    assert res.verdict.status != "failed", res.verdict.describe()
    th = np.array(BAXTER_Q0) + np.random.default_rng(2).uniform(-0.3, 0.3, (30, 14))
    diff, _ = _contact_error(res, truth, true_prob, th)
    assert np.abs(diff).max() < 1e-7, np.abs(diff).max()


def test_charts_flip_and_prepare():
    """Each normal round-trips through its chart; (m, n, d) and (-m, -n, -d) are one contact and `normalize`
    keeps the one nearer the references; `prepare` turns A's reference round when the data's face points
    the other way, and leaves the caller's loop as it was."""
    loop = FaceLoop("f", "tool0", face=[0.0, 1.0, 0.0], normal=[1.0, 0.0, 1.0])
    rng = np.random.default_rng(0)
    for _ in range(10):
        m, n = rng.normal(size=3), rng.normal(size=3)
        m, n = m / np.linalg.norm(m), n / np.linalg.norm(n)
        p = loop.angles(m, n, 0.3)
        assert np.allclose(loop.face_normal(p[:2]), m) and np.allclose(loop.normal(p[2:4]), n)
        q = loop.normalize(p)
        assert np.linalg.norm(q[:2]) + np.linalg.norm(q[2:4]) <= np.pi + 1e-12
        same = np.allclose(q, p)
        sign = 1.0 if same else -1.0
        assert np.allclose(loop.face_normal(q[:2]), sign * m) and np.allclose(loop.normal(q[2:4]), sign * n)
        assert np.isclose(q[4], sign * 0.3)
    # data: the tool's x axis held against -z of the world (a face whose outward normal is A's +x)
    R = np.array([pin.exp3(np.array([0.0, 0.0, a])) @ pin.exp3(np.array([0.0, np.pi / 2, 0.0])) for a in (0, 1, 2)])
    TA = np.tile(np.eye(4), (3, 1, 1))
    TA[:, :3, :3] = R
    TA[:, :3, 3] = [[0.1, 0.2, 0.5], [0.3, -0.1, 0.5], [0.0, 0.0, 0.5]]
    TB = np.tile(np.eye(4), (3, 1, 1))
    want = FaceLoop("f", "tool0", face=[-1.0, 0.0, 0.0])
    assert want.prepare(TA, TB) is not want and np.allclose(want.prepare(TA, TB).m_ref, [1.0, 0.0, 0.0])
    assert np.allclose(want.m_ref, [-1.0, 0.0, 0.0])  # the caller's loop untouched
    good = FaceLoop("f", "tool0", face=[1.0, 0.0, 0.0])
    assert good.prepare(TA, TB) is good
    p = good.initialize(TA, TB)
    assert np.allclose(p, [0.0, 0.0, 0.0, 0.0, 0.5]) and np.abs(good.evaluate(TA, TB, p).r).max() < 1e-12


def test_a_point_on_a_plane_is_no_face():
    """A tool point sliding and tilting on a table: no direction of the tool stays fixed, and the face loop
    says so before any fit, naming the plane loop."""
    robot = robot_of(UR5)
    loop = PlaneLoop("floor", "tool0", tip=[0.0, 0.0, 0.1])
    prob = CalibrationProblem(
        robot, robot.supporting_joints("tool0"), [LoopBlock(loop, np.atleast_2d(UR5_Q0), np.arange(1))]
    )
    x = prob.nominal.copy()
    x[prob.loop_slices[0]] = loop.initialize(*prob.loop_poses(x, 0))
    th = self_motion(prob, x, np.atleast_2d(UR5_Q0), 40, np.random.default_rng(1), step=0.1)
    Ts = list(prob.loop_poses(x, 0, th))
    msg = FaceLoop("floor", "tool0").mismatch(Ts)
    assert msg is not None and "--loop plane:frame=tool0,name=floor" in msg, msg


def test_spec_and_refusals():
    robot = robot_of(PANDA)
    lp = parse_loop(
        'face:frame=panda_hand,name=palm,tip=[0,0,0.1],face="0 0 1",normal=0/0/1'.replace("0/0/1", "[0,0,1]"), robot
    )
    assert isinstance(lp, FaceLoop) and lp.dim == 3 and lp.scale_free and np.allclose(lp.tip, [0, 0, 0.1])
    assert [p.name for p in lp.parameters()] == [f"palm.{f}" for f in ("mrx", "mry", "nrx", "nry", "d")]
    with pytest.raises(LoopError, match="face= must be a non-zero direction"):
        parse_loop("face:frame=panda_hand,face=[0,0,0]", robot)
    with pytest.raises(LoopError, match="needs frame"):
        parse_loop("face:to=panda_hand", robot)
