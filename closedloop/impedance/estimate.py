"""Ensemble time-varying identification of I(t), B(t), K(t) (thesis 9.6), batched over all instants.

At every instant c of the cycle the n cycles of the ensemble give n equations of a second-order
discrete model with lag spacing D samples (T = D h):

    dth(c+D) + a1 dth(c) + a2 dth(c-D) = b0 dtau(c+D) + b1 dtau(c) + b2 dtau(c-D)

(eq. 9.3/9.6).  The continuous parameters follow from the poles and the static gain, exact for any
hold: z_i = exp(s_i T), w0^2 = s1 s2, 2 zeta w0 = -(s1 + s2), K = (1 + a1 + a2) / (b0 + b1 + b2),
I = K / w0^2, B = 2 zeta w0 I (the inverse of eq. 9.7, written through the poles).

method="thesis": the literal thesis estimator - D = 1 sample, no b0, no pre-filter, TLS (eq. 9.10-9.13)
with the noise-variance ratio 1, the estimate stamped at the newest sample.  At h = 1.67 ms both poles
sit at z ~ 1 and the second difference of the noise is ~100x the acceleration: it fails at 5 % noise
and works only below ~0.01 % (README, "Time-varying joint impedance").

method="default" (TLS), "ols", "iv": the same zero-phase low-pass pre-filter on angle and torque (an
identical filter leaves the input-output relation of eq. 9.6 unchanged); by default its cut-off is chosen
from the data (`auto_prefilter`: where the angle perturbation's spectrum falls to 30 times the white
noise floor, 6 Hz at least), lags spaced `lag_ms` (~20 ms) apart, the
direct term b0 (first-order-hold-like input) and, when the pre-filter allows, torque taps at c +- D/2
as well (the filtered torque is not piecewise linear between the lags: the extra taps remove a 2 % bias
of I), estimates stamped at the window centre c and the equations pooled over +-20 ms.  TLS scales the
columns by the noise std estimated from each signal (Koopman's equal-variance assumption, 9.6.2).
"iv" uses the commanded perturbation at lags c+D, c, ..., c-(iv_lags-2)D as instruments (independent of
voluntary torque and of measurement noise; two-stage least squares over the over-determined set) and
needs temporal regularisation: equations pooled over +-`pool_ms` and the parameters smoothed over
`smooth_ms`.

Steps in I, B or K are kept sharp (method "default"): a step makes the centred fit's TLS residual (the
smallest eigenvalue of eq. 9.13) peak where the window straddles it; beside such a peak the estimate is
taken from one-sided fits (causal pre-filter and equations ending at the instant before the step,
anti-causal and starting at it after), which see only one regime (`edge_weights`).

The default also tests for unmeasured torque that is not the perturbation's response (voluntary torque
variability, which biases every least-squares form of eq. 9.8-9.13): where the record has the command,
the IV estimate is computed as well and, if the two differ by more than 10 % (mean over the cycle of
I, B or K), the IV estimate is returned with a note saying so (10 %-trimmed means; a Hausman-type comparison: both are
consistent without voluntary torque, only IV with it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Any, overload

import numpy as np

from closedloop.errors import InputError
from closedloop.impedance.data import Ensemble
from closedloop.impedance.filters import causal, filtfilt, find_peaks, gaussian_filter1d, welch

log = logging.getLogger(__name__)


def single_thread():
    """Limit BLAS/LAPACK to one thread (threadpoolctl): the work here is many tiny batched
    problems, for which threads only add contention (100x slower on a loaded 2-core machine).  The
    controller is cached (`closedloop.estimate.threads`): a fresh one scans the loaded libraries, ~1 ms."""
    from closedloop.estimate.threads import blas_threads

    return blas_threads(1)


METHODS = ("default", "thesis", "ols", "iv")
COND_WARN = 1e5
IV_SWITCH = 0.10  # relative TLS-IV difference (median over the cycle) above which the default switches


@dataclass
class EstimateOptions:
    method: str = "default"
    prefilter_hz: float | str | None = "auto"  # Hz; "auto": chosen from the data; None or 0: no filter
    lag_ms: float = 20.0
    direct_term: bool = True
    pool_ms: float = 20.0
    smooth_ms: float = 0.0
    noise_ratio: float | None = None  # std(angle noise)/std(torque noise); None = estimated
    taps: int | None = None  # torque samples over [c-D, c+D]; None: 5 if their spacing D/2 is
    # at least 1/(5 f_c) of the pre-filter, else 3 (the lags only)
    iv_lags: int = 10  # instruments: command at c+D, c, ..., c-(iv_lags-2) D (2SLS)
    order: int = 4
    auto_iv: bool = True  # "default" only: switch to IV when the command shows voluntary torque
    edges: bool = True  # "default" only: one-sided estimates beside abrupt changes (`edge_weights`)
    edge_ratio: float = 2.0  # a step: the centred fit's residual this many times its median ...
    edge_contrast: float = 1.8  # ... and this many times the one-sided fits' (each relative to its median);
    # both for 100 cycles: their excess over 1 scales as sqrt(100 / n)

    @classmethod
    def for_method(cls, method: str, **kw) -> "EstimateOptions":
        if method not in METHODS:
            raise InputError(f"method '{method}': expected one of {', '.join(METHODS)}")
        presets: dict[str, dict[str, Any]] = {
            "thesis": dict(prefilter_hz=None, lag_ms=0.0, direct_term=False, noise_ratio=1.0, pool_ms=0.0),
            "iv": dict(pool_ms=50.0, smooth_ms=30.0),
        }
        base = presets.get(method, {})
        base.update({k: v for k, v in kw.items() if v is not None})
        return cls(method=method, **base)


@dataclass
class ImpedanceEstimate:
    """I(t), B(t), K(t) on the cycle's time grid, with per-instant diagnostics."""

    t: np.ndarray
    I: np.ndarray
    B: np.ndarray
    K: np.ndarray
    cond: np.ndarray  # condition number of the scaled regressor moment matrix
    options: EstimateOptions
    lag: int
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    weights: np.ndarray | None = None  # (3, L): centred, left-sided, right-sided estimates' weights
    steps: np.ndarray | None = None  # instants (s) of the abrupt changes found
    blend_spread: np.ndarray | None = None  # (3, L): w_c |centred - one-sided| where the two are blended
    # the designs of the fit over the cycle's instants, by side (0 centred, -1 / +1 one-sided): the
    # bootstrap resamples their rows instead of filtering the same ensemble again
    designs: dict[int, "Design"] = field(default_factory=dict, repr=False, compare=False)

    @property
    def wn(self) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return np.sqrt(self.K / self.I)

    @property
    def zeta(self) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return self.B / (2 * np.sqrt(self.K * self.I))


def noise_std(x: np.ndarray) -> float:
    """Robust white-noise std from second differences: 1.4826 MAD(d2 x) / sqrt(6)."""
    d2 = np.diff(x, 2, axis=-1).ravel()
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


@dataclass
class Design:
    """Scaled regressors X (L, n, 6) = [th(c+D), th(c), th(c-D), tau(c+D), tau(c), tau(c-D)] and
    optional instruments Z (L, n, q); `scale` un-scales the null vector; T the lag in seconds."""

    X: np.ndarray
    Z: np.ndarray | None
    scale: np.ndarray
    T: float
    lag: int
    stamps: np.ndarray


def auto_prefilter(ens: Ensemble, snr: float = 30.0, lo: float = 6.0) -> float:
    """Pre-filter cut-off (Hz) from the data: the highest frequency at which the ensemble's angle
    perturbation (Welch spectrum, averaged over cycles) stands `snr` times above its white-noise floor (the
    median of the spectrum above fs/4), between `lo` and fs/5.  At 5 % noise this is 9-12 Hz for a human
    limb (the best fixed setting), higher with less noise or faster dynamics."""
    dth, _, _ = ens.deltas()
    nper = min(1024, dth.shape[1])
    f, P = welch(dth, ens.fs, nper)
    P = P.mean(0)
    floor = np.median(P[f > ens.fs / 4])
    above = np.flatnonzero(P > snr * floor)
    hz = float(f[above.max()]) if above.size else lo
    return float(np.clip(hz, lo, ens.fs / 5))


def resolved(opt: "EstimateOptions", ens: Ensemble) -> "EstimateOptions":
    """The options with an "auto" pre-filter replaced by its value for this ensemble."""
    if isinstance(opt.prefilter_hz, str):
        if opt.prefilter_hz != "auto":
            raise InputError(f"pre-filter '{opt.prefilter_hz}': expected a frequency in Hz, 'auto' or none")
        return replace(opt, prefilter_hz=round(auto_prefilter(ens), 2))
    return opt


def cutoff(opt: EstimateOptions) -> float | None:
    """The pre-filter cut-off (Hz) of options passed through `resolved` (None or 0: no filter)."""
    hz = opt.prefilter_hz
    assert not isinstance(hz, str), f"pre-filter '{hz}' not resolved to Hz"  # `resolved` replaces "auto"
    return hz


def lowpass(x: np.ndarray, fs: float, hz: float | None, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass (the pre-filter of both signals; none when `hz` is None or 0)."""
    if x is None or not hz:
        return x
    if not 0 < hz < fs / 2:
        raise InputError(f"pre-filter {hz} Hz must be below the Nyquist frequency {fs / 2:g} Hz and above 0")
    return filtfilt(x, order, hz, fs)


def _one_sided(x: np.ndarray, fs: float, hz: float | None, order: int, side: int) -> np.ndarray:
    """Causal (side -1) or anti-causal (side +1) Butterworth low-pass: the value at c depends only on the
    samples up to c (or from c on)."""
    if not hz:
        return x
    return causal(x, order, hz, fs, side)


def design(ens: Ensemble, opt: EstimateOptions, ref: Ensemble | None = None, side: int = 0, extend: int = 0) -> Design:
    """Pre-filter the perturbations and build the per-instant regressors of eq. 9.6 (window-centre stamps).

    side 0: the zero-phase pre-filter, equations centred on each instant t.  side -1 (+1): a causal
    (anti-causal) pre-filter and equations whose data end at t (start at t), pooled over the instants
    before (after) it: estimates that see only one side of t.  `extend` adds that many instants before and
    after the cycle (from the padding)."""
    opt = resolved(opt, ens)
    hz = cutoff(opt)
    dth, dtau, du = ens.deltas(ref)
    fs, P, L = ens.fs, ens.pad, ens.length
    D = max(1, int(round(opt.lag_ms * 1e-3 * fs)))
    if opt.method == "thesis":
        D = 1
    h = int(round(opt.pool_ms * 1e-3 * fs))
    shift = side * (D + h)
    need = (max(2, opt.iv_lags - 2) if opt.method == "iv" else 2) * D + h + extend + abs(shift)
    if P < need:
        raise InputError(f"cycle padding {P} samples is shorter than the lags and pooling need ({need})")
    if opt.noise_ratio is not None:
        s_th, s_tau = opt.noise_ratio, 1.0
    else:
        s_th, s_tau = max(noise_std(dth), 1e-12), max(noise_std(dtau), 1e-12)
    if side == 0:
        dth, dtau = lowpass(dth, fs, hz, opt.order), lowpass(dtau, fs, hz, opt.order)
    else:
        dth = _one_sided(dth, fs, hz, opt.order, side)
        dtau = _one_sided(dtau, fs, hz, opt.order, side)
    c = P + np.arange(-extend, L + extend) + shift
    if opt.method == "thesis":  # newest sample k = c; lags k-1, k-2 (eq. 9.10), stamped at k
        idx = [c, c - 1, c - 2]
    else:
        idx = [c + D, c, c - D]
    tidx = idx
    taps = opt.taps
    if taps is None:
        taps = 5 if hz and (D / 2) / fs >= 1 / (5 * hz) else 3
    if opt.method != "thesis" and taps > 3:
        tidx = [c + o for o in np.unique(np.round(np.linspace(D, -D, taps)).astype(int))[::-1]]
    cols = [dth[:, i] / s_th for i in idx] + [dtau[:, i] / s_tau for i in tidx]
    if opt.method == "thesis" or not opt.direct_term:
        cols.pop(3)
    X = np.stack(cols, axis=-1).transpose(1, 0, 2)  # (L, n, m)
    Z = None
    if opt.method == "iv":
        if du is None:
            raise InputError("method 'iv' needs the commanded perturbation (a 'command' column)")
        du = lowpass(du, fs, hz, opt.order)
        nz = max(opt.iv_lags, X.shape[-1] - 1)
        Z = np.stack([du[:, c + D - j * D] for j in range(nz)], axis=-1).transpose(1, 0, 2)
        Z = Z / du.std()
    scale = np.array([1 / s_th] * 3 + [1 / s_tau] * (X.shape[-1] - 3))
    return Design(X, Z, scale, D / fs, D, c - P - shift)


def moments(d: Design) -> tuple[np.ndarray, np.ndarray | None]:
    """Ensemble moment matrices per instant, sum_i x_i x_i^T (and sum_i z_i [x_i; z_i]^T)."""
    Mxx = np.swapaxes(d.X, -1, -2) @ d.X  # batched matrix products (BLAS): ~10x faster than einsum
    Mzx = None if d.Z is None else np.swapaxes(d.Z, -1, -2) @ np.concatenate([d.X, d.Z], -1)
    return Mxx, Mzx


def per_cycle_moments(d: Design, half: int, at: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-cycle moment matrices pooled over +-half instants (clipped to the cycle), at the instants `at`
    only: sum_k x_ik x_ik^T over the window of each instant, (n, len(at), m, m) (and the instruments'
    (n, len(at), q, m + q)); their weighted sums over cycles are the bootstrap's resampled moments."""
    offsets = np.arange(-half, half + 1)

    def windows(A: np.ndarray) -> np.ndarray:  # (n, instants, window, columns), zeros beyond the cycle
        padded = np.zeros((A.shape[1], A.shape[0] + 2 * half, A.shape[2]))
        padded[:, half : half + A.shape[0]] = A.transpose(1, 0, 2)
        return padded[:, at[:, None] + half + offsets]

    Xw = windows(d.X)
    per = np.swapaxes(Xw, -1, -2) @ Xw
    perz = None
    if d.Z is not None:
        Zw = windows(d.Z)
        Zt = np.swapaxes(Zw, -1, -2)
        perz = np.concatenate([Zt @ Xw, Zt @ Zw], -1)
    return per, perz


@overload
def pool(M: np.ndarray, half: int) -> np.ndarray: ...
@overload
def pool(M: None, half: int) -> None: ...


def pool(M: np.ndarray | None, half: int) -> np.ndarray | None:
    """Moving sum over +-half instants along the time axis (-3)."""
    if half <= 0 or M is None:
        return M
    L = M.shape[-3]
    cs = np.cumsum(np.concatenate([np.zeros_like(M[..., :1, :, :]), M], axis=-3), axis=-3)
    lo, hi = np.clip(np.arange(L) - half, 0, L), np.clip(np.arange(L) + half + 1, 0, L)
    return np.take(cs, hi, axis=-3) - np.take(cs, lo, axis=-3)


def solve(
    Mxx: np.ndarray, Mzx: np.ndarray | None, method: str, start: np.ndarray | None = None, want_cond: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Null vector p (normalised p[0] = 1, in scaled units) and the regressor condition number.

    TLS (eq. 9.13): the eigenvector of the smallest eigenvalue of J^T J, one batched `eigh`; with a
    `start` (the full-sample solution, in the bootstrap) four steps of inverse iteration instead."""
    R = Mxx[..., 1:, 1:]
    cond = None
    with np.errstate(invalid="ignore", divide="ignore"):
        if start is None and want_cond:  # condition of the regressors' correlation matrix (scale-free)
            dg = 1.0 / np.sqrt(np.maximum(np.diagonal(R, axis1=-2, axis2=-1), 1e-300))
            ev = np.linalg.eigvalsh(R * dg[..., :, None] * dg[..., None, :])
            cond = ev[..., -1] / np.maximum(ev[..., 0], 1e-300)
        if method in ("default", "thesis") and start is not None:
            Minv = np.linalg.inv(Mxx)
            p = np.broadcast_to(start, Mxx.shape[:-1]).copy()
            for _ in range(4):
                p = np.einsum("...ij,...j->...i", Minv, p)
                p /= np.linalg.norm(p, axis=-1, keepdims=True)
        elif method in ("default", "thesis"):
            w, V = np.linalg.eigh(Mxx)
            p = V[..., :, 0]
        elif method == "ols":
            beta = np.linalg.solve(R, Mxx[..., 1:, :1])[..., 0]
            p = np.concatenate([np.ones_like(beta[..., :1]), -beta], axis=-1)
        else:  # two-stage least squares: beta = (A^T W A)^-1 A^T W b, A = Z^T X, W = (Z^T Z)^-1
            assert Mzx is not None  # the IV design carries instruments (`moments` of a design with Z)
            m = Mxx.shape[-1]
            A, bz, Wz = Mzx[..., :, 1:m], Mzx[..., :, :1], np.linalg.inv(Mzx[..., :, m:])
            AtW = np.swapaxes(A, -1, -2) @ Wz
            beta = np.linalg.solve(AtW @ A, AtW @ bz)[..., 0]
            p = np.concatenate([np.ones_like(beta[..., :1]), -beta], axis=-1)
        p = p / p[..., :1]
    return p, cond


def to_ibk(p: np.ndarray, scale: np.ndarray, T: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuous I, B, K from the discrete coefficients: poles z = exp(sT), DC gain 1/K."""
    q = p * scale
    q = q / q[..., :1]
    a1, a2 = q[..., 1], q[..., 2]
    b = -q[..., 3:].sum(-1)
    disc = np.sqrt((a1**2 - 4 * a2).astype(complex))
    z1, z2 = (-a1 + disc) / 2, (-a1 - disc) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        s1, s2 = np.log(z1) / T, np.log(z2) / T
        w02 = np.real(s1 * s2)
        K = (1 + a1 + a2) / b
        I = K / w02
        B = -np.real(s1 + s2) * I
    return I, B, K


def estimate(
    ens: Ensemble, method: str = "default", options: EstimateOptions | None = None, warn: bool = True, **kw
) -> ImpedanceEstimate:
    """Identify I(t), B(t), K(t) at every instant of the cycle (eq. 9.6 per instant, solved by eq. 9.13
    for TLS; see the module docstring), with the default's automatic switch to IV."""
    opt = resolved(options or EstimateOptions.for_method(method, **kw), ens)
    est = _fit(ens, opt)
    if opt.method == "default" and opt.auto_iv and ens.command is not None:
        iv = _fit(ens, EstimateOptions.for_method("iv", prefilter_hz=opt.prefilter_hz))
        dev: dict[str, float] = {}
        for k in "IBK":  # 10 %-trimmed means over the cycle: robust, and blind to the time resolution
            a, b = _trimmed_mean(getattr(est, k)), _trimmed_mean(getattr(iv, k))
            dev[k] = abs(a / b - 1) if np.isfinite(a) and np.isfinite(b) and b != 0 else np.inf
        worst = max(dev, key=dev.__getitem__)
        if dev[worst] > IV_SWITCH and np.nanmedian(iv.I) > 0:
            iv.notes.append(
                f"least squares and the instrumental-variable fit differ by {min(dev[worst], 9.99):.0%} on {worst} (mean over the cycle): "
                "unmeasured (voluntary) torque in the record; the IV estimate (command as instrument) is reported"
            )
            est = iv
    est.warnings = diagnose(est, ens.n, ens.command is not None)
    for w in est.warnings if warn else ():
        log.warning(w)
    return est


def _trimmed_mean(x: np.ndarray, cut: float = 0.1) -> float:
    x = np.sort(np.asarray(x, float)[np.isfinite(x)])
    k = int(cut * x.size)
    return float(np.mean(x[k : x.size - k])) if x.size > 2 * k else float("nan")


def _fit(ens: Ensemble, opt: EstimateOptions) -> ImpedanceEstimate:
    edges = opt.method == "default" and opt.edges and bool(opt.prefilter_hz)
    with single_thread():
        if not edges:
            d = design(ens, opt)
            Mxx, Mzx = moments(d)
            I, B, K, cond = finish(d, Mxx, Mzx, opt, ens.fs)
            return ImpedanceEstimate(d.stamps / ens.fs, I, B, K, cond, opt, d.lag, designs={0: d})
        hz = cutoff(opt)
        assert hz is not None  # edges: a pre-filter is set
        L, fs = ens.length, ens.fs
        half = int(round(opt.pool_ms * 1e-3 * fs))
        D = max(1, int(round(opt.lag_ms * 1e-3 * fs)))
        W = edge_width(D, half, hz, fs)
        E = min(W, ens.pad - 2 * D - 2 * half)
        d = design(ens, opt, extend=E)
        Mxx, _ = moments(d)
        p, cond, lam = tls(pool(Mxx, half))
        assert cond is not None  # asked for (want_cond)
        I, B, K = to_ibk(p[E : E + L], d.scale, d.T)
        est = ImpedanceEstimate(d.stamps[E : E + L] / fs, I, B, K, cond[E : E + L], opt, d.lag)
        cycle = slice(E, E + L)  # the design over the cycle alone: design(ens, opt)
        z = None if d.Z is None else d.Z[cycle]
        est.designs[0] = replace(d, X=d.X[cycle], Z=z, stamps=d.stamps[cycle])
        r = lam / np.median(lam[E : E + L])
        spread = np.sqrt(100.0 / max(ens.n, 1))  # the residual's sampling spread grows as 1/sqrt(n)
        ratio, contrast = 1 + (opt.edge_ratio - 1) * spread, 1 + (opt.edge_contrast - 1) * spread
        cand = find_peaks(np.nan_to_num(r), ratio, max(1, W))
        if cand.size:  # confirmed where both one-sided fits fit much better than the centred one
            th, rs = [np.stack([I, B, K])], []
            for side in (-1, 1):
                ds = est.designs[side] = design(ens, opt, side=side)
                ps, _, ls = tls(pool(moments(ds)[0], half), want_cond=False)
                th.append(np.stack(to_ibk(ps, ds.scale, ds.T)))
                rs.append(ls / np.median(ls))
            at = np.mod(cand - E, L)
            cand = cand[r[cand] > contrast * np.maximum(rs[0][at], rs[1][at])]
        w, steps = edge_weights(cand - E, L, W)
        if steps.size:
            sides = np.stack(th)  # (3 estimates, 3 parameters, L)
            est.I, est.B, est.K = blend(sides, w)
            alt = np.where(w[1] >= w[2], sides[1], sides[2])  # the one-sided estimate blended in at each instant
            taper = (w[0] > 0) & (w[0] < 1)
            est.blend_spread = np.where(taper, w[0] * np.nan_to_num(np.abs(sides[0] - alt)), 0.0)
            uniq = np.unique(np.mod(steps, L))  # a step at the cycle's end is also one before its start
            uniq = uniq[np.r_[True, np.diff(uniq) > 2]]
            if uniq.size > 1 and uniq[0] + L - uniq[-1] <= 2:
                uniq = uniq[:-1]
            est.weights, est.steps = w, uniq / fs
            est.notes.append(
                f"abrupt changes at {', '.join(f'{t:.3f}' for t in uniq / fs)} s: within {1e3 * W / fs:.0f} ms of "
                "them the estimate uses only the data on its own side (edge-preserving)"
            )
    return est


def refit(ens: Ensemble, opt: EstimateOptions, weights: np.ndarray | None = None) -> np.ndarray:
    """I, B, K (3, L) of the estimator `opt` on another ensemble, with the blend of centred and one-sided
    fits given (`weights` of an earlier `ImpedanceEstimate`, or None: the centred fit only) instead of
    searched for, and no switch of method: the same estimator applied to simulated data."""
    opt = resolved(opt, ens)
    half = int(round(opt.pool_ms * 1e-3 * ens.fs))
    with single_thread():
        d = design(ens, opt)
        Mxx, Mzx = moments(d)
        I, B, K, _ = finish(d, Mxx, Mzx, opt, ens.fs)
        th = [np.stack([I, B, K])]
        if weights is None or not (opt.method == "default" and opt.prefilter_hz):
            return th[0]
        for side in (-1, 1):
            ds = design(ens, opt, side=side)
            ps, _, _ = tls(pool(moments(ds)[0], half), want_cond=False)
            th.append(np.stack(to_ibk(ps, ds.scale, ds.T)))
    return blend(np.stack(th), weights)


def blend(sides: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The weighted mean (3, L) of the centred, left- and right-sided estimates `sides` (3, 3, L) with the
    `edge_weights` (3, L), each instant over the estimates that are finite there."""
    ok = np.isfinite(sides)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sum(np.where(ok, sides, 0) * weights[:, None], 0) / np.sum(ok * weights[:, None], 0)


def tls(M: np.ndarray, want_cond: bool = True) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """TLS per instant (eq. 9.13): the null vector p (p[0] = 1), the regressor condition number and the
    smallest eigenvalue of the pooled moment matrix (the residual sum of squares of the fit)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        w, V = np.linalg.eigh(M)
        p = V[..., :, 0] / V[..., :1, 0]
        cond = None
        if want_cond:
            R = M[..., 1:, 1:]
            dg = 1.0 / np.sqrt(np.maximum(np.diagonal(R, axis1=-2, axis2=-1), 1e-300))
            ev = np.linalg.eigvalsh(R * dg[..., :, None] * dg[..., None, :])
            cond = ev[..., -1] / np.maximum(ev[..., 0], 1e-300)
    return p, cond, w[..., 0]


def edge_width(D: int, half: int, hz: float, fs: float) -> int:
    """Half-width (samples) of the instants a step reaches in the centred estimate: the lag span D, the
    pooling half-width and 0.35 / f_c of the zero-phase pre-filter's response."""
    return int(round(D + half + 0.35 / hz * fs))


def edge_weights(steps: np.ndarray, L: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """Weights (3, L) of the centred, left-sided and right-sided estimates around the `steps` (instants,
    samples; below 0 or from L on: in the padding), and the steps that reach the cycle.

    A step in I, B or K makes the centred fit's residual (TLS smallest eigenvalue, eq. 9.13) peak where
    the window straddles it, while the one-sided fits, which see one regime each, stay at their usual
    residual (`_fit` finds the steps so).  Within W instants before a step only the left-sided estimate is
    used (its data end at the instant), within W after it the right-sided one, tapering back to the
    centred estimate over the outer 30 %."""
    steps = np.asarray(steps, int)
    steps = steps[(steps > -W) & (steps < L + W)]
    wl, wr = np.zeros(L), np.zeros(L)
    k = np.arange(W)
    ramp = np.clip((W - k) / (0.3 * W), 0, 1)
    for t0 in steps:
        before, after = t0 - 1 - k, t0 + k
        m = (before >= 0) & (before < L)
        wl[before[m]] = np.maximum(wl[before[m]], ramp[m])
        m = (after >= 0) & (after < L)
        wr[after[m]] = np.maximum(wr[after[m]], ramp[m])
    both = (wl > 0) & (wr > 0)  # between two close steps: the side of the nearer one
    wl[both & (wl < wr)] = 0
    wr[both & (wl >= wr) & (wl > 0)] = 0
    return np.stack([1 - wl - wr, wl, wr]), steps


def finish(d: Design, Mxx, Mzx, opt: EstimateOptions, fs: float, start: np.ndarray | None = None):
    """Pool, solve, convert and smooth (shared by `estimate` and the bootstrap)."""
    half = int(round(opt.pool_ms * 1e-3 * fs))
    p, cond = solve(pool(Mxx, half), pool(Mzx, half), opt.method, start)
    if opt.smooth_ms > 0:
        p = gaussian_filter1d(p, opt.smooth_ms * 1e-3 * fs, axis=-2)
    I, B, K = to_ibk(p, d.scale, d.T)
    return (I, B, K, cond) if start is None else (I, B, K, p)


def diagnose(est: ImpedanceEstimate, n: int, has_command: bool = True) -> list[str]:
    """Per-instant conditioning warnings, the sign check and the +-10 % inertia-constancy check, each
    naming its likely cause and remedy."""
    out = []
    bad = ~np.isfinite(est.cond) | (est.cond > COND_WARN)
    if np.mean(bad) > 0.02:
        t = est.t[bad]
        out.append(
            f"ill-conditioned regressors at {np.mean(bad):.0%} of the instants (first at {t[0]:.3f} s):"
            " the perturbation may be locked to the cycle clock or too weak"
        )
    nan = ~np.isfinite(est.I + est.B + est.K)
    if np.mean(nan) > 0.01:
        out.append(f"no valid (I, B, K) at {np.mean(nan):.0%} of the instants (complex or unstable poles)")
    I = est.I[~nan]
    if I.size and np.median(I) <= 0:
        if np.median(est.K[~nan]) < 0:
            out.append(
                "the estimated inertia and stiffness are negative: is the torque sign reversed? (torque must be "
                "positive in the direction of increasing angle; --torque-sign -1 flips it)"
            )
        else:
            out.append(
                "the estimated inertia is not positive: the model does not fit (check segmentation and "
                "alignment: misaligned cycles leave the mean movement in the perturbations)"
            )
    elif I.size > 10:  # on the 50 ms-smoothed curve: random error alone is not a warning
        Is = gaussian_filter1d(I, 0.05 / max(est.t[1] - est.t[0], 1e-9))
        dev = np.max(np.abs(Is - np.median(I))) / np.median(I)
        if dev > 0.10 and est.options.method != "iv":
            remedy = (
                "compare with --method iv"
                if has_command
                else "record the commanded perturbation as a 'command' column, for --method iv"
            )
            out.append(
                f"estimated inertia varies by +-{dev:.0%} over the cycle (more than +-10 %): unmeasured "
                f"(voluntary) torque, misalignment or unmodelled dynamics; {remedy}"
            )
    if n < 30:
        out.append(f"only {n} cycles: estimates will be noisy (the random error grows as 1/sqrt(cycles))")
    return out


def posture_fit(ens: Ensemble, method: str = "default", **kw) -> tuple[float, float, float]:
    """Time-invariant (ergodic) fit, 9.6.4: the equations of all instants and cycles pooled."""
    opt = resolved(EstimateOptions.for_method(method, **kw), ens)
    d = design(ens, opt)
    Mxx, Mzx = moments(d)
    Mzx = None if Mzx is None else Mzx.sum(0)[None]
    p, _ = solve(Mxx.sum(0)[None], Mzx, opt.method)
    I, B, K = to_ibk(p, d.scale, d.T)
    return float(I[0]), float(B[0]), float(K[0])
