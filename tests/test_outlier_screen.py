"""The outlier screen's metric: the noise ratio it whitens with, and each row's share of the fit.

Clean data must keep their rows (a screen at Bonferroni level 0.01 rejects a clean row about once in a
hundred calibrations); corrupted rows must still go.  Figures over many seeds: benchmarks/outlier_screen.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.estimate.robust import MAD_TO_SIGMA, median_joint_scale, studentize


def _tracker_like(rng: np.random.Generator, n: int, s_true: float, sigma_t: float, bad: float = 0.0):
    """n point closures with joint noise of variance s_true (pattern 1) through random arm Jacobians
    (3 x 6, singular values 0.02-0.8 m) and a tracker's isotropic sigma_t; a fraction `bad` of them 1 cm off."""
    U = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    V = np.linalg.qr(rng.normal(size=(n, 6, 6)))[0][:, :3, :]
    Jq = U @ (rng.uniform(0.02, 0.8, (n, 3))[:, :, None] * V)
    C = sigma_t**2 * np.eye(3)
    W = s_true * Jq @ np.swapaxes(Jq, 1, 2) + C
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(W), rng.normal(size=(n, 3)))
    k = int(round(bad * n))
    r[:k] += rng.normal(scale=1e-2, size=(k, 3))
    return r, Jq, C


@pytest.mark.parametrize("bad", [0.0, 0.2])
def test_median_joint_scale_finds_the_ratio_gross_errors_do_not_drag(bad):
    """Joint noise 2e-5 rad beside a 1e-5 m tracker, 600 closures (20 % 1 cm off): s within 25 % of the
    truth (seeds 0-2 give 0.94-1.18 of it clean, 0.91-1.15 with 20 % and 0.85-1.08 with 40 % off; without
    the re-solve on the configurations within the threshold, 20 % off doubled it)."""
    rng = np.random.default_rng(3)
    r, Jq, C = _tracker_like(rng, 600, (2e-5) ** 2, 1e-5, bad)
    s = median_joint_scale([r], [Jq], [C], np.ones(6))
    assert s == pytest.approx((2e-5) ** 2, rel=0.25)


def test_median_joint_scale_is_zero_when_the_tracker_explains_everything():
    """Noise-free joints: the tracker's own noise explains the closures, nothing is left for the joints
    (at most a joint level whose closure is a tenth of the tracker's over the median configuration)."""
    rng = np.random.default_rng(4)
    r, Jq, C = _tracker_like(rng, 400, 0.0, 1e-5)
    s = median_joint_scale([r], [Jq], [C], np.ones(6))
    assert np.sqrt(s) * 0.3 < 1e-6
    # a closed loop (no measurement covariance): s only scales, which the screen's MAD absorbs
    assert median_joint_scale([r], [Jq], [None], np.ones(6)) == 1.0


def test_studentized_residuals_have_unit_spread_for_every_row():
    """A weighted linear fit (rows of weight 1, 0.4 and 0 = left out) of 40 two-dimensional rows in 12
    parameters, refitted on 4,000 noise draws: every row's studentized components have variance 1 (to 10 %),
    where the raw residuals of high-leverage rows are far below it and of left-out rows above it."""
    rng = np.random.default_rng(5)
    n, m, p = 40, 2, 12
    J = rng.normal(size=(n, m, p)) * rng.uniform(0.2, 3.0, (n, 1, 1))  # rows of very different leverage
    w = np.ones(n)
    w[:5], w[5:10] = 0.0, 0.4
    Jf = J.reshape(-1, p)
    wr = np.repeat(w, m)
    eps = rng.normal(size=(4000, n * m))
    delta = np.linalg.solve(Jf.T @ (wr[:, None] * Jf), (Jf.T * wr) @ eps.T).T
    e = (eps - delta @ Jf.T).reshape(4000, n, m)
    raw = e.var(axis=0).mean(axis=1)
    assert raw.min() < 0.6 and raw[:5].max() > 1.1  # what the screen read as noise before
    # studentize is linear in the residuals: one call per draw on the stacked draws' shared Jacobian
    out = np.stack([studentize([e[k]], [J], [w])[0] for k in range(0, 4000, 4)])
    var = out.var(axis=0).mean(axis=1)
    assert np.all(np.abs(var - 1.0) < 0.1), var
    # the pooled MAD scale of the studentized components is the noise's (1) to 2 %
    assert MAD_TO_SIGMA * np.median(np.abs(out)) == pytest.approx(1.0, abs=0.02)


@pytest.mark.slow
def test_tracker_scenario_keeps_its_clean_rows(tmp_path):
    """The MuJoCo ur5_tracker scenario, 120 clean configurations, the tracker noise stated and the joint
    noise left to the calibration: no row rejected (the screen read the tracker's noise as joint noise and
    rejected 13, at standardized closures up to 17.9), the verdict ok."""
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.io.logs import read_log
    from closedloop.loops.spec import parse_loop
    from closedloop.model.robot import RobotModel
    from closedloop.sims import simulate

    simulate("ur5_tracker", 120, 6, tmp_path)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    log = read_log(tmp_path / "log.csv", robot.joint_names)
    loop = parse_loop("measured_point:frame=stylus_tip,name=tracker,sigma_t=1e-5", robot)
    res = calibrate(robot, log, [loop], CalibrationOptions())
    assert [r.row for r in res.outliers.rejected] == []
    assert res.verdict.status == "ok"


@pytest.mark.slow
def test_plane_loop_keeps_the_rows_that_fix_the_fit():
    """A UR5 on a plane, 100 configurations with 1e-4 rad joint noise (one row each, 23 parameters): the
    rows a refit left out are re-checked as left out (their closure carries the fit's error too), and none
    stays rejected (10 did), the robot right within the zoo's tolerances."""
    import zoo

    o = zoo.run_case(zoo.make_case("ur5", "plane", n=100, sigma=1e-4, seed=0))
    assert o.result is not None, o.error
    assert [r.row for r in o.result.outliers.rejected] == []
    assert o.right and o.status == "ok", o.line()


@pytest.mark.slow
def test_corrupted_tracker_rows_still_go():
    """An xArm7 measured by a tracker (1e-5 m stated, joints 1e-5 rad), 12 of 60 rows replaced by random
    readings: exactly those 12 rejected, the robot right within the zoo's tolerances."""
    import zoo

    case = zoo.make_case("xarm7", "measured_point", n=60, sigma=1e-5, sigma_t=1e-5, seed=1, corrupt_rows=0.2)
    o = zoo.run_case(case)
    assert o.result is not None, o.error
    assert sorted(r.row - 1 for r in o.result.outliers.rejected) == sorted(int(b) for b in case.corrupted)
    assert o.right, o.line()
