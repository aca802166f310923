"""Model error in the predicted accuracy (`closedloop.analysis.accuracy`, Model error): the estimators'
disagreement judged against its noise, and a calibration whose data carry more error than the nominal
model has, judged against an independent measurement of the true robot.

The robots come from the robot zoo (`tests/zoo.py`: errors on every joint origin, a generator independent
of closedloop's parametrization).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
import zoo

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.analysis.accuracy import PriorTolerance, followed_frames, judge_disagreement, predict_from_result
from closedloop.calibration.verdict import judge_workspace
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop


def test_disagreement_beyond_the_noise_is_model_error():
    """R = |d|^2 / E|d|^2 under the noise model; above 1 + 3 sqrt(2 / nu) the share beyond the noise,
    sqrt(1 - 1 / R), is model error; within it, none."""
    noise = np.diag([3.0, 4.0, 0.0])  # the shift's covariance factor: E|d|^2 = 25, nu = 625 / 337
    dof = 25.0**2 / (3.0**4 + 4.0**4)
    limit = 1.0 + 3.0 * np.sqrt(2.0 / dof)
    me = judge_disagreement(np.array([3.0, 4.0, 0.0]), noise)  # exactly the noise's size
    assert me.ratio == pytest.approx(1.0) and me.dof == pytest.approx(dof) and me.limit == pytest.approx(limit)
    assert not me.found and me.share == 0.0
    me = judge_disagreement(np.array([30.0, 40.0, 0.0]), noise)  # ten times the noise's size
    assert me.ratio == pytest.approx(100.0) and me.share == pytest.approx(np.sqrt(0.99))
    assert judge_disagreement(np.array([1.0, 0.0, 0.0]), np.zeros((3, 0))).share == 0.0  # no noise: no test


def _rigid_rms(P: np.ndarray, Q: np.ndarray) -> float:
    """RMS of P - (R Q + t) after the best rigid fit of Q onto P (the tracker's frame is not known)."""
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - mp).T @ (Q - mq))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return float(np.sqrt(np.mean(np.sum((P - mp - (Q - mq) @ R.T) ** 2, axis=1))))


@pytest.mark.slow
def test_model_error_larger_than_the_nominal_models_never_makes_the_robot_worse():
    """A UR5 whose nominal model is within 0.3 mm of the truth (up to 0.08 mm, 0.08 mrad per joint origin,
    0.15 mrad zeros; the maker's tolerance, 0.1 mm, 0.1 mrad and 0.2 mrad, given as the prior), one socket touched with face errors of up to 1 mm
    per contact (a contact that seats anywhere on a 1 mm face), 1e-5 rad of joint noise.  An independent
    tracker measures the true tool at 100 random configurations: where the calibrated model predicts it
    more than 10 % worse than the nominal model (after the best rigid fit of each), the verdict is failed."""
    prior = PriorTolerance(length_m=1e-4, angle_rad=1e-4, offset_rad=2e-4)
    judged = []
    for seed in (0, 2, 3):
        case = zoo.make_case("ur5", "point", n=60, sigma=0.0, seed=seed, err_m=8e-5, err_rad=8e-5, offset_rad=1.5e-4)
        offsets = np.array([case.true_offsets[j] for j in case.joints])
        kin = zoo.Kin(case.true_model, case.joints)
        socket = case.meta["geo"]["T0"].translation
        rng = np.random.default_rng(seed + 100)
        rows = []
        for th in case.q_true:  # each contact moved onto its own point of the socket's 1 mm face
            at = socket + rng.uniform(-1e-3, 1e-3, 3)

            def on_face(q, at=at):
                return kin.pose(q).translation - at, kin.jacobian(q, pin.LOCAL_WORLD_ALIGNED)[:3]

            q = zoo._project(on_face, th, case.lower - 1.0, case.upper + 1.0)
            assert q is not None
            rows.append(q - offsets + rng.normal(scale=1e-5, size=q.shape))
        robot = RobotModel.from_file(case.nominal_urdf)
        loops = [parse_loop(s, robot) for s in case.loop_specs]
        res = calibrate(robot, JointLog(list(case.joints), np.array(rows)), loops, CalibrationOptions())
        acc = predict_from_result(res, prior=prior)
        verdict = judge_workspace(res.verdict, acc)  # as calibrate judges: the prediction against the nominal's
        # the tracker: the true tool at random readings, and where each model puts it
        readings = rng.uniform(case.lower, case.upper, (100, len(case.joints))) - offsets
        tracker = np.array([kin.pose(q).translation for q in readings + offsets])
        nominal = zoo.Kin(pin.buildModelFromUrdf(str(case.nominal_urdf)), case.joints)
        at_nominal = np.array([nominal.pose(q).translation for q in readings])
        x = np.asarray(res.fit.values, dtype=float)
        (item,) = followed_frames(res.problem, x)
        state = res.problem.rp.apply(x[: res.problem.n_robot])
        fid = res.problem.robot.frame_id(item.frame_a)
        T = res.problem.frame_kinematics(state, readings, [fid], False)[fid][0]
        at_calibrated = T[:, :3, :3] @ item.tip + T[:, :3, 3]
        nominal_rms, calibrated_rms = _rigid_rms(tracker, at_nominal), _rigid_rms(tracker, at_calibrated)
        assert nominal_rms < 3e-4  # the nominal model is within 0.3 mm
        judged.append((verdict.status, nominal_rms, calibrated_rms))
        if calibrated_rms > 1.1 * nominal_rms:
            assert verdict.status == "failed", judged
            assert any("does not make the robot more accurate" in r for r in verdict.reasons)
    assert any(c > 1.1 * n for _, n, c in judged), judged  # the face errors do make the calibration worse
