"""`CalibrationProblem.evaluate` keeps its last two results for the same parameter vector: what it
gives again equals a fresh evaluation to the bit, is a copy the caller may change, and is never given to a
problem whose loops differ (a re-charted copy) or for other parameters, readings or columns."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from closedloop import RobotModel
from closedloop.assets.catalog import ROBOTS
from closedloop.loops import WeldLoop
from closedloop.studies.truth import make_dataset


@pytest.fixture(scope="module")
def problem():
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    ds = make_dataset(
        robot, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 20, np.random.default_rng(0)
    )
    return ds.problem, ds.truth


def _fresh(problem, x, jac, cols=None):
    return problem._evaluate(x, jac, None, cols)


def test_memo_gives_the_fresh_result_as_a_copy(problem):
    prob, x = problem
    x = x + 1e-4
    a = prob.evaluate(x, True, columns=[0, 3, 5])
    b = prob.evaluate(x, True, columns=[0, 3, 5])  # from the memo
    ref = _fresh(prob, x, True, [0, 3, 5])
    for e, f in zip(b, ref):
        assert np.array_equal(e.r, f.r) and np.array_equal(e.J, f.J) and np.array_equal(e.Jq, f.Jq)
    a[0].r[:] = 99.0  # the caller's copy
    a[0].J[:] = 99.0
    c = prob.evaluate(x, False)  # residual only, from the Jacobian evaluation
    assert c[0].J is None and np.array_equal(c[0].r, ref[0].r)
    d = prob.evaluate(x, True, columns=[])  # Jq alone
    assert d[0].J.shape[2] == 0 and np.array_equal(d[0].Jq, ref[0].Jq)


def test_memo_misses_what_differs(problem):
    prob, x = problem
    x = x + 2e-4
    prob.evaluate(x, True, columns=[0, 1])
    other = prob.evaluate(x, True, columns=[2])  # other columns: evaluated
    assert np.array_equal(other[0].J, _fresh(prob, x, True, [2])[0].J)
    y = x.copy()
    y[0] += 1e-12  # another vector, by one bit or so
    assert np.array_equal(prob.evaluate(y, False)[0].r, _fresh(prob, y, False)[0].r)
    th = [b.theta + 1e-3 for b in prob.blocks]  # other readings: never kept
    assert np.array_equal(prob.evaluate(x, False, th)[0].r, prob._evaluate(x, False, th, None)[0].r)
    moved = copy.copy(prob)  # a copy with other loops (a re-charted problem) shares no result
    moved.blocks = [replace(b, loop=WeldLoop("fixture", "panda_link7")) for b in prob.blocks]
    assert not np.array_equal(moved.evaluate(x, False)[0].r, prob.evaluate(x, False)[0].r)
