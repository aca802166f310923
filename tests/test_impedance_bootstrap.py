"""Bootstrap bands, free-run VAF and the impulse-response model check."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.impedance.bootstrap import bootstrap, free_run_vaf
from closedloop.impedance.data import onsets_from_events, segment
from closedloop.impedance.estimate import EstimateOptions, estimate
from closedloop.impedance.metrics import coverage
from closedloop.impedance.model import ExperimentConfig, natural
from closedloop.impedance.nonparam import model_check
from closedloop.impedance.simulation import simulate


@pytest.fixture(scope="module")
def data():
    sim = simulate(ExperimentConfig(n_cycles=100, noise=0.05, seed=21, stiffness="dip:20,0.4,0.15"))
    return segment(sim.record, onsets_from_events(sim.record)), sim.truth


def test_bands_cover_truth(data):
    ens, truth = data
    b = bootstrap(ens, EstimateOptions(), n_boot=200, seed=1)
    for k in "BK":
        assert coverage(b.lo[k], b.hi[k], truth[k]) >= 0.85, k
    assert np.all(b.hi["K"] >= b.lo["K"]) and np.median(b.hi["K"] - b.lo["K"]) < 2.0
    wn, zeta = natural(truth["I"], truth["B"], truth["K"])
    assert coverage(b.lo["wn"], b.hi["wn"], wn) > 0.8 and coverage(b.lo["zeta"], b.hi["zeta"], zeta) > 0.8


def test_free_run_vaf_on_held_out_cycles(data):
    ens, _ = data
    fit = free_run_vaf(ens, EstimateOptions(), folds=5)
    assert fit.vaf > 99.0 and np.nanmin(fit.vaf_t) > 95.0
    # a wrong model (stiffness halved) must fit worse
    from closedloop.impedance.bootstrap import free_run

    est = estimate(ens)
    dth, dtau, _ = ens.deltas()
    P, L = ens.pad, ens.length
    y = dth[:10, P : P + L]
    v0 = (dth[:10, P + 1] - dth[:10, P - 1]) * ens.fs / 2
    good = free_run(est.I, est.B, est.K, dtau[:10, P : P + L], y[:, 0], v0, ens.fs)
    bad = free_run(est.I, est.B, est.K / 2, dtau[:10, P : P + L], y[:, 0], v0, ens.fs)
    assert np.sum((y - good) ** 2) < 0.5 * np.sum((y - bad) ** 2)


def test_impulse_response_model_check(data):
    ens, _ = data
    est = estimate(ens)
    checks = model_check(ens, est, times=[0.5, 1.0])
    assert all(c.vaf > 90 for c in checks), [c.vaf for c in checks]
    # a wrong parametric model (inertia doubled, stiffness halved) fits the measured response worse
    est.I = est.I * 2
    assert all(c.vaf < 80 for c in model_check(ens, est, times=[0.5, 1.0]))
    est.I, est.K = est.I / 2, est.K / 2
    assert all(c.vaf < 60 for c in model_check(ens, est, times=[0.5, 1.0]))
