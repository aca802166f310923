"""MuJoCo simulation of the impedance experiments, and truth by finite differences of any model.

Forearm (thesis 9.6.5, eq. 9.20): a hinge `elbow` (axis y; th = 0 upright, so gravity destabilises),
the forearm body (1.84 kg, c.o.m. 0.175 m, 0.075 kg m^2 about the elbow) and a welded child body
`airjet` (0.2 kg point mass at 0.4 m).  Actuators, all driven through `mujoco.rollout`:

    jet    motor on the site `jet` (force along the tangent, x of the site frame, gear 1/r_a so that the
           control is the torque in N m): the PRBS airjet
    stiff  general, gain affine in the joint angle (gainprm 0 -1 0): force = -th * ctrl, ctrl = K(t)
    ref    motor on the joint, ctrl = K(t) th_ref(t)
    damp   general, gain affine in the joint velocity (gainprm 0 0 -1): force = -th' * ctrl, ctrl = B(t)
    vol    motor on the joint: the voluntary torque tau_v(t)

A `torque` sensor at the elbow on the airjet body reads the interaction torque between arm and airjet
(actuator forces enter as generalised forces, so the sensed torque is I_a th'' - m_a g r_a sin th and the
airjet's force is added: tau_m = u - sensor_y).  The integrator is RK4 at the sampling interval, controls
held over a step: the numpy twin `model.rk4_blocks` integrates the same discretisation.

Truth (`fd_truth`): with the airjet removed, tau(th, th', th'', t) = qfrc_inverse - qfrc_actuator(arm) is
the torque an external agent must apply; its central differences about the nominal trajectory give
K_eff = d tau / d th, B = d tau / d th', I = d tau / d th'' at every instant (eq. 7.9), for any model.
"""

from __future__ import annotations

import os

import numpy as np

from closedloop.impedance.model import ExperimentConfig, ForearmParams, Trajectory

FOREARM_XML = """
<mujoco model="forearm_airjet">
  <option timestep="{dt}" integrator="RK4" gravity="0 0 {g}">
    <flag contact="disable" constraint="disable" warmstart="disable" filterparent="disable"/>
  </option>
  <worldbody>
    <body name="forearm">
      <joint name="elbow" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 {r}" mass="{m}" diaginertia="{ic} {ic} 1e-4"/>
      <body name="airjet">
        <inertial pos="0 0 {ra}" mass="{ma}" diaginertia="1e-9 1e-9 1e-9"/>
        <site name="jet" pos="0 0 {ra}"/>
        <site name="sensor" pos="0 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="jet" site="jet" gear="{gj} 0 0 0 0 0" ctrllimited="false"/>
    <general name="stiff" joint="elbow" gaintype="affine" gainprm="0 -1 0" ctrllimited="false"/>
    <motor name="ref" joint="elbow" ctrllimited="false"/>
    <general name="damp" joint="elbow" gaintype="affine" gainprm="0 0 -1" ctrllimited="false"/>
    <motor name="vol" joint="elbow" ctrllimited="false"/>
  </actuator>
  <sensor>
    <torque name="cuff" site="sensor"/>
  </sensor>
</mujoco>
"""


def forearm_xml(arm: ForearmParams, fs: float, airjet: bool = True) -> str:
    ic = arm.I - arm.m * arm.r**2  # about the c.o.m., so that I about the elbow = arm.I
    return FOREARM_XML.format(
        dt=1.0 / fs,
        g=-9.8 if arm.gravity else 0.0,
        r=arm.r,
        m=arm.m,
        ic=ic,
        ra=arm.r_a,
        ma=arm.m_a if airjet else 1e-9,
        gj=1.0 / arm.r_a,
    )


def forearm_rollout(cfg: ExperimentConfig, nom: Trajectory, u: np.ndarray, tv: np.ndarray) -> np.ndarray:
    """Blocks in parallel through `mujoco.rollout`; returns (n_blocks, N, 3) th, th', th'' at the samples
    (th'' recovered from the cuff torque sensor), aligned with `model.rk4_blocks`."""
    import mujoco
    from mujoco import rollout

    m = mujoco.MjModel.from_xml_string(forearm_xml(cfg.arm, cfg.fs))
    d = mujoco.MjData(m)
    nb, N = u.shape
    ctrl = np.empty((nb, N, 5))
    ctrl[..., 0] = u
    ctrl[..., 1] = nom.K
    ctrl[..., 2] = nom.K * nom.theta_ref
    ctrl[..., 3] = nom.B
    ctrl[..., 4] = tv
    d.qpos[0], d.qvel[0] = nom.theta_d[0], 0.0
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s0, spec)
    threads = [mujoco.MjData(m) for _ in range(max(1, min(nb, os.cpu_count() or 1, 4)))]
    state, sens = rollout.rollout(m, threads, np.tile(s0, (nb, 1)), ctrl)
    # state[k] is after step k; sensors of step k are computed at the state before it
    qpos = np.concatenate([np.full((nb, 1), nom.theta_d[0]), state[:, :-1, 1]], axis=1)
    qvel = np.concatenate([np.zeros((nb, 1)), state[:, :-1, 2]], axis=1)
    a = cfg.arm
    tau_m = u - sens[..., 1]
    acc = (u + a.magra * np.sin(qpos) - tau_m) / a.I_a  # from tau_m = u - I_a th'' + m_a g r_a sin th
    return np.stack([qpos, qvel, acc], axis=-1)


def fd_truth(
    xml: str, qpos: np.ndarray, qvel: np.ndarray, qacc: np.ndarray, ctrl: np.ndarray, joint: int = 0, eps: float = 1e-5
) -> dict[str, np.ndarray]:
    """I, B, K_eff of joint `joint` by central differences of the torque an external agent applies,
    tau = qfrc_inverse - qfrc_actuator, about the nominal (qpos, qvel, qacc, ctrl) at every instant."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    T = len(qpos)
    out = {k: np.empty(T) for k in ("I", "B", "K")}

    def tau(t, dq=0.0, dv=0.0, da=0.0):
        d.qpos[:], d.qvel[:], d.qacc[:] = qpos[t], qvel[t], qacc[t]
        d.qpos[joint] += dq
        d.qvel[joint] += dv
        d.qacc[joint] += da
        d.ctrl[:] = ctrl[t]
        mujoco.mj_inverse(m, d)
        mujoco.mj_fwdActuation(m, d)
        return d.qfrc_inverse[joint] - d.qfrc_actuator[joint]

    for t in range(T):
        out["K"][t] = (tau(t, dq=eps) - tau(t, dq=-eps)) / (2 * eps)
        out["B"][t] = (tau(t, dv=eps) - tau(t, dv=-eps)) / (2 * eps)
        out["I"][t] = (tau(t, da=eps) - tau(t, da=-eps)) / (2 * eps)
    return out


def forearm_truth(cfg: ExperimentConfig) -> dict[str, np.ndarray]:
    """Finite-difference truth of the forearm (airjet removed: only the arm's inertia is identified)."""
    from closedloop.impedance.model import nominal

    L = cfg.samples_per_cycle
    nom = nominal(cfg, L)
    w = 2 * np.pi / cfg.period
    qacc = cfg.amplitude / 2 * w**2 * np.cos(w * nom.t) if cfg.posture is None else np.zeros(L)
    qvel = np.gradient(nom.theta_d, 1.0 / cfg.fs) if cfg.posture is None else np.zeros(L)
    if cfg.posture is None:
        qvel = cfg.amplitude / 2 * w * np.sin(w * nom.t)
    ctrl = np.stack([np.zeros(L), nom.K, nom.K * nom.theta_ref, nom.B, np.zeros(L)], axis=1)
    tr = fd_truth(forearm_xml(cfg.arm, cfg.fs, airjet=False), nom.theta_d[:, None], qvel[:, None], qacc[:, None], ctrl)
    tr["t"] = nom.t
    tr["theta0"] = nom.theta_d
    return tr


ROBOT_XML = """
<mujoco model="two_link_impedance">
  <option timestep="{dt}" integrator="RK4" gravity="0 0 -9.8"/>
  <worldbody>
    <body name="link1">
      <joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.4" size="0.03" mass="3"/>
      <body name="link2" pos="0 0 0.4">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.35" size="0.025" mass="1.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="perturb" joint="elbow" ctrllimited="false"/>
    <general name="stiff0" joint="shoulder" gaintype="affine" gainprm="0 -1 0" ctrllimited="false"/>
    <general name="damp0" joint="shoulder" gaintype="affine" gainprm="0 0 -1" ctrllimited="false"/>
    <motor name="ref0" joint="shoulder" ctrllimited="false"/>
    <general name="stiff1" joint="elbow" gaintype="affine" gainprm="0 -1 0" ctrllimited="false"/>
    <general name="damp1" joint="elbow" gaintype="affine" gainprm="0 0 -1" ctrllimited="false"/>
    <motor name="ref1" joint="elbow" ctrllimited="false"/>
  </actuator>
</mujoco>
"""
# Held angle (rad), stiffness (N m/rad), damping (N m s/rad) of the shoulder's impedance loop.  The elbow's
# torque moves the shoulder: the elbow then shows the apparent inertia M22 + M12^2 w^2 / (K0 - M11 w^2), rising
# with frequency w, while the truth holds the shoulder still (M22).  With K0 = 2e5 (the shoulder's resonance
# near 90 Hz, damping ratio ~0.7) that excess is 0.3-0.6 % at an elbow resonance of 8.5 Hz (K = 200); with
# K0 = 2e4 (resonance 27-29 Hz) it was 3-6 %, outside the estimate's bands.  RK4 at 600 Hz: w h ~ 1, stable.
SHOULDER = (0.5, 200000.0, 500.0)


def robot_nominal(cfg: ExperimentConfig, N: int, shoulder: tuple[float, float, float] = SHOULDER):
    """Nominal joint trajectories and controls (perturbation 0) of the robot case: the elbow follows the
    0.5 Hz sinusoid under K(t), B(t) with computed-torque feed-forward; the shoulder is held stiffly by
    the impedance loop `shoulder` (angle, stiffness, damping)."""
    import mujoco

    from closedloop.impedance.model import nominal

    nom = nominal(cfg, N)
    w = 2 * np.pi / cfg.period
    qd = np.stack([np.full(N, shoulder[0]), nom.theta_d], 1)
    vd = np.stack([np.zeros(N), cfg.amplitude / 2 * w * np.sin(w * nom.t)], 1)
    ad = np.stack([np.zeros(N), cfg.amplitude / 2 * w**2 * np.cos(w * nom.t)], 1)
    m = mujoco.MjModel.from_xml_string(ROBOT_XML.format(dt=1.0 / cfg.fs))
    d = mujoco.MjData(m)
    ff = np.empty((N, 2))
    for k in range(N):
        d.qpos[:], d.qvel[:], d.qacc[:] = qd[k], vd[k], ad[k]
        mujoco.mj_inverse(m, d)
        ff[k] = d.qfrc_inverse
    K0, B0 = shoulder[1], shoulder[2]
    ctrl = np.stack(
        [
            np.zeros(N),
            np.full(N, K0),
            np.full(N, B0),
            K0 * qd[:, 0] + B0 * vd[:, 0] + ff[:, 0],
            nom.K,
            nom.B,
            nom.K * qd[:, 1] + nom.B * vd[:, 1] + ff[:, 1],
        ],
        1,
    )
    return m, qd, vd, ad, ctrl


def simulate_robot(cfg: ExperimentConfig, shoulder: tuple[float, float, float] = SHOULDER):
    """Robot case: one joint (the elbow of a two-link arm in a vertical plane) under a time-varying
    impedance controller K(t), B(t), perturbed by a PRBS joint torque measured by a torque sensor.
    Truth: finite differences of the elbow's external torque with the shoulder at its nominal, which
    holds for the data as far as the shoulder's loop (`shoulder`: angle, stiffness, damping; see
    `SHOULDER`) keeps the shoulder still at the elbow's frequencies."""
    import time as _time

    import mujoco
    from mujoco import rollout

    from closedloop.impedance.model import Simulation, block_record, prbs

    t0 = _time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    L, nb = cfg.samples_per_cycle, cfg.n_blocks
    N = (cfg.cycles_per_block + 2) * L
    m, qd, vd, ad, ctrl0 = robot_nominal(cfg, N, shoulder)
    u = prbs(cfg, N, rng)
    ctrl = np.repeat(ctrl0[None], nb, 0)
    ctrl[..., 0] = u
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qd[0], vd[0]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    s0 = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s0, spec)
    state, _ = rollout.rollout(m, d, np.tile(s0, (nb, 1)), ctrl)
    q1 = np.concatenate([np.full((nb, 1), qd[0, 1]), state[:, :-1, 2]], axis=1)  # [time, qpos0, qpos1, ...]
    s_th, s_tau = cfg.noise * (q1 - qd[:, 1])[:, L:].std(), cfg.noise * u.std()
    th = q1 + s_th * rng.standard_normal(q1.shape)
    tau = u + s_tau * rng.standard_normal(u.shape)
    rec = block_record(cfg, th, tau, u)
    c = slice(0, L)
    tr = fd_truth(ROBOT_XML.format(dt=1.0 / cfg.fs), qd[c], vd[c], ad[c], ctrl0[c], joint=1)
    tr["t"], tr["theta0"] = np.arange(L) / cfg.fs, qd[c, 1]
    return Simulation(rec, tr, cfg, (s_th, s_tau), _time.perf_counter() - t0)
