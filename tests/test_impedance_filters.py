"""The estimator's numpy signal processing (closedloop.impedance.filters) equals scipy's on random
signals, and `impedance identify` runs without importing scipy.signal or scipy.ndimage."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from closedloop.impedance import filters as F

FS = 600.0000083339121  # a rate read from rounded time stamps, as `Record.fs` gives it


# scipy's references are imported when a test asks, not at import: every xdist worker imports this file to
# collect it, and scipy.signal alone takes a second and a half.
@pytest.fixture(scope="module")
def signal():
    from scipy import signal

    return signal


@pytest.fixture(scope="module")
def ndimage():
    from scipy import ndimage

    return ndimage


@pytest.fixture(scope="module")
def x():
    rng = np.random.default_rng(0)  # a random walk plus white noise: low and high frequencies, no zero mean
    return np.cumsum(rng.standard_normal((40, 1620)), -1) * 0.01 + rng.standard_normal((40, 1620)) + 3.0


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("hz", [1.0, 6.0, 11.13, 40.0, 250.0])
def test_butterworth_filters_equal_scipys(signal, x, order, hz):
    sos = signal.butter(order, hz, fs=FS, output="sos")
    if order % 2 == 0 or hz < 100:  # (odd orders near Nyquist: scipy pairs the real pole elsewhere)
        np.testing.assert_allclose(F.butter_sos(order, hz, FS), sos, rtol=1e-13, atol=1e-16)
    scale = np.abs(x).max()
    tol = 1e-11 * scale  # the recursion's rounding, amplified by the poles' closeness to 1 at low cut-off
    ref = signal.sosfiltfilt(sos, x, axis=-1)
    assert np.abs(F.filtfilt(x, order, hz, FS) - ref).max() < tol
    assert np.abs(F.causal(x, order, hz, FS) - signal.sosfilt(sos, x, axis=-1)).max() < tol
    back = signal.sosfilt(sos, x[:, ::-1], axis=-1)[:, ::-1]
    assert np.abs(F.causal(x, order, hz, FS, side=1) - back).max() < tol
    assert np.abs(F.filtfilt(x[0], order, hz, FS) - ref[0]).max() < tol  # one signal, 1-D


def test_filtfilt_refuses_a_signal_shorter_than_its_padding():
    with pytest.raises(ValueError, match="padding"):
        F.filtfilt(np.ones(10), 4, 10.0, FS)


@pytest.mark.parametrize("n, nperseg", [(1620, 1024), (1001, 1001), (3000, 511), (700, 256)])
def test_welch_equals_scipys(signal, n, nperseg):
    y = np.cumsum(np.random.default_rng(1).standard_normal((3, n)), -1)
    f, P = F.welch(y, FS, nperseg)
    f0, P0 = signal.welch(y, fs=FS, nperseg=nperseg, axis=-1)
    np.testing.assert_allclose(f, f0, rtol=1e-15)
    np.testing.assert_allclose(P, P0, rtol=1e-12, atol=1e-14 * P0.max())


def test_find_peaks_equals_scipys_with_plateaus_and_ties(signal):
    rng = np.random.default_rng(2)
    for _ in range(400):
        y = np.round(rng.standard_normal(int(rng.integers(1, 300))) * 3) / 3  # coarse values: plateaus, ties
        height, distance = float(rng.uniform(-1, 2)), int(rng.integers(1, 40))
        expected = signal.find_peaks(y, height=height, distance=distance)[0]
        np.testing.assert_array_equal(F.find_peaks(y, height, distance), expected)


@pytest.mark.parametrize("sigma", [0.4, 3.0, 18.0, 30.0])
@pytest.mark.parametrize("shape, axis", [((1200,), -1), ((1200, 8), -2), ((25, 201, 8), -2), ((5, 40), -1)])
def test_gaussian_filter1d_equals_scipys(ndimage, sigma, shape, axis):
    a = np.random.default_rng(3).standard_normal(shape) + 1.0
    ref = ndimage.gaussian_filter1d(a, sigma, axis=axis, mode="nearest")
    np.testing.assert_allclose(F.gaussian_filter1d(a, sigma, axis=axis), ref, rtol=0, atol=1e-14)


RUN = """
import json, sys
from closedloop.cli.main import main
rc = main(sys.argv[2:])
with open(sys.argv[1], "w") as fh:
    json.dump({"rc": rc, "modules": sorted(m for m in sys.modules if m.startswith(("scipy.signal", "scipy.ndimage")))}, fh)
"""


def test_identify_imports_no_scipy_signal(tmp_path):
    """scipy.signal's import (scipy.stats, interpolate, optimize) would cost more than the estimation."""
    from closedloop.impedance.data import write_record
    from closedloop.impedance.model import ExperimentConfig
    from closedloop.impedance.simulation import simulate

    data = tmp_path / "data.csv"
    write_record(data, simulate(ExperimentConfig(n_cycles=30, noise=0.05, seed=5, cycles_per_block=3)).record)
    out = tmp_path / "modules.json"
    argv = ["impedance", "identify", str(data), "--out", str(tmp_path / "r.json")]
    p = subprocess.run([sys.executable, "-c", RUN, str(out), *argv], capture_output=True, text=True, timeout=600)
    assert out.exists(), p.stderr
    res = json.loads(out.read_text())
    assert res["rc"] == 0 and res["modules"] == [], res
    summary = json.loads((tmp_path / "r.json").read_text())["summary"]
    assert summary["vaf_free_run"] > 95 and 0 < summary["expected_error_percent"]["K"] < 5, summary
