"""The outlier screen at the start (`outliers.gross_outliers`): a model error is no outlier, a corrupted
reading is; and held-out refits reuse the full calibration's screen (`kfold.cross_validate`).

At the nominal model of a robot whose joint origins are millimetres off, the closures spread with the model
error, smoothly over the workspace, and their tails cross the screen's threshold on a clean log; the robust
refit that follows rejects nothing and costs most of the run (a robot sweep's hand socket: 76 % of its time).
"""

from __future__ import annotations

import numpy as np
import pytest

from closedloop import CalibrationOptions, calibrate
from closedloop.analysis.identifiability import analyse_structure
from closedloop.analysis.selection import initial_values, select_parameters, structure_problem
from closedloop.calibration.pipeline import build_problem
from closedloop.estimate import outliers
from closedloop.estimate.noise import noise_vector
from closedloop.estimate.robust import flagged
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.records import ParamStatus
from closedloop.validation.kfold import cross_validate

NOISE = 1e-5


@pytest.fixture(scope="module")
def weld(panda, panda_weld):
    """The Panda welded at the hand (`panda_weld`'s truth), its first 60 configurations read with 1e-5 rad
    noise: 17 of the 60 beyond the screen's threshold at the nominal model."""
    th = panda_weld.readings[:60] + np.random.default_rng(0).normal(0.0, NOISE, (60, 7))
    return panda, WeldLoop("fixture", "panda_hand"), th, panda_weld.truth


def _start(robot: RobotModel, loop, readings: np.ndarray):
    """The problem, the nominal start, the parameters the fit estimates and the joint noise."""
    opt = CalibrationOptions(noise=NOISE)
    problem = build_problem(robot, JointLog(list(robot.supporting_joints("panda_hand")), readings), [loop])
    x0 = initial_values(problem, opt.initial)
    free = [k for k, s in enumerate(select_parameters(problem, opt.identify, opt.fix, x0)) if s == ParamStatus.SELECTED]
    kept = analyse_structure(structure_problem(problem), x0, free).kept
    return problem, x0, kept, noise_vector(problem, NOISE)[0], opt


def test_a_model_error_is_no_gross_outlier(weld):
    robot, loop, readings, truth = weld
    problem, x0, kept, sigma_q, opt = _start(robot, loop, readings)
    at_start = flagged(outliers.screen(problem, x0, sigma_q, True), [6], opt.outlier_alpha)[0]
    assert at_start.size >= 10  # the model error's tails: the closures alone cannot tell them from outliers
    assert not outliers.gross_outliers(problem, x0, kept, sigma_q, opt)


@pytest.mark.parametrize("row, joint, error", [(17, 2, 100.0), (40, 0, 0.05)])
def test_a_corrupted_reading_is(weld, row, joint, error):
    """A reading of 100 rad (a corrupted cell) and one 0.05 rad off (the loop closed centimetres away)."""
    robot, loop, readings, truth = weld
    th = readings.copy()
    th[row, joint] += error
    problem, x0, kept, sigma_q, opt = _start(robot, loop, th)
    assert outliers.gross_outliers(problem, x0, kept, sigma_q, opt)


def test_a_clean_log_with_a_model_error_runs_no_robust_refit(weld, monkeypatch):
    """The calibration keeps every row, finds the truth, and never runs the robust refit."""
    robot, loop, readings, truth = weld
    calls = []
    refit = outliers._robust_refit
    monkeypatch.setattr(outliers, "_robust_refit", lambda *a: calls.append(1) or refit(*a))
    res = calibrate(
        robot, JointLog(list(robot.supporting_joints("panda_hand")), readings), [loop], CalibrationOptions(noise=NOISE)
    )
    assert calls == [] and res.outliers.rejected == []
    est = res.fit.estimated
    err = np.abs(res.fit.values[est] - truth[est])
    assert np.all(err < 6.0 * res.fit.std[est] + 1e-9)


@pytest.mark.slow
def test_held_out_refits_reuse_the_screen(weld, monkeypatch):
    """A log with one corrupted row: the calibration rejects it, and validated with its rejection left out
    of the refits' data no refit screens again (no robust refit), while the held-out closure stays at the
    noise (1e-5 rad through a ~1 m arm)."""
    robot, loop, readings, truth = weld
    th = readings.copy()
    th[17, 2] += 100.0
    lg = JointLog(list(robot.supporting_joints("panda_hand")), th)
    opt = CalibrationOptions(noise=NOISE)
    res = calibrate(robot, lg, [loop], opt)
    bad = [rj.row - 1 for rj in res.outliers.rejected]
    assert bad == [17]
    calls = []
    refit = outliers._robust_refit
    monkeypatch.setattr(outliers, "_robust_refit", lambda *a: calls.append(1) or refit(*a))
    cv = cross_validate(robot, lg, [loop], opt, k=3, seed=0, exclude=bad, train_without_excluded=True)
    assert calls == [] and cv["excluded"] == [17]
    assert cv["test"][0]["n"] == 59 and cv["test"][0]["rms_m"] < 5e-5
    # the rejected row is in no fold's training rows, and judged in no held-out fold
    assert all(
        f["train"]["skipped"] == 0 and f["n_train"] + f["n_test"] - f["test"]["skipped"] == 59 for f in cv["folds"]
    )
    assert sum(f["test"]["skipped"] for f in cv["folds"]) == 1
