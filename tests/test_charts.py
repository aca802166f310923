"""The hinge's line chart: regular at any tilt, re-centred by the solver without changing the model.

The hinge line is H = H0 Rot(exp3(rx, ry, 0)) Trans(x, y, 0): (x, y) is the line's offset normal
to its own direction, so the chart is regular up to a half-turn of tilt (the former
H0 (exp3(rx, ry, 0), (x, y, 0)) put the point in H0's xy-plane and lost a rank at 90 degrees).
`HingeLoop.recentred` / `express` move the chart; the solver re-centres it after each step
(`residual.ResidualFunction.retract`) and returns its solution in the problem's own chart.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.loops.hinge import HingeLoop


def _plucker(lp: HingeLoop, p: np.ndarray) -> np.ndarray:
    """The line as (direction, moment): coordinates of the line itself, independent of any chart."""
    point, d = lp.line(p)
    return np.concatenate([d, np.cross(point, d)])


def _rig(seed: int = 1, n: int = 20):
    rng = np.random.default_rng(seed)
    lp = HingeLoop("door", "tool", axis=(rng.normal(size=3), rng.normal(size=3)))
    truth = np.concatenate([rng.normal(0, 0.5, 4), [0.4, 0.1], rng.normal(0, 0.3, 3)])
    H, G = lp.hinge(truth), lp.grasp(truth)
    TB = np.array([pin.SE3.Random().homogeneous for _ in range(n)])
    TA = np.array(
        [
            tb
            @ (
                H * pin.SE3(pin.exp3(np.array([0.0, 0.0, a])), np.zeros(3)) * G * pin.exp6(rng.normal(0, 0.01, 6))
            ).homogeneous
            for tb, a in zip(TB, rng.uniform(-3.0, 3.0, n))
        ]
    )
    return lp, truth, TA, TB, rng


@pytest.mark.parametrize("tilt", [0.0, 0.8, np.pi / 2, 2.5])
def test_line_chart_is_regular_at_any_tilt(tilt):
    """The line's Plucker coordinates have rank 4 in (x, y, rx, ry), at 90 degrees of tilt too."""
    lp = HingeLoop("door", "tool", axis=(np.zeros(3), np.array([0.0, 0.0, 1.0])))
    p = np.array([0.3, -0.2, tilt, 0.0, 0.5, 0.0, 0.1, 0.2, 0.3])
    h = 1e-6
    D = np.column_stack([(_plucker(lp, p + h * e) - _plucker(lp, p - h * e)) / (2 * h) for e in np.eye(9)[:4]])
    s = np.linalg.svd(D, compute_uv=False)
    assert s[3] > 0.05 * s[0]


def test_recentred_chart_is_the_same_model():
    """Residuals equal to round-off in the re-centred chart, and `express` maps back exactly."""
    lp, truth, TA, TB, rng = _rig()
    p = truth + rng.normal(0, 0.3, 9)
    other, q = lp.recentred(p)
    assert np.allclose(q[:4], 0.0) and np.array_equal(q[4:], p[4:])
    assert np.abs(lp.evaluate(TA, TB, p).r - other.evaluate(TA, TB, q).r).max() < 1e-12
    assert np.abs(other.express(q, lp) - p).max() < 1e-12
    p2 = p + rng.normal(0, 0.2, 9)  # any point, expressed in the other chart: the same residual
    assert np.abs(lp.evaluate(TA, TB, p2).r - other.evaluate(TA, TB, lp.express(p2, other)).r).max() < 1e-12
    assert lp.recentred(np.concatenate([np.full(4, 0.01), p[4:]])) is None  # near H0: the chart stays


def test_solver_returns_the_problem_chart(tmp_path):
    """Loop parameters fitted from far off H0 on the thesis's door: the chart follows the solver, and its
    solution comes back in the problem's own chart, closing the loop there to round-off."""
    import thesis_examples as te

    from closedloop import RobotModel, read_log
    from closedloop.analysis.selection import initial_values
    from closedloop.calibration.pipeline import build_problem
    from closedloop.estimate.lm import SolverOptions, levenberg_marquardt
    from closedloop.estimate.residual import ResidualFunction, unweighted_closure
    from closedloop.loops.spec import parse_loop

    ex = te.door()
    robot = RobotModel.from_file(te.write_table(ex, ex.rows, tmp_path / "door.yaml"))
    log = tmp_path / "door.csv"
    log.write_text(
        ",".join(ex.joints) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in ex.readings) + "\n"
    )
    problem = build_problem(robot, read_log(log, robot.joint_names), [parse_loop(ex.loop_specs[0], robot)], None)
    x0 = initial_values(problem, {})
    est = [int(k) for k in problem.loop_columns[0]]
    start = x0[est] + np.array([0.3, -0.3, 0.6, -0.5, 0.1, 0.1, 0.2, -0.2, 0.2])
    fun = ResidualFunction(problem, x0, est, np.ones(len(problem.joints)), "none")
    moves = []
    retract = fun.retract
    fun.retract = lambda xe: (moves.append(1), retract(xe))[1]
    sol = levenberg_marquardt(fun, start, np.full(len(est), 0.1), SolverOptions(max_iter=200, noise=0.0))
    assert moves and fun.settle(sol.x) is None  # the chart moved on the way, and was reset at the end
    x = fun.full(sol.x)
    assert np.array_equal(x[est], sol.x)  # in the problem's own chart
    assert unweighted_closure(problem, x) < 1e-12
