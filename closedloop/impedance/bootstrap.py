"""Uncertainty and fit: bootstrap bands over cycles and free-run VAF on held-out cycles.

Bootstrap: the cycles are the independent units (the noise and the perturbation are independent across
cycles, thesis 9.6.2), so R resamples of n cycles with replacement give R estimates; their 2.5 and
97.5 percentiles are the 95 % bands.  All resamples share the per-cycle moment matrices: a resample is a
vector of counts w, its moment matrix sum_i w_i x_i x_i^T a matrix product, and the R x L small
eigen-problems are solved in one batched call.  (The ensemble mean is kept from the full sample: its
resampling changes the perturbations by O(1/n).)

Free-run VAF: k-fold over cycles, each fold's cycles are predicted by the time-varying model fitted to
the others, integrating I(t) x'' + B(t) x' + K(t) x = dtau(t) from the measured initial state only
(no measured output afterwards; the one-step-ahead VAF is ~99.9 % for any model at 600 Hz):

    VAF = 1 - sum (dth - x)^2 / sum dth^2     (overall and per instant, across the held-out cycles).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from closedloop.impedance.data import Ensemble
from closedloop.impedance.estimate import (
    EstimateOptions,
    design,
    estimate,
    finish,
    lowpass,
    moments,
    per_cycle_moments,
    pool,
    single_thread,
    solve,
)

log = logging.getLogger(__name__)


@dataclass
class Bands:
    """Percentile bands (lo, hi) per parameter on the estimate's time grid."""

    level: float
    n_boot: int
    lo: dict[str, np.ndarray]
    hi: dict[str, np.ndarray]
    std: dict[str, np.ndarray]


def bootstrap(
    ens: Ensemble,
    options: EstimateOptions,
    n_boot: int = 200,
    level: float = 0.95,
    seed: int = 0,
    chunk: int = 25,
    executor=None,
) -> Bands:
    """Bootstrap over cycles (see module docstring): bands for I, B, K, wn and zeta.

    The resamples go in chunks of `chunk` as jobs on `executor` (``closedloop.parallel.executor``: None or
    'serial' in this process, 'local', 'ray', or an engine); chunk c draws its resamples from
    ``default_rng(SeedSequence(seed).spawn(n_chunks)[c])``, so the bands are the same on every
    engine and worker count (for a given `chunk`).  The shared moments travel once per worker.
    """
    from closedloop.parallel.executor import run

    with single_thread():
        d = design(ens, options)
        per, perz = per_cycle_moments(d)
        Mxx, Mzx = moments(d)
        half = int(round(options.pool_ms * 1e-3 * ens.fs))
        p0 = (
            solve(pool(Mxx, half), pool(Mzx, half), options.method)[0]
            if options.method in ("default", "thesis")
            else None
        )
        sizes = [min(chunk, n_boot - c) for c in range(0, n_boot, max(1, chunk))]
        dims = (d.X.shape[0], d.X.shape[2], None if d.Z is None else d.Z.shape[-1])
        light = SimpleNamespace(scale=d.scale, T=d.T)  # what `finish` needs of the design (not X, Z)
        parts = run(
            _resample_chunk, sizes, executor, shared=(light, dims, per, perz, p0, options, ens.fs, ens.n), seed=seed
        )
    q = (1 - level) / 2 * 100
    lo, hi, sd = {}, {}, {}
    for j, k in enumerate(("I", "B", "K", "wn", "zeta")):
        a = np.concatenate([p[j] for p in parts])
        ok = np.isfinite(a)
        if ok.all():
            lo[k], hi[k] = np.percentile(a, [q, 100 - q], axis=0)
            sd[k] = a.std(axis=0)
        else:
            a = np.where(ok, a, np.nan)
            lo[k], hi[k] = np.nanpercentile(a, q, axis=0), np.nanpercentile(a, 100 - q, axis=0)
            sd[k] = np.nanstd(a, axis=0)
    return Bands(level, n_boot, lo, hi, sd)


def _resample_chunk(
    d,
    dims: tuple,
    per: np.ndarray,
    perz: np.ndarray | None,
    p0,
    options: EstimateOptions,
    fs: float,
    n: int,
    r: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, ...]:
    """One job: r resamples of the n cycles (counts w), their moments sum_i w_i x_i x_i^T, (I, B, K, wn, zeta).

    d: the design's scale and lag (for `finish`); dims: (instants L, regressors m, instruments q)."""
    L, m, qz = dims
    with single_thread():
        W = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(r)]).astype(float)
        Mxx = (W @ per).reshape(r, L, m, m)
        Mzx = None if perz is None else (W @ perz).reshape(r, L, qz, -1)
        I, B, K, _ = finish(d, Mxx, Mzx, options, fs, start=p0)
    with np.errstate(invalid="ignore"):
        wn, zeta = np.sqrt(K / I), B / (2 * np.sqrt(K * I))
    return I, B, K, wn, zeta


def _fill(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    if ok.all() or not ok.any():
        return x
    i = np.arange(len(x))
    return np.interp(i, i[ok], x[ok])


def free_run(I, B, K, u: np.ndarray, x0: np.ndarray, v0: np.ndarray, fs: float) -> np.ndarray:
    """RK4 of I x'' + B x' + K x = u for all rows of u (n, L); parameters and input linear between
    samples."""
    I, B, K = _fill(np.asarray(I, float)), _fill(np.asarray(B, float)), _fill(np.asarray(K, float))
    h = 1.0 / fs
    n, L = u.shape
    mid = lambda a: np.r_[0.5 * (a[1:] + a[:-1]), a[-1]]  # noqa: E731
    Im, Bm, Km, um = mid(I), mid(B), mid(K), np.c_[0.5 * (u[:, 1:] + u[:, :-1]), u[:, -1]]
    x, v = x0.astype(float).copy(), v0.astype(float).copy()
    out = np.empty((n, L))
    for k in range(L):
        out[:, k] = x
        k1 = (x, v, (u[:, k] - B[k] * v - K[k] * x) / I[k])
        f = lambda xx, vv, uu, i, b, kk: (uu - b * vv - kk * xx) / i  # noqa: E731
        x2, v2 = x + 0.5 * h * k1[1], v + 0.5 * h * k1[2]
        a2 = f(x2, v2, um[:, k], Im[k], Bm[k], Km[k])
        x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = f(x3, v3, um[:, k], Im[k], Bm[k], Km[k])
        kn = min(k + 1, L - 1)
        x4, v4 = x + h * v3, v + h * a3
        a4 = f(x4, v4, u[:, kn], I[kn], B[kn], K[kn])
        x = x + h / 6 * (v + 2 * v2 + 2 * v3 + v4)
        v = v + h / 6 * (k1[2] + 2 * a2 + 2 * a3 + a4)
        if not np.all(np.isfinite(x)):
            out[:, k + 1 :] = np.nan
            break
    return out


@dataclass
class FitReport:
    vaf: float  # overall free-run VAF (%) on held-out cycles
    vaf_t: np.ndarray  # per instant (%)
    folds: int


def free_run_vaf(ens: Ensemble, options: EstimateOptions, folds: int = 5, seed: int = 0) -> FitReport:
    """k-fold free-run VAF of the time-varying model on held-out cycles (module docstring)."""
    from dataclasses import replace

    from closedloop.impedance.estimate import resolved

    options = replace(resolved(options, ens), auto_iv=False)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(ens.n)
    P, L, fs = ens.pad, ens.length, ens.fs
    err = np.zeros((ens.n, L))
    ref = np.zeros((ens.n, L))
    for f in range(folds):
        test = perm[f::folds]
        train = np.setdiff1d(perm, test)
        tr, te = ens.subset(train), ens.subset(test)
        est = estimate(tr, options=options, warn=False)
        dth, dtau, _ = te.deltas(tr)
        dth, dtau = lowpass(dth, fs, options.prefilter_hz), lowpass(dtau, fs, options.prefilter_hz)
        y = dth[:, P : P + L]
        v0 = (dth[:, P + 1] - dth[:, P - 1]) * fs / 2
        x = free_run(est.I, est.B, est.K, dtau[:, P : P + L], y[:, 0], v0, fs)
        err[test], ref[test] = y - x, y
    with np.errstate(invalid="ignore", divide="ignore"):
        vaf_t = 100 * (1 - np.sum(err**2, 0) / np.sum(ref**2, 0))
        vaf = 100 * (1 - np.nansum(err**2) / np.sum(ref**2)) if np.all(np.isfinite(err)) else -np.inf
    return FitReport(float(vaf), vaf_t, folds)
