"""HingeLoop (thesis 3.4.2) and PassiveChainLoop (3.4.3): Jacobians, elimination, recovery."""

from __future__ import annotations

import site
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from closedloop.calibration import CalibrationOptions, calibrate
from closedloop.data import JointLog
from closedloop.errors import LoopError
from closedloop.loops.hinge import HingeLoop
from closedloop.loops.passive import PassiveChainLoop
from closedloop.loops.spec import parse_loop
from closedloop.problem import CalibrationProblem, LoopBlock
from closedloop.robot import RobotModel
from closedloop.synthetic import close, self_motion
from closedloop.truth import draw_truth

ROBOTS = Path(site.getsitepackages()[0]) / "cmeel.prefix/share/example-robot-data/robots"
PANDA = ROBOTS / "panda_description/urdf/panda.urdf"
TASKS = Path(__file__).resolve().parents[1] / "closedloop" / "models" / "tasks"
TOOL = "panda_hand"
TH0 = np.array([[0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8]])
AXIS = (np.array([0.475, 0.45, 0.594]), np.array([0.0, 0.0, 1.0]))  # 0.45 m beside the hand at TH0
TILT = np.array([0.01, -0.02, 0.07, -0.07])  # true hinge: 2 cm off, ~0.1 rad tilted from AXIS


@pytest.fixture(scope="module")
def robot():
    return RobotModel.from_file(PANDA)


@pytest.fixture(scope="module")
def joints(robot):
    return robot.supporting_joints(TOOL)


def _problem(robot, joints, loop, theta):
    return CalibrationProblem(robot, joints, [LoopBlock(loop, np.atleast_2d(theta), np.arange(len(theta)))])


def _fd_jacobian_error(prob, x, h=1e-6):
    P = x.size
    J = prob.evaluate(x)[0].J.reshape(-1, P)
    worst = 0.0
    for k in range(P):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        fd = (prob.evaluate(xp, False)[0].r - prob.evaluate(xm, False)[0].r).ravel() / (2 * h)
        worst = max(worst, float(np.abs(fd - J[:, k]).max()))
    return worst / np.abs(J).max()


def _fd_readings_error(prob, x, h=1e-6):
    ev = prob.evaluate(x)[0]
    th = prob.blocks[0].theta
    worst = 0.0
    for j in range(th.shape[1]):
        tp, tm = th.copy(), th.copy()
        tp[:, j] += h
        tm[:, j] -= h
        fd = (prob.evaluate(x, False, [tp])[0].r - prob.evaluate(x, False, [tm])[0].r) / (2 * h)
        worst = max(worst, float(np.abs(fd - ev.Jq[:, :, j]).max()))
    return worst / np.abs(ev.Jq).max()


def _fd_gradient_error(prob, x, h=1e-6):
    """The reduced Jacobian gives the exact gradient of 1/2|r*|^2 anywhere (envelope theorem)."""
    ev = prob.evaluate(x)[0]
    P = x.size
    g = ev.J.reshape(-1, P).T @ ev.r.ravel()
    gfd = np.empty(P)
    for k in range(P):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        gfd[k] = 0.5 * (np.sum(prob.evaluate(xp, False)[0].r ** 2) - np.sum(prob.evaluate(xm, False)[0].r ** 2)) / (2 * h)
    return float(np.abs(g - gfd).max() / np.abs(g).max()), float(np.abs(ev.r).max())


def _estimated_errors(res, truth, prob):
    return {n: float(res.values[i] - truth[prob.index[n]])
            for i, (n, s) in enumerate(zip(res.names, res.status)) if s == "estimated"}


# ------------------------------------------------------------------ hinge
@pytest.fixture(scope="module")
def hinge_truth(robot, joints):
    """Identifiable robot errors, a tilted hinge, data walked on the true closure manifold."""
    rng = np.random.default_rng(1)
    lp = HingeLoop("door", TOOL, axis=AXIS)
    prob = _problem(robot, joints, lp, TH0)
    # which robot parameters the hinge loop identifies (nominal data)
    x = prob.nominal.copy()
    sl = prob.loop_slices[0]
    TA, TB = prob.loop_poses(x, 0)
    x[sl] = lp.initialize(TA, TB)
    th = self_motion(prob, x, TH0, 30, rng)
    res = calibrate(robot, JointLog(joints, th), [HingeLoop("door", TOOL, axis=AXIS)], CalibrationOptions())
    names = [n for n, s in zip(res.names, res.status) if s == "estimated" and not n.startswith("door.")]
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, names, rng).items():
        truth[prob.index[n]] = v
    TA, TB = prob.loop_poses(truth, 0)
    truth[sl] = lp.closing_parameters(TILT, pin.SE3(np.linalg.solve(TB[0], TA[0])))
    th = self_motion(prob, truth, TH0, 40, rng)
    return prob, truth, th


def test_hinge_jacobians_match_finite_differences(robot, joints, hinge_truth):
    _, truth, th = hinge_truth
    lp = HingeLoop("door", TOOL, axis=AXIS)
    prob = _problem(robot, joints, lp, th[::8])
    assert np.abs(prob.evaluate(truth, False)[0].r).max() < 1e-12  # closes: r* = 0 on the manifold
    assert _fd_jacobian_error(prob, truth) < 1e-6
    assert _fd_readings_error(prob, truth) < 1e-6
    x = truth.copy()
    x[prob.loop_slices[0]] += np.array([0.01, 0.02, -0.05, 0.03, 0.02, -0.01, 0.05, 0.02, -0.03])
    err, rmax = _fd_gradient_error(prob, x)
    assert rmax > 1e-3 and err < 1e-6


def test_hinge_angle_elimination_is_exact_far_from_closure(robot, joints, hinge_truth):
    """phi* minimises |r|: r* is orthogonal to dr/dphi, and no other phi does better."""
    _, truth, th = hinge_truth
    lp = HingeLoop("door", TOOL, axis=AXIS)
    prob = _problem(robot, joints, lp, th[:3])
    x = truth.copy()
    p = x[prob.loop_slices[0]] + np.array([0.02, -0.02, 0.1, 0.0, 0.02, 0.02, 0.1, 0.0, 0.0])
    x[prob.loop_slices[0]] = p
    TA, TB = prob.loop_poses(x, 0)
    phis = lp.solve_angles(TA, TB, p)
    H, G = lp.hinge(p), lp.grasp(p)
    for i, phi in enumerate(phis):
        M = pin.SE3(TB[i]).actInv(pin.SE3(TA[i]))
        cost = lambda a: float(np.sum(pin.log6((H * pin.SE3(pin.exp3(np.array([0, 0, a])), np.zeros(3)) * G)
                                               .actInv(M)).vector ** 2))
        grid = np.linspace(phi - 0.3, phi + 0.3, 601)
        assert cost(phi) <= min(cost(a) for a in grid) + 1e-15


def test_hinge_recovery_from_far_initial_guess(robot, joints, hinge_truth):
    """0.1 rad / 2 cm off on the hinge axis, 2 cm / 0.05 rad on the grasp; noise free -> 1e-8."""
    prob, truth, th = hinge_truth
    sl = prob.loop_slices[0]
    names = prob.names[sl]
    init = {n: 0.0 for n in names[:4]}  # the reference axis, ~0.1 rad and 2 cm from the true one
    for k, n in enumerate(names[4:]):
        init[n] = float(truth[sl][4 + k] + (0.02 if k < 2 else 0.05 * (-1) ** k))
    res = calibrate(robot, JointLog(joints, th), [HingeLoop("door", TOOL, axis=AXIS)],
                    CalibrationOptions(initial=init))
    assert res.converged
    err = _estimated_errors(res, truth, prob)
    assert all(n in err for n in names)  # every hinge parameter is estimated
    assert max(abs(v) for v in err.values()) < 1e-8, max(err.items(), key=lambda kv: abs(kv[1]))


def test_hinge_axis_from_circle_fit(robot, joints, hinge_truth):
    """initialize() on all configurations finds the line exactly; calibration from there recovers it."""
    prob, truth, th = hinge_truth
    sl = prob.loop_slices[0]
    ref = HingeLoop("door", TOOL, axis=AXIS)
    pt, dt = ref.line(truth[sl])
    fit = HingeLoop("door", TOOL)
    TA, TB = _problem(robot, joints, fit, th).loop_poses(truth, 0)
    pf, df = fit.line(fit.initialize(TA, TB))
    assert np.abs(pf - pt).max() < 1e-9 and abs(abs(df @ dt) - 1) < 1e-12
    # calibrate() initialises from every row at the nominal robot: the circle fit, then the solve
    fit = HingeLoop("door", TOOL)
    res = calibrate(robot, JointLog(joints, th), [fit], CalibrationOptions())
    assert res.converged
    ps, ds = fit.line(res.values[sl])
    assert np.abs(ps - pt).max() < 1e-8 and abs(abs(ds @ dt) - 1) < 1e-12
    assert abs(abs(res.value("door.radius")) - abs(truth[prob.index["door.radius"]])) < 1e-8


def test_hinge_needs_axis_or_arc():
    lp = HingeLoop("door", TOOL)
    with pytest.raises(LoopError, match="axis"):
        lp.initialize(np.eye(4)[None], np.eye(4)[None])


# ------------------------------------------------------------ passive chain
Q0 = np.array([0.3, 0.1])  # door opened 0.3 rad, handle turned 0.1 rad at the first logged row


@pytest.fixture(scope="module")
def door_truth(robot, joints):
    rng = np.random.default_rng(0)
    ref = PassiveChainLoop("door", TOOL, TASKS / "door.urdf", "grip", q0=Q0)
    ref.initialize(*_problem(robot, joints, ref, TH0).loop_poses(_problem(robot, joints, ref, TH0).nominal, 0))
    mk = lambda: PassiveChainLoop("door", TOOL, TASKS / "door.urdf", "grip", q0=Q0, pose=ref.P0)  # noqa: E731
    lp = mk()
    prob = _problem(robot, joints, lp, TH0)
    x = prob.nominal.copy()
    th = np.vstack([close(prob, x, TH0)[0], self_motion(prob, x, TH0, 30, rng)])
    res = calibrate(robot, JointLog(joints, th), [mk()], CalibrationOptions())
    est = [n for n, s in zip(res.names, res.status) if s == "estimated"]
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, [n for n in est if not n.startswith("door.")], rng).items():
        truth[prob.index[n]] = v
    for n in est:
        if n.startswith("door.") and n.count(".") == 2:  # task placements and grasp: +-5 mm / rad
            truth[prob.index[n]] += rng.uniform(-0.005, 0.005)
    th = np.vstack([close(prob, truth, TH0)[0], self_motion(prob, truth, TH0, 40, rng)])
    return prob, truth, th, mk, est


def test_passive_jacobians_match_finite_differences(robot, joints, door_truth):
    _, truth, th, mk, _ = door_truth
    prob = _problem(robot, joints, mk(), th[::8])
    assert np.abs(prob.evaluate(truth, False)[0].r).max() < 1e-12
    assert _fd_jacobian_error(prob, truth) < 1e-6
    assert _fd_readings_error(prob, truth) < 1e-6
    x = truth.copy()
    x[prob.loop_slices[0]] += np.random.default_rng(3).uniform(-0.01, 0.01, prob.loop_slices[0].stop
                                                                - prob.loop_slices[0].start)
    err, rmax = _fd_gradient_error(prob, x)
    assert rmax > 1e-3 and err < 1e-6


def test_passive_door_recovery(robot, joints, door_truth):
    prob, truth, th, mk, est = door_truth
    res = calibrate(robot, JointLog(joints, th), [mk()], CalibrationOptions())
    assert res.converged
    err = _estimated_errors(res, truth, prob)
    assert any(n.startswith("door.handle.") for n in err) and any(n.startswith("door.grasp.") for n in err)
    assert max(abs(v) for v in err.values()) < 1e-8, max(err.items(), key=lambda kv: abs(kv[1]))
    # the revolute joints' own rotations are their eliminated angles: dropped, never estimated
    assert res.status[res.names.index("door.hinge.rz")] == "dropped"
    assert res.status[res.names.index("door.handle.ry")] == "dropped"


def test_passive_solves_task_angles(robot, joints, door_truth):
    """The eliminated door angles reproduce the tool pose through the task model."""
    prob, truth, th, mk, _ = door_truth
    lp = mk()
    p = _problem(robot, joints, lp, th[:4])
    TA, TB = p.loop_poses(truth, 0)
    qs = lp.solve_angles(TA, TB, truth[p.loop_slices[0]])
    model = lp.task_model(truth[p.loop_slices[0]])
    data = model.createData()
    for i, q in enumerate(qs):
        pin.forwardKinematics(model, data, q)
        X = lp.pose(truth[p.loop_slices[0]]) * pin.updateFramePlacement(model, data, lp.fid)
        assert np.abs(X.homogeneous - TA[i]).max() < 1e-10


def test_passive_refuses_more_than_five_dof(tmp_path):
    links = "".join(f'<link name="l{i}"/>' for i in range(7))
    jts = "".join(f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/>'
                  f'<axis xyz="0 0 1"/><origin xyz="0.1 0 0"/><limit lower="-1" upper="1" effort="0" velocity="1"/>'
                  f'</joint>' for i in range(6))
    path = tmp_path / "arm6.urdf"
    path.write_text(f'<robot name="arm6">{links}{jts}</robot>')
    with pytest.raises(LoopError, match=r"arm6\.urdf has 6 passive DOF"):
        PassiveChainLoop("t", TOOL, path, "l6")


def test_passive_unknown_frame_and_file():
    with pytest.raises(LoopError, match="no frame 'knob'"):
        PassiveChainLoop("t", TOOL, TASKS / "door.urdf", "knob")
    with pytest.raises(LoopError, match="no such file"):
        PassiveChainLoop("t", TOOL, TASKS / "nope.urdf", "grip")


@pytest.mark.parametrize("task,dof", [("drawer.urdf", 1), ("crank.urdf", 2)])
def test_other_task_models_jacobians(robot, joints, task, dof):
    rng = np.random.default_rng(5)
    lp = PassiveChainLoop("t", TOOL, TASKS / task, "grip")
    assert lp.dof == dof
    prob = _problem(robot, joints, lp, TH0)
    x = prob.nominal.copy()
    lp.initialize(*prob.loop_poses(x, 0))
    sl = prob.loop_slices[0]
    x[sl] = rng.uniform(-0.003, 0.003, sl.stop - sl.start)
    th = self_motion(prob, x, TH0, 4, rng, stride=2)
    prob = _problem(robot, joints, lp, th)
    assert np.abs(prob.evaluate(x, False)[0].r).max() < 1e-12
    assert _fd_jacobian_error(prob, x) < 1e-6


def test_specs(robot):
    lp = parse_loop('hinge:frame=panda_hand,axis="0.5 0.4 0.6 0 0 1",name=door', robot)
    assert isinstance(lp, HingeLoop) and lp.name == "door" and np.allclose(lp.H0.rotation[:, 2], [0, 0, 1])
    lp = parse_loop(f'passive:frame=panda_hand,task={TASKS / "door.urdf"},task_frame=grip,q0="0.3 0.1"', robot)
    assert isinstance(lp, PassiveChainLoop) and lp.dof == 2 and np.allclose(lp.q0, Q0)
    with pytest.raises(LoopError, match="task_frame"):
        parse_loop(f'passive:frame=panda_hand,task={TASKS / "door.urdf"}', robot)
    with pytest.raises(LoopError, match="axis"):
        parse_loop('hinge:frame=panda_hand,axis="1 2 3"', robot)
