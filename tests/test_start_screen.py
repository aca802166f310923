"""A long log's start screen (`outliers.start_screen`): the presolve sample screened whitened, every row raw.

Whitening every row at the start costs a pass with the joints' Jacobian over the whole log; on a clean long
log the sample's screen and the raw closures (read anyway for the start's statistics) stand for it, and the
calibration is the same to the bit.  A gross error outside the sample stands out in the raw closure: the
whole log is then screened as a short one, and the corrupted rows are rejected."""

from __future__ import annotations

import numpy as np
import pytest

import closedloop.estimate.outliers as outliers
import closedloop.estimate.residual as residual
from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.analysis.selection import initial_values
from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import build_problem
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.problem.problem import even_sample
from closedloop.studies.truth import make_dataset

ROWS, ABOVE, SAMPLE = 600, 500, 100  # the log, the presolve's threshold and sample, scaled down


@pytest.fixture(scope="module")
def long_log():
    """600 rows: 150 exact self-motion configurations of a random true Panda, four times, 1e-4 rad noise."""
    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(3)
    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], ROWS // 4, rng, stride=1
    )
    th = np.tile(ds.readings, (4, 1))
    return panda, JointLog(ds.joints, th + rng.normal(0.0, 1e-4, th.shape))


@pytest.fixture
def long_(monkeypatch):
    """The presolve (and so the start screen on a sample) from `ABOVE` configurations, on `SAMPLE` of them;
    the sizes `gross_outliers` is called on, recorded."""
    monkeypatch.setattr(residual, "PRESOLVE_ABOVE", ABOVE)
    monkeypatch.setattr(residual, "PRESOLVE_ROWS", SAMPLE)
    sizes: list[int] = []
    real = outliers.gross_outliers

    def spy(problem, *args, **kwargs):
        sizes.append(sum(b.theta.shape[0] for b in problem.blocks))
        return real(problem, *args, **kwargs)

    monkeypatch.setattr(outliers, "gross_outliers", spy)
    return sizes


def test_a_clean_long_log_is_screened_on_its_sample_and_calibrates_the_same(long_log, long_, monkeypatch):
    panda, log = long_log
    loops = [WeldLoop("fixture", "panda_hand")]
    res = calibrate(panda, log, loops, CalibrationOptions())
    assert long_ == [SAMPLE]  # the sample screened, whitened; the whole log not
    assert res.verdict.status == "ok" and not res.outliers.rejected
    long_.clear()
    monkeypatch.setattr(outliers, "beyond_sample", lambda *a: True)  # as if a row were far: every row screened
    whole = calibrate(panda, log, loops, CalibrationOptions())
    assert long_ == [SAMPLE, ROWS]
    assert np.array_equal(res.fit.values, whole.fit.values) and np.array_equal(res.fit.std, whole.fit.std, True)


def test_gross_errors_outside_the_sample_are_screened_and_rejected(long_log, long_):
    panda, log = long_log
    outside = np.setdiff1d(np.arange(ROWS), even_sample(ROWS, SAMPLE))
    rng = np.random.default_rng(8)
    bad = np.sort(rng.choice(outside, 3, replace=False))
    th = log.angles.copy()
    th[bad, rng.integers(0, 7, bad.size)] += rng.choice([-1.0, 1.0], bad.size) * rng.uniform(0.1, 0.3, bad.size)
    res = calibrate(panda, JointLog(log.joints, th), [WeldLoop("fixture", "panda_hand")], CalibrationOptions())
    assert long_ == [SAMPLE, ROWS]  # the sample clean, a row far beyond it in the raw closure: all screened
    assert sorted(r.row - 1 for r in res.outliers.rejected) == bad.tolist()


def test_beyond_sample_reads_raw_closures_against_the_samples_worst(long_log):
    panda, log = long_log
    problem = build_problem(panda, log, [WeldLoop("fixture", "panda_hand")])
    x = initial_values(problem, {})  # the nominal model: closures of millimetres
    sample = problem.sampled(SAMPLE)
    assert not outliers.beyond_sample(problem, sample, x)
    th = log.angles.copy()
    row = int(np.setdiff1d(np.arange(ROWS), even_sample(ROWS, SAMPLE))[7])
    th[row, 3] += 0.2  # a corrupted elbow reading: the hand 5-10 cm off, where the loop's closures are mm
    bad = build_problem(panda, JointLog(log.joints, th), [WeldLoop("fixture", "panda_hand")])
    assert outliers.beyond_sample(bad, bad.sampled(SAMPLE), x)
