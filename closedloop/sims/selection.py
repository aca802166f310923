"""Planning the simulator's samples with pose selection (setting ``select``).

With ``select`` set to a method of :func:`closedloop.design.poses.select_poses`
(``greedy``: D-optimal forward selection, ``detmax``: greedy then Mitchell's
exchange, ``greedy-a``: forward selection minimising the covariance trace, or any
method that function accepts), :func:`closedloop.sims.simulate` plans its n
samples in four steps, all on the robot's NOMINAL model (no MuJoCo, no truth):

1. **Pool** (:func:`candidate_pool`): the nominal-loop planner of
   :mod:`closedloop.sims.driver` walks the nominal self-motion from the grasp
   for ``select_pool * n`` waypoints (pure kinematics; open loops: random
   configurations), the candidate configurations.
2. **Information** (:func:`information_result`): the calibration problem of the
   loop the scenario is calibrated with (:meth:`closedloop.sims.loop_types.SimLoop.core_loop`)
   on the pool's exact nominal readings, with the loop's unknowns that close them, and
   the parameters a calibration estimates there with the default selection
   (placement, offset, loop; plus scale when the truth has scale errors): the
   structural reduction and length gauge of :mod:`closedloop.studies.identifiable`, no
   fit (the nominal model closes the nominal loop).  The choice reads their whitened,
   prior-scaled Jacobian.  The joint noise is the setting ``noise`` or, if 0, 1e-6 rad
   (one level on every joint only scales the information and leaves the choice
   unchanged; it matters only against a tracker's own noise, measured loops).
3. **Choice**: ``closedloop.design.poses.select_poses`` on that problem, values, parameters and noise.
4. **Path** (:func:`order_path`, :func:`bridge`): the chosen configurations are
   visited in nearest-neighbour order (joint space, from the grasp); where two
   consecutive ones are more than ``step_rad`` apart (largest joint change), the
   robot is led through intermediate waypoints on the nominal loop (steps
   towards the next configuration, each projected back onto the loop) at which
   it only moves (no relax, no record).

The robot is then driven through the path in MuJoCo exactly as without
selection (position servos, settle, relax, record).  A sample dropped there
(joint limit, not settled) is not replaced: the dataset then has fewer than n
configurations and a warning says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from closedloop.errors import ScenarioError
from closedloop.model.robot import find_frame
from closedloop.sims.driver import NominalLoop, NominalLoopPlanner, RandomConfigurations
from closedloop.sims.loop_types import sim_loop
from closedloop.sims.scenarios import Scenario, SimSettings

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem

__all__ = ["Plan", "Information", "candidate_pool", "information_result", "order_path", "bridge", "plan_selected"]

log = logging.getLogger(__name__)

#: joint noise for the information when the simulation has none [rad]
DEFAULT_NOISE = 1e-6


@dataclass
class Plan:
    """A selected sample plan.

    Attributes:
        waypoints: (m, nq) planning vectors to drive through, in order.
        record: (m,) whether the sample at each waypoint is recorded (False: bridge waypoint).
        info: what is written to ``truth.json`` under ``selection``.
    """

    waypoints: np.ndarray
    record: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def candidate_pool(planner: NominalLoopPlanner | RandomConfigurations, size: int) -> np.ndarray:
    """``size`` consecutive waypoints of the planner (planning vectors), the candidate pool."""
    return np.array([planner.step() for _ in range(size)])


@dataclass
class Information:
    """What the choice reads: the nominal problem on the pool, the values closing it, the estimated
    parameters and the joint noise (`closedloop.design.poses.select_poses` on a bare problem)."""

    problem: CalibrationProblem
    values: np.ndarray
    estimated: list[int]
    noise: float

    @property
    def names(self) -> list[str]:
        """The estimated parameters' names."""
        return [self.problem.names[k] for k in self.estimated]


def information_result(
    sc: Scenario,
    settings: SimSettings,
    nominal_path: Path,
    joint_names: list[str],
    pool: np.ndarray,
    tool_frame_points: np.ndarray | None = None,
) -> Information:
    """The information of the pool's nominal readings (see the module docstring, step 2).

    Args:
        sc: the scenario (its core loop).
        settings: simulation settings (``noise``, ``scale``, ``tracker_noise``).
        nominal_path: the nominal URDF.
        joint_names: arm joints (columns of ``pool``).
        pool: (N, nj) nominal readings of the candidates.
        tool_frame_points: measured loops: (N, 3) nominal tool points, the measurements of a
            tracker at the world origin (the information does not depend on the tracker pose).
    """
    from closedloop.model.robot import RobotModel
    from closedloop.studies.identifiable import (
        DEFAULT_IDENTIFY,
        closing_values,
        estimated_indices,
        loop_joints,
        nominal_problem,
    )

    kind = sim_loop(sc.loop_type)
    loop = kind.core_loop(sc, nominal_path, sigma_t=None if kind.closed else settings.tracker_noise)
    if loop is None:
        raise ScenarioError(f"{sc.name}: the calibration core has no loop for '{sc.loop_type}' (needed by select)")
    noise = settings.noise if settings.noise > 0.0 else DEFAULT_NOISE
    meas = None
    if not kind.closed:  # an open loop: the nominal tool points are its measurements
        if tool_frame_points is None:
            raise ScenarioError(f"{sc.name}: measured loops need the nominal tool points")
        columns = {c: tool_frame_points[:, k] for k, c in enumerate(loop.columns())}
        meas = loop.measurements(columns, np.arange(len(pool)))
    robot = RobotModel.from_file(nominal_path)
    pool = np.asarray(pool, dtype=float)[:, [list(joint_names).index(j) for j in loop_joints(robot, [loop])]]
    problem = nominal_problem(robot, [loop], [pool], [meas])
    x = closing_values(problem)
    identify = DEFAULT_IDENTIFY + (("scale",) if settings.scale > 0.0 else ())
    # every parameter the solve estimates (those the noise swamps included: they are reported, not dropped)
    return Information(problem, x, estimated_indices(problem, x, identify, snr=None), noise)


def order_path(points: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Nearest-neighbour tour through ``points`` from ``start`` (Euclidean joint distance); the visiting order."""
    left = list(range(len(points)))
    order = []
    here = np.asarray(start, dtype=float)
    while left:
        d = np.linalg.norm(points[left] - here, axis=1)
        k = left.pop(int(np.argmin(d)))
        order.append(k)
        here = points[k]
    return np.array(order, dtype=int)


def bridge(loop: NominalLoop | None, a: np.ndarray, b: np.ndarray, step_rad: float) -> list[np.ndarray]:
    """Intermediate waypoints from ``a`` to ``b`` (planning vectors), none if no joint moves more than ``step_rad``.

    Each intermediate is a step of at most ``step_rad`` from the previous one towards
    ``b``, projected onto the nominal loop (``loop.project``) and clipped to the joint
    limits; without a loop (measured loops: the robot moves freely) there are none.
    """
    if loop is None:
        return []
    out: list[np.ndarray] = []
    here = np.asarray(a, dtype=float)
    for _ in range(1000):
        gap = b - here
        m = int(np.ceil(float(np.max(np.abs(gap))) / step_rad)) if gap.size else 0
        if m <= 1:
            break
        nxt = np.clip(loop.project(here + gap / m), loop.lower, loop.upper)
        if float(np.max(np.abs(nxt - here))) < 1e-6:  # no progress (the loop bends away): go straight
            break
        out.append(nxt)
        here = nxt
    return out


def plan_selected(
    sc: Scenario,
    settings: SimSettings,
    nominal_path: Path,
    joint_names: list[str],
    planner: NominalLoopPlanner | RandomConfigurations,
    loop: NominalLoop | None,
    start: np.ndarray,
    n: int,
    model: pin.Model | None = None,
) -> Plan:
    """Steps 1-4 of the module docstring: the path through the n chosen configurations.

    Args:
        sc, settings: the scenario and its settings (``select``, ``select_pool``, ``step_rad``).
        nominal_path, joint_names: the nominal URDF and its arm joints.
        planner: the nominal planner (consumed: it walks the pool).
        loop: the nominal loop the planner walks (None for measured loops).
        start: the robot's planning vector at the grasp.
        n: configurations to choose.
        model: nominal Pinocchio model (measured loops: the nominal tool points).
    """
    from closedloop.design.poses import select_poses

    method = settings.select
    if method is None:
        raise ScenarioError(f"{sc.name}: pose selection needs a method (setting select)")
    nj = len(joint_names)
    size = max(int(settings.select_pool * n), n)
    pool = candidate_pool(planner, size)
    points = None
    if not sim_loop(sc.loop_type).closed:
        if model is None:
            raise ScenarioError(f"{sc.name}: measured loops need the nominal model")
        data = model.createData()
        fid = find_frame(model, sc.tool_frame)
        points = np.empty((size, 3))
        for i, q in enumerate(pool):
            pin.framesForwardKinematics(model, data, q[:nj])
            points[i] = data.oMf[fid].translation
    res = information_result(sc, settings, nominal_path, joint_names, pool[:, :nj], points)
    cols = [joint_names.index(j) for j in res.problem.joints]
    chosen = np.asarray(
        select_poses(res.problem, res.values, pool[:, cols], n, method, params=res.estimated, noise=res.noise),
        dtype=int,
    )
    chosen = chosen[order_path(pool[chosen, :nj], start[:nj])]
    waypoints: list[np.ndarray] = []
    record: list[bool] = []
    here = np.asarray(start, dtype=float)
    for k in chosen:
        for w in bridge(loop, here, pool[k], settings.step_rad):
            waypoints.append(w)
            record.append(False)
        waypoints.append(pool[k])
        record.append(True)
        here = pool[k]
    info = {
        "method": settings.select,
        "pool": size,
        "chosen": int(len(chosen)),
        "bridge_waypoints": int(len(record) - int(np.sum(record))),
        "parameters": res.names,
    }
    log.info(
        "%s: chose %d of %d candidates (%s), %d bridge waypoints",
        sc.name,
        len(chosen),
        size,
        settings.select,
        info["bridge_waypoints"],
    )
    return Plan(np.array(waypoints), np.array(record, dtype=bool), info)
