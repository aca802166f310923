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
    lowpass,
    per_cycle_moments,
    single_thread,
    solve,
)

log = logging.getLogger(__name__)


@dataclass
class Bands:
    """Percentile bands (lo, hi) per parameter on the estimate's time grid; `bias`, the estimator's bias
    found by simulation (`simulated_bias`) by which I, B and K's bands were widened (None: not widened)."""

    level: float
    n_boot: int
    lo: dict[str, np.ndarray]
    hi: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    bias: dict[str, np.ndarray] | None = None


def _smooth(v: np.ndarray, sigma: float, cuts: np.ndarray) -> np.ndarray:
    """Gaussian smoothing (std `sigma` samples) of a cycle-periodic curve, within each stretch between the
    instants `cuts` (the steps: never across one; at most a quarter of the stretch) or around the cycle."""
    L = v.size
    v = np.where(np.isfinite(v), v, np.nanmedian(v))
    cuts = np.unique(np.mod(np.asarray(cuts, int), L))
    r = int(cuts[0]) if cuts.size else 0
    u = np.roll(v, -r)
    bounds = np.r_[cuts - r, L] if cuts.size else np.array([0, L])
    out = np.empty(L)
    for a, b in zip(bounds[:-1], bounds[1:]):
        sg = min(sigma, (b - a) / 4)
        if sg < 0.5:
            out[a:b] = u[a:b]
            continue
        k = np.arange(-int(3 * sg), int(3 * sg) + 1)
        g = np.exp(-0.5 * (k / sg) ** 2)
        g /= g.sum()
        y = u[a:b].copy()
        if cuts.size and b - a > 8:  # the instants at a step belong to neither side for certain
            y[:2], y[-2:] = y[2], y[-3]
        out[a:b] = np.convolve(np.pad(y, k[-1], mode="reflect" if cuts.size else "wrap"), g, "valid")
    return np.roll(out, r)


def smoothed_model(est, fs: float, smooth_ms: float = 50.0) -> np.ndarray:
    """I, B, K (3, L) of `est` smoothed over `smooth_ms` (Gaussian std) within the stretches between the
    steps it found, never across one: the model `simulated_bias` simulates, its random wiggles removed."""
    cuts = np.array([]) if est.steps is None else np.round(np.asarray(est.steps) * fs)
    return np.stack([_smooth(np.asarray(getattr(est, k), float), smooth_ms * 1e-3 * fs, cuts) for k in "IBK"])


def model_response(ens: Ensemble, est, smooth_ms: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed identified model (`smoothed_model`, (3, L)) and its noise-free response (n, L + 2 pad)
    to each cycle's measured torque perturbation (eq. 7.9, `free_run` from the pre-filtered initial state at
    the start of the padding, the cycle's parameters repeated over the padding)."""
    P, L, fs = ens.pad, ens.length, ens.fs
    dth, dtau, _ = ens.deltas()
    truth = smoothed_model(est, fs, smooth_ms)
    on_pad = np.mod(np.arange(L + 2 * P) - P, L)
    hz = est.options.prefilter_hz
    f = lowpass(dth, fs, hz) if hz else dth
    I_pad, B_pad, K_pad = (t[on_pad] for t in truth)
    return truth, free_run(I_pad, B_pad, K_pad, dtau, f[:, 0], (f[:, 1] - f[:, 0]) * fs, fs)


def simulated_bias(ens: Ensemble, est, smooth_ms: float = 50.0) -> np.ndarray:
    """The estimator's own bias (3, L) near the identified model, by simulation.

    The identified I(t), B(t), K(t), smoothed over `smooth_ms` between the steps found (so that their
    random wiggles are not taken for structure), are driven by the measured torque perturbations of every
    cycle (`model_response`); the responses, free of noise, go through the same estimator (options,
    pre-filter and blend of one-sided fits as `est`; the measured noise ratio).  What comes back minus what
    went in is the bias that the pre-filter's and the pooling's reach, the one-sided fits' blend and the
    discrete model's approximation put into an estimate of such a truth: next to steps of K it is as large
    as the random error (the other level leaks in), on smooth truths a fraction of it."""
    from dataclasses import replace

    from closedloop.impedance.estimate import noise_std, refit

    dth, dtau, _ = ens.deltas()
    truth, x = model_response(ens, est, smooth_ms)
    sim = replace(ens, angle=ens.angle.mean(0) + x)
    ratio = max(noise_std(dth), 1e-12) / max(noise_std(dtau), 1e-12)
    back = refit(sim, replace(est.options, noise_ratio=ratio, auto_iv=False), est.weights)
    return np.where(np.isfinite(back), back - truth, 0.0)


def bootstrap(
    ens: Ensemble,
    options: EstimateOptions,
    n_boot: int = 200,
    level: float = 0.95,
    seed: int = 0,
    chunk: int = 25,
    executor=None,
    est=None,
    bias_check: bool = True,
) -> Bands:
    """Bootstrap over cycles (see module docstring): bands for I, B, K, wn and zeta.

    `est`, the `ImpedanceEstimate` (optional): where it blends the centred fit with one-sided fits beside
    steps (`est.weights`), so does every resample (the one-sided fits resampled only where they weigh), and
    within 10 ms of a step the band spans both sides' levels (the step's time is known to a few samples).
    Where the centred and a one-sided fit are blended (the taper at the edge of a step's reach), the centred
    fit still sees the step: the band is widened by its weight times the two fits' difference, a bound on
    the bias it brings in (`ImpedanceEstimate.blend_spread`).  With `bias_check` (and `est`), I, B and K's
    bands are widened on both sides by the estimator's own bias at the identified model (`simulated_bias`,
    in `Bands.bias`): bias-aware bands.  What they still miss is model error outside eq. 7.9 (the
    linearisation of a nonlinear limb, unmodelled actuator dynamics).
    The bands are computed every 10 ms (at most half the pooling half-width) and interpolated:
    the pooled, pre-filtered estimate does not change faster.  `est` must be the estimate of `ens`: its
    designs (the filtered, scaled regressors) are reused when its options are `options`.

    The resamples go in chunks of `chunk` as jobs on `executor` (``closedloop.parallel.executor``: None or
    'serial' in this process, 'local', 'ray', or an engine); chunk c draws its resamples from
    ``default_rng(SeedSequence(seed).spawn(n_chunks)[c])``, so the bands are the same on every
    engine and worker count (for a given `chunk`).  The shared moments travel once per worker.
    """
    from closedloop.impedance.estimate import resolved
    from closedloop.parallel.executor import run

    options = resolved(options, ens)
    L = ens.length
    half = int(round(options.pool_ms * 1e-3 * ens.fs))
    stride = max(1, min(half // 2, int(round(0.010 * ens.fs))))
    if options.smooth_ms > 0:  # IV: smoothed over smooth_ms, pooled over +-pool_ms
        stride = max(stride, int(round(0.25 * options.smooth_ms * 1e-3 * ens.fs)))
    # (side, instants the weights cover, instants computed): the centred fit on every stride-th instant
    grid = np.unique(np.r_[np.arange(0, L, stride), L - 1])
    comps: list[tuple[int, np.ndarray, np.ndarray]] = [(0, grid, grid)]
    weights = None if est is None else est.weights
    if weights is not None:
        for j, side in ((1, -1), (2, 1)):
            at = np.flatnonzero(weights[j] > 0)
            if at.size:  # every stride-th instant of each run of non-zero weight, and its ends
                ends = at[np.r_[True, np.diff(at) > 1] | np.r_[np.diff(at) > 1, True]]
                comps.append((side, at, np.unique(np.r_[at[::stride], ends])))
    with single_thread():
        pers, perzs, lights, sizes_t = [], [], [], []
        m = qz = None
        for side, _, at in comps:
            sizes_t.append(at.size)
            d = est.designs.get(side) if est is not None and est.options == options else None
            d = design(ens, options, side=side) if d is None else d
            _, n, m = d.X.shape
            qz = None if d.Z is None else d.Z.shape[-1]
            per, perz = per_cycle_moments(d, half, at)
            pers.append(per.reshape(n, -1))
            if perz is not None:
                perzs.append(perz.reshape(n, -1))
            lights.append(SimpleNamespace(scale=d.scale, T=d.T))
        per = np.concatenate(pers, axis=1)
        perz = np.concatenate(perzs, axis=1) if perzs else None
        Ls = sum(sizes_t)
        Mxx = per.sum(0).reshape(Ls, m, m)
        Mzx = None if perz is None else perz.sum(0).reshape(Ls, qz, -1)
        p0 = solve(Mxx, Mzx, options.method)[0] if options.method in ("default", "thesis") else None
        sizes = [min(chunk, n_boot - c) for c in range(0, n_boot, max(1, chunk))]
        dims = (sizes_t, m, qz, stride)
        parts = run(
            _resample_chunk, sizes, executor, shared=(lights, dims, per, perz, p0, options, ens.fs, n), seed=seed
        )
    I, B, K = (np.concatenate([p[j] for p in parts]) for j in range(3))  # (R, Ls)
    bounds = np.cumsum([0] + sizes_t)
    full = np.arange(L)
    blended = []
    for a in (I, B, K):
        parts_k = [a[:, bounds[c] : bounds[c + 1]] for c in range(len(comps))]
        centre = _interp_rows(parts_k[0], comps[0][1], full)
        if len(comps) == 1:
            blended.append(centre)
            continue
        assert weights is not None  # the one-sided components come with the estimate's weights
        num = weights[0] * np.nan_to_num(centre)
        den = weights[0] * np.isfinite(centre)
        for (side, at, sub), v in zip(comps[1:], parts_k[1:]):
            j = 1 if side < 0 else 2
            v = _interp_rows(v, sub, at)
            num[:, at] += weights[j][at] * np.nan_to_num(v)
            den[:, at] += weights[j][at] * np.isfinite(v)
        with np.errstate(invalid="ignore", divide="ignore"):
            blended.append(np.where(den > 0, num / den, np.nan))
    I, B, K = blended
    with np.errstate(invalid="ignore"):
        wn, zeta = np.sqrt(K / I), B / (2 * np.sqrt(K * I))
    q = (1 - level) / 2 * 100
    lo, hi, sd = {}, {}, {}
    for k, a in zip(("I", "B", "K", "wn", "zeta"), (I, B, K, wn, zeta)):
        ok = np.isfinite(a)
        if ok.all():
            lo[k], hi[k] = np.percentile(a, [q, 100 - q], axis=0)
            sd[k] = a.std(axis=0)
        else:
            a = np.where(ok, a, np.nan)
            with np.errstate(invalid="ignore"):
                lo[k], hi[k] = np.nanpercentile(a, q, axis=0), np.nanpercentile(a, 100 - q, axis=0)
                sd[k] = np.nanstd(a, axis=0)
    if est is not None and est.steps is not None and len(est.steps):
        from numpy.lib.stride_tricks import sliding_window_view

        r = max(1, int(round(0.010 * ens.fs)))

        def running(fn, a: np.ndarray) -> np.ndarray:  # min or max over +-r samples (edges repeated)
            return fn(sliding_window_view(np.pad(a, r, mode="edge"), 2 * r + 1), axis=-1)

        near = np.zeros(L, bool)
        for t0 in np.round(np.asarray(est.steps) * ens.fs).astype(int):
            for t in (t0 - L, t0, t0 + L):  # the cycle's ends are neighbours
                near[max(0, t - r) : max(0, t + r)] = True
        for k in lo:
            lo[k] = np.where(near, running(np.min, lo[k]), lo[k])
            hi[k] = np.where(near, running(np.max, hi[k]), hi[k])
    if est is not None and est.blend_spread is not None:  # the centred fit's share of a step's bias
        for j, k in enumerate("IBK"):
            lo[k], hi[k] = lo[k] - est.blend_spread[j], hi[k] + est.blend_spread[j]
    bias = None
    if est is not None and bias_check:
        b = simulated_bias(ens, est)
        bias = {k: b[j] for j, k in enumerate("IBK")}
        for k in "IBK":
            lo[k], hi[k] = lo[k] - np.abs(bias[k]), hi[k] + np.abs(bias[k])
    return Bands(level, n_boot, lo, hi, sd, bias)


def _interp_rows(a: np.ndarray, at: np.ndarray, full: np.ndarray) -> np.ndarray:
    """Linear interpolation of every row of `a` (given at the sorted instants `at`) onto `full`."""
    if at.size == full.size:
        return a
    j = np.clip(np.searchsorted(at, full, side="right"), 1, at.size - 1)
    f = (full - at[j - 1]) / (at[j] - at[j - 1])
    return a[:, j - 1] * (1 - f) + a[:, j] * f


def _resample_chunk(
    lights: list,
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
    """One job: r resamples of the n cycles (counts w), their pooled moments sum_i w_i x_i x_i^T, solved
    (eq. 9.13 by inverse iteration from the full-sample solution, or 2SLS) and converted: (I, B, K).

    lights: each component's scale and lag; dims: (instants per component, regressors m, instruments q,
    stride of the centred component)."""
    from closedloop.impedance.estimate import to_ibk
    from closedloop.impedance.filters import gaussian_filter1d

    sizes_t, m, qz, stride = dims
    Ls = sum(sizes_t)
    with single_thread():
        W = np.stack([np.bincount(rng.integers(0, n, n), minlength=n) for _ in range(r)]).astype(float)
        Mxx = (W @ per).reshape(r, Ls, m, m)
        Mzx = None if perz is None else (W @ perz).reshape(r, Ls, qz, -1)
        p, _ = solve(Mxx, Mzx, options.method, start=p0, want_cond=False)
        out = []
        lo = 0
        for c, (size, light) in enumerate(zip(sizes_t, lights)):
            pc = p[:, lo : lo + size]
            if options.smooth_ms > 0 and c == 0:
                pc = gaussian_filter1d(pc, options.smooth_ms * 1e-3 * fs / stride, axis=-2)
            out.append(np.stack(to_ibk(pc, light.scale, light.T)))
            lo += size
    return tuple(np.concatenate(out, axis=-1))


def _fill(x: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x)
    if ok.all() or not ok.any():
        return x
    i = np.arange(len(x))
    return np.interp(i, i[ok], x[ok])


def free_run(I, B, K, u: np.ndarray, x0: np.ndarray, v0: np.ndarray, fs: float) -> np.ndarray:
    """RK4 of I x'' + B x' + K x = u (eq. 7.9 driven by the measured torque perturbation) for all rows of
    u (n, L); the parameters are one curve (L,) for every row or one per row (n, L), linear between
    samples as the input is."""
    I, B, K = (np.apply_along_axis(_fill, -1, np.asarray(a, float)) for a in (I, B, K))
    I, B, K = (np.broadcast_to(a, u.shape) for a in (I, B, K))
    h = 1.0 / fs
    n, L = u.shape

    def mid(a):
        return np.concatenate([0.5 * (a[:, 1:] + a[:, :-1]), a[:, -1:]], axis=1)

    Im, Bm, Km, um = mid(I), mid(B), mid(K), mid(u)
    x, v = x0.astype(float).copy(), v0.astype(float).copy()
    out = np.empty((n, L))
    np_err = np.seterr(over="ignore", invalid="ignore")  # a diverging row runs on as inf/NaN
    for k in range(L):
        out[:, k] = x
        a1 = (u[:, k] - B[:, k] * v - K[:, k] * x) / I[:, k]
        x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
        a2 = (um[:, k] - Bm[:, k] * v2 - Km[:, k] * x2) / Im[:, k]
        x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = (um[:, k] - Bm[:, k] * v3 - Km[:, k] * x3) / Im[:, k]
        kn = min(k + 1, L - 1)
        x4, v4 = x + h * v3, v + h * a3
        a4 = (u[:, kn] - B[:, kn] * v4 - K[:, kn] * x4) / I[:, kn]
        x = x + h / 6 * (v + 2 * v2 + 2 * v3 + v4)
        v = v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
    np.seterr(**np_err)
    return out


@dataclass
class FitReport:
    vaf: float  # overall free-run VAF (%) on held-out cycles
    vaf_t: np.ndarray  # per instant (%)
    folds: int


def free_run_vaf(ens: Ensemble, options: EstimateOptions, folds: int = 5, seed: int = 0) -> FitReport:
    """k-fold free-run VAF of the time-varying model on held-out cycles (module docstring)."""
    from dataclasses import replace

    from closedloop.impedance.estimate import cutoff, resolved

    options = replace(resolved(options, ens), auto_iv=False)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(ens.n)
    P, L, fs = ens.pad, ens.length, ens.fs
    n = ens.n
    prm = np.empty((3, n, L))
    u = np.empty((n, L))
    ref = np.empty((n, L))
    x0, v0 = np.empty(n), np.empty(n)
    for f in range(folds):  # each fold's cycles get the model fitted to the others; one integration for all
        test = perm[f::folds]
        train = np.setdiff1d(perm, test)
        tr, te = ens.subset(train), ens.subset(test)
        est = estimate(tr, options=options, warn=False)
        prm[:, test] = np.stack([est.I, est.B, est.K])[:, None, :]
        dth, dtau, _ = te.deltas(tr)
        with single_thread():  # (the pre-filter's small products: BLAS threads only contend)
            dth, dtau = lowpass(dth, fs, cutoff(options)), lowpass(dtau, fs, cutoff(options))
        ref[test], u[test] = dth[:, P : P + L], dtau[:, P : P + L]
        x0[test], v0[test] = dth[:, P], (dth[:, P + 1] - dth[:, P - 1]) * fs / 2
    x = free_run(prm[0], prm[1], prm[2], u, x0, v0, fs)
    err = ref - x
    with np.errstate(invalid="ignore", divide="ignore"):
        vaf_t = 100 * (1 - np.sum(err**2, 0) / np.sum(ref**2, 0))
        vaf = 100 * (1 - np.nansum(err**2) / np.sum(ref**2)) if np.all(np.isfinite(err)) else -np.inf
    return FitReport(float(vaf), vaf_t, folds)
