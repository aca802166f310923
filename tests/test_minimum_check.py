"""The verdict checks that the solver's stop is a minimum (`CalibrationResult.reducible`, `verdict._minimum`).

At a least-squares minimum the whitened residual is orthogonal to the Jacobian's columns: one
Gauss-Newton step removes nothing.  A fit displaced from its minimum by a known number of standard
errors must show the share of the cost that step removes, d^2 / (dof + d^2), and a result whose stop
is not a minimum is never `ok`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from closedloop import CalibrationOptions, JointLog, WeldLoop, calibrate
from closedloop.calibration.pipeline import analyse_solution
from closedloop.calibration.verdict import judge
from closedloop.estimate.residual import Fit, ResidualFunction, StageResult


@pytest.fixture(scope="module")
def noisy(panda, panda_weld):
    rng = np.random.default_rng(5)
    log = JointLog(panda_weld.joints, panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape))
    return calibrate(panda, log, [WeldLoop("fixture", "panda_hand")])


def _analysed_at(res, x: np.ndarray) -> dict:
    """`analyse_solution` of the result's problem at `x` (the unweighted-noise weighted fit, as calibrate runs)."""
    fun = ResidualFunction(res.problem, x, list(res.fit.estimated), np.ones(len(res.problem.joints)), "noise")
    fit = Fit(x, StageResult(None, fun), list(res.fit.estimated), fun.sigma_q, False, 0, [])
    return analyse_solution(res.problem, fit, CalibrationOptions(), list(res.fit.status))


def test_nothing_is_reducible_at_the_solution(noisy):
    assert noisy.verdict.status == "ok"
    assert noisy.fit.reducible < 1e-6  # seen: ~1e-11
    assert noisy.verdict.evidence["reducible"] == noisy.fit.reducible
    assert _analysed_at(noisy, noisy.fit.values)["reducible"] < 1e-6


@pytest.mark.slow
def test_a_point_off_the_minimum_shows_the_cost_a_step_removes(noisy):
    """Moved by d = 200 standard errors along one well-determined parameter: a Gauss-Newton step removes
    d^2 / (dof + d^2) of the cost (at least: the Mahalanobis distance of the move is at least d), and the
    verdict on such a stop is failed."""
    k = int(
        np.nanargmin(
            noisy.fit.std[noisy.fit.estimated] / np.array([noisy.problem.params[i].prior for i in noisy.fit.estimated])
        )
    )
    idx = noisy.fit.estimated[k]
    x = noisy.fit.values.copy()
    x[idx] += 200.0 * noisy.fit.std[idx]
    a = _analysed_at(noisy, x)
    expected = 200.0**2 / (a["dof"] + 200.0**2)
    assert expected > 0.8
    assert a["reducible"] >= 0.9 * expected and a["reducible"] < 1.0
    v = judge(replace(noisy, fit=replace(noisy.fit, reducible=a["reducible"])))
    assert v.status == "failed" and any("Gauss-Newton step" in r for r in v.reasons)


def test_the_thresholds_and_the_round_off_exception(noisy):
    assert judge(replace(noisy, fit=replace(noisy.fit, reducible=0.2))).status == "suspect"
    assert judge(replace(noisy, fit=replace(noisy.fit, reducible=0.05))).status == "ok"
    # a closure at round-off: the residual is no least-squares residual there, nothing is judged
    at_round_off = [replace(r, rms_m=1e-14, rms_rad=1e-14) for r in noisy.fit.residuals_after]
    v = judge(replace(noisy, fit=replace(noisy.fit, reducible=0.99, residuals_after=at_round_off)))
    assert not any("Gauss-Newton step" in r for r in v.reasons)
    v = judge(replace(noisy, fit=replace(noisy.fit, reducible=float("nan"))))  # bounds: not checked
    assert "reducible" not in v.evidence and v.status == "ok"


def test_a_profile_that_falls_restarts_the_fit_and_converged_means_a_minimum(panda, panda_weld, monkeypatch):
    """Where the profile check finds the cost lower beside the solution (`linearity.Profile.falls`), the fit
    restarts at that lower point, once: the result says so, counts both fits' iterations and keeps the first
    start's closures; where it falls again the result is not `converged` and the verdict is failed."""
    from closedloop.analysis.linearity import Profile
    from closedloop.calibration import pipeline

    rng = np.random.default_rng(5)
    log = JointLog(panda_weld.joints, panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape))
    seen = []

    def falls_once(problem, record, *args):
        seen.append(record)
        if len(seen) == 1:  # a lower point: the solution itself moved by 1e-4 along every estimated parameter
            return [Profile("a test direction", 1.0, (-1.0, 2.0), record.values[record.estimated] + 1e-4)], []
        return [], []

    monkeypatch.setattr(pipeline, "check_error_bars", falls_once)
    res = calibrate(panda, log, [WeldLoop("fixture", "panda_hand")])
    assert len(seen) == 2 and res.converged and res.verdict.status != "failed"
    assert np.allclose(seen[1].initial[seen[0].estimated], seen[0].values[seen[0].estimated] + 1e-4)
    assert res.fit.iterations == seen[0].iterations + seen[1].iterations
    assert np.array_equal(res.fit.initial, seen[0].initial)
    assert res.fit.residuals_before == seen[0].residuals_before
    a, b = (
        res.fit.residuals_after[0],
        seen[0].residuals_after[0],
    )  # the same closure (weak directions kept at the start)
    assert abs(a.rms_m - b.rms_m) <= 0.02 * b.rms_m and abs(a.rms_rad - b.rms_rad) <= 0.02 * b.rms_rad
    assert any("restarted at the profile's lower point" in n for n in res.notes), res.notes

    def always_falls(problem, record, *args):
        return [Profile("a test direction", 1.0, (-1.0, 2.0), record.values[record.estimated])], []

    monkeypatch.setattr(pipeline, "check_error_bars", always_falls)
    res = calibrate(panda, log, [WeldLoop("fixture", "panda_hand")])
    assert not res.converged and res.fit.solver_status == "stalled" and "no minimum" in res.fit.solver_message
    assert res.verdict.status == "failed"
