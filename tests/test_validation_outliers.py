"""K-fold validation on a log with corrupted rows: the rejected rows are not judged (closedloop.validation.kfold)."""

import numpy as np
import pytest

from closedloop import CalibrationOptions, calibrate
from closedloop.calibration.pipeline import build_problem
from closedloop.studies.montecarlo import weld_scenario
from closedloop.validation.kfold import cross_validate, folds

NOISE = 1e-4
BAD = [5, 23, 42, 61, 77]  # 0-based rows whose joint 1 reading is off by what closes the loop 5 cm away


@pytest.fixture(scope="module")
def dirty():
    sc = weld_scenario(n=100, seed=0, stride=6)
    problem = build_problem(sc.robot, sc.log(), sc.loops)
    truth = sc.truth_vector(problem)
    th = sc.theta + np.random.default_rng(11).normal(0, NOISE, sc.theta.shape)
    for i in BAD:
        Jq = problem.evaluate(truth, True, [sc.theta[i : i + 1]])[0].Jq[0]
        th[i, 0] += 0.05 / np.linalg.norm(Jq[:3, 0])
    lg = sc.log(th)
    res = calibrate(sc.robot, lg, sc.loops, CalibrationOptions(noise=NOISE))
    return sc, lg, res


@pytest.mark.slow
def test_rejected_rows_are_left_out_of_both_figures(dirty):
    sc, lg, res = dirty
    assert sorted(rj.row - 1 for rj in res.outliers.rejected) == BAD
    opts = CalibrationOptions(noise=NOISE)
    cv = cross_validate(sc.robot, lg, sc.loops, opts, k=5, seed=0, exclude=[rj.row - 1 for rj in res.outliers.rejected])
    assert cv["excluded"] == BAD
    parts = folds(lg, 5, seed=0)
    for f, rows in zip(cv["folds"], parts):
        held_bad = int(np.isin(rows, BAD).sum())
        assert f["test"]["skipped"] == held_bad and f["test"]["loops"][0]["n"] == rows.size - held_bad
        # training: the full fit's outliers in this fold's training rows, and the refit's own rejections
        assert f["train"]["skipped"] >= len(BAD) - held_bad
        assert f["train"]["loops"][0]["n"] == 100 - rows.size - f["train"]["skipped"]
    test, train = cv["test"][0], cv["train"][0]
    assert test["n"] == 100 - len(BAD)
    # held-out closure at the noise level (1e-4 rad through a ~0.5-1 m arm), as on a clean log, and the
    # held-out to training ratio of a model that generalises
    assert test["rms_m"] < 5e-4 and test["rms_rad"] < 1e-3
    assert test["rms_m"] < 3.0 * train["rms_m"]
    assert 0.8 < cv["test_whitened_rms"] < 1.3


@pytest.mark.slow
def test_judged_outliers_would_hide_the_ratio(dirty):
    """Without `exclude` the corrupted rows set the held-out figure at centimetres (the old behaviour)."""
    sc, lg, res = dirty
    cv = cross_validate(sc.robot, lg, sc.loops, CalibrationOptions(noise=NOISE), k=5, seed=0)
    assert cv["excluded"] == [] and all(f["test"]["skipped"] == 0 for f in cv["folds"])
    assert cv["test"][0]["rms_m"] > 5e-3  # the 5 cm closures of 5 rows in 100
