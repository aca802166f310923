"""Which parameters a calibration can tell apart, read off the nominal robot's structure (no fit).

The simulator draws its truth in the identifiable parameterisation: an error in a structurally
redundant parameter cannot be told from an error in the parameters that absorb it, so a truth that
``closedloop check`` compares parameter by parameter perturbs only the parameters a calibration of
the same loop estimates.  That set is decided before any solve, from kinematics alone, and is found
here without the calibrator:

1. exact data of the NOMINAL robot: the loop's self-motion through the grasp configuration
   (`closedloop.studies.synthetic.self_motion`, Lemma 4), random configurations with the tool
   point measured exactly for an open loop (thesis 3.2), or the caller's own readings;
2. the loop's unknowns closing that data (`closing_values`: the loops' own initialisation,
   polished by Gauss-Newton on the loop parameters alone, the robot held nominal);
3. the parameter selection and the motion checks of `closedloop.analysis.selection` (one scale
   factor held when all are free, thesis 4.2.2; joints that never move, Singularity 5);
4. the structural reduction and the length gauge of `closedloop.analysis.identifiability`
   (`analyse_structure`: greedy column reduction of the prior-scaled Jacobian on closure, thesis
   3.2.2; the held length that sets the size, 3.3).

On exact nominal data the nominal robot closes every loop, so the structure at the start is the
structure at the solution a calibration would reach: the kept parameters, less the held length,
are the ones it estimates.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from closedloop.analysis.identifiability import analyse_structure, compress, weak_directions
from closedloop.analysis.observability import whitened_blocks
from closedloop.analysis.selection import check_motion, initial_values, select_parameters
from closedloop.errors import NotIdentifiableError
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel, find_frame
from closedloop.problem.problem import CalibrationProblem, LoopBlock

__all__ = [
    "loop_joints",
    "nominal_problem",
    "closing_values",
    "estimated_indices",
    "swamped_indices",
    "identifiable_names",
    "measured_identifiable_names",
]

#: identify patterns of a default calibration (placement errors, offsets, the loops' unknowns)
DEFAULT_IDENTIFY = ("placement", "offset", "loop")


def loop_joints(robot: RobotModel, loops: Sequence[Loop]) -> list[str]:
    """The movable joints between the loops' frames and the base, in the model's order."""
    js: list[str] = []
    for lp in loops:
        for f in lp.frames:
            for j in robot.supporting_joints(f):
                if j not in js:
                    js.append(j)
    return sorted(js, key=robot.joint_names.index)


def nominal_problem(
    robot: RobotModel,
    loops: Sequence[Loop],
    thetas: Sequence[np.ndarray],
    measurements: Sequence[np.ndarray | None] | None = None,
) -> CalibrationProblem:
    """The calibration problem of `loops` over readings `thetas` (one (N, n_joints) array per loop,
    columns in `loop_joints` order) and each loop's measurements, every loop prepared at the nominal
    robot (`Loop.prepare`: the hinge's chart) as a calibration prepares it."""
    joints = loop_joints(robot, loops)
    meas = list(measurements) if measurements is not None else [None] * len(loops)
    rows, blocks = 1, []
    for lp, th, m in zip(loops, thetas, meas):
        th = np.atleast_2d(np.asarray(th, dtype=float))
        blocks.append(LoopBlock(lp, th, np.arange(rows, rows + th.shape[0]), None, m))
        rows += th.shape[0]
    problem = CalibrationProblem(robot, joints, blocks)
    prepared = [b.loop.prepare(*problem.loop_poses(problem.nominal, bi), b.meas) for bi, b in enumerate(blocks)]
    if all(p is b.loop for p, b in zip(prepared, blocks)):
        return problem
    return CalibrationProblem(
        robot,
        joints,
        [LoopBlock(p, b.theta, b.rows, b.tau, b.meas) for p, b in zip(prepared, blocks)],
    )


def closing_values(problem: CalibrationProblem, iters: int = 20, tol: float = 1e-12) -> np.ndarray:
    """The nominal robot with the loops' unknowns that close the problem's data.

    Starts from the loops' own initialisation (`analysis.selection.initial_values`), then
    Gauss-Newton on the loop parameters alone (least-squares steps on the plain closure residual,
    thesis eq. 3.8), the robot held nominal, until the largest residual is below `tol` or stops
    falling.  The data being exact readings of the nominal robot, the minimum is a closure.
    """
    x = initial_values(problem, {})
    cols = [int(k) for c in problem.loop_columns for k in c]
    if not cols:
        return x
    worst = np.inf
    for _ in range(iters):
        evs = problem.evaluate(x, True, columns=cols)
        r = np.concatenate([ev.r.ravel() for ev in evs])
        now = float(np.abs(r).max()) if r.size else 0.0
        if now < tol or now >= worst:
            break
        worst = now
        stacked = []
        for ev in evs:
            assert ev.J is not None  # evaluated with the Jacobian
            stacked.append(ev.J.reshape(-1, len(cols)))
        J = np.vstack(stacked)
        x[cols] -= np.linalg.lstsq(J, r, rcond=None)[0]
    return x


def estimated_indices(
    problem: CalibrationProblem,
    x: np.ndarray,
    identify: Sequence[str] = DEFAULT_IDENTIFY,
    snr: float | None = 1.0,
) -> list[int]:
    """Indices of the parameters a calibration of `problem` estimates when `x` closes its data.

    The selection (`identify` patterns, nothing fixed), the motion checks, then the structural
    reduction at `x` with its held length left out (module docstring, steps 3-4), less what the
    loops' measurement noise swamps (`swamped_indices`; ``snr=None``: kept, as the solver keeps them).
    """
    status = select_parameters(problem, list(identify), {}, x.copy())
    check_motion(problem, x, status)
    free = [k for k, s in enumerate(status) if s == "selected"]
    if not free:
        raise NotIdentifiableError("no parameter is left to identify (all fixed or not selected)")
    structure = analyse_structure(problem, x, free)
    if structure.provisional:
        raise NotIdentifiableError(
            "the nominal data do not close the loops: the structure of the problem cannot be read there"
        )
    kept = [k for k in structure.kept if k != structure.gauge]
    weak = swamped_indices(problem, x, kept, snr) if snr is not None else set()
    return [k for k in kept if k not in weak]


def swamped_indices(problem: CalibrationProblem, x: np.ndarray, kept: list[int], snr: float = 1.0) -> set[int]:
    """The parameters of the directions a loop's measurement noise swamps on this data (thesis 4.2.6).

    Only loops that measure (a camera's pixels, a tracker with its noise) have a noise level in
    exact data: their declared measurement covariance.  The Jacobian of the `kept` parameters,
    whitened by it (no joint noise: exact readings) and scaled by the parameters' priors, has
    singular values in units of "determined as well as the prior"; the directions below `snr`
    (Singularity 2, insufficient excitation) are reported unidentifiable by a calibration, and
    their main parameters (`analysis.identifiability.weak_directions`) are returned.  A pure
    closure (no measurement noise) has none.
    """
    if not kept or all(nz.measurement_cov is None for nz in problem.noise):
        return set()
    blocks = whitened_blocks(problem, x, kept, np.zeros(len(problem.joints)), "noise")
    J = compress(np.vstack([Jb.reshape(-1, len(kept)) for _, Jb in blocks]))
    _, S, Vt = np.linalg.svd(J, full_matrices=False)
    threshold = max(1e-10 * (S[0] if S.size else 0.0), snr)
    names = [problem.names[k] for k in kept]
    return {problem.index[n] for c in weak_directions(S, Vt, threshold, names) for n, _ in c.terms}


def _robot_names(problem: CalibrationProblem, indices: list[int]) -> list[str]:
    own = tuple(f"{b.loop.name}." for b in problem.blocks)
    return [problem.names[k] for k in indices if not problem.names[k].startswith(own)]


def identifiable_names(
    robot: RobotModel,
    loops: Sequence[Loop],
    theta0: np.ndarray,
    identify: Sequence[str] = DEFAULT_IDENTIFY,
    n: int = 30,
    seed: int = 0,
) -> list[str]:
    """The robot parameters a calibration of the closed `loops` estimates, on the nominal robot's
    self-motion through the model angles `theta0` (n configurations per loop, random walk `seed`)."""
    problem = nominal_problem(robot, loops, nominal_walks(robot, loops, theta0, n, seed))
    return _robot_names(problem, estimated_indices(problem, closing_values(problem), identify))


def nominal_walks(
    robot: RobotModel, loops: Sequence[Loop], theta0: np.ndarray, n: int = 30, seed: int = 0
) -> list[np.ndarray]:
    """Readings (n, joints) per loop along the nominal robot's self-motion through the model angles `theta0`
    (random walk `seed`), each loop's own values initialised at `theta0`."""
    from closedloop.studies.synthetic import self_motion

    theta0 = np.atleast_2d(np.asarray(theta0, dtype=float))
    start = nominal_problem(robot, loops, [theta0] * len(loops))
    x = start.nominal
    for bi, sl in enumerate(start.loop_slices):
        if sl.stop > sl.start:
            x[sl] = start.initialize_loop(x, bi)
    rng = np.random.default_rng(seed)
    return [self_motion(start, x, theta0, n, rng, block=bi) for bi in range(len(loops))]


def tool_points(robot: RobotModel, frame: str, q: np.ndarray) -> np.ndarray:
    """(N, 3) positions in the base of frame `frame` at the configurations `q` (N, nq): forward kinematics."""
    model = robot.model
    data = model.createData()
    fid = find_frame(model, frame)
    out = np.empty((len(q), 3))
    for i, qi in enumerate(q):
        pin.framesForwardKinematics(model, data, qi)
        out[i] = data.oMf[fid].translation
    return out


def measured_identifiable_names(
    robot: RobotModel,
    loop: Loop,
    identify: Sequence[str] = DEFAULT_IDENTIFY,
    n: int = 40,
    seed: int = 0,
) -> list[str]:
    """The robot parameters a calibration of the measured (open) `loop` estimates.

    An open loop has no self-motion (every configuration is allowed): `n` random configurations
    within the nominal joint limits (random stream `seed`), the nominal tool point measured exactly
    by a tracker at the base (identity pose).
    """
    model = robot.model
    rng = np.random.default_rng(seed)
    lo = np.maximum(model.lowerPositionLimit, -np.pi)
    hi = np.minimum(model.upperPositionLimit, np.pi)
    q = rng.uniform(lo, hi, size=(n, model.nq))
    joints = loop_joints(robot, [loop])
    theta = q[:, [robot.joint_names.index(j) for j in joints]]
    points = tool_points(robot, loop.frame_a, q)
    meas = loop.measurements({c: points[:, k] for k, c in enumerate(loop.columns())}, np.arange(n))
    problem = nominal_problem(robot, [loop], [theta], [meas])
    return _robot_names(problem, estimated_indices(problem, closing_values(problem), identify))
