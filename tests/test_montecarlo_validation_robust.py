"""Monte Carlo against the Cramer-Rao bound, cross-validation, robust weights and suspects."""

import numpy as np
import pytest

from closedloop import CalibrationOptions, calibrate
from closedloop.calibration.pipeline import build_problem
from closedloop.estimate.robust import config_residuals, irls, mad_scale, suspects, weights
from closedloop.io.logs import JointLog
from closedloop.problem.unwrap import unwrap_rotation_vector
from closedloop.studies.montecarlo import monte_carlo, weld_scenario
from closedloop.validation.kfold import cross_validate, folds, validation_rows

NOISE = 1e-4


@pytest.fixture(scope="module")
def scenario():
    # 100 configurations spread along the self-motion (one every 6 steps of 0.04 rad)
    return weld_scenario(n=100, seed=0, stride=6)


def test_unwrap_rotation_vector():
    r = np.array([0.0, 0.0, np.pi - 0.01])
    other = np.array([0.0, 0.0, -(np.pi + 0.01)])  # the same rotation on the other branch
    assert np.allclose(unwrap_rotation_vector(other, r), other + [0, 0, 2 * np.pi])
    assert np.allclose(unwrap_rotation_vector(r, r), r)


@pytest.mark.slow
def test_monte_carlo_against_cramer_rao(scenario):
    """M = 30 runs, 100 configurations, 1e-4 rad.

    Tolerances from the sampling distribution under H0 (estimator unbiased and
    efficient, estimates ~ N(truth, CRB)):
    * (M-1) tr(CRB^-1 cov_emp) ~ chi2((M-1) L): the efficiency tr(CRB^-1 cov_emp)/L
      has mean 1 and std sqrt(2 / ((M-1) L)) = 0.05 for L = 27; allow 4 std.
    * each bias component over its standard error is N(0, 1/M): |b|/se < 1 fails only
      beyond 5.5 sigma; M b^T CRB^-1 b ~ chi2(L): below its 0.999 quantile.
    The unweighted estimator is consistent but not efficient: its first-order
    (sandwich) covariance is ~2.2 x the bound here, and it carries a second-order
    errors-in-variables bias; require efficiency > 1.3 (a > 6 std excess).
    """
    from scipy import stats  # here, not at import: every xdist worker imports this file to collect it

    M = 30
    mc = monte_carlo(scenario, NOISE, M, seed=1)
    L = len(mc.names)
    assert L == 27 and "fixture.rx" in mc.names
    w, u = mc.stats["noise"], mc.stats["none"]
    assert w.failures == 0 and u.failures == 0 and w.truncated == 0
    sd_eff = np.sqrt(2.0 / ((M - 1) * L))
    assert abs(w.efficiency - 1.0) < 4 * sd_eff, mc.summary()
    assert abs(w.trace_ratio - 1.0) < 4 * mc.tolerance_trace, mc.summary()
    assert np.max(np.abs(w.bias_over_se)) < 1.0, mc.summary()
    assert w.bias_chi2 < stats.chi2.ppf(0.999, L), mc.summary()
    assert u.efficiency > 1.3, mc.summary()
    assert u.predicted_trace_ratio > 1.5


def test_cross_validation(scenario):
    rng = np.random.default_rng(3)
    lg = scenario.log(scenario.theta + rng.normal(0, NOISE, scenario.theta.shape))
    parts = folds(lg, 5, seed=0)
    assert sorted(np.concatenate(parts).tolist()) == list(range(100))
    told = []  # each refit reported as it finishes (a long log's refit is a calibration of its own)
    cv = cross_validate(
        scenario.robot,
        lg,
        scenario.loops,
        CalibrationOptions(noise=NOISE),
        k=5,
        seed=0,
        progress=lambda task, done, k, note="": told.append((done, k)),
    )
    assert told == [(1, 5), (2, 5), (3, 5), (4, 5), (5, 5)]
    assert len(cv["folds"]) == 5 and all(f["converged"] for f in cv["folds"])
    assert not cv["inconsistent"]
    test, train = cv["test"][0], cv["train"][0]
    assert test["n"] == 100 and train["n"] == 400
    # Held-out whitened RMS per row ~ 1 (noise-level prediction error), slightly above the fit's.
    assert 0.8 < cv["test_whitened_rms"] < 1.3
    assert cv["test_whitened_rms"] > cv["train_whitened_rms"]
    # Unweighted closure errors at the noise level (1e-4 rad through a ~0.5-1 m arm).
    assert test["rms_m"] < 5e-4 and test["rms_rad"] < 1e-3


def test_a_long_fold_is_an_even_sample_of_each_loop():
    """A held-out refit on a long log trains and is judged on at most `cap` rows per loop, spread from the
    first row to the last of each; a short one on all its rows."""
    loops = np.array(["door"] * 9000 + ["wall"] * 300 + ["door"] * 1000)
    lg = JointLog(["j"], np.zeros((loops.size, 1)), loop=loops)
    rows = np.arange(0, loops.size, 2)  # a fold's rows: every other row
    picked = validation_rows(lg, rows, cap=1000)
    assert np.all(np.diff(picked) > 0) and np.isin(picked, rows).all()
    door, wall = picked[loops[picked] == "door"], picked[loops[picked] == "wall"]
    assert door.size == 1000 and wall.size == 150  # the wall's 150 rows of the fold are all kept
    assert door[0] == 0 and door[-1] == rows[loops[rows] == "door"][-1]  # from the first row to the last
    gaps = np.diff(door)  # evenly spread (5,000 rows of the fold, 1,000 kept: every 10th row of the log) ...
    assert np.sort(gaps)[-2] <= 12 and gaps.max() <= 300 + 12  # ... but across the wall's 300 rows
    assert np.array_equal(validation_rows(lg, rows[:500], cap=1000), rows[:500])
    one = JointLog(["j"], np.zeros((5000, 1)))
    assert validation_rows(one, np.arange(5000), cap=100).size == 100


def test_weights_and_scale_on_synthetic_blocks():
    rng = np.random.default_rng(0)
    r = rng.normal(0, 2.0, (400, 6))
    r[:4] += 100.0
    assert mad_scale([r]) == pytest.approx(2.0, rel=0.1)
    wh = weights([r], "huber")[0]
    wc = weights([r], "cauchy")[0]
    assert np.all(wh[:4] < 0.1) and np.all(wc[:4] < 0.01)
    assert np.mean(wh[4:] == 1.0) > 0.9  # Huber leaves ~95 % of clean configurations alone
    assert np.all((wc > 0) & (wc <= 1))
    s = suspects([r])
    assert sorted(x.index for x in s) == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        weights([r], "l1")


@pytest.mark.slow
def test_three_gross_outliers_are_flagged(scenario):
    sc = scenario
    problem = build_problem(sc.robot, sc.log(), sc.loops)
    truth = sc.truth_vector(problem)
    rng = np.random.default_rng(7)
    th = sc.theta + rng.normal(0, NOISE, sc.theta.shape)
    bad = [5, 42, 77]
    for i in bad:  # shift joint 1 so that the closure (at the truth) is off by 5 cm
        Jq = problem.evaluate(truth, True, [sc.theta[i : i + 1]])[0].Jq[0]
        th[i, 0] += 0.05 / np.linalg.norm(Jq[:3, 0])
        r = problem.evaluate(truth, False, [th[i : i + 1]])[0].r[0]
        assert np.linalg.norm(r[:3]) == pytest.approx(0.05, rel=0.02)
    # Least squares (unweighted: the noise-weighted LM does not converge with these outliers),
    # then Cauchy IRLS from it; flags at the robust solution.
    ls = calibrate(sc.robot, sc.log(th), sc.loops, CalibrationOptions(noise=NOISE, weighting="none", robust=None))
    d_ls = np.linalg.norm(config_residuals(ls.problem, ls.fit.values, NOISE)[0], axis=1)
    assert set(np.argsort(-d_ls)[:3]) == set(bad)  # already the three largest at the LS fit
    out = irls(ls, "cauchy", noise=NOISE, max_iter=100)
    flagged = sorted(s.row for s in out.suspects)
    assert flagged == [i + 1 for i in bad]  # log rows are 1-based
    assert all(s.standardized > 100 for s in out.suspects)
    w = out.weights[0]
    assert np.all(w[bad] < 1e-4) and np.delete(w, bad).min() > 0.1
    # Robust estimate is back at clean accuracy (in units of the clean standard errors)
    clean_th = th.copy()
    clean_th[bad] = sc.theta[bad]
    clean = calibrate(sc.robot, sc.log(clean_th), sc.loops, CalibrationOptions(noise=NOISE))
    est = clean.fit.estimated
    assert ls.fit.estimated == est
    z = (out.values - truth)[est] / clean.fit.std[est]
    assert np.max(np.abs(z)) < 4.0
    # Huber: the outliers get tiny weights and are the three most suspect
    hub = irls(ls, "huber", noise=NOISE, max_iter=100)
    assert sorted(s.row for s in hub.suspects[:3]) == [i + 1 for i in bad]
    assert np.all(hub.weights[0][bad] < 0.05)
