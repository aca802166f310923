"""A fit whose weld rotation vector ends beyond pi: the analysis at the canonical form (within pi) reads the
fit's Jacobian carried there by the chain rule (`ResidualFunction.normalized`), equal to a fresh evaluation."""

from __future__ import annotations

import numpy as np

from closedloop.calibration.pipeline import build_problem, initial_values
from closedloop.estimate.residual import ResidualFunction
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop


def test_chain_rule_jacobian_equals_a_fresh_evaluation(panda):
    rng = np.random.default_rng(8)
    theta = np.array([0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]) + rng.normal(0.0, 0.1, (40, 7))
    problem = build_problem(
        panda, JointLog([f"panda_joint{i}" for i in range(1, 8)], theta), [WeldLoop("fixture", "panda_hand")]
    )
    x = initial_values(problem, {}) + rng.normal(0.0, 1e-3, len(problem.params))
    cols = problem.loop_columns[0]
    axis = np.array([0.6, -0.64, 0.48])
    x[cols[3:6]] = (np.pi + 0.4) * axis  # the same rotation as (pi - 0.4) about -axis
    est = list(range(10)) + [int(c) for c in cols] + list(range(problem.n_robot - 7, problem.n_robot))
    sigma = np.full(7, 1e-4)
    fun = ResidualFunction(problem, x, est, sigma, "noise")
    r, J = fun(x[est], True)
    xn = fun.normalized(x)
    assert np.linalg.norm(xn[cols[3:6]]) < np.pi and np.allclose(xn[cols[3:6]], -(np.pi - 0.4) * axis)
    r_chain, J_chain = fun(xn[est], True)  # no evaluation: the carried Jacobian
    assert r_chain is r
    fresh = ResidualFunction(problem, xn, est, sigma, "noise")
    r_new, J_new = fresh(xn[est], True)
    np.testing.assert_allclose(r_chain, r_new, rtol=0, atol=1e-12 * np.abs(r_new).max())
    np.testing.assert_allclose(J_chain, J_new, rtol=0, atol=1e-9 * np.abs(J_new).max())
    assert np.abs(J_chain - J).max() > 1e-3 * np.abs(J).max()  # the rotation's columns did change
