"""Ensemble non-parametric impulse response as a model check (thesis 9.6.3, eq. 9.14-9.17).

At an instant c the compliance impulse response h_l (dth per unit dtau, l = 0 .. M-1 lags of `step`
samples) is taken constant over a window of +-w/2 (thesis: w = 60 ms), which stacks n x (w fs) equations

    dth_i(t) = sum_l h_l dtau_i(t - l step)      (t in the window, i over cycles)

solved by truncated SVD (eq. 9.17; the thesis zeroed singular values below 1e-4 of the largest, here
`rcond` = 0.1 by default: the PRBS of 20 ms elements has little power above 25 Hz, and the directions
it does not excite only add noise).
The parametric check: the impulse response of 1 / (I s^2 + B s + K) with the estimate's values at c,
h(t) = exp(-zeta w0 t) sin(w_d t) / (I w_d), and the VAF between the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from closedloop.impedance.data import Ensemble
from closedloop.impedance.estimate import lowpass, single_thread


@dataclass
class ImpulseCheck:
    t: float  # instant in the cycle (s)
    lags: np.ndarray  # s
    h_np: np.ndarray  # non-parametric (rad / (N m s))
    h_par: np.ndarray  # parametric, from I, B, K at t
    vaf: float  # % of the non-parametric response explained by the parametric one


def impulse_response(
    ens: Ensemble,
    t: float,
    length: float = 0.3,
    window: float = 0.06,
    step: int = 2,
    rcond: float = 0.1,
    prefilter_hz: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Non-parametric impulse response (per second of lag) at instant `t` of the cycle."""
    dth, dtau, _ = ens.deltas()
    dth, dtau = lowpass(dth, ens.fs, prefilter_hz), lowpass(dtau, ens.fs, prefilter_hz)
    fs, P = ens.fs, ens.pad
    M = int(length * fs / step)
    c = P + int(round(t * fs))
    half = int(window * fs / 2)
    rows = np.arange(max(c - half, M * step), min(c + half + 1, dth.shape[1]))
    lag = np.arange(M) * step
    y = dth[:, rows].ravel()
    X = dtau[:, rows[:, None] - lag[None, :]].reshape(-1, M)
    with single_thread():
        U, s, Vt = np.linalg.svd(X, full_matrices=False)
    keep = s > rcond * s[0]
    h = Vt[keep].T @ ((U[:, keep].T @ y) / s[keep])
    return lag / fs, h * fs / step  # per unit time: h_l ~ h(t_l) dt


def parametric_ir(I: float, B: float, K: float, lags: np.ndarray) -> np.ndarray:
    w0 = np.sqrt(K / I)
    z = B / (2 * np.sqrt(K * I))
    if z < 1:
        wd = w0 * np.sqrt(1 - z * z)
        return np.exp(-z * w0 * lags) * np.sin(wd * lags) / (I * wd)
    r1, r2 = -z * w0 + w0 * np.sqrt(z * z - 1), -z * w0 - w0 * np.sqrt(z * z - 1)
    return (np.exp(r1 * lags) - np.exp(r2 * lags)) / (I * (r1 - r2))


def model_check(ens: Ensemble, est, times: list[float] | None = None, **kw) -> list[ImpulseCheck]:
    """Compare the non-parametric impulse response with the parametric one at a few instants."""
    times = times if times is not None else list(np.linspace(0, ens.length / ens.fs, 5, endpoint=False))
    out = []
    for t in times:
        lags, h = impulse_response(ens, t, **kw)
        i = int(np.argmin(np.abs(est.t - t)))
        hp = parametric_ir(est.I[i], est.B[i], est.K[i], lags)
        vaf = 100 * (1 - np.sum((h - hp) ** 2) / np.sum(h**2))
        out.append(ImpulseCheck(float(t), lags, h, hp, float(vaf)))
    return out
