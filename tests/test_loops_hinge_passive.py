"""HingeLoop (thesis 3.4.2) and PassiveChainLoop (3.4.3): Jacobians, elimination, recovery."""

from __future__ import annotations

import site
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.errors import LoopError
from closedloop.io.logs import JointLog
from closedloop.loops.hinge import HingeLoop
from closedloop.loops.passive import PassiveChainLoop
from closedloop.loops.projection import SECANT_REACH
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.studies.synthetic import close, self_motion
from closedloop.studies.truth import draw_truth

ROBOTS = Path(site.getsitepackages()[0]) / "cmeel.prefix/share/example-robot-data/robots"
PANDA = ROBOTS / "panda_description/urdf/panda.urdf"
TASKS = Path(__file__).resolve().parents[1] / "closedloop" / "assets" / "tasks"
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
        gfd[k] = (
            0.5 * (np.sum(prob.evaluate(xp, False)[0].r ** 2) - np.sum(prob.evaluate(xm, False)[0].r ** 2)) / (2 * h)
        )
    return float(np.abs(g - gfd).max() / np.abs(g).max()), float(np.abs(ev.r).max())


def _estimated_errors(res, truth, prob):
    return {
        n: float(res.fit.values[i] - truth[prob.index[n]])
        for i, (n, s) in enumerate(zip(res.fit.names, res.fit.status))
        if s == "estimated"
    }


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
    names = [n for n, s in zip(res.fit.names, res.fit.status) if s == "estimated" and not n.startswith("door.")]
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, names, rng).items():
        truth[prob.index[n]] = v
    TA, TB = prob.loop_poses(truth, 0)
    truth[sl] = lp.closing_parameters(TILT, pin.SE3(np.linalg.solve(TB[0], TA[0])))
    th = self_motion(prob, truth, TH0, 40, rng)
    return prob, truth, th


@pytest.mark.slow
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
        cost = lambda a: float(
            np.sum(pin.log6((H * pin.SE3(pin.exp3(np.array([0, 0, a])), np.zeros(3)) * G).actInv(M)).vector ** 2)
        )
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
    res = calibrate(robot, JointLog(joints, th), [HingeLoop("door", TOOL, axis=AXIS)], CalibrationOptions(initial=init))
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
    ps, ds = res.loops[0].line(res.fit.values[sl])  # in the chart of the loop as calibrated (prepared)
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
    ref = ref.prepare(*_problem(robot, joints, ref, TH0).loop_poses(_problem(robot, joints, ref, TH0).nominal, 0))
    mk = lambda: PassiveChainLoop("door", TOOL, TASKS / "door.urdf", "grip", q0=Q0, pose=ref.P0)  # noqa: E731
    lp = mk()
    prob = _problem(robot, joints, lp, TH0)
    x = prob.nominal.copy()
    th = np.vstack([close(prob, x, TH0)[0], self_motion(prob, x, TH0, 30, rng)])
    res = calibrate(robot, JointLog(joints, th), [mk()], CalibrationOptions())
    est = [n for n, s in zip(res.fit.names, res.fit.status) if s == "estimated"]
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, [n for n in est if not n.startswith("door.")], rng).items():
        truth[prob.index[n]] = v
    for n in est:
        if n.startswith("door.") and n.count(".") == 2:  # task placements and grasp: +-5 mm / rad
            truth[prob.index[n]] += rng.uniform(-0.005, 0.005)
    th = np.vstack([close(prob, truth, TH0)[0], self_motion(prob, truth, TH0, 40, rng)])
    return prob, truth, th, mk, est


@pytest.mark.slow
def test_passive_jacobians_match_finite_differences(robot, joints, door_truth):
    _, truth, th, mk, _ = door_truth
    prob = _problem(robot, joints, mk(), th[::8])
    assert np.abs(prob.evaluate(truth, False)[0].r).max() < 1e-12
    assert _fd_jacobian_error(prob, truth) < 1e-6
    assert _fd_readings_error(prob, truth) < 1e-6
    x = truth.copy()
    x[prob.loop_slices[0]] += np.random.default_rng(3).uniform(
        -0.01, 0.01, prob.loop_slices[0].stop - prob.loop_slices[0].start
    )
    err, rmax = _fd_gradient_error(prob, x)
    assert rmax > 1e-3 and err < 1e-6


@pytest.mark.slow
def test_passive_door_recovery(robot, joints, door_truth):
    prob, truth, th, mk, est = door_truth
    res = calibrate(robot, JointLog(joints, th), [mk()], CalibrationOptions())
    assert res.converged
    err = _estimated_errors(res, truth, prob)
    assert any(n.startswith("door.handle.") for n in err) and any(n.startswith("door.grasp.") for n in err)
    assert max(abs(v) for v in err.values()) < 1e-8, max(err.items(), key=lambda kv: abs(kv[1]))
    # the revolute joints' own rotations are their eliminated angles: dropped, never estimated
    assert res.fit.status[res.fit.names.index("door.hinge.rz")] == "dropped"
    assert res.fit.status[res.fit.names.index("door.handle.ry")] == "dropped"


@pytest.mark.slow
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
    jts = "".join(
        f'<joint name="j{i}" type="revolute"><parent link="l{i}"/><child link="l{i + 1}"/>'
        f'<axis xyz="0 0 1"/><origin xyz="0.1 0 0"/><limit lower="-1" upper="1" effort="0" velocity="1"/>'
        f"</joint>"
        for i in range(6)
    )
    path = tmp_path / "arm6.urdf"
    path.write_text(f'<robot name="arm6">{links}{jts}</robot>')
    with pytest.raises(LoopError, match=r"arm6\.urdf has 6 passive DOF"):
        PassiveChainLoop("t", TOOL, path, "l6")


def test_passive_unknown_frame_and_file():
    with pytest.raises(LoopError, match="no frame 'knob'"):
        PassiveChainLoop("t", TOOL, TASKS / "door.urdf", "knob")
    with pytest.raises(LoopError, match="no such file"):
        PassiveChainLoop("t", TOOL, TASKS / "nope.urdf", "grip")


@pytest.mark.slow
@pytest.mark.parametrize("task,dof", [("drawer.urdf", 1), ("crank.urdf", 2)])
def test_other_task_models_jacobians(robot, joints, task, dof):
    rng = np.random.default_rng(5)
    lp = PassiveChainLoop("t", TOOL, TASKS / task, "grip")
    assert lp.dof == dof
    prob = _problem(robot, joints, lp, TH0)
    x = prob.nominal.copy()
    lp = lp.prepare(*prob.loop_poses(x, 0))  # the reference pose read off the first configuration
    prob = _problem(robot, joints, lp, TH0)
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
        parse_loop(f"passive:frame=panda_hand,task={TASKS / 'door.urdf'}", robot)
    with pytest.raises(LoopError, match="axis"):
        parse_loop('hinge:frame=panda_hand,axis="1 2 3"', robot)


# --------------------------------------- batched elimination vs the per-configuration reference
# The loops eliminate the passive values of every configuration at once (loops/projection.py).  The
# reference below is the former per-configuration loop (Gauss-Newton with pin.SE3 objects and numpy
# lstsq / pinv on each 6 x k system), kept verbatim in substance: the batched results must equal it.
def _ref_eliminate(M, pose, starts, integrate=None, tol=1e-13, max_iter=100, snap=None):
    if snap is not None:
        phi, *_ = _ref_eliminate(M, pose, starts, integrate, tol, max_iter)
        return _ref_eliminate(M, pose, [snap(phi)], integrate, tol, max_iter)
    integ = integrate if integrate is not None else (lambda a, d: a + d)
    best = None
    for phi in starts:
        X, Xd = pose(phi)
        E = X.actInv(M)
        r = pin.log6(E).vector
        if best is None or float(r @ r) < best[0]:
            best = (float(r @ r), np.array(phi, dtype=float), np.reshape(Xd, (6, -1)), E, r)
    c, phi, Xd, E, r = best
    Jl = pin.Jlog6(E)
    Jphi = -Jl @ E.inverse().action @ Xd
    it = 0
    secant, prev = integrate is None and phi.size == 1 and Jphi.shape[1] == 1, None  # one additive angle
    for it in range(1, max_iter + 1):
        step = -np.linalg.lstsq(Jphi, r, rcond=1e-12)[0]
        g = float(Jphi[:, 0] @ r)
        if secant and prev is not None and phi[0] != prev[0]:  # the secant step on the gradient
            h = (g - prev[1]) / (phi[0] - prev[0])
            if h > 0 and abs(g / h) <= SECANT_REACH * abs(step[0]):
                step = np.array([-g / h])
        if np.max(np.abs(step)) < tol:  # converged here: the step is not taken
            it -= 1
            break
        t, small = 1.0, np.max(np.abs(step)) < 1e-6
        while True:
            phin = integ(phi, t * step)
            Xn, Xdn = pose(phin)
            En = Xn.actInv(M)
            rn = pin.log6(En).vector
            cn = float(rn @ rn)
            if small or cn <= c or t < 1e-4:
                break
            t *= 0.5
        if not small and cn > c:
            break
        prev = (phi[0], g)
        phi, Xd, E, r, c = phin, np.reshape(Xdn, (6, -1)), En, rn, cn
        Jl = pin.Jlog6(E)
        Jphi = -Jl @ E.inverse().action @ Xd
        if np.max(np.abs(t * step)) < tol:
            break
    return phi, r, Jl, E, Jphi, it


def _ref_rows(M, phi, ri, Jl, E, Jphi, TAi, TBi):
    Pp = np.eye(6) - Jphi @ np.linalg.pinv(Jphi, rcond=1e-10)
    return Pp @ ri, Pp @ Jl, -Pp @ Jl @ TAi.actInv(TBi).action, -Pp @ Jl @ E.inverse().action


def _ref_hinge(lp, TA, TB, p):
    """(phi (N,), r, dA, dB, dp, largest iteration count), one configuration at a time."""
    H, G = lp.hinge(p), lp.grasp(p)
    rz = lambda a: pin.SE3(pin.exp3(np.array([0.0, 0.0, a])), np.zeros(3))  # noqa: E731
    XdG = (G.inverse().action @ np.array([0, 0, 0, 0, 0, 1.0]))[:, None]
    gen_h = np.zeros((6, 4))
    gen_h[:2, :2] = np.eye(2)  # H = H0 Rot(exp3(rx, ry, 0)) Trans(x, y, 0): right twists
    gen_h[:3, 2:] = np.cross(pin.Jexp3(np.array([p[2], p[3], 0.0]))[:, :2].T, [p[0], p[1], 0.0]).T
    gen_h[3:, 2:] = pin.Jexp3(np.array([p[2], p[3], 0.0]))[:, :2]
    gen_g = np.zeros((6, 5))
    gen_g[:3, 0], gen_g[:3, 1], gen_g[3:, 2:] = G.rotation.T[:, 0], G.rotation.T[:, 2], pin.Jexp3(p[6:9])
    out = [[] for _ in range(6)]
    for TAi, TBi in zip(map(pin.SE3, TA), map(pin.SE3, TB)):
        M = TBi.actInv(TAi)
        R = (H.actInv(M) * G.inverse()).rotation
        starts = [np.array([np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])])]
        q, g = H.actInv(M).translation, G.translation
        if np.hypot(g[0], g[1]) > 1e-9 and np.hypot(q[0], q[1]) > 1e-9:
            starts.append(np.array([np.arctan2(q[1], q[0]) - np.arctan2(g[1], g[0])]))
        phi, ri, Jl, E, Jphi, it = _ref_eliminate(M, lambda a: (H * rz(a[0]) * G, XdG), starts)
        r, dA, dB, dX = _ref_rows(M, phi, ri, Jl, E, Jphi, TAi, TBi)
        dp = np.hstack([dX @ (rz(phi[0]) * G).inverse().action @ gen_h, dX @ gen_g])
        for lst, v in zip(out, (phi[0], r, dA, dB, dp, it)):
            lst.append(v)
    return [np.array(v) for v in out[:5]] + [max(out[5])]


def _ref_passive(lp, TA, TB, p, cache):
    """(q (N, nq), r, dA, dB, dp), rows in order, each from the best of cache[i], the previous row's q, q0."""
    model = lp.task_model(p)
    data = model.createData()
    base = lp.pose(p)
    nj = lp.nj

    def pose(q):
        pin.computeJointJacobians(model, data, q)
        return base * pin.updateFramePlacement(model, data, lp.fid), pin.getFrameJacobian(
            model, data, lp.fid, pin.LOCAL
        )

    G = np.zeros((6 * nj, 6 * nj))
    for j in range(nj):
        G[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = pin.Jexp6(p[6 + 6 * j : 12 + 6 * j])
    out, prev = [[] for _ in range(5)], None
    for i, (TAi, TBi) in enumerate(zip(map(pin.SE3, TA), map(pin.SE3, TB))):
        M = TBi.actInv(TAi)
        starts = ([cache[i]] if cache is not None else []) + ([prev] if prev is not None else []) + [lp.q0]
        q, ri, Jl, E, Jq, _ = _ref_eliminate(
            M,
            pose,
            starts,
            lambda a, d: pin.integrate(model, a, d),
            snap=lambda a: pin.normalize(model, np.round(a, 8)),
        )
        prev = q
        r, dA, dB, dX = _ref_rows(M, q, ri, Jl, E, Jq, TAi, TBi)
        pose(q)
        Reg = pin.computeFrameKinematicRegressor(model, data, lp.fid, pin.LOCAL)
        dp = np.hstack(
            [dX @ data.oMf[lp.fid].inverse().action @ pin.Jexp6(p[0:6]), dX @ Reg @ G, dX @ pin.Jexp6(p[6 + 6 * nj :])]
        )
        for lst, v in zip(out, (q, r, dA, dB, dp)):
            lst.append(v)
    return [np.array(v) for v in out]


def _random_poses(rng, n):
    return np.array([pin.SE3.Random().homogeneous for _ in range(n)])


@pytest.mark.parametrize("off", [1e-3, 0.3])
def test_hinge_batched_elimination_equals_per_configuration_reference(off):
    """Random hinge, grasp, frames B and tool poses off the closure by `off` (rad / m twists)."""
    rng = np.random.default_rng(11)
    lp = HingeLoop("door", TOOL, axis=(rng.normal(size=3), rng.normal(size=3)))
    truth = np.concatenate([rng.normal(0, 0.05, 4), [0.4, 0.1], rng.normal(0, 0.3, 3)])
    H, G = lp.hinge(truth), lp.grasp(truth)
    TB = _random_poses(rng, 60)
    TA = np.array(
        [
            tb
            @ (
                H * pin.SE3(pin.exp3(np.array([0, 0, a])), np.zeros(3)) * G * pin.exp6(rng.normal(0, off, 6))
            ).homogeneous
            for tb, a in zip(TB, rng.uniform(-3.0, 3.0, 60))
        ]
    )
    p = truth + rng.normal(0, 0.02, 9)
    ev = lp.evaluate(TA, TB, p)
    phi, r, dA, dB, dp, it = _ref_hinge(lp, TA, TB, p)
    assert np.abs(lp.solve_angles(TA, TB, p) - phi).max() < 1e-10
    for a, b in ((ev.r, r), (ev.dA, dA), (ev.dB, dB), (ev.dp, dp)):
        assert np.abs(a - b).max() < 1e-10
    assert ev.iterations == it and np.abs(r).max() > 0.1 * off  # really off the closure
    assert np.array_equal(lp.residual(TA, TB, p), ev.r)  # the residual alone: the evaluation's, to the bit


PLANAR_TASK = """<robot name="sled"><link name="floor"/><link name="sled"/><link name="grip"/>
<joint name="glide" type="planar"><parent link="floor"/><child link="sled"/><axis xyz="0 0 1"/></joint>
<joint name="grip_joint" type="fixed"><parent link="sled"/><child link="grip"/><origin xyz="0.3 0.1 0.05"/>
</joint></robot>"""


@pytest.mark.parametrize("task", ["door.urdf", "drawer.urdf", "crank.urdf", "planar"])
def test_passive_batched_elimination_equals_per_configuration_reference(task, tmp_path):
    """A passive task moved along a path far from q0 (previous-row starts needed), twice: the
    second evaluation, at other parameters, starts from the first's solutions (warm starts).
    Revolute, prismatic and continuous (crank) task joints have batched kinematics; a planar joint
    (3 DOF, (x, y, cos, sin)) takes Pinocchio's, row by row."""
    from closedloop.loops.passive import ChainKinematics

    rng = np.random.default_rng(12)
    P0 = pin.SE3(pin.exp3(np.array([0.1, -0.2, 0.3])), np.array([0.6, 0.2, 0.3]))
    path = TASKS / task
    if task == "planar":
        path = tmp_path / "sled.urdf"
        path.write_text(PLANAR_TASK)
    lp = PassiveChainLoop("t", TOOL, path, "grip", pose=P0)
    assert (ChainKinematics.of(lp.model, lp.fid) is None) == (task == "planar")
    data = lp.model.createData()
    N, nv = 40, lp.model.nv
    # beyond pi from q0 at the end: the same poses are closer to q0 - 2 pi, which only the previous
    # rows' solutions (not q0) lead to
    path = np.linspace(0.0, 5.0, N)[:, None] * np.linspace(1.0, 0.5, nv)[None]
    TA = []
    for v in path:
        pin.forwardKinematics(lp.model, data, pin.integrate(lp.model, lp.q0, v))
        TF = pin.updateFramePlacement(lp.model, data, lp.fid)
        TA.append((P0 * TF * pin.exp6(rng.normal(0, 1e-3, 6))).homogeneous)
    TA, TB = np.array(TA), np.repeat(np.eye(4)[None], N, axis=0)
    cache = None
    for _ in range(2):
        p = rng.normal(0, 0.01, 12 + 6 * lp.nj)
        ev = lp.evaluate(TA, TB, p)
        q, r, dA, dB, dp = _ref_passive(lp, TA, TB, p, cache)  # no warm start: the loop keeps no state
        assert np.abs(lp.solve_angles(TA, TB, p) - q).max() < 1e-10
        for a, b in ((ev.r, r), (ev.dA, dA), (ev.dB, dB), (ev.dp, dp)):
            assert np.abs(a - b).max() < 1e-10


def test_projector_and_step_equal_the_svd_pseudo_inverse_also_when_rank_deficient():
    """k = 1..3 columns, well-conditioned and rank-deficient (parallel or zero columns) in one stack."""
    from closedloop.loops.projection import gauss_newton, projector

    rng = np.random.default_rng(13)
    for k in (1, 2, 3):
        J = rng.normal(size=(30, 6, k))
        J[:5, :, -1] = 0.0
        if k > 1:
            J[5:10, :, 1] = 2.0 * J[5:10, :, 0]  # rank k - 1
        ref = np.eye(6) - J @ np.linalg.pinv(J, rcond=1e-10)
        assert np.abs(projector(J) - ref).max() < 1e-12
    # one Gauss-Newton step on a pose that is linear in phi: X(phi) = exp6(B phi), M = X(phi_true)
    B = rng.normal(size=(6, 2))
    B[:, 1] = 3.0 * B[:, 0]  # the two passive joints move alike: the minimum-norm phi is the answer

    def pose(phi):
        X = np.array([pin.exp6(B @ f).homogeneous for f in phi])
        return X, np.array([pin.Jexp6(B @ f) @ B for f in phi])

    phi_true = np.array([[0.1, 0.2], [-0.3, 0.05]])
    M = pose(phi_true)[0]
    el = gauss_newton(M, pose, np.zeros((2, 2)))
    assert np.abs(el.r).max() < 1e-12
    assert np.abs(B @ el.phi.T - B @ phi_true.T).max() < 1e-12  # the same closure
    assert np.abs(el.phi[:, 1] - 3.0 * el.phi[:, 0]).max() < 1e-12  # minimum-norm along the pair's null space


def test_the_hinge_start_ignores_positions_off_the_arc():
    """Positions on an arc of 60 degrees with 1e-5 m of scatter, five of forty moved off it (corrupted
    readings, the first among them): `arc_inliers` finds exactly those five, and the fitted hinge axis is
    the arc's to 1e-4 (a least-squares fit of all forty tilts it by radians)."""
    from closedloop.loops.hinge import arc_inliers, fit_hinge_axis

    rng = np.random.default_rng(4)
    centre, radius = np.array([0.4, -0.2, 0.9]), 0.3
    R = pin.exp3(np.array([0.3, -0.2, 0.5]))
    phi = np.linspace(0.0, np.pi / 3, 40)
    P = centre + radius * (R @ np.array([np.cos(phi), np.sin(phi), np.zeros(40)])).T + rng.normal(0, 1e-5, (40, 3))
    bad = np.array([0, 7, 19, 23, 38])
    P[bad] += rng.uniform(-0.5, 0.5, (5, 3))
    keep = arc_inliers(P)
    np.testing.assert_array_equal(np.flatnonzero(~keep), bad)
    H = fit_hinge_axis([pin.SE3(R @ pin.exp3(np.array([0.0, 0.0, f])), p) for f, p in zip(phi, P)])
    assert abs(abs(H.rotation[:, 2] @ R[:, 2]) - 1.0) < 1e-4
    d = H.translation - centre
    assert np.linalg.norm(d - (d @ R[:, 2]) * R[:, 2]) < 1e-3
