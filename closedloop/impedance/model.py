"""The forearm-and-airjet experiment of thesis 9.6.5 (eq. 9.18-9.20) and a numpy RK4 twin.

The perturbed forearm obeys (eq. 9.20, with settable time-varying muscle stiffness and damping)

    tau_m(t) = I th'' + B(t) th' + K(t) (th - th_ref(t)) - m g r sin(th) - tau_v(t)
    tau_m(t) = tau_PRBS(t) - I_a th'' + m_a g r_a sin(th)          (the force sensor on the airjet)

(the thesis prints "- m_a g r_a sin" in the sensor equation; with its sign of gravity in eq. 9.20 the
airjet's own weight adds to the sensed torque, as written here, otherwise the sensed torque would not
obey eq. 9.20), so the whole limb moves as
(I + I_a) th'' = tau_PRBS - B th' - K (th - th_ref) + (m g r + m_a g r_a) sin th + tau_v.  th = 0 is the upright forearm (target 1), so gravity lowers the effective stiffness there
(thesis Fig. 9-9).  th_ref(t) is computed so that the unperturbed arm follows the 0.5 Hz, 1 rad
peak-to-peak sinusoid th_d(t) = 0.5 - 0.5 cos(2 pi t / T) exactly.  tau_v is a band-limited
"voluntary" torque that varies from cycle to cycle.

The truth of the linearised perturbation model (eq. 7.9) along th_0 = th_d is

    I(t) = I,  B(t) = B(t),  K_eff(t) = K(t) - m g r cos(th_0(t)).

`simulate_rk4` integrates independent blocks of consecutive cycles (as the thesis's 30 s blocks) in
parallel with classical fourth-order Runge-Kutta, every input held over the sample interval (as
MuJoCo holds its controls), which is what `mujoco_sim` reproduces.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from closedloop.errors import InputError
from closedloop.impedance.data import Record
from closedloop.impedance.filters import filtfilt

log = logging.getLogger(__name__)
G = 9.8


class ProfileError(InputError):
    """A K(t) or B(t) profile specification is wrong."""


@dataclass(frozen=True)
class Profile:
    """A cyclic parameter profile p(t_c), t_c the time within the cycle (s).

    kinds: ``constant:V``; ``step:V0,V1,T_STEP`` (V0 before T_STEP, V1 after, every cycle);
    ``square:V0,V1,PERIOD`` (V0 for the first half of each period); ``dip:V,DEPTH,WIDTH`` (V lowered by
    the fraction DEPTH in Gaussian dips of std WIDTH centred on each movement's peak velocity, T/4 and
    3T/4 - the mid-movement stiffness dip of the thesis's results).
    """

    kind: str = "constant"
    values: tuple[float, ...] = (20.0,)

    @classmethod
    def from_spec(cls, spec: "str | float | Profile", name: str = "profile") -> "Profile":
        if isinstance(spec, Profile):
            return spec
        if isinstance(spec, (int, float)):
            if not np.isfinite(spec):
                raise ProfileError(f"{name} {spec}: must be a finite number")
            return cls("constant", (float(spec),))
        kind, _, rest = str(spec).partition(":")
        kind = kind.strip().lower()
        need = {"constant": 1, "step": 3, "square": 3, "dip": 3}
        if kind not in need:
            try:
                v = float(kind)
                if not np.isfinite(v):
                    raise ValueError
                return cls("constant", (v,))
            except ValueError:
                raise ProfileError(f"{name} '{spec}': kind must be one of {sorted(need)}") from None
        try:
            vals = tuple(float(v) for v in rest.split(",")) if rest.strip() else ()
        except ValueError:
            raise ProfileError(f"{name} '{spec}': values must be numbers") from None
        if len(vals) != need[kind]:
            raise ProfileError(f"{name} '{spec}': {kind} takes {need[kind]} comma-separated values")
        if not all(np.isfinite(vals)) or max(abs(v) for v in vals) > 1e6:
            raise ProfileError(f"{name} '{spec}': values must be finite numbers (below 1e6 in magnitude)")
        if kind == "square" and vals[2] <= 0 or kind == "dip" and vals[2] <= 0:
            raise ProfileError(f"{name} '{spec}': period/width must be positive")
        return cls(kind, vals)

    def __call__(self, tc: np.ndarray, period: float) -> np.ndarray:
        tc = np.asarray(tc, float)
        v = self.values
        if self.kind == "constant":
            return np.full_like(tc, v[0])
        if self.kind == "step":
            return np.where(tc < v[2], v[0], v[1])
        if self.kind == "square":
            return np.where(np.mod(tc, v[2]) < v[2] / 2, v[0], v[1])
        dips = np.zeros_like(tc)
        for c in (period / 4, 3 * period / 4):
            dips += np.exp(-0.5 * ((tc - c) / v[2]) ** 2)
        return v[0] * (1.0 - v[1] * dips)

    @property
    def spec(self) -> str:
        return f"{self.kind}:" + ",".join(f"{x:g}" for x in self.values)


@dataclass
class ForearmParams:
    """Thesis 9.6.5: forearm I = 0.075 kg m^2 (a uniform 0.35 m rod of 1.84 kg, c.o.m. at 0.175 m),
    airjet m_a = 0.2 kg at r_a = 0.4 m (I_a = 0.032 kg m^2), K = 20 N m/rad, B = 1 N m s/rad."""

    I: float = 0.075
    m: float = 1.84
    r: float = 0.175
    m_a: float = 0.2
    r_a: float = 0.4
    gravity: bool = True

    @property
    def I_a(self) -> float:
        return self.m_a * self.r_a**2

    @property
    def mgr(self) -> float:
        return self.m * G * self.r if self.gravity else 0.0

    @property
    def magra(self) -> float:
        return self.m_a * G * self.r_a if self.gravity else 0.0


@dataclass
class ExperimentConfig:
    """The simulated experiment: cycles, sampling, perturbation, noise and variability."""

    n_cycles: int = 100
    period: float = 2.0  # s, one movement target 1 -> target 2 -> target 1
    amplitude: float = 1.0  # rad peak to peak
    fs: float = 600.0  # Hz
    stiffness: Profile = field(default_factory=lambda: Profile("constant", (20.0,)))
    damping: Profile = field(default_factory=lambda: Profile("constant", (1.0,)))
    prbs_amplitude: float = 1.6  # N m
    prbs_element: float = 0.020  # s
    prbs_phase: str = "random"  # "random" per cycle or "locked" to the cycle clock
    noise: float = 0.05  # measurement noise std as a fraction of the perturbation std
    voluntary_rms: float = 0.0  # N m, band-limited voluntary torque variability
    voluntary_band: float = 3.0  # Hz
    cycles_per_block: int = 10
    posture: float | None = None  # hold this angle (rad) instead of moving
    seed: int = 0
    arm: ForearmParams = field(default_factory=ForearmParams)

    def __post_init__(self):
        self.stiffness = Profile.from_spec(self.stiffness, "stiffness")
        self.damping = Profile.from_spec(self.damping, "damping")
        if self.n_cycles < 1 or self.cycles_per_block < 1:
            raise InputError("n_cycles and cycles_per_block must be at least 1")
        if self.prbs_phase not in ("random", "locked"):
            raise InputError(f"prbs_phase '{self.prbs_phase}': expected 'random' or 'locked'")
        tc = np.linspace(0.0, self.period, 4001)
        if np.min(self.stiffness(tc, self.period)) <= 0:
            raise ProfileError(
                f"stiffness '{self.stiffness.spec}': K(t) must stay positive over the cycle "
                f"(minimum {np.min(self.stiffness(tc, self.period)):.3g})"
            )
        if np.min(self.damping(tc, self.period)) < 0:
            raise ProfileError(
                f"damping '{self.damping.spec}': B(t) must not be negative (minimum "
                f"{np.min(self.damping(tc, self.period)):.3g}): a negative damping makes the joint unstable"
            )

    @property
    def samples_per_cycle(self) -> int:
        return int(round(self.period * self.fs))

    @property
    def n_blocks(self) -> int:
        return -(-self.n_cycles // self.cycles_per_block)


@dataclass
class Trajectory:
    """Nominal trajectory and gains on the sample grid of one block (held over each interval)."""

    t: np.ndarray  # (N,) time from block start
    theta_d: np.ndarray
    theta_ref: np.ndarray
    K: np.ndarray
    B: np.ndarray
    tau_nom: np.ndarray  # measured torque of the unperturbed movement


def nominal(cfg: ExperimentConfig, n_samples: int) -> Trajectory:
    """th_d, the motor input th_ref(t) that makes eq. 9.19 follow it, and K(t), B(t)."""
    a = cfg.arm
    t = np.arange(n_samples) / cfg.fs
    tc = np.mod(t, cfg.period)
    w = 2 * np.pi / cfg.period
    if cfg.posture is None:
        th = cfg.amplitude / 2 * (1 - np.cos(w * t))
        thd = cfg.amplitude / 2 * w * np.sin(w * t)
        thdd = cfg.amplitude / 2 * w**2 * np.cos(w * t)
    else:
        th, thd, thdd = np.full_like(t, cfg.posture), np.zeros_like(t), np.zeros_like(t)
    K, B = cfg.stiffness(tc, cfg.period), cfg.damping(tc, cfg.period)
    if np.any(K <= 0):
        raise ProfileError("stiffness profile must stay positive")
    ref = th + ((a.I + a.I_a) * thdd + B * thd - (a.mgr + a.magra) * np.sin(th)) / K
    tau_nom = -a.I_a * thdd + a.magra * np.sin(th)
    return Trajectory(t, th, ref, K, B, tau_nom)


def prbs(cfg: ExperimentConfig, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """+-A PRBS with elements of `prbs_element` s; the element clock restarts at every cycle onset with
    a random phase (or phase 0 when locked to the cycle clock).  Returns (n_blocks, n_samples)."""
    L, e = cfg.samples_per_cycle, int(round(cfg.prbs_element * cfg.fs))
    n_cyc = -(-n_samples // L)
    k = np.arange(L)
    out = np.empty((cfg.n_blocks, n_cyc * L))
    for b in range(cfg.n_blocks):
        ph = rng.integers(0, e, n_cyc) if cfg.prbs_phase == "random" else np.zeros(n_cyc, int)
        elem = (k[None, :] + ph[:, None]) // e  # element index within cycle
        signs = rng.choice([-1.0, 1.0], size=(n_cyc, elem.max() + 1))
        out[b] = np.take_along_axis(signs, elem, axis=1).ravel()
    return cfg.prbs_amplitude * out[:, :n_samples]


def voluntary(cfg: ExperimentConfig, n_samples: int, rng: np.random.Generator) -> np.ndarray:
    """Band-limited (Butterworth, `voluntary_band` Hz) Gaussian torque of RMS `voluntary_rms`."""
    if cfg.voluntary_rms <= 0:
        return np.zeros((cfg.n_blocks, n_samples))
    x = filtfilt(rng.standard_normal((cfg.n_blocks, n_samples)), 4, cfg.voluntary_band, cfg.fs)
    return cfg.voluntary_rms * x / np.sqrt(np.mean(x**2))


def rk4_blocks(cfg: ExperimentConfig, nom: Trajectory, u: np.ndarray, tv: np.ndarray) -> np.ndarray:
    """Integrate (I + I_a) th'' = u + tv - B th' - K (th - th_ref) + (mgr + m_a g r_a) sin th, all
    inputs held over each sample interval.  Returns (n_blocks, N, 3): th, th', th''."""
    a = cfg.arm
    h, itot, grav = 1.0 / cfg.fs, a.I + a.I_a, a.mgr + a.magra
    nb, N = u.shape
    x = np.full(nb, nom.theta_d[0])
    v = np.full(nb, (nom.theta_d[1] - nom.theta_d[0]) * 0.0)
    out = np.empty((nb, N, 3))
    for n in range(N):
        f = u[:, n] + tv[:, n]
        K, B, ref = nom.K[n], nom.B[n], nom.theta_ref[n]

        def acc(xx, vv):
            return (f - B * vv - K * (xx - ref) + grav * np.sin(xx)) / itot

        a1 = acc(x, v)
        out[:, n, 0], out[:, n, 1], out[:, n, 2] = x, v, a1
        k1x, k1v = v, a1
        k2x, k2v = v + 0.5 * h * k1v, acc(x + 0.5 * h * k1x, v + 0.5 * h * k1v)
        k3x, k3v = v + 0.5 * h * k2v, acc(x + 0.5 * h * k2x, v + 0.5 * h * k2v)
        k4x, k4v = v + h * k3v, acc(x + h * k3x, v + h * k3v)
        x = x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return out


def truth_curves(cfg: ExperimentConfig) -> dict[str, np.ndarray]:
    """I(t), B(t), K_eff(t) = K(t) - m g r cos th_0(t) over one cycle (analytic truth of eq. 7.9)."""
    nom = nominal(cfg, cfg.samples_per_cycle)
    a = cfg.arm
    return {
        "t": nom.t,
        "I": np.full_like(nom.t, a.I),
        "B": nom.B.copy(),
        "K": nom.K - a.mgr * np.cos(nom.theta_d),
        "K_muscle": nom.K.copy(),
        "theta0": nom.theta_d.copy(),
    }


def natural(I: np.ndarray, B: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Natural frequency w0 = sqrt(K/I) (rad/s) and damping ratio zeta = B / (2 sqrt(K I))."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(K / I), B / (2 * np.sqrt(K * I))


@dataclass
class Simulation:
    """A simulated record with its ground truth and the noise actually added."""

    record: Record
    truth: dict[str, np.ndarray]
    config: ExperimentConfig
    noise_std: tuple[float, float]  # angle (rad), torque (N m)
    seconds: float = 0.0


def block_record(cfg: ExperimentConfig, th: np.ndarray, tau: np.ndarray, u: np.ndarray) -> Record:
    """Blocks (n_blocks, N) -> one Record with a `block` column and events at the usable cycles' onsets
    (the lead-in cycle and the tail only pad them); a partial last block is trimmed."""
    L, (nb, N) = cfg.samples_per_cycle, th.shape
    usable = np.full(nb, cfg.cycles_per_block)
    usable[-1] -= nb * cfg.cycles_per_block - cfg.n_cycles
    ev = np.zeros((nb, N), int)
    for b in range(nb):
        ev[b, L : (usable[b] + 1) * L : L] = 1
    keep = (np.arange(N)[None, :] < ((usable + 2) * L)[:, None]).ravel()
    time = np.arange(nb * N) / cfg.fs
    return Record(
        time[keep],
        th.ravel()[keep],
        tau.ravel()[keep],
        u.ravel()[keep],
        ev.ravel()[keep],
        np.repeat(np.arange(nb), N)[keep],
    )
