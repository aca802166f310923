"""The error bars checked along the cost's profile (`closedloop.analysis.linearity`): exact on a linear problem, failing on
a curved valley, and on the weakly determined weld where the linearised standard errors were 3-10x too small."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.analysis import linearity
from closedloop.analysis.linearity import K, profile
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop
from closedloop.problem.lengths import LengthLoop


class _Residual:
    """r(x) and its Jacobian for `profile` (the calibration's ResidualFunction interface)."""

    def __init__(self, f, jac):
        self.f, self.jac = f, jac

    def __call__(self, x, jac):
        return self.f(x), (self.jac(x) if jac else None)


def _covariance(J, noise):
    return np.linalg.inv(J.T @ J) * noise**2


def test_a_linear_problem_rises_by_k_squared_over_two():
    rng = np.random.default_rng(0)
    A, b, noise = rng.normal(size=(40, 3)), rng.normal(size=40), 0.3
    make = lambda: _Residual(lambda x: (A @ x - b) / 1.0, lambda x: A)  # noqa: E731
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    for u in (np.array([1.0, 0.0, 0.0]), rng.normal(size=3)):
        p = profile(make, x, _covariance(A, noise), u, noise, np.ones(3), "u")
        assert np.allclose(p.rise, K * K / 2, rtol=1e-5) and p.holds  # the pin's own slack: 1/PIN^2


def test_a_curved_valley_does_not_hold():
    """r = (10 (x2 - x1^2 - 0.3 x1), x1) at its minimum x = 0: the curvature there gives x2 a standard error of
    sqrt(0.1), but x2 = t > 0 costs only x1^2 / 2 along the valley's floor x1^2 + 0.3 x1 = t (0.22 at +2
    standard errors); x2 = -t leaves the valley (18.6). The linear model says 2 on both sides."""
    f = lambda x: np.array([10.0 * (x[1] - x[0] ** 2 - 0.3 * x[0]), x[0]])  # noqa: E731
    jac = lambda x: np.array([[-10.0 * (2.0 * x[0] + 0.3), 10.0], [1.0, 0.0]])  # noqa: E731
    x = np.zeros(2)
    p = profile(lambda: _Residual(f, jac), x, _covariance(jac(x), 1.0), np.array([0.0, 1.0]), 1.0, np.ones(2), "x2")
    assert abs(p.std - np.sqrt(0.1)) < 1e-12
    assert p.rise[0] > 10.0 and abs(p.rise[1] - 0.217) < 0.01
    assert not p.holds


@pytest.mark.slow
def test_the_weak_weld_is_suspect_where_its_error_bars_fail(monkeypatch):
    """The zoo's Panda weld, 80 configurations of one self-motion at 5e-5 rad, a known length link2-link4: the
    fit's size is 9.8 of its reported standard errors off the truth; the profile along the size rises by -0.38
    and 1.75 (2 expected), so the verdict is `suspect`, not `ok` as it was.  The plain fit of the same log,
    whose error bars hold (its size 0.2 standard errors off), passes the check: profiled whatever its
    iterations (it now converges within `PROFILE_AFTER`, below which a fit is not profiled)."""
    import zoo
    from test_rigs import Z_LEVEL
    from zoo_judge import judge

    case = zoo.make_case("panda", "weld", n=80, seed=0)
    robot = RobotModel.from_file(case.nominal_urdf)
    L = case.true_distance("panda_link2", "panda_link4")
    off = np.array([case.true_offsets[j] for j in case.joints])
    readings = case.q_true - off + np.random.default_rng(1000).normal(0.0, 5e-5, case.q_true.shape)
    loops = [parse_loop(s, robot) for s in case.loop_specs] + [LengthLoop("panda_link2", "panda_link4", L)]
    res = calibrate(robot, JointLog(list(case.joints), readings), loops, CalibrationOptions())
    size_error = judge(case, dict(zip(res.fit.names, res.fit.values))).scale - 1.0
    assert abs(size_error) > 3 * res.scale.scale_std  # what the check is for: the error bar does not cover the truth
    size = [p for p in res.noise.profiles if "size" in p.name]
    assert size and not size[0].holds
    assert res.verdict.status == "suspect"
    assert any("error bars do not hold" in r for r in res.verdict.reasons)
    loops = [parse_loop(s, robot) for s in case.loop_specs] + [LengthLoop("panda_link2", "panda_link4", L)]
    monkeypatch.setattr(linearity, "PROFILE_AFTER", 0)
    plain = calibrate(robot, JointLog(list(case.joints), readings), loops, CalibrationOptions(weighting="none"))
    # covered at 4 standard errors (a level a normal draw exceeds with probability 6e-5; test_rigs.Z_LEVEL): this
    # draw is 0.2 off, the weighted fit's 9.8
    assert abs(judge(case, dict(zip(plain.fit.names, plain.fit.values))).scale - 1.0) < Z_LEVEL * plain.scale.scale_std
    assert plain.noise.profiles and all(p.holds for p in plain.noise.profiles)
    assert not any("error bars" in r for r in plain.verdict.reasons)
