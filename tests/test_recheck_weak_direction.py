"""A re-check at the solution re-solves through the plain residual (floor truncation only) and then the weighted
fit; the plain fit may move a long way along a combination the data barely see (on the SO-101 arm, two joint
origins along one line: 0.93 m each way for a cost within the noise), and the weighted fit, which truncates
that direction, would hold the move.  The weighted fit starts from the plain solution with the directions it
truncates at the start set back to the start's (`residual.below_noise_reset`)."""

from __future__ import annotations

import numpy as np

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import example_robot_data_dir
from closedloop.calibration import solve
from closedloop.estimate.lm import scaled_svd
from closedloop.estimate.residual import ResidualFunction
from closedloop.io.logs import JointLog
from closedloop.loops import PointLoop
from closedloop.studies.truth import make_dataset

SO101 = example_robot_data_dir() / "so_arm_description" / "urdf" / "so101.urdf"
NOISE = 1e-5


def _so101_socket():
    robot = RobotModel.from_file(SO101)
    loop = PointLoop("socket", "gripper_frame_link", initial_tip=np.array([0.03, 0.0, 0.0]))
    rng = np.random.default_rng(3)
    q0 = np.array([0.3, -0.6, 0.9, 0.6, 0.4])
    ds = make_dataset(robot, loop, q0, 150, rng)
    lg = JointLog(list(ds.joints), ds.readings + rng.normal(0.0, NOISE, ds.readings.shape))
    return calibrate(robot, lg, [loop], CalibrationOptions(noise=NOISE))


def test_a_plain_fits_move_along_a_truncated_direction_is_not_carried_into_the_weighted_fit(monkeypatch):
    res = _so101_socket()
    problem, fit = res.problem, res.fit
    est, x = list(fit.estimated), np.asarray(fit.values, dtype=float)
    scale = np.array([p.prior for p in problem.params])[est]
    sigma_q = np.full(len(problem.joints), NOISE)
    fun = ResidualFunction(problem, x, est, sigma_q, "noise")
    r, J = fun.linearized(x[est])
    S, Vt, _ = scaled_svd(J, r, scale)
    weak = Vt[np.argmin(S)]
    assert S.min() < 1.0  # the premise: the weighted fit truncates a direction at the solution (eq. 4.17)
    real_plain = solve.plain_stage

    def wandering_plain(*args, **kwargs):  # the plain fit, then 90 prior units along that direction
        a = real_plain(*args, **kwargs)
        a.solution.x = a.solution.x + 90.0 * weak * scale
        return a

    monkeypatch.setattr(solve, "plain_stage", wandering_plain)
    again = solve.solve_staged(problem, x, x, est, CalibrationOptions(noise=NOISE), sigma_q, True, plain_start=True)
    moved = float(weak @ ((again.x - x)[est] / scale))
    assert abs(moved) < 1.0  # held where the start had it (the wander carried over: 90)
    r_again = fun(again.x[est], False)[0]
    assert r_again @ r_again <= (r @ r) * 1.01 + 2.0  # and as good a fit (chi-square within 2 of it)
