"""Coupled joints (URDF ``<mimic>``) on a loop's path: the coupled joint moves with the joint it follows
(multiplier * angle + offset), its readings' Jacobian includes it, a calibration through it recovers the
truth, and the written URDF (which keeps the ``<mimic>``) predicts the fit."""

from __future__ import annotations

import re

import numpy as np
import pinocchio as pin
import pytest

from closedloop.assets.catalog import nominal_urdf
from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.errors import ModelError
from closedloop.io.logs import JointLog
from closedloop.loops.point import PointLoop
from closedloop.model.robot import RobotModel
from closedloop.output.urdf import model_frames, write_model
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.studies.synthetic import self_motion
from closedloop.studies.truth import draw_truth
from closedloop.validation.evaluate import evaluate_model

MULT, OFF = -0.7, 0.2
Q0 = np.array([[0.1, 0.3, -0.2, -1.8, 0.4, 0.8]])  # panda_joint1..5, 7 (6 follows 5)


def _mimic_panda(path, followed="panda_joint5"):
    text = nominal_urdf("panda")
    text = re.sub(
        r'(<joint name="panda_joint6"[^>]*>)',
        rf'\1<mimic joint="{followed}" multiplier="{MULT}" offset="{OFF}"/>',
        text,
        count=1,
    )
    path.write_text(text)
    return RobotModel.from_file(path)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    return _mimic_panda(tmp_path_factory.mktemp("mimic") / "panda.urdf")


def make():
    return PointLoop("socket", "panda_hand", initial_tip=[0.0, 0.0, 0.1])


def test_the_coupled_joint_follows(robot):
    joints = robot.supporting_joints("panda_hand")
    assert "panda_joint6" not in joints and joints == [f"panda_joint{i}" for i in (1, 2, 3, 4, 5, 7)]
    q = robot.configurations(Q0, joints)[0]
    assert q[robot.joint("panda_joint6").idx_q] == pytest.approx(MULT * Q0[0, 4] + OFF, abs=1e-15)
    # the same pose as the plain Panda with joint 6 set by hand
    plain = pin.buildModelFromXML(nominal_urdf("panda"))
    d, dm = plain.createData(), robot.model.createData()
    qp = pin.neutral(plain)
    for k, j in enumerate(joints):
        qp[plain.joints[plain.getJointId(j)].idx_q] = Q0[0, k]
    qp[plain.joints[plain.getJointId("panda_joint6")].idx_q] = MULT * Q0[0, 4] + OFF
    pin.framesForwardKinematics(plain, d, qp)
    pin.framesForwardKinematics(robot.model, dm, q)
    f = "panda_hand"
    assert np.abs(d.oMf[plain.getFrameId(f)].homogeneous - dm.oMf[robot.model.getFrameId(f)].homogeneous).max() < 1e-14


def test_reading_jacobian_includes_the_coupled_joint(robot):
    rng = np.random.default_rng(0)
    joints = robot.supporting_joints("panda_hand")
    th = Q0 + rng.uniform(-0.3, 0.3, (5, 6))
    prob = CalibrationProblem(robot, joints, [LoopBlock(make(), th, np.arange(5))])
    x = prob.nominal + rng.normal(scale=1e-3, size=len(prob.nominal))
    Jq = prob.evaluate(x, True)[0].Jq
    h = 1e-6
    for k in range(len(joints)):
        tp, tm = th.copy(), th.copy()
        tp[:, k] += h
        tm[:, k] -= h
        fd = (prob.evaluate(x, False, [tp])[0].r - prob.evaluate(x, False, [tm])[0].r) / (2 * h)
        assert np.abs(fd - Jq[:, :, k]).max() < 1e-7, joints[k]


def test_calibration_through_a_coupled_joint_recovers_the_truth_and_is_written(robot, tmp_path):
    rng = np.random.default_rng(1)
    joints = robot.supporting_joints("panda_hand")
    prob = CalibrationProblem(robot, joints, [LoopBlock(make(), Q0, np.arange(1))])
    x = prob.nominal.copy()
    x[prob.loop_slices[0]] = prob.initialize_loop(x, 0)
    th = self_motion(prob, x, Q0, 40, rng)
    res0 = calibrate(robot, JointLog(joints, th), [make()])
    names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("socket.")]
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, names, rng).items():
        truth[prob.index[n]] = v
    truth[prob.loop_slices[0]] = prob.initialize_loop(truth, 0)
    th = self_motion(prob, truth, Q0, 50, rng)
    log = JointLog(joints, th)
    res = calibrate(robot, log, [make()], CalibrationOptions(noise=1e-7))
    assert res.converged
    err = max(
        abs(res.fit.values[k] - truth[prob.index[res.fit.names[k]]])
        for k in res.fit.estimated
        if not res.fit.names[k].startswith("socket.")
    )
    assert err < 1e-8
    out = tmp_path / "cal.urdf"
    write_model(robot, res.as_dict(), out, frames=model_frames(res))
    assert '<mimic joint="panda_joint5"' in out.read_text()
    written = RobotModel.from_file(out)
    ev = evaluate_model(
        written,
        log,
        res.loops,
        calibration={n: res.value(n) for n in res.fit.names if n.startswith("socket.")},
        places=False,
    )
    assert np.abs(ev.residuals[0] - res.problem.evaluate(res.fit.values, False)[0].r).max() < 1e-9


def test_a_chain_of_mimics_is_refused(tmp_path):
    text = nominal_urdf("panda")
    text = re.sub(r'(<joint name="panda_joint6"[^>]*>)', r'\1<mimic joint="panda_joint5"/>', text, count=1)
    text = re.sub(r'(<joint name="panda_joint5"[^>]*>)', r'\1<mimic joint="panda_joint4"/>', text, count=1)
    (tmp_path / "p.urdf").write_text(text)
    robot = RobotModel.from_file(tmp_path / "p.urdf")
    with pytest.raises(ModelError, match="joint 'panda_joint6'.*mimics joint 'panda_joint5'.*itself coupled"):
        robot.supporting_joints("panda_hand")


def test_the_coupling_is_a_parameter_where_it_can_be_identified(robot, tmp_path):
    """``--identify ...,mimic``: the multiplier of the coupled joint, its Jacobian column exact, recovered from
    exact data with the placements, and written into the URDF's <mimic>."""
    rng = np.random.default_rng(2)
    joints = robot.supporting_joints("panda_hand")
    prob = CalibrationProblem(robot, joints, [LoopBlock(make(), Q0, np.arange(1))])
    k = prob.index["panda_joint6.mimic"]
    assert prob.params[k].kind == "mimic" and prob.nominal[k] == MULT
    th = Q0 + rng.uniform(-0.3, 0.3, (5, 6))
    fd_prob = CalibrationProblem(robot, joints, [LoopBlock(make(), th, np.arange(5))])
    x = fd_prob.nominal + rng.normal(scale=1e-3, size=len(fd_prob.nominal))
    J = fd_prob.evaluate(x, True)[0].J
    xp, xm = x.copy(), x.copy()
    xp[k] += 1e-6
    xm[k] -= 1e-6
    fd = (fd_prob.evaluate(xp, False)[0].r - fd_prob.evaluate(xm, False)[0].r) / 2e-6
    assert np.abs(fd - J[:, :, k]).max() < 1e-7
    x = prob.nominal.copy()
    x[prob.loop_slices[0]] = prob.initialize_loop(x, 0)
    th = self_motion(prob, x, Q0, 40, rng)
    opts = CalibrationOptions(identify=["placement", "offset", "mimic", "loop"])
    res0 = calibrate(robot, JointLog(joints, th), [make()], opts)
    names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("socket.")]
    assert "panda_joint6.mimic" in names
    truth = prob.nominal.copy()
    for n, v in draw_truth(robot, [n for n in names if n != "panda_joint6.mimic"], rng).items():
        truth[prob.index[n]] = v
    truth[k] = MULT * 1.03
    truth[prob.loop_slices[0]] = prob.initialize_loop(truth, 0)
    th = self_motion(prob, truth, Q0, 60, rng)
    log = JointLog(joints, th)
    res = calibrate(robot, log, [make()], CalibrationOptions(identify=opts.identify, noise=1e-7))
    assert res.converged and abs(res.value("panda_joint6.mimic") - MULT * 1.03) < 1e-8
    out = tmp_path / "cal.urdf"
    write_model(robot, res.as_dict(), out, frames=model_frames(res))
    written = RobotModel.from_file(out)
    assert written.mimic_coupling["panda_joint6"][0] == pytest.approx(res.value("panda_joint6.mimic"), abs=1e-15)
    ev = evaluate_model(
        written,
        log,
        res.loops,
        calibration={n: res.value(n) for n in res.fit.names if n.startswith("socket.")},
        places=False,
    )
    assert np.abs(ev.residuals[0] - res.problem.evaluate(res.fit.values, False)[0].r).max() < 1e-9
