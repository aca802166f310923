"""Calibration of the model-error check (`closedloop.impedance.modelcheck`): the equation-residual ratio
of the data to its noise-only twin on truths where eq. 7.9 holds (the independent elbow's five truths,
the thesis forearm, the robot case) and where it does not (the robot's shoulder loop softened so that the
shoulder yields to the elbow's perturbation), with the estimate's error against the truth.

    python benchmarks/bench_model_check.py [--seeds 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from closedloop.impedance.data import onsets_from_events, segment
from closedloop.impedance.estimate import estimate
from closedloop.impedance.metrics import rel_errors
from closedloop.impedance.modelcheck import RATIO_ALARM, model_check


def cases(seed: int):
    from closedloop.impedance.elbow import ElbowConfig, simulate_elbow
    from closedloop.impedance.model import ExperimentConfig
    from closedloop.impedance.mujoco_sim import simulate_robot
    from closedloop.impedance.simulation import simulate

    for name, kw in {
        "constant": {},
        "dip": {"stiffness": "dip"},
        "ramp-b": {"stiffness": "ramp-b"},
        "square": {"stiffness": "square"},
        "voluntary 0.5": {"voluntary_rms": 0.5},
    }.items():
        yield f"elbow, {name}", *simulate_elbow(ElbowConfig(seed=seed, **kw))
    for name, kw in {
        "constant": {},
        "dip": {"stiffness": "dip:20,0.4,0.15"},
        "square": {"stiffness": "square:20,8,0.5"},
        "noise 1 %": {"noise": 0.01},
        "noise 10 %": {"noise": 0.1},
    }.items():
        sim = simulate(ExperimentConfig(seed=seed, **kw), "rk4")
        yield f"forearm, {name}", sim.record, sim.truth
    robot = {"n_cycles": 100, "noise": 0.1, "seed": seed, "stiffness": "square:200,80,0.5"}
    for name, noise, shoulder in (
        ("shoulder 2e5 (shipped)", 0.1, (0.5, 2e5, 500.0)),
        ("shoulder 2e5 (shipped), noise 2 %", 0.02, (0.5, 2e5, 500.0)),
        ("shoulder 2e4", 0.1, (0.5, 2e4, 150.0)),
        ("shoulder 2e4, noise 2 %", 0.02, (0.5, 2e4, 150.0)),
        ("shoulder 5e3", 0.1, (0.5, 5e3, 75.0)),
        ("shoulder 2e3", 0.1, (0.5, 2e3, 50.0)),
    ):
        sim = simulate_robot(ExperimentConfig(**{**robot, "noise": noise}), shoulder)
        yield f"robot K 200/80, {name}", sim.record, sim.truth


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=2)
    a = ap.parse_args()
    t0 = time.perf_counter()
    print(f"| case | seed | estimate | I / B / K error | residual ratio (alarm above {RATIO_ALARM:g}) |")
    print("|---|---|---|---|---|")
    for seed in range(1, a.seeds + 1):
        for name, rec, truth in cases(seed):
            ens = segment(rec, onsets_from_events(rec))
            est = estimate(ens, warn=False)
            chk = model_check(ens, est)
            err = rel_errors(est, truth)
            r = "not made" if chk is None else f"{chk.ratio:.3f}" + (" **alarm**" if chk.fires else "")
            e = " / ".join(f"{err[k]:.2f}" for k in "IBK")
            print(f"| {name} | {seed} | {est.options.method} | {e} % | {r} |", flush=True)
    print(f"\n{time.perf_counter() - t0:.0f} s, load average {np.round(__import__('os').getloadavg(), 1).tolist()}")


if __name__ == "__main__":
    main()
