"""The simulated experiment: a forearm (eq. 9.20) driven along its movement with a perturbation, on the
numpy RK4 twin (`model`) or on MuJoCo (`mujoco_sim`), recorded in blocks of cycles with noise."""

from __future__ import annotations

import logging

import numpy as np

from closedloop.errors import InputError
from closedloop.impedance.model import (
    ExperimentConfig,
    Simulation,
    block_record,
    nominal,
    prbs,
    rk4_blocks,
    truth_curves,
    voluntary,
)

log = logging.getLogger(__name__)


def simulate(cfg: ExperimentConfig, engine: str = "rk4") -> Simulation:
    """Simulate `n_cycles` usable cycles in blocks: each block runs cycles_per_block + 2 cycles (a
    lead-in and a tail that give the usable cycles their padding), from the nominal state.
    `engine` is "rk4" (this module) or "mujoco" (`mujoco_sim`).  Noise: Gaussian on angle and torque with
    std `noise` times the std of the perturbation (signal minus nominal)."""
    import time as _time

    t0 = _time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    L = cfg.samples_per_cycle
    N = (cfg.cycles_per_block + 2) * L
    nom = nominal(cfg, N)
    u = prbs(cfg, N, rng)
    tv = voluntary(cfg, N, rng)
    if engine == "rk4":
        st = rk4_blocks(cfg, nom, u, tv)
    elif engine == "mujoco":
        from closedloop.impedance.mujoco_sim import forearm_rollout

        st = forearm_rollout(cfg, nom, u, tv)
    else:
        raise InputError(f"engine '{engine}': expected rk4 or mujoco")
    a = cfg.arm
    th = st[..., 0]
    tau = u - a.I_a * st[..., 2] + a.magra * np.sin(th)
    dth, dtau = th - nom.theta_d, tau - nom.tau_nom
    s_th, s_tau = cfg.noise * dth[:, L:].std(), cfg.noise * dtau[:, L:].std()
    th = th + s_th * rng.standard_normal(th.shape)
    tau = tau + s_tau * rng.standard_normal(tau.shape)
    rec = block_record(cfg, th, tau, u)
    log.info("simulated %d cycles (%s) in %.2f s", cfg.n_cycles, engine, _time.perf_counter() - t0)
    return Simulation(rec, truth_curves(cfg), cfg, (s_th, s_tau), _time.perf_counter() - t0)
