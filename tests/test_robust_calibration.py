"""Robust fitting: three 5 cm outliers in 200 configurations change neither the
estimated parameter set nor the held-out error by more than 10%, and are reported as suspects."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PANDA_Q0

from closedloop.calibration.pipeline import CalibrationOptions, calibrate, residual_stats
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.studies.truth import make_dataset


@pytest.fixture(scope="module")
def data(panda):
    rng = np.random.default_rng(21)
    ds = make_dataset(panda, WeldLoop("fixture", "panda_hand"), PANDA_Q0, 400, rng)
    train = ds.readings[::2] + rng.normal(0.0, 1e-4, ds.readings[::2].shape)
    held_out = ds.readings[1::2]  # exact readings of the same true robot
    return ds, train, held_out


def held_out_error(res, held_out) -> float:
    ev = res.problem.evaluate(res.fit.values, False, [held_out])
    return residual_stats(res.problem, ev)[0].rms_m


@pytest.mark.slow
def test_three_outliers(panda, data):
    ds, train, held_out = data
    clean = calibrate(panda, JointLog(ds.joints, train), [WeldLoop("fixture", "panda_hand")])
    bad_rows = [17, 88, 150]
    corrupt = train.copy()
    corrupt[bad_rows, 1] += 0.1  # shoulder: ~0.1 rad x ~0.5 m reach = ~5 cm closure error
    ev = clean.problem.evaluate(clean.fit.values, False, [corrupt])[0]
    assert np.linalg.norm(ev.r[bad_rows, :3], axis=1).min() > 0.03
    robust = calibrate(
        panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")], CalibrationOptions(robust="cauchy")
    )
    assert robust.converged
    assert [n for n, s in zip(robust.fit.names, robust.fit.status) if s == "estimated"] == [
        n for n, s in zip(clean.fit.names, clean.fit.status) if s == "estimated"
    ]
    h0, h1 = held_out_error(clean, held_out), held_out_error(robust, held_out)
    assert abs(h1 / h0 - 1.0) < 0.10, (h0, h1)
    assert sorted(s.row for s in robust.outliers.suspects) == [r + 1 for r in bad_rows]  # 1-based log rows
    assert any("suspect configuration: log row 18" in n for n in robust.notes)
    # plain least squares is pulled away by the same outliers
    plain = calibrate(
        panda,
        JointLog(ds.joints, corrupt),
        [WeldLoop("fixture", "panda_hand")],
        CalibrationOptions(weighting="none", robust=None),
    )
    assert held_out_error(plain, held_out) > 3 * h0


def test_default_rejects_the_three_outliers(panda, data):
    """The default (robust='auto') finds the same three rows, leaves them out, and predicts as the clean fit."""
    ds, train, held_out = data
    clean = calibrate(panda, JointLog(ds.joints, train), [WeldLoop("fixture", "panda_hand")])
    corrupt = train.copy()
    corrupt[[17, 88, 150], 1] += 0.1
    res = calibrate(panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")])
    assert sorted(r.row for r in res.outliers.rejected) == [18, 89, 151]
    h0, h1 = held_out_error(clean, held_out), held_out_error(res, held_out)
    assert abs(h1 / h0 - 1.0) < 0.10, (h0, h1)
    assert res.verdict.status == "ok", res.verdict.describe()


def test_screen_scale_is_the_same_for_either_whitening_root():
    """The outlier screen's scale (MAD of the whitened closures' components) on Gaussian closures with
    correlated, unequal covariances W_i: the inverse Cholesky factor (what the screen uses) and the symmetric
    root W_i^-1/2 both give the noise's scale, within the MAD's own sampling error."""
    from closedloop.estimate.noise import cholesky_inverse, pinv_sqrt
    from closedloop.estimate.robust import mad_scale

    rng = np.random.default_rng(5)
    A = rng.normal(size=(3000, 6, 7)) * rng.uniform(0.1, 3.0, (3000, 1, 7))
    W = A @ np.swapaxes(A, 1, 2)
    r = np.einsum("nij,nj->ni", A, rng.normal(0.0, 0.7, (3000, 7)))  # r_i ~ N(0, 0.49 W_i)
    F, kappa = cholesky_inverse(W)
    S, dropped = pinv_sqrt(W)
    assert np.all(kappa < 1e9) and dropped == 0
    chol = mad_scale([np.einsum("nij,nj->ni", F, r)])
    sym = mad_scale([np.einsum("nij,nj->ni", S, r)])
    assert chol == pytest.approx(0.7, rel=0.03) and sym == pytest.approx(0.7, rel=0.03)
    # the norms, which decide each configuration, are the same for either root
    np.testing.assert_allclose(
        np.linalg.norm(np.einsum("nij,nj->ni", F, r), axis=1),
        np.linalg.norm(np.einsum("nij,nj->ni", S, r), axis=1),
        rtol=1e-9,
    )


@pytest.mark.slow
def test_long_log_refit_on_a_sample(panda, data, monkeypatch):
    """A log longer than ROBUST_ROWS: the robust refit runs on an evenly spaced sample, every row is screened
    at its solution; the corrupted rows are rejected and the fit predicts as the clean fit on the rows kept
    (16 % corrupted rows of 200, the refit on 100)."""
    from closedloop.estimate import outliers

    ds, train, held_out = data
    rng = np.random.default_rng(5)
    bad = np.sort(rng.choice(train.shape[0], 32, replace=False))
    corrupt = train.copy()
    corrupt[bad, rng.integers(0, 7, bad.size)] += rng.choice([-1.0, 1.0], bad.size) * rng.uniform(0.05, 0.2, bad.size)
    sizes = []
    real = outliers.levenberg_marquardt

    def spy(fun, *args, **kw):
        sizes.append(sum(b.theta.shape[0] for b in fun.problem.blocks))
        return real(fun, *args, **kw)

    monkeypatch.setattr(outliers, "ROBUST_ROWS", 100)
    monkeypatch.setattr(outliers, "levenberg_marquardt", spy)
    res = calibrate(panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")])
    assert sizes and set(sizes) == {100}  # every pass of the refit on the sample
    assert sorted(r.row - 1 for r in res.outliers.rejected) == bad.tolist()
    kept = np.delete(train, bad, axis=0)
    clean = calibrate(panda, JointLog(ds.joints, kept), [WeldLoop("fixture", "panda_hand")])
    h0, h1 = held_out_error(clean, held_out), held_out_error(res, held_out)
    assert abs(h1 / h0 - 1.0) < 0.02, (h0, h1)
