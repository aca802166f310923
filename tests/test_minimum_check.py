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


def _weld_log(panda_weld) -> JointLog:
    rng = np.random.default_rng(5)
    return JointLog(panda_weld.joints, panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape))


def test_a_solver_stopped_short_is_continued_to_the_minimum(panda, panda_weld, noisy, monkeypatch):
    """A solve that stops 4 standard errors short of the minimum along the weakest direction yet says
    `converged`: the profile check (run on every fit here) finds the cost falling by ~6 noise variances
    toward the minimum, the fit is solved again from the profile's lower point and ends at the minimum
    (the undisturbed calibration's values, to a hundredth of their standard errors), `converged`, with the
    profile check passed and the continuation said in the notes."""
    from closedloop.analysis import linearity
    from closedloop.calibration import pipeline

    monkeypatch.setattr(linearity, "PROFILE_AFTER", -1)
    est = list(noisy.fit.estimated)
    cov = noisy.fit.covariance
    prior = np.array([noisy.problem.params[k].prior for k in est])
    lam, V = np.linalg.eigh(cov / np.outer(prior, prior))
    u = V[:, -1] * prior  # the weakest direction, in parameter units, one standard error long
    u *= np.sqrt(lam[-1]) / np.linalg.norm(V[:, -1])
    screened = pipeline.solve_screened
    first = []

    def short(problem, x0, *args, **kw):
        out = screened(problem, x0, *args, **kw)
        fit = out[1]
        if not first:  # the first solve stops 4 standard errors away along u, and says converged
            fit.x = fit.x.copy()
            fit.x[fit.est] += 4.0 * u
            first.append(fit.x.copy())
        return out

    monkeypatch.setattr(pipeline, "solve_screened", short)
    res = calibrate(panda, _weld_log(panda_weld), [WeldLoop("fixture", "panda_hand")])
    assert first and res.converged and res.verdict.status == "ok", res.verdict.reasons
    assert res.noise.profiles and not any(p.falls for p in res.noise.profiles)
    assert any(n.startswith("the solver stopped short of the minimum") for n in res.notes), res.notes
    err = (res.fit.values - noisy.fit.values)[est] / np.sqrt(np.diag(cov))
    assert np.abs(err).max() < 0.01, np.abs(err).max()  # at the minimum (started 4 standard errors off)


def test_converged_only_where_the_profile_check_finds_a_minimum(panda, panda_weld, monkeypatch):
    """Where every profile falls (a cost that keeps falling: no minimum) the fit is solved again
    `MINIMUM_RESTARTS` times, then not called converged: the verdict fails, saying the profile found no
    minimum.  (With the check passed the fit is `converged`: the test above.)"""
    from closedloop.analysis import linearity
    from closedloop.calibration import pipeline

    monkeypatch.setattr(linearity, "PROFILE_AFTER", -1)
    profile = linearity.profile
    calls = []

    def falling(*args, **kw):
        p = profile(*args, **kw)
        calls.append(p)
        return replace(p, rise=(-1.0, p.rise[1]), lower=args[1].copy())  # lower at the solution itself

    monkeypatch.setattr(linearity, "profile", falling)
    res = calibrate(panda, _weld_log(panda_weld), [WeldLoop("fixture", "panda_hand")])
    assert len(calls) == (pipeline.MINIMUM_RESTARTS + 1) * len(res.noise.profiles)
    assert not res.converged and res.fit.solver_status == "stalled"
    assert res.fit.solver_message.startswith(f"no minimum found: after {pipeline.MINIMUM_RESTARTS} restart(s)")
    assert res.verdict.status == "failed"
    assert any("no minimum found" in r for r in res.verdict.reasons), res.verdict.reasons
