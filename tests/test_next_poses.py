"""Where to measure next (`closedloop.design.next_poses`): the predicted error the suggestions promise is the
one the calibration with them reports.

Data from the robot zoo (`tests/zoo.py`): the suggested readings are played on the true robot (moved onto
its loop from them, with fresh joint noise) and calibrated again with the log they extend.
"""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.analysis.accuracy import predict_from_result
from closedloop.design.next_poses import suggest_poses
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop


def _promised_and_obtained(robot: str, seed: int, k: int = 8):
    """A zoo robot's tool on a plane (40 configurations, 1e-4 rad): the `k` suggestions (the suggestion record)
    and the workspace prediction of the calibration with them played on the true robot (moved onto its
    plane from them, with fresh joint noise) beside the log."""
    case = zoo.make_case(robot, "plane", n=40, sigma=1e-4, seed=seed)
    model = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, model) for s in case.loop_specs]
    options = CalibrationOptions(noise=1e-4)
    res = calibrate(model, JointLog(list(case.joints), case.readings), loops, options)
    acc = predict_from_result(res)
    nxt = suggest_poses(res, acc, k)
    assert nxt is not None and nxt.readings.shape == (k, len(case.joints))

    on_true_plane = zoo.on_true_loop(case)
    offsets = np.array([case.true_offsets[j] for j in case.joints])
    rng = np.random.default_rng(3)
    new = [zoo._project(on_true_plane, r + offsets, case.lower - 1.0, case.upper + 1.0) for r in nxt.readings]
    assert all(th is not None for th in new)  # each suggestion is a configuration the true robot reaches
    played = np.array([th - offsets + rng.normal(scale=1e-4, size=th.shape) for th in new])
    assert np.abs(played - nxt.readings).max() < 0.05  # recorded where suggested
    res2 = calibrate(model, JointLog(list(case.joints), np.vstack([case.readings, played])), loops, options)
    return nxt, predict_from_result(res2).frames[0]


def test_the_promised_error_is_the_recalibrations_prediction():
    """A UR3's tool on a plane: the 8 suggestions' promised RMS error over the workspace lies within 20 % of
    the one the calibration with them predicts (1.00x; 0.67x where the promise took the plane's place as
    known, without its uncertainty and its correlation with the arm's).  The recalibration estimates the
    plane's place again: what the new rows tell of it is not what they tell of the arm."""
    nxt, obtained = _promised_and_obtained("ur3", 0)
    assert nxt.rms_after_m[-1] < 0.5 * nxt.rms_before_m  # they are worth recording
    assert abs(obtained.rms_m / nxt.rms_after_m[-1] - 1.0) < 0.2, (nxt.rms_after_m[-1], obtained.rms_m)


@pytest.mark.slow
def test_the_promise_keeps_what_the_recalibration_still_does_not_see():
    """A Z1's tool on a plane leaves three directions unestimated, and most of its predicted error is the
    nominal tolerance along them (0.68 of 0.81 mm).  The recalibration with the suggestions still leaves
    three, other ones: the promise finds them from the log and the new rows, at their tolerance, and lies
    within 20 % of the recalibration's prediction (1.02x; 1.70x where that part was updated as a prior)."""
    nxt, obtained = _promised_and_obtained("z1", 0)
    assert obtained.unseen_rms_m > 0.5 * obtained.rms_m  # what it does not see is most of the error
    assert abs(obtained.rms_m / nxt.rms_after_m[-1] - 1.0) < 0.2, (nxt.rms_after_m[-1], obtained.rms_m)


def test_a_door_loop_gets_its_suggestions():
    """A door (hinge) loop's residual has a direction no joint noise moves (the door's angle, projected out):
    its noise covariance is singular there, weighed as in the fit (nothing), not inverted (a Cholesky
    factorisation of it failed: an internal error on every door).  The suggestions promise less error."""
    case = zoo.make_case("ur10", "hinge", n=40, sigma=1e-5, seed=2)
    model = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, model) for s in case.loop_specs]
    res = calibrate(model, JointLog(list(case.joints), case.readings), loops, CalibrationOptions(noise=1e-5))
    nxt = suggest_poses(res, predict_from_result(res), 6)
    assert nxt is not None and nxt.readings.shape == (6, len(case.joints))
    assert np.all(np.isfinite(nxt.rms_after_m)) and 0.0 < nxt.rms_after_m[-1] < nxt.rms_before_m
