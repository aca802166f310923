"""The defaults judged on the independent elbow (`impedance.elbow`: another limb, a 5 ms actuator delay and
lag, minimum-jerk movements, continuous-time inputs), 100 cycles of 2 s at 600 Hz, 5 % noise."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.impedance.bootstrap import bootstrap
from closedloop.impedance.data import onsets_from_events, segment
from closedloop.impedance.elbow import ElbowConfig, simulate_elbow
from closedloop.impedance.estimate import estimate
from closedloop.impedance.metrics import coverage, mean_rise_time, rel_errors

CASES = {
    "constant": {},
    "dip": {"stiffness": "dip"},
    "ramp-b": {"stiffness": "ramp-b"},
    "square": {"stiffness": "square"},
    "voluntary": {"voluntary_rms": 0.5},
}


class _Runs(dict):
    """Each case simulated and estimated when a test first asks for it (a test needs one or two of them)."""

    def __missing__(self, name: str):
        rec, truth = simulate_elbow(ElbowConfig(seed=1, **CASES[name]))
        ens = segment(rec, onsets_from_events(rec))
        self[name] = (ens, truth, estimate(ens, warn=False))
        return self[name]


@pytest.fixture(scope="module")
def runs():
    return _Runs()


def test_truth_is_the_linearised_model():
    """K_eff = K - m g r sin th_0 along the movement: gravity lowers it most with the forearm up."""
    cfg = ElbowConfig()
    from closedloop.impedance.elbow import truth

    tr = truth(cfg)
    assert np.isclose(tr["K"][0], 15.0 - 1.5 * 9.81 * 0.15 * np.sin(0.3))
    assert np.isclose(tr["K"].min(), 15.0 - 1.5 * 9.81 * 0.15 * np.sin(1.3), rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["constant", "dip", "ramp-b"])
def test_defaults_accuracy(runs, name):
    ens, truth, est = runs[name]
    err = rel_errors(est, truth)
    assert est.options.method == "default"
    assert err["I"] <= 1.5 and err["B"] <= 2.0 and err["K"] <= 1.5, err


def test_square_wave_sharp_and_accurate_away_from_steps(runs):
    ens, truth, est = runs["square"]
    assert mean_rise_time(est.t, est.K, truth["K"]) <= 0.045
    T = np.r_[truth["K"], truth["K"][:1]]
    jumps = np.r_[np.flatnonzero(np.abs(np.diff(T)) > 2) + 1, 0]
    d = np.min(np.abs(np.arange(len(est.t))[:, None] - jumps[None, :]), axis=1) / ens.fs
    away = 100 * np.mean(np.abs(est.K[d > 0.05] / truth["K"][d > 0.05] - 1))
    assert away <= 1.5, away


@pytest.mark.slow  # the same checks on the thesis forearm: test_impedance_estimate.py::test_iv_removes_voluntary_torque_bias
def test_voluntary_torque_switches_to_iv(runs):
    ens, truth, est = runs["voluntary"]
    assert est.options.method == "iv" and any("instrumental-variable" in n for n in est.notes)
    err = rel_errors(est, truth)
    assert max(err.values()) <= 10.0, err
    assert est.warnings == []


@pytest.mark.slow
def test_bootstrap_bands_cover_the_truth(runs):
    """95 % bias-aware bands: the truth inside them over at least 90 % of the cycle for every truth and
    parameter on average, never below 85 % (one realisation each; the benchmark averages over more).
    Without the simulated bias the square wave's K is covered over 76-83 % only (seeds 11-14)."""
    cov = {}
    for name in CASES:
        ens, truth, est = runs[name]
        b = bootstrap(ens, est.options, n_boot=100, seed=2, est=est)
        cov[name] = [coverage(b.lo[k], b.hi[k], truth[k]) for k in "IBK"]
    assert np.mean(list(cov.values())) >= 0.93 and np.min(list(cov.values())) >= 0.85, cov
    assert np.mean(cov["square"]) >= 0.9, cov


def test_simulated_bias_finds_the_leak_of_the_other_level(runs):
    """On the square wave of K the estimate of each level is pulled towards the other one (the pre-filter's
    and the pooling's reach): the simulated bias has that sign on both levels, is about the size of the
    actual error's mean there, and follows the actual error (correlation 0.44-0.48 at 5 % noise on seeds
    1-2, 0.76-0.77 without noise, where only the bias is left)."""
    from closedloop.impedance.bootstrap import simulated_bias

    ens, truth, est = runs["square"]
    b = simulated_bias(ens, est)[2]
    err = est.K - truth["K"]
    T = np.r_[truth["K"], truth["K"][:1]]
    jumps = np.r_[np.flatnonzero(np.abs(np.diff(T)) > 2) + 1, 0]
    d = np.min(np.abs(np.arange(len(err))[:, None] - jumps[None, :]), axis=1)
    low, away = truth["K"] < np.median(truth["K"]), d > 6
    assert np.mean(b[low & away]) > 0 > np.mean(b[~low & away])
    for m in (low & away, ~low & away):
        assert 0.3 < np.mean(b[m]) / np.mean(err[m]) < 3.0
    assert np.corrcoef(b[away], err[away])[0, 1] > 0.3


def test_bands_widened_where_the_step_fits_are_blended(runs):
    """Where the centred fit (which still sees the step) is blended with a one-sided one, the band takes
    its share of the difference: on the square wave the truth of B and K is inside it there at least 75 % of
    the time (the random-error band alone: 54-79 % over seeds 1-3), and nowhere else is it widened."""
    ens, truth, est = runs["square"]
    b = bootstrap(ens, est.options, n_boot=100, seed=2, est=est, bias_check=False)
    taper = (est.weights[0] > 0) & (est.weights[0] < 1)
    assert 0.1 < taper.mean() < 0.3
    for j, k in enumerate("BK"):
        sp = est.blend_spread[j + 1]
        assert np.all(sp[~taper] == 0) and np.mean(sp[taper] > 0) > 0.9
        inside = (truth[k] >= b.lo[k]) & (truth[k] <= b.hi[k])
        narrow = (truth[k] >= b.lo[k] + sp) & (truth[k] <= b.hi[k] - sp)
        assert inside[taper].mean() >= 0.75 and inside[taper].mean() > narrow[taper].mean() + 0.1, k
