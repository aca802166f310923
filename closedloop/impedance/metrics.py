"""Comparisons with simulated truth: errors, rise time, bias and random error, band coverage.

Bias and random error follow van de Ruit et al.'s comparison protocol of time-varying identification
methods: over R independent realisations, the bias at instant t is |mean_r(p_r(t)) - p(t)| / |p(t)| and
the random error std_r(p_r(t)) / |p(t)|, both averaged over the cycle.
"""

from __future__ import annotations

import numpy as np


def rel_errors(est, truth: dict[str, np.ndarray], trim: float = 0.0) -> dict[str, float]:
    """Mean absolute relative error (%) of I, B, K over the cycle (instants with NaN count as 100 %)."""
    out = {}
    n = len(truth["t"])
    sl = slice(int(trim * n), n - int(trim * n))
    for k in "IBK":
        e = np.abs(np.asarray(getattr(est, k) if not isinstance(est, dict) else est[k])[sl] / truth[k][sl] - 1)
        out[k] = float(100 * np.mean(np.where(np.isfinite(e), np.minimum(e, 1.0), 1.0)))
    return out


def median_errors(est, truth) -> dict[str, float]:
    out = {}
    for k in "IBK":
        e = np.abs(np.asarray(getattr(est, k)) / truth[k] - 1)
        out[k] = float(100 * np.nanmedian(e))
    return out


def rise_times(t: np.ndarray, est: np.ndarray, truth: np.ndarray, half_window: float = 0.1) -> np.ndarray:
    """10-90 % rise (or fall) time (s) of `est` at every jump of `truth` (jumps > 20 % of its range)."""
    jumps = np.flatnonzero(np.abs(np.diff(truth)) > 0.2 * np.ptp(truth)) + 1
    fs = 1.0 / (t[1] - t[0])
    w = int(half_window * fs)
    out = []
    for j in jumps:
        if j - w < 0 or j + w >= len(t):
            continue
        lo, hi = truth[j - 1], truth[j]
        y = (est[j - w : j + w] - lo) / (hi - lo)  # 0 before, 1 after
        tt = t[j - w : j + w]
        try:
            t10 = _cross(tt, y, 0.1)
            t90 = _cross(tt, y, 0.9)
        except ValueError:
            out.append(np.nan)
            continue
        out.append(t90 - t10)
    return np.array(out)


def mean_rise_time(t: np.ndarray, est: np.ndarray, truth: np.ndarray, half_window: float = 0.1) -> float:
    """10-90 % rise time (s) of the estimator's mean step response: the normalised estimate around every
    jump of `truth` (0 before, 1 after; rises and falls alike) averaged over the jumps, so that the
    random error does not masquerade as a slow transition."""
    est = np.atleast_2d(est)
    jumps = np.flatnonzero(np.abs(np.diff(truth)) > 0.2 * np.ptp(truth)) + 1
    fs = 1.0 / (t[1] - t[0])
    w = int(half_window * fs)
    segs = [
        (e[j - w : j + w] - truth[j - 1]) / (truth[j] - truth[j - 1]) for j in jumps if w <= j < len(t) - w for e in est
    ]
    if not segs:
        return float("nan")
    y = np.nanmean(segs, axis=0)
    tt = t[: 2 * w] - t[0]
    try:
        return float(_cross(tt, y, 0.9) - _cross(tt, y, 0.1))
    except ValueError:
        return float("nan")


def _cross(t, y, level):
    """Last upward crossing of `level` before y stays above it (linear interpolation)."""
    above = y >= level
    if not above[-1]:
        raise ValueError("never settles")
    k = len(y) - 1
    while k > 0 and above[k - 1]:
        k -= 1
    if k == 0:
        raise ValueError("starts above")
    return t[k - 1] + (level - y[k - 1]) * (t[k] - t[k - 1]) / (y[k] - y[k - 1])


def bias_random(estimates: list, truth: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Van de Ruit-style bias and random error (%) over independent realisations."""
    out = {}
    for k in "IBK":
        P = np.stack([np.asarray(getattr(e, k)) for e in estimates])
        P = np.where(np.isfinite(P), P, np.nan)
        bias = np.abs(np.nanmedian(P, 0) - truth[k]) / np.abs(truth[k])
        rnd = np.nanstd(P, 0) / np.abs(truth[k])
        out[k] = (float(100 * np.nanmean(bias)), float(100 * np.nanmean(rnd)))
    return out


def coverage(lo: np.ndarray, hi: np.ndarray, truth: np.ndarray) -> float:
    """Fraction of instants at which truth lies inside [lo, hi]."""
    return float(np.mean((truth >= lo) & (truth <= hi)))
