"""Ground truth for simulation: which parameters to perturb, and by how much.

Errors in structurally redundant parameters are indistinguishable from errors
in the parameters that absorb them, so a truth meant to be compared
parameter by parameter with a calibration is drawn in the identifiable
parameterization: the set `calibrate` estimates for the same loops, read off
the nominal robot's structure without a fit
(`closedloop.studies.identifiable.identifiable_names`).  Everything else keeps
its nominal value.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.analysis.selection import DEFAULT_IDENTIFY
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.studies.identifiable import identifiable_names
from closedloop.studies.synthetic import self_motion

DEFAULT_MAGNITUDES = {"translation": 2e-3, "rotation": 2e-3, "offset": 0.02, "scale": 0.0}


def draw_truth(
    robot: RobotModel, names: list[str], rng: np.random.Generator, magnitudes: dict[str, float] | None = None
) -> dict[str, float]:
    """True values of `names`: nominal + U(-m, m) with m by kind (scale: 1 + U(-m, m))."""
    mag = {**DEFAULT_MAGNITUDES, **(magnitudes or {})}
    joints = sorted({n.rsplit(".", 1)[0] for n in names}, key=robot.joint_names.index)
    from closedloop.model.parameters import RobotParameters

    rp = RobotParameters(robot, joints)
    out = {}
    for n in names:
        p = rp.params[rp.index[n]]
        if p.kind == "scale":
            m = mag["scale"]
        elif p.kind == "offset":
            m = mag["offset"]
        else:
            m = mag["translation"] if p.unit == "m" else mag["rotation"]
        out[n] = float(p.nominal + rng.uniform(-m, m)) if m > 0 else float(p.nominal)
    return out


def closure_from_pose(loop_name: str, X: pin.SE3) -> dict[str, float]:
    """Weld closure parameters of a pose (translation, rotation vector)."""
    v = np.concatenate([X.translation, pin.log3(X.rotation)])
    return {f"{loop_name}.{f}": float(v[k]) for k, f in enumerate(("x", "y", "z", "rx", "ry", "rz"))}


def _joints(robot: RobotModel, loops: list[Loop]) -> list[str]:
    js: list[str] = []
    for lp in loops:
        for f in (lp.frame_a, lp.frame_b):
            for j in robot.supporting_joints(f):
                if j not in js:
                    js.append(j)
    return sorted(js, key=robot.joint_names.index)


class SyntheticDataset:
    """A pure-kinematic dataset with its ground truth (see `make_dataset`)."""

    def __init__(self, problem, truth: np.ndarray, readings: np.ndarray, noisy: np.ndarray, perturbed: list[str]):
        self.problem = problem
        self.truth = truth  # full parameter vector of `problem`
        self.readings = readings  # exact readings (on the true closure manifold)
        self.noisy = noisy  # readings + noise
        self.perturbed = perturbed

    @property
    def joints(self) -> list[str]:
        return self.problem.joints

    def log(self, noisy: bool = True) -> JointLog:
        return JointLog(list(self.joints), self.noisy if noisy else self.readings)

    def truth_dict(self) -> dict[str, float]:
        return dict(zip(self.problem.names, map(float, self.truth)))


def make_dataset(
    robot: RobotModel,
    loop: Loop,
    theta0: np.ndarray,
    n: int,
    rng: np.random.Generator,
    magnitudes: dict[str, float] | None = None,
    noise: float = 0.0,
    perturb: list[str] | None = None,
    **walk,
) -> SyntheticDataset:
    """Truth = nominal + random errors in the identifiable set (or `perturb`), then n
    configurations along the TRUE loop's self-motion through the model angles theta0.

    The loop's own true parameters are those that close it at theta0 (its
    `initialize` on the true model).  Readings follow the sensor model of
    eq. 4.4 inverted: reading = (theta' - theta_off) / k, plus N(0, noise).
    """
    from closedloop.problem.problem import CalibrationProblem, LoopBlock

    theta0 = np.atleast_2d(np.asarray(theta0, dtype=float))
    names = perturb if perturb is not None else identifiable_names(robot, [loop], theta0, DEFAULT_IDENTIFY[robot.kind])
    tv = draw_truth(robot, names, rng, magnitudes)
    joints = _joints(robot, [loop])
    problem = CalibrationProblem(robot, joints, [LoopBlock(loop, theta0, np.arange(1))])
    truth = problem.nominal
    for name, v in tv.items():
        truth[problem.index[name]] = v
    th0 = (theta0 - truth[problem.rp.offset_index()]) / truth[problem.rp.scale_index()]
    sl = problem.loop_slices[0]
    if sl.stop > sl.start:
        TA, TB = problem.loop_poses(truth, 0, th0)
        init = loop.initialize(TA, TB)
        if init is not None:
            truth[sl] = init
    readings = self_motion(problem, truth, th0, n, rng, **walk)
    noisy = readings + rng.normal(0.0, noise, readings.shape) if noise > 0 else readings.copy()
    return SyntheticDataset(problem, truth, readings, noisy, names)
