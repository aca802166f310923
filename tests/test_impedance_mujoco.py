"""MuJoCo forearm agrees with the numpy RK4 twin; finite-difference truth; the robot case."""

from __future__ import annotations

import numpy as np

from closedloop.impedance.data import onsets_from_events, segment
from closedloop.impedance.estimate import estimate
from closedloop.impedance.metrics import rel_errors
from closedloop.impedance.model import ExperimentConfig, truth_curves
from closedloop.impedance.mujoco_sim import forearm_truth, simulate_robot
from closedloop.impedance.simulation import simulate


def test_mujoco_matches_rk4_twin():
    cfg = ExperimentConfig(
        n_cycles=4,
        cycles_per_block=2,
        noise=0.0,
        seed=2,
        voluntary_rms=0.5,
        stiffness="square:20,8,0.5",
        damping="dip:1,0.3,0.1",
    )
    a, b = simulate(cfg, "rk4"), simulate(cfg, "mujoco")
    assert np.max(np.abs(a.record.angle - b.record.angle)) < 1e-7
    assert np.max(np.abs(a.record.torque - b.record.torque)) < 1e-6
    assert np.ptp(a.record.torque) > 2.0  # the PRBS is there


def test_finite_difference_truth_equals_analytic():
    cfg = ExperimentConfig(stiffness="dip:20,0.5,0.15", damping="step:1,2,1.0")
    fd, an = forearm_truth(cfg), truth_curves(cfg)
    for k in "IBK":
        assert np.max(np.abs(fd[k] - an[k])) < 1e-5 * np.max(np.abs(an[k])), k
    assert an["K"][0] < an["K"][600] - 1.0  # gravity lowers K near target 1


def test_robot_joint_under_time_varying_impedance_controller():
    sim = simulate_robot(ExperimentConfig(n_cycles=40, noise=0.05, seed=1, stiffness="dip:20,0.5,0.15"))
    ens = segment(sim.record, onsets_from_events(sim.record))
    err = rel_errors(estimate(ens), sim.truth)
    assert err["I"] < 6 and err["B"] < 6 and err["K"] < 6, err
    assert np.ptp(sim.truth["K"]) > 5  # the dip is in the truth
