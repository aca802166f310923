"""The outlier screen's metric is the joint-noise whitening whatever the fit's weighting (`outliers.screen`):
an unweighted calibration of clean data rejects nothing.  Screened on its raw closures (metres and radians,
per component), it flagged configurations where the Jacobian amplifies the joint noise: on the Monte Carlo
weld (200 configurations, 1e-4 rad), 7 of 20 unweighted calibrations rejected one or two clean rows, and
every one of them went through the robust refit."""

from __future__ import annotations

import pytest

import closedloop.estimate.outliers as outliers
import closedloop.studies.montecarlo as mc_module
from closedloop.studies.montecarlo import monte_carlo, weld_scenario


@pytest.mark.slow
def test_unweighted_fit_of_clean_data_rejects_nothing(monkeypatch):
    results, refits = [], []
    calibrate, refit = mc_module.calibrate, outliers.robust_refit

    def recording_calibrate(*args, **kwargs):
        res = calibrate(*args, **kwargs)
        results.append(res)
        return res

    def recording_refit(*args, **kwargs):
        refits.append(args)
        return refit(*args, **kwargs)

    monkeypatch.setattr(mc_module, "calibrate", recording_calibrate)
    monkeypatch.setattr(outliers, "robust_refit", recording_refit)
    mc = monte_carlo(weld_scenario(n=200, seed=0), 1e-4, 12, seed=1, executor="serial")
    unweighted = [r for r in results if r.noise.weighting == "none"]
    assert len(unweighted) == 12
    assert all(not r.outliers.rejected for r in unweighted), [len(r.outliers.rejected) for r in unweighted]
    assert all(r.verdict.status == "ok" for r in results)
    assert not refits
    assert abs(mc.stats["noise"].trace_ratio - 1.0) < 0.25  # 12 draws: the bound to the sampling spread
