"""Cycle-onset timing: a check that the onsets are where the cycles start, and re-alignment by the model.

A cycle cut d_i seconds late carries d_i v_0(t) in its angle perturbation and d_i tau_0'(t) in its torque
perturbation (the mean movement's velocity and the mean torque's rate, eq. 7.9 to first order), which is
no response to the perturbation and biases every estimate of eq. 9.6.  Jittered onset marks (an event
channel or an onsets file with timing errors of a few ms) or cycles cut by peak velocity (whose peaks the
perturbation responses move) leave such shifts.  The thesis re-aligns by peak velocity and RMS
difference to the mean (9.5.1); with strong perturbations both are pulled by the responses themselves.

Here the identified model removes the responses first.  At every instant c the fitted equation of eq. 9.6
(TLS, or IV where the estimate is IV; pre-filtered, lags D, coefficients p(c), scaled as in `design`)
leaves each cycle the equation residual e_i(c) = p(c) . x_i(c).  A shift d_i adds d_i w(c) to it, with
w(c) = p(c) . g(c) and g(c) the regressors built from (v_0, tau_0') in place of (dth, dtau); so

    d_i = sum_c e_i(c) w(c) / sum_c w(c)^2

is the least-squares estimate of the cycle's timing error (relative to the ensemble's mean timing), with
the perturbation responses already explained by the model.

**Statistic and threshold (`check_onsets`).**  The cycle is split in two halves of equal sum w(c)^2 (a
50 ms guard between them) and d_i is estimated from each half, in one least-squares fit per cycle with a
constant and a linear trend over the cycle (slow unmeasured torque drifting across a cycle is not a
timing error): dA_i and dB_i.  Their noises are independent (the residual decorrelates within tens of
ms), a timing error is common to both, so the across-cycle correlation r(dA, dB) is zero on aligned
records whatever the noise, voluntary torque or model error in each half, and its Fisher statistic
z = atanh(r) sqrt(n - 3) would be standard normal; the shared constant and trend make the two noises
slightly anti-correlated, which shifts z below zero where noise dominates (voluntary torque: mean -2 on
the forearm), so the test errs toward no alarm.  cov(dA, dB) estimates the variance of the timing
errors.  The onsets are reported as misaligned when z >= 4 (a one-sided false-alarm probability of 3e-5
for a standard normal z) **and** the timing errors' std sqrt(cov(dA, dB)) is at least 1 ms (below that
the bias is far under the random error: +-10 ms uniform jitter, 5.8 ms std, costs 2-3 % on I, B, K; the
bias grows as the variance).  The false-alarm rate over simulated records is measured by
benchmarks/bench_onset_timing.py.

**Re-alignment (`realign`).**  Each cycle's onset is moved by its estimated timing error d_i shrunk by
1 - s^2 / var(d_hat), s^2 = var(dA_raw - dB_raw) / 4 the noise variance of d_hat (from the two halves'
plain estimates, which a timing error does not enter), so noisy estimates move little; rounded to
samples and limited to the maximum shift; the check is repeated on the re-cut ensemble (the model
refitted) until no cycle moves (at most `iterations` times).  It is worth keeping when the fit's mean
squared equation residual fell by at least 2 % (misalignment adds var(d) w(c)^2 to it; re-aligning
aligned records lowers it by a fraction ~1/L from the n fitted shifts).

**Far-off onsets (`check_timing`).**  Beyond a few tens of ms the model fitted to the misaligned cycles is
too wrong to re-align them.  The cycles are then also cut with the thesis's RMS alignment (reach 200 ms,
pulled by a few ms by the responses) and re-aligned by the model from there; the candidate with the
smaller equation residual is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from closedloop.impedance.data import Ensemble, Record, recut, segment
from closedloop.impedance.estimate import (
    EstimateOptions,
    ImpedanceEstimate,
    design,
    estimate,
    moments,
    noise_std,
    pool,
    resolved,
    solve,
)

Z_ALARM = 4.0  # Fisher z of the split-half correlation: one-sided false-alarm probability 3e-5
MIN_SPREAD_S = 0.001  # timing errors' std below which they are left alone (s)
MIN_GAIN = 0.02  # relative fall of the equation residual that makes a re-alignment worth keeping
GUARD_S = 0.05  # gap between the two halves (s)
COARSE_SHIFT_S = 0.2  # reach of the RMS alignment tried when the model alone cannot re-align (s)


@dataclass
class OnsetCheck:
    """What `check_onsets` found: per-cycle timing errors (s, positive: the cycle was cut late, relative to
    the ensemble's mean timing), the split-half correlation r, its Fisher z, the timing errors' std
    (s, from the split-half covariance), the mean squared equation residual and the verdict."""

    errors: np.ndarray
    r: float
    z: float
    spread: float
    noise: float
    residual: float
    noise_ratio: float
    misaligned: bool

    def describe(self) -> str:
        return (
            f"timing errors std {1e3 * self.spread:.1f} ms (split-half correlation {self.r:.2f}, z {self.z:.1f} over "
            f"{self.errors.size} cycles)"
        )


def _form(opt: EstimateOptions, ens: Ensemble, ratio: float) -> EstimateOptions:
    """The fit used by the check: the estimate's own form (TLS, or IV when the estimate is IV and the
    command is recorded) with its pre-filter and lags, centred, without the edge-preserving blend."""
    method = "iv" if opt.method == "iv" and ens.command is not None else "default"
    lag = opt.lag_ms if opt.method != "thesis" else None
    pre = opt.prefilter_hz if opt.method != "thesis" and opt.prefilter_hz else "auto"
    form = EstimateOptions.for_method(method, prefilter_hz=pre, lag_ms=lag, noise_ratio=ratio)
    return resolved(replace(form, edges=False, auto_iv=False), ens)


def check_onsets(
    ens: Ensemble, options: EstimateOptions | None = None, noise_ratio: float | None = None
) -> OnsetCheck | None:
    """Timing errors of the cycle onsets and the split-half test for them (module docstring); None with
    fewer than 8 cycles.  `noise_ratio` (angle/torque noise std) fixes the residual's scale, so that the
    residuals of two alignments of the same record compare."""
    n = ens.n
    if n < 8:
        return None
    if noise_ratio is None:
        dth, dtau, _ = ens.deltas()
        noise_ratio = max(noise_std(dth), 1e-300) / max(noise_std(dtau), 1e-300)
    opt = _form(resolved(options or EstimateOptions(), ens), ens, noise_ratio)
    d = design(ens, opt)
    half = int(round(opt.pool_ms * 1e-3 * ens.fs))
    Mxx, Mzx = moments(d)
    p, _ = solve(pool(Mxx, half), pool(Mzx, half), opt.method, want_cond=False)
    p = np.nan_to_num(p)
    th0, tau0 = ens.mean()
    g = np.stack([np.gradient(th0), -np.gradient(th0)]) * ens.fs
    gt = np.stack([np.gradient(tau0), -np.gradient(tau0)]) * ens.fs
    sig = Ensemble(ens.fs, ens.pad, ens.length, g, gt, None, ens.onsets[:2])
    w = np.einsum("lm,lm->l", design(sig, replace(opt, method="default")).X[:, 0, :], p)
    e = np.einsum("lnm,lm->nl", d.X, p)
    if not float(w @ w) > 0:
        return None
    errors = e @ w / float(w @ w)
    cw = np.cumsum(w**2)
    k = int(np.searchsorted(cw, cw[-1] / 2))
    guard = int(round(GUARD_S * ens.fs))
    a, b = slice(0, max(k - guard, 1)), slice(min(k + guard, w.size - 1), w.size)
    dA, dB = _split_halves(e, w, a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = float(np.corrcoef(dA, dB)[0, 1])
    r = r if np.isfinite(r) else 0.0
    z = float(np.arctanh(np.clip(r, -0.999999, 0.999999)) * np.sqrt(n - 3))
    spread = float(np.sqrt(max(np.cov(dA, dB)[0, 1], 0.0)))
    rawA = e[:, a] @ w[a] / max(float(w[a] @ w[a]), 1e-300)
    rawB = e[:, b] @ w[b] / max(float(w[b] @ w[b]), 1e-300)
    noise = float(np.std(rawA - rawB) / 2)  # the noise of `errors` (two halves of equal information)
    return OnsetCheck(
        errors=errors,
        r=r,
        z=z,
        spread=spread,
        noise=noise,
        residual=float(np.mean(e**2)),
        noise_ratio=float(noise_ratio),
        misaligned=bool(z >= Z_ALARM and spread >= MIN_SPREAD_S),
    )


def _split_halves(e: np.ndarray, w: np.ndarray, a: slice, b: slice) -> tuple[np.ndarray, np.ndarray]:
    """Each cycle's residual e_i over the two halves `a` and `b` fitted by w on `a`, w on `b`, a constant and
    a linear trend over the cycle (least squares): the coefficients of the two halves' w.  The shared
    constant and trend take slow unmeasured torque that drifts across a cycle, which would otherwise make
    the halves agree; the same fit makes the two coefficients' noises slightly anti-correlated, so the
    test errs on the side of no alarm."""
    n = w.size
    ia, ib = np.arange(n)[a], np.arange(n)[b]
    idx = np.r_[ia, ib]
    t = np.linspace(-1.0, 1.0, n)[idx]
    wa = np.r_[w[ia], np.zeros(ib.size)]
    wb = np.r_[np.zeros(ia.size), w[ib]]
    coef = e[:, idx] @ np.linalg.pinv(np.stack([np.ones_like(t), t, wa, wb], axis=1)).T
    return coef[:, 2], coef[:, 3]


@dataclass
class Realignment:
    """The re-aligned ensemble, the checks before and after (None: no cycle moved), the shifts applied
    (samples) and whether they are worth keeping (the residual fell by `MIN_GAIN`)."""

    ensemble: Ensemble
    before: OnsetCheck
    after: OnsetCheck | None
    shifts: np.ndarray
    kept: bool

    @property
    def gain(self) -> float:
        """Relative fall of the mean squared equation residual."""
        return 0.0 if self.after is None else 1.0 - self.after.residual / self.before.residual


def realign(
    rec: Record,
    ens: Ensemble,
    options: EstimateOptions | None = None,
    max_shift_s: float = 0.05,
    iterations: int = 12,
    before: OnsetCheck | None = None,
) -> Realignment | None:
    """Re-align the cycles of `ens` (cut from `rec`) by their timing errors (module docstring): shrunk
    estimates, rounded to samples, at most `max_shift_s`, repeated until no cycle moves; worth keeping
    when the equation residual falls by at least `MIN_GAIN`.  None when there are too few cycles to check."""
    chk0 = before or check_onsets(ens, options)
    if chk0 is None:
        return None
    S = int(round(max_shift_s * ens.fs))
    total = np.zeros(ens.n, int)
    cur, chk = ens, chk0
    for _ in range(iterations):
        var = float(np.var(chk.errors))
        lam = max(0.0, 1.0 - chk.noise**2 / var) if var > 0 else 0.0
        step = np.round(lam * chk.errors * ens.fs).astype(int)
        new = np.clip(total - step, -S, S)
        if np.array_equal(new, total):
            break
        total = new
        cur = recut(rec, ens, total)
        assert cur.alignment is not None  # `recut` records each cycle's total shift
        total = cur.alignment.shifts - (ens.alignment.shifts if ens.alignment is not None else 0)
        nxt = check_onsets(cur, options, chk0.noise_ratio)
        if nxt is None:
            return None
        chk = nxt
    res = Realignment(cur, chk0, chk, total, False)
    res.kept = bool(total.any() and res.gain >= MIN_GAIN)
    return res


@dataclass
class TimingOutcome:
    """`check_timing`'s result: the ensemble and estimate to report (re-aligned or not), the notes and
    warnings to print and a summary for the results file."""

    ensemble: Ensemble
    estimate: ImpedanceEstimate
    notes: list[str]
    warnings: list[str]
    summary: dict


def check_timing(
    rec: Record,
    ens: Ensemble,
    est: ImpedanceEstimate,
    options: EstimateOptions | None = None,
    allow_realign: bool = True,
    max_shift_s: float = 0.05,
    onsets: list[tuple[int, int]] | None = None,
    period: float | None = None,
) -> TimingOutcome:
    """The onsets of `ens` checked against `est`'s model (`check_onsets`); when they are off, the cycles
    re-aligned (`realign`, unless `allow_realign` is False) and `options` estimated again on them, with a
    note saying so, or a warning naming what to do when re-aligning is not allowed or does not help.

    When the model cannot bring the cycles in line (timing errors left, or no fall of the residual) and the
    `onsets` that cut `ens` are given, the cycles are also cut again with the thesis's RMS alignment within
    `COARSE_SHIFT_S` (9.5.1: pulled by the responses by a few ms, but it reaches errors of 100 ms and more)
    and re-aligned by the model from there; of the two, the one with the smaller equation residual is
    kept (and only if it is `MIN_GAIN` below the original's)."""
    chk = check_onsets(ens, est.options)
    if chk is None:
        return TimingOutcome(ens, est, [], [], {"checked": False})
    summary: dict[str, Any] = {
        "checked": True,
        "z": round(chk.z, 2),
        "split_half_r": round(chk.r, 3),
        "timing_error_std_ms": round(1e3 * chk.spread, 2),
        "misaligned": chk.misaligned,
        "realigned": False,
    }
    if not chk.misaligned:
        return TimingOutcome(ens, est, [], [], summary)
    what = f"the cycle onsets are misaligned: {chk.describe()}"
    if not allow_realign:
        return TimingOutcome(
            ens,
            est,
            [],
            [f"{what}; the estimates are biased by it: --align auto re-aligns the cycles by the model"],
            summary,
        )
    ra = realign(rec, ens, est.options, max_shift_s, before=chk)
    assert ra is not None  # re-cut cycles keep their number, which the check above found enough
    cands = [(ra.ensemble, ra.after or chk, "by the model")]
    if (not ra.kept or cands[0][1].misaligned) and onsets is not None:
        reach = max(COARSE_SHIFT_S, max_shift_s)
        coarse = segment(rec, onsets, period=period, align="rms", max_shift_s=reach)
        c0 = check_onsets(coarse, est.options, chk.noise_ratio)
        if c0 is not None:
            rb = realign(rec, coarse, est.options, reach, before=c0)
            assert rb is not None  # as `ra`: c0 found enough cycles
            how = f"by RMS difference to the mean and then by the model, each within {1e3 * reach:g} ms"
            cands.append((rb.ensemble, rb.after or c0, how))
    out, after, how = min(cands, key=lambda c: c[1].residual)
    gain = 1.0 - after.residual / chk.residual
    summary["residual_fall_percent"] = round(100 * gain, 1)
    if gain < MIN_GAIN:
        return TimingOutcome(
            ens,
            est,
            [],
            [
                f"{what}; re-aligning them did not lower the fit's residual ({100 * gain:.1f} %): check the onset "
                "marks (an event channel recorded with the data)"
            ],
            summary,
        )
    assert out.alignment is not None  # cut by `segment` and re-cut by `recut`, which record the shifts
    ms = out.alignment.shifts / out.fs * 1e3
    new = estimate(out, options=options, warn=False)
    summary.update(
        realigned=True,
        how=how,
        shift_std_ms=round(float(np.std(ms)), 2),
        shift_max_abs_ms=round(float(np.max(np.abs(ms))), 2),
        after={
            "z": round(after.z, 2),
            "timing_error_std_ms": round(1e3 * after.spread, 2),
            "misaligned": after.misaligned,
        },
    )
    notes = [
        f"{what}; the cycles were re-aligned {how}: shifts std {np.std(ms):.1f} ms, largest "
        f"{np.max(np.abs(ms)):.1f} ms; the fit's residual fell by {100 * gain:.0f} %; timing errors left: "
        f"std {1e3 * after.spread:.1f} ms"
    ]
    warnings = []
    if after.misaligned:
        warnings.append(
            f"the cycle onsets are still misaligned after re-aligning them ({after.describe()}): give onsets "
            "from an event channel recorded with the data"
        )
    return TimingOutcome(out, new, notes, warnings, summary)
