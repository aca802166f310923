"""Simulated data WITH model error: the estimator tests whether joint noise explains the residual.

A UR5 with placement errors carries a tool point a tracker measures (its frame and the point unknown).
The joint readings the calibration gets are not the joints' true angles: the truth is the reading plus
a configuration-dependent term the model cannot represent (an elastic joint under gravity, a gear-ratio
error, a cyclic encoder error), plus 1 urad of reading noise.  Held out: 60 other configurations.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.analysis.accuracy import predict_from_result
from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import EIV, NOISE_MODEL, PLAIN, SANDWICH, build_problem, calibrate
from closedloop.estimate.model_error import ENCODER_NOISE, neighbour_correlation, noise_test
from closedloop.io.logs import JointLog
from closedloop.loops.measured import MeasuredPointLoop
from closedloop.model.robot import RobotModel
from closedloop.records import CalibrationOptions
from closedloop.studies.truth import draw_truth
from closedloop.validation.kfold import closure_residuals

X_TRUE = pin.SE3(pin.exp3(np.array([0.1, -0.2, 2.0])), np.array([1.5, 0.3, 0.2]))
TIP_TRUE = np.array([0.01, -0.02, 0.1])


def elastic(th: np.ndarray) -> np.ndarray:
    """Shoulder and elbow bent by gravity: a deflection proportional to the gravity torque's shape."""
    e = np.zeros_like(th)
    e[:, 1] = 4e-3 * np.cos(th[:, 1])
    e[:, 2] = 2.5e-3 * np.cos(th[:, 1] + th[:, 2])
    return e


def gear(th: np.ndarray) -> np.ndarray:
    """Gear ratios 0.3 % off on the base and elbow joints (joint scales are not identified by default)."""
    e = np.zeros_like(th)
    e[:, 0] = 3e-3 * th[:, 0]
    e[:, 2] = 3e-3 * th[:, 2]
    return e


def cyclic(th: np.ndarray) -> np.ndarray:
    """A cyclic encoder error on every joint (twice per turn): no geometric parameter represents it."""
    return 1e-3 * np.sin(2.0 * th + 0.3)


def no_error(th: np.ndarray) -> np.ndarray:
    return np.zeros_like(th)


@pytest.fixture(scope="module")
def ur5():
    robot = RobotModel.from_file(ROBOTS["ur5"].path)
    return robot, robot.supporting_joints("tool0")


def dataset(robot, joints, error, n, rng, truth=None, noise=1e-6):
    """Readings and tracker positions of `n` random configurations; the truth drawn once (`truth`)."""
    th = rng.uniform(-1.5, 1.5, (n, len(joints)))
    zeros = {f"m:{c}": np.zeros(n) for c in "xyz"}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    if truth is None:
        names = [p.name for p in prob.params if p.kind == "placement"]
        truth = prob.nominal.copy()
        for k, v in draw_truth(robot, names, rng).items():
            truth[prob.index[k]] = v
    TA, TB = prob.loop_poses(truth, 0, th + error(th))
    meas = np.array([X_TRUE.actInv(pin.SE3(TB[i]).actInv(pin.SE3(TA[i])).act(TIP_TRUE)) for i in range(n)])
    readings = th + rng.normal(scale=noise, size=th.shape)
    return JointLog(joints, readings, None, None, {f"m:{c}": meas[:, k] for k, c in enumerate("xyz")}), truth


def held_out_rms(res, robot, log_) -> float:
    return closure_residuals(res, robot, log_, [MeasuredPointLoop("m", "tool0")])["loops"][0]["rms_m"]


@pytest.mark.parametrize("error", [elastic, gear, cyclic])
def test_model_error_is_found_and_the_plain_fit_kept(ur5, error):
    robot, joints = ur5
    rng = np.random.default_rng(3)
    train, truth = dataset(robot, joints, error, 80, rng)
    test, _ = dataset(robot, joints, error, 60, rng, truth)
    loops = [MeasuredPointLoop("m", "tool0")]
    res = calibrate(robot, train, loops)
    ev = res.noise.model_error
    assert not ev["noise_explains"] and ev["joint_noise_implied"] > 2 * ENCODER_NOISE
    assert res.noise.estimator == PLAIN and res.noise.error_bars == SANDWICH
    assert "joint noise does not explain the residual" in res.noise.estimator_reason
    plain = calibrate(robot, train, loops, CalibrationOptions(weighting="none"))
    eiv = calibrate(robot, train, loops, CalibrationOptions(choose_estimator=False))
    assert eiv.noise.estimator == EIV and eiv.noise.error_bars == NOISE_MODEL
    # the workspace prediction propagates, and names, the covariance the calibration trusts
    assert predict_from_result(res).error_bars == SANDWICH and predict_from_result(eiv).error_bars == NOISE_MODEL
    figures = {k: held_out_rms(r, robot, test) for k, r in (("default", res), ("none", plain), ("eiv", eiv))}
    assert figures["default"] <= 1.02 * min(figures["none"], figures["eiv"]), figures


def test_joint_noise_alone_keeps_errors_in_variables(ur5):
    """Data drawn from the noise model (50 urad of reading noise): the hypothesis holds, nothing changes."""
    robot, joints = ur5
    rng = np.random.default_rng(4)
    train, _ = dataset(robot, joints, no_error, 80, rng, noise=5e-5)
    res = calibrate(robot, train, [MeasuredPointLoop("m", "tool0")])
    ev = res.noise.model_error
    assert ev["noise_explains"]
    assert ev["joint_noise_implied"] == pytest.approx(5e-5, rel=0.3)
    assert abs(ev["neighbour_correlation"]) < 0.3  # independent noise: no structure across the workspace
    assert res.noise.estimator == EIV and res.noise.error_bars == NOISE_MODEL and res.noise.weighting == "noise"
    assert "joint noise explains the residual" in res.noise.estimator_reason


def test_a_given_noise_is_what_the_residual_is_tested_against(ur5):
    """Given 1 mrad (a coarse encoder), the cyclic 1 mrad error is within it: errors in variables kept."""
    robot, joints = ur5
    rng = np.random.default_rng(5)
    train, _ = dataset(robot, joints, cyclic, 80, rng)
    res = calibrate(robot, train, [MeasuredPointLoop("m", "tool0")], CalibrationOptions(noise=1e-3))
    assert res.noise.model_error["joint_noise_tested"] == pytest.approx(1e-3)
    assert res.noise.model_error["noise_explains"] and res.noise.estimator == EIV


def test_noise_test_limits():
    """chi-square per dof (sigma_hat / sigma_0)^2 against 1 + 3 sqrt(2 / dof)."""
    t = noise_test(1.1e-4, 1e-4, 200, 0.0)
    assert t.chi2_per_dof == pytest.approx(1.21) and t.limit == pytest.approx(1.3) and t.holds
    assert not noise_test(1.2e-4, 1e-4, 200, 0.0).holds  # 1.44 > 1.3


def test_neighbour_correlation_sees_a_smooth_misfit(ur5):
    """Independent residuals ~0, a residual that is a smooth function of the configuration near 1."""
    robot, joints = ur5
    rng = np.random.default_rng(6)
    th = rng.uniform(-1.5, 1.5, (400, 6))
    zeros = {f"m:{c}": np.zeros(400) for c in "xyz"}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    smooth = np.column_stack([np.sin(th[:, 0]), np.cos(th[:, 1]), np.sin(th[:, 2] + th[:, 1])]).ravel()
    noise = rng.standard_normal(1200)
    assert neighbour_correlation(prob, smooth) > 0.6
    assert abs(neighbour_correlation(prob, noise)) < 0.15


def test_error_bars_hold_under_model_error(ur5):
    """Eight calibrations on fresh configurations of the same robot with the cyclic encoder error: the
    sandwich standard errors against the spread of the estimates, mean z^2 within [0.5, 2]."""
    robot, joints = ur5
    rng = np.random.default_rng(11)
    _, truth = dataset(robot, joints, cyclic, 10, rng)
    runs = []
    for _ in range(8):
        log_, _ = dataset(robot, joints, cyclic, 80, rng, truth)
        res = calibrate(robot, log_, [MeasuredPointLoop("m", "tool0")])
        assert res.noise.error_bars == SANDWICH
        runs.append({res.fit.names[k]: (res.fit.values[k], res.fit.std[k]) for k in res.fit.estimated})
    names = [n for n in set.intersection(*(set(r) for r in runs)) if not n.startswith("m.")]
    z2 = []
    for n in names:
        x = np.array([r[n][0] for r in runs])
        se = np.array([r[n][1] for r in runs])
        if np.all(np.isfinite(se)):
            z2.append(np.mean(((x - x.mean()) / se) ** 2) * len(runs) / (len(runs) - 1))
    assert len(z2) >= 12
    assert 0.5 <= np.mean(z2) <= 2.0, np.mean(z2)
