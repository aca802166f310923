"""`CalibrationProblem.evaluate` keeps its last two results for the same parameter vector: what it
gives again equals a fresh evaluation to the bit, is a copy the caller may change, and is never given to a
problem whose loops differ (a re-charted copy) or for other parameters, readings or columns."""

from __future__ import annotations

import copy
import importlib
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


def test_long_log_keeps_the_jacobian_within_its_byte_budget(problem, monkeypatch):
    """Above MEMO_ROWS configurations the parameter Jacobian is kept while it takes at most MEMO_BYTES: the
    same columns at the same vector are given again (equal to a fresh evaluation, shared read-only), without
    a pass over the log; beyond the budget only the residual and Jq are kept."""
    P = importlib.import_module("closedloop.problem.problem")

    prob, x = problem
    x = x + 3e-4
    monkeypatch.setattr(P, "MEMO_ROWS", 0)  # the problem is a long log
    calls = []
    real = P.CalibrationProblem._evaluate
    monkeypatch.setattr(P.CalibrationProblem, "_evaluate", lambda s, *a: calls.append(a[1]) or real(s, *a))
    a = prob.evaluate(x, True, columns=[1, 4])
    with pytest.raises(ValueError):  # shared with the memo: read-only
        a[0].J[:] = 99.0
    b = prob.evaluate(x, True, columns=[1, 4])
    assert len(calls) == 1 and np.array_equal(b[0].J, real(prob, x, True, None, [1, 4])[0].J)
    monkeypatch.setattr(P, "MEMO_BYTES", 0)
    y = x + 1e-4
    prob.evaluate(y, True, columns=[1, 4])
    prob.evaluate(y, True, columns=[1, 4])  # not kept: evaluated again
    assert calls[1:] == [True, True]
    r = prob.evaluate(y, False)[0].r  # the residual kept
    assert len(calls) == 3 and np.array_equal(r, real(prob, y, True, None, [1, 4])[0].r)


def test_loop_poses_are_kept_for_the_robot_values(problem):
    """The loop's frame poses at the problem's readings are given again for the same robot parameters (a
    loop parameter changed does not move them) and made again for others."""
    prob, x = problem
    first = prob.loop_frame_poses(x, 0)
    y = x.copy()
    y[-1] += 0.1  # a loop parameter
    again = prob.loop_frame_poses(y, 0)
    assert all(a is b for a, b in zip(first, again))
    z = x.copy()
    z[0] += 1e-3  # a robot parameter
    moved = prob.loop_frame_poses(z, 0)
    assert not np.array_equal(moved[1], first[1]) or not np.array_equal(moved[0], first[0])
    fresh = prob.frame_kinematics(
        prob.rp.apply(z[: prob.n_robot]),
        prob.blocks[0].theta,
        [prob.robot.frame_id(f) for f in prob.blocks[0].loop.frames],
        False,
    )
    assert all(np.array_equal(m, fresh[prob.robot.frame_id(f)][0]) for m, f in zip(moved, prob.blocks[0].loop.frames))


def test_weighting_roots_are_reused_at_the_same_point_for_a_proportional_noise(problem, monkeypatch):
    """`ResidualFunction._kept_roots`: a second function of the same problem at the same point, with the
    joint noise c times the first's (the outlier screen's and the closure level's at the fit's solution),
    whitens with the first's roots divided by c, to the whitening it would form itself (1e-12); another
    point or noise pattern forms its own."""
    import closedloop.estimate.noise as noise_module
    from closedloop.estimate.residual import ResidualFunction

    prob, x = problem
    prob = copy.copy(prob)  # no roots kept from other tests
    prob.__dict__.pop("_roots_kept", None)
    sigma = np.full(len(prob.joints), 1e-4)
    formed = {"n": 0}
    real = noise_module._roots

    def counting(*args, **kwargs):
        formed["n"] += 1
        return real(*args, **kwargs)

    def whitened(s, at, reuse):
        if not reuse:
            prob.__dict__.pop("_roots_kept", None)
        return ResidualFunction(prob, at, [], s, "noise").blocks(np.zeros(0), symmetric=False)

    first = whitened(sigma, x, True)
    monkeypatch.setattr(noise_module, "_roots", counting)
    again = whitened(3.0 * sigma, x, True)
    assert formed["n"] == 0
    own = whitened(3.0 * sigma, x, False)
    assert formed["n"] == 1
    for a, b, f in zip(again, own, first):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
        assert np.allclose(3.0 * a, f, rtol=1e-12, atol=1e-12 * np.abs(f).max())
    whitened(sigma * np.linspace(1.0, 2.0, sigma.size), x, True)  # another pattern
    whitened(3.0 * sigma, x + 1e-5, True)  # another point
    assert formed["n"] == 3
