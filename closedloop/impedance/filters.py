"""The estimator's signal processing in numpy: the Butterworth pre-filter (zero-phase and one-sided), the
Welch spectrum, peak picking and Gaussian smoothing.

They return what scipy's `butter(output="sos")` with `sosfiltfilt` / `sosfilt`, `welch`, `find_peaks`
(height, distance) and `scipy.ndimage.gaussian_filter1d(mode="nearest")` return, to rounding
(tests/test_impedance_filters.py compares them on random signals), without importing `scipy.signal`
or `scipy.ndimage`.

This module is the one way the package filters, takes spectra and picks peaks: the estimator, the
segmentation (`data`), both simulators (`model`, `elbow`) and the command line use it, and nothing in
the package imports `scipy.signal` or `scipy.ndimage` (tests/test_one_way.py).  Measured (CPU seconds,
the least of 5 runs, on the 2-core AMD EPYC development machine shared with other work, load average
15): importing `scipy.signal` costs 1.38 s more than numpy alone (it loads scipy.stats,
scipy.interpolate and scipy.optimize), `scipy.ndimage` 0.39 s, both 1.75 s; `closedloop impedance
identify` on 100 cycles (benchmarks/bench_impedance.py's record) takes 1.83 s of CPU as it is and
3.40 s with the two loaded: the command, which must stay under 2 s on an idle machine (1.47 s there,
docs/guide/impedance.md), would take about twice as long.

The Butterworth filter is linear and time-invariant, so a run started in the steady state of a constant
input x0 (`sosfilt` with `sosfilt_zi(sos) * x0`, as `sosfiltfilt` starts each pass) is the constant
g x0 (g the DC gain) plus the response from rest to x - x0.  That response is computed a block of 16
samples at a time, for all rows at once: inside a block a matrix product, between blocks the sections'
state carried over; the block matrices come from the sections' own difference equations.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def butter_poles(order: int, hz: float, fs: float) -> tuple[np.ndarray, float]:
    """Digital poles and gain of the Butterworth low-pass (zeros: -1, `order` times): the analog
    prototype's poles pre-warped to `hz` and mapped by the bilinear transform (as `scipy.signal.butter`)."""
    m = np.arange(-order + 1, order, 2)
    warped = 2 * fs * np.tan(np.pi * hz / fs)
    p = warped * -np.exp(1j * np.pi * m / (2 * order))
    k = float(np.real(warped**order / np.prod(2 * fs - p)))
    return (2 * fs + p) / (2 * fs - p), k


def butter_sos(order: int, hz: float, fs: float) -> np.ndarray:
    """Second-order sections (b0, b1, b2, 1, a1, a2) of the Butterworth low-pass, for an even order as
    `scipy.signal.butter(order, hz, fs=fs, output="sos")` gives them: the poles nearest the unit circle
    last, the gain in the first section.  An odd order's real pole gets the first section and the last
    section one zero less (scipy orders its sections so too, except near the Nyquist frequency)."""
    p, k = butter_poles(order, hz, fs)
    pairs = sorted((q for q in p if q.imag > 0), key=lambda q: -abs(1 - abs(q)))
    sections = [[1.0, 2.0, 1.0, 1.0, -2 * q.real, q.real**2 + q.imag**2] for q in pairs]
    if order % 2:
        sections.insert(0, [1.0, 2.0, 1.0, 1.0, -float(p[np.argmin(np.abs(p.imag))].real), 0.0])
        sections[-1][:3] = [1.0, 1.0, 0.0]
    sos = np.array(sections)
    sos[0, :3] *= k
    return sos


def _run(sos: np.ndarray, x: list[float], state: list[list[float]]) -> list[float]:
    """The cascade's difference equations (transposed direct form II per section, as `sosfilt`) on a
    scalar sequence, from `state` (updated in place)."""
    out = []
    for v in x:
        for z, (b0, b1, b2, _, a1, a2) in zip(state, sos):
            y = b0 * v + z[0]
            z[0], z[1] = b1 * v - a1 * y + z[1], b2 * v - a2 * y
            v = y
        out.append(v)
    return out


@lru_cache(maxsize=32)
def _blocks(
    order: int, hz: float, fs: float, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, int]:
    """The cascade over a block of `size` samples from its state s (2 per section): outputs
    y = T u + O s and the next state s' = Phi s + G u, from the sections' own recursion."""
    sos = butter_sos(order, hz, fs)
    ns = 2 * len(sos)

    def run(u: list[float], s0: list[float]) -> tuple[list[float], list[float]]:
        state = [s0[i : i + 2] for i in range(0, ns, 2)]
        y = _run(sos, u, state)
        return y, [v for z in state for v in z]

    zero = [0.0] * ns
    h, states = [], []
    state = [[0.0, 0.0] for _ in sos]
    for v in [1.0] + [0.0] * (size - 1):  # the impulse response and the state after each sample
        h += _run(sos, [v], state)
        states.append([c for z in state for c in z])
    T = np.zeros((size, size))
    for j in range(size):
        T[j:, j] = h[: size - j]
    G = np.array([states[size - 1 - j] for j in range(size)]).T  # (ns, size)
    O, Phi = np.zeros((size, ns)), np.zeros((ns, ns))
    for i in range(ns):
        e = list(zero)
        e[i] = 1.0
        O[:, i], Phi[:, i] = run([0.0] * size, e)
    gain = float(np.prod(sos[:, :3].sum(1) / sos[:, 3:].sum(1)))
    ntaps = 2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    return T, O, Phi, G, gain, 3 * ntaps


BLOCK = 16  # samples per block of the filter's block recursion


def _zero_state(x: np.ndarray, order: int, hz: float, fs: float) -> np.ndarray:
    """The cascade's response from rest along the last axis: within each block of `BLOCK` samples a
    matrix product, from block to block the state carried (`_blocks`)."""
    T, O, Phi, G, _, _ = _blocks(order, float(hz), float(fs), BLOCK)
    n = x.shape[-1]
    nb = -(-n // BLOCK)
    u = np.zeros(x.shape[:-1] + (nb * BLOCK,))
    u[..., :n] = x
    u = u.reshape(x.shape[:-1] + (nb, BLOCK))
    y = u @ T.T
    g = u @ G.T  # each block's input, carried to its end
    s = np.zeros(g.shape)  # the state at each block's start
    for b in range(1, nb):
        s[..., b, :] = s[..., b - 1, :] @ Phi.T + g[..., b - 1, :]
    y += s @ O.T
    return y.reshape(x.shape[:-1] + (nb * BLOCK,))[..., :n]


def filtfilt(x: np.ndarray, order: int, hz: float, fs: float) -> np.ndarray:
    """Zero-phase Butterworth low-pass along the last axis: forward and backward over the signal extended
    by odd reflection, each pass started in the steady state of its first value
    (`scipy.signal.sosfiltfilt(butter(order, hz, fs=fs, output="sos"), x, axis=-1)`)."""
    x = np.asarray(x, float)
    n = x.shape[-1]
    *_, g, pad = _blocks(order, float(hz), float(fs), BLOCK)
    if n <= pad:
        raise ValueError(f"the signal ({n} samples) must be longer than the filter's padding ({pad})")
    ext = np.concatenate(
        [2 * x[..., :1] - x[..., pad:0:-1], x, 2 * x[..., -1:] - x[..., -2 : -(pad + 2) : -1]], axis=-1
    )
    y = g * ext[..., :1] + _zero_state(ext - ext[..., :1], order, hz, fs)
    y = y[..., ::-1]
    y = g * y[..., :1] + _zero_state(y - y[..., :1], order, hz, fs)
    return y[..., ::-1][..., pad:-pad]


def causal(x: np.ndarray, order: int, hz: float, fs: float, side: int = -1) -> np.ndarray:
    """Butterworth low-pass from rest along the last axis: causal (side -1, `sosfilt`) or anti-causal
    (side +1: run backward in time)."""
    x = np.asarray(x, float)
    if side > 0:
        return causal(x[..., ::-1], order, hz, fs)[..., ::-1]
    return _zero_state(x, order, hz, fs)


def welch(x: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density along the last axis (`scipy.signal.welch` defaults: periodic
    Hann window, half overlap, each segment's mean removed, density scaling, mean over segments)."""
    x = np.asarray(x, float)
    step = nperseg - nperseg // 2
    w = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(nperseg) / nperseg)
    starts = np.arange(0, x.shape[-1] - nperseg + 1, step)
    seg = np.stack([x[..., s : s + nperseg] for s in starts], axis=-2)
    seg = seg - seg.mean(-1, keepdims=True)
    P = np.abs(np.fft.rfft(seg * w, nperseg)) ** 2 / (fs * np.sum(w**2))
    P[..., 1 : nperseg // 2 + (nperseg % 2)] *= 2
    return np.fft.rfftfreq(nperseg, 1 / fs), P.mean(-2)


def find_peaks(x: np.ndarray, height: float, distance: int) -> np.ndarray:
    """Indices of the local maxima of x (a plateau: its middle, rounded down) at least `height` high and
    at least `distance` samples apart, the higher kept first (`scipy.signal.find_peaks`)."""
    x = np.asarray(x, float)
    found: list[int] = []
    i, last = 1, x.size - 1
    while i < last:
        if x[i - 1] < x[i]:
            ahead = i + 1
            while ahead < last and x[ahead] == x[i]:
                ahead += 1
            if x[ahead] < x[i]:
                found.append((i + ahead - 1) // 2)
                i = ahead
        i += 1
    peaks = np.array(found, int)
    peaks = peaks[x[peaks] >= height] if peaks.size else peaks
    if peaks.size > 1 and distance > 1:
        keep = np.ones(peaks.size, np.bool_)
        for j in np.argsort(x[peaks])[::-1]:
            if keep[j]:
                near = np.abs(peaks - peaks[j]) < distance
                near[j] = False
                keep &= ~near
        peaks = peaks[keep]
    return peaks


def gaussian_filter1d(x: np.ndarray, sigma: float, axis: int = -1, truncate: float = 4.0) -> np.ndarray:
    """Gaussian smoothing along `axis`, edges extended by their value
    (`scipy.ndimage.gaussian_filter1d(x, sigma, axis, mode="nearest")`)."""
    x = np.moveaxis(np.asarray(x, float), axis, -1)
    r = int(truncate * float(sigma) + 0.5)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    idx = np.clip(np.arange(x.shape[-1])[:, None] + np.arange(-r, r + 1), 0, x.shape[-1] - 1)
    return np.moveaxis(x[..., idx] @ k, -1, axis)
