"""The floor: what Pinocchio and MuJoCo themselves take, on the robots the benchmarks use.

* Pinocchio: `forwardKinematics` + `computeFrameJacobian` (LOCAL) of the tool frame
  over 1,000 random configurations within the joint limits, per robot (the
  kinematics a calibration iteration cannot avoid: one residual and one Jacobian
  per configuration), and `computeFrameJacobian` alone (it runs its own forward
  pass).  A calibration solve is quoted as a ratio to `floor x iterations`.
* MuJoCo: the stepping rate of each simulator scenario's own scene (the scene a
  dataset is simulated in, loaded from its ``scene.xml``), one `mj_step(m, d,
  nstep)` call from its initial, closed-loop state while the servos hold the
  initial command.  A simulation's bound is that rate / steps per configuration.

    python benchmarks/floor.py                   # both, single-threaded and default BLAS, idle
    python benchmarks/floor.py --loaded          # also with both cores kept busy

Functions `pinocchio_floor(robot)` and `mujoco_rate(scene_xml)` are used by the
other benchmark scripts to give their figures as ratios to the floor measured in
the same conditions.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import pinocchio as pin
from machine import add_arguments, condition, conditions, header, threads_mode, timed  # benchmarks/machine.py

TOOL_FRAMES = {"panda": "panda_hand", "ur5": "tool0", "utah_hand": "finger_tip"}


def _model(robot: str) -> tuple[pin.Model, int]:
    from closedloop.assets.catalog import ROBOTS

    model = pin.buildModelFromUrdf(str(ROBOTS[robot].path))
    frame = TOOL_FRAMES.get(robot, "")
    fid = model.getFrameId(frame) if model.existFrame(frame) else model.nframes - 1
    return model, fid


def pinocchio_floor(robot: str, n: int = 1000, repeat: int = 5, fk: bool = True) -> tuple[float, float]:
    """(wall, CPU) seconds for forward kinematics + a LOCAL frame Jacobian at `n` configurations.

    Each the best of `repeat` passes.
    """
    model, fid = _model(robot)
    data = model.createData()
    rng = np.random.default_rng(0)
    lo = np.where(np.isfinite(model.lowerPositionLimit), model.lowerPositionLimit, -np.pi)
    hi = np.where(np.isfinite(model.upperPositionLimit), model.upperPositionLimit, np.pi)
    qs = rng.uniform(lo, hi, (n, model.nq))
    jac, fwd, local = pin.computeFrameJacobian, pin.forwardKinematics, pin.LOCAL

    def run() -> None:
        if fk:
            for q in qs:
                fwd(model, data, q)
                jac(model, data, q, fid, local)
        else:
            for q in qs:
                jac(model, data, q, fid, local)

    runs = [timed(run)[1:] for _ in range(repeat)]
    return min(w for w, _ in runs), min(c for _, c in runs)


def scenario_scene(scenario: str, workdir: Path) -> Path:
    """The scene.xml of a small dataset of `scenario` (cached in `workdir`)."""
    from closedloop.sims import simulate

    out = workdir / scenario
    if not (out / "scene.xml").exists():
        simulate(scenario, 3, 0, out)
    return out / "scene.xml"


def mujoco_rate(scene_xml: Path, nstep: int = 20000, repeat: int = 3) -> tuple[float, float]:
    """MuJoCo's own steps per second on a scene, (wall, CPU): the best of `repeat` calls of `nstep` steps."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(scene_xml))
    walls, cpus = [], []
    for _ in range(repeat):
        d = mujoco.MjData(m)
        if m.nkey:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        mujoco.mj_forward(m, d)
        mujoco.mj_step(m, d, 100)  # settle the warm start
        _, w, c = timed(mujoco.mj_step, m, d, nstep)
        walls.append(w)
        cpus.append(c)
    return nstep / min(walls), nstep / max(min(cpus), 1e-9)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=list(TOOL_FRAMES))
    ap.add_argument("--scenarios", nargs="*", default=None, help="simulator scenarios (default: all)")
    add_arguments(ap)
    args = ap.parse_args()
    from closedloop.sims import SCENARIOS

    scenarios = sorted(SCENARIOS) if args.scenarios is None else args.scenarios
    print(header())
    with tempfile.TemporaryDirectory() as tmp:
        scenes = {s: scenario_scene(s, Path(tmp)) for s in scenarios}
        for cond in conditions(args.loaded):
            for mode in args.threads:
                with condition(cond) as cdesc, threads_mode(mode) as tdesc:
                    print(f"\n[{cdesc}; BLAS threads {tdesc}]")
                    print(
                        f"{'robot':<10} {'FK+Jac 1000 cfg [ms] wall':>26} {'cpu':>7} {'Jac only wall':>14} {'cpu':>7}"
                    )
                    for r in args.robots:
                        (bw, bc), (ow, oc) = pinocchio_floor(r), pinocchio_floor(r, fk=False)
                        print(f"{r:<10} {1e3 * bw:>26.3f} {1e3 * bc:>7.3f} {1e3 * ow:>14.3f} {1e3 * oc:>7.3f}")
                    print(f"{'scenario':<12} {'MuJoCo steps/s wall':>20} {'cpu':>9} {'us/step wall':>13} {'cpu':>6}")
                    for s, xml in scenes.items():
                        rw, rc = mujoco_rate(xml)
                        print(f"{s:<12} {rw:>20,.0f} {rc:>9,.0f} {1e6 / rw:>13.2f} {1e6 / rc:>6.2f}", flush=True)


if __name__ == "__main__":
    main()
