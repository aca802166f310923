"""An elbow experiment independent of `model`, for judging the estimator's defaults on data it was not tuned on.

It differs from the thesis forearm of `model` (eq. 9.20) wherever a lab's rig would:

* the limb: an elbow with I = 0.065 kg m^2, m = 1.5 kg at r = 0.15 m, the angle measured from the
  horizontal (gravity torque -m g r cos th, so gravity lowers the stiffness most when the forearm points
  up), movements between 0.3 and 1.3 rad with a minimum-jerk-like profile (not a sinusoid);
* the perturbation: a +-A PRBS command with 20 ms elements, passed through a 5 ms actuator delay and a
  first-order actuator lag (time constant 2 ms) before it reaches the limb; the torque sensor measures the
  torque the actuator applies (after delay and lag), the command column records the command;
* the integration: classical RK4 on a 4x finer grid with the actuator state integrated with the limb,
  so the input is not held over the sample interval as in `model`;
* the noise: Gaussian, 5 % of the standard deviation of each measured perturbation (angle and torque);
* the record: one continuous recording per block of cycles (lead-in and tail cycles) with events at the
  cycle onsets.

The linearised truth (eq. 7.9) along the nominal movement th_0(t) is I(t) = I, B(t),
K_eff(t) = K(t) - m g r sin th_0(t) (the derivative of the gravity torque -m g r cos th).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from closedloop.impedance.data import Record
from closedloop.impedance.filters import filtfilt

G = 9.81


@dataclass
class ElbowConfig:
    """Settings of the independent elbow experiment (see the module docstring)."""

    n_cycles: int = 100
    period: float = 2.0
    fs: float = 600.0
    I: float = 0.065
    m: float = 1.5
    r: float = 0.15
    stiffness: str = "constant"  # constant | dip | square | ramp-b (B ramps) | voluntary
    K0: float = 15.0
    B0: float = 0.8
    prbs_amplitude: float = 1.2
    prbs_element: float = 0.020
    delay: float = 0.005
    lag: float = 0.002
    noise: float = 0.05
    voluntary_rms: float = 0.0
    cycles_per_block: int = 10
    substeps: int = 4
    seed: int = 0


def _profiles(cfg: ElbowConfig, tc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K(t), B(t) of the truth named by `cfg.stiffness` at cycle time tc."""
    T = cfg.period
    K = np.full_like(tc, cfg.K0)
    B = np.full_like(tc, cfg.B0)
    if cfg.stiffness == "dip":  # stiffness halved mid-movement, Gaussian dips of 120 ms std
        dips = np.zeros_like(tc)
        for c in (0.3 * T, 0.8 * T):
            dips += np.exp(-0.5 * ((tc - c) / 0.12) ** 2)
        K = cfg.K0 * (1 - 0.5 * dips)
    elif cfg.stiffness == "square":  # 250 ms on, 250 ms off
        K = np.where(np.mod(tc, 0.5) < 0.25, cfg.K0, 0.45 * cfg.K0)
    elif cfg.stiffness == "ramp-b":  # B rises from B0 to 2.5 B0 over the middle of the cycle
        B = cfg.B0 * (1 + 1.5 * np.clip((tc - 0.4 * T) / (0.4 * T), 0, 1))
    return K, B


def _movement(cfg: ElbowConfig, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nominal angle, velocity, acceleration: 0.3 -> 1.3 rad in the first half, back in the second
    (minimum-jerk profile), every cycle."""
    T = cfg.period
    tc = np.mod(t, T)
    s = np.where(tc < T / 2, tc, T - tc) / (T / 2)  # 0 -> 1 -> 0
    sgn = np.where(tc < T / 2, 1.0, -1.0)
    p = 10 * s**3 - 15 * s**4 + 6 * s**5
    dp = (30 * s**2 - 60 * s**3 + 30 * s**4) * sgn / (T / 2)
    ddp = (60 * s - 180 * s**2 + 120 * s**3) / (T / 2) ** 2
    return 0.3 + p, dp, ddp


def truth(cfg: ElbowConfig) -> dict[str, np.ndarray]:
    """I(t), B(t), K_eff(t) over one cycle on the sample grid (eq. 7.9 along th_0)."""
    t = np.arange(int(round(cfg.period * cfg.fs))) / cfg.fs
    K, B = _profiles(cfg, t)
    th, _, _ = _movement(cfg, t)
    return {"t": t, "I": np.full_like(t, cfg.I), "B": B, "K": K - cfg.m * G * cfg.r * np.sin(th)}


def simulate_elbow(cfg: ElbowConfig) -> tuple[Record, dict[str, np.ndarray]]:
    """The record (blocks of cycles, events at the usable onsets, command = the PRBS command) and its truth."""
    rng = np.random.default_rng(cfg.seed)
    L = int(round(cfg.period * cfg.fs))
    nb = -(-cfg.n_cycles // cfg.cycles_per_block)
    N = (cfg.cycles_per_block + 2) * L
    h = 1.0 / (cfg.fs * cfg.substeps)
    M = N * cfg.substeps
    tf = np.arange(M + 1) * h
    th_d, v_d, a_d = _movement(cfg, tf)
    K, B = _profiles(cfg, np.mod(tf, cfg.period))
    mgr = cfg.m * G * cfg.r
    # equilibrium that makes the unperturbed limb follow th_d: K (th_d - eq) = -I a - B v + mgr cos th ...
    eq = th_d + (cfg.I * a_d + B * v_d + mgr * np.cos(th_d)) / K
    e = int(round(cfg.prbs_element * cfg.fs * cfg.substeps))
    n_el = M // e + 2
    cmd_el = cfg.prbs_amplitude * rng.choice([-1.0, 1.0], size=(nb, n_el))
    offset = rng.integers(0, e, nb)
    idx = (np.arange(M + 1)[None, :] + offset[:, None]) // e
    cmd = np.take_along_axis(cmd_el, idx, axis=1)  # (nb, M+1) command on the fine grid
    dly = int(round(cfg.delay / h))
    cmd_d = np.concatenate([np.repeat(cmd[:, :1], dly, 1), cmd[:, :-dly]], axis=1) if dly else cmd
    vol = np.zeros((nb, M + 1))
    if cfg.voluntary_rms > 0:
        x = filtfilt(rng.standard_normal((nb, M + 1)), 2, 4.0, 1 / h)
        vol = cfg.voluntary_rms * x / x.std()

    # The inputs at each fine step k (`at`) and half a step on (`mid`), as Python floats and (M+1, nb) rows
    # laid out before the loop: indexing them is most of the cost of a Python RK4 step.
    at = (K.tolist(), B.tolist(), eq.tolist(), np.ascontiguousarray(cmd_d.T), np.ascontiguousarray(vol.T))
    mid = (
        ((K[:-1] + K[1:]) / 2).tolist(),
        ((B[:-1] + B[1:]) / 2).tolist(),
        ((eq[:-1] + eq[1:]) / 2).tolist(),
        np.ascontiguousarray(((cmd_d[:, :-1] + cmd_d[:, 1:]) / 2).T),
        np.ascontiguousarray(((vol[:, :-1] + vol[:, 1:]) / 2).T),
    )
    inertia, lag = cfg.I, cfg.lag

    def f(k: int, y: np.ndarray, half: bool) -> np.ndarray:
        """Derivatives of y = (angle, velocity, actuator torque), (3, nb), at fine step k (+ 1/2)."""
        Ks, Bs, eqs, us, tvs = mid if half else at
        x, v, a = y
        out = np.empty_like(y)
        out[0] = v
        out[1] = (a + tvs[k] - Bs[k] * v - Ks[k] * (x - eqs[k]) - mgr * np.cos(x)) / inertia
        out[2] = (us[k] - a) / lag
        return out

    y = np.array([np.full(nb, th_d[0]), np.full(nb, v_d[0]), np.zeros(nb)])
    th = np.empty((nb, N))
    tau = np.empty((nb, N))
    for k in range(M):
        if k % cfg.substeps == 0:
            th[:, k // cfg.substeps], tau[:, k // cfg.substeps] = y[0], y[2]
        k1 = f(k, y, False)
        k2 = f(k, y + h / 2 * k1, True)
        k3 = f(k, y + h / 2 * k2, True)
        k4 = f(min(k + 1, M), y + h * k3, False)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    sub = np.arange(N) * cfg.substeps
    nom = th_d[sub]
    dth, dtau = th - nom, tau - tau.mean(0)
    th = th + cfg.noise * dth[:, L:].std() * rng.standard_normal(th.shape)
    tau = tau + cfg.noise * dtau[:, L:].std() * rng.standard_normal(tau.shape)
    usable = np.full(nb, cfg.cycles_per_block)
    usable[-1] -= nb * cfg.cycles_per_block - cfg.n_cycles
    ev = np.zeros((nb, N), int)
    for b in range(nb):
        ev[b, L : (usable[b] + 1) * L : L] = 1
    keep = (np.arange(N)[None, :] < ((usable + 2) * L)[:, None]).ravel()
    time = np.arange(nb * N) / cfg.fs + np.repeat(np.arange(nb) * 5.0, N)  # 5 s pause between blocks
    rec = Record(
        time[keep],
        th.ravel()[keep],
        tau.ravel()[keep],
        cmd[:, sub].ravel()[keep],
        ev.ravel()[keep],
        np.repeat(np.arange(nb), N)[keep],
    )
    return rec, truth(cfg)
