"""The length gauge: which length sets the overall size when the loops cannot (thesis 3.3).

Closed loops close at any overall size: scaling every length by (1 + eps)
leaves every closure intact (the loop equations are homogeneous in the
lengths), so one length must be held.  Which one matters.  A length that
other parameters absorb (``joint5.z`` moved along its own axis is the same
robot as ``joint6.y`` moved back) does not set the size when held: the size
escapes through the redundancy.  The gauge is therefore chosen by what the
robot *does*, not by the parameter vector:

* `scale_content(v)`: the size change per unit step along a parameter
  direction v.  The open-chain forward kinematics of the loops' frames at
  random configurations is differentiated along v and fitted by
  dp_i = c p_i + w x p_i + t + R_i d   (a scaling c, a rigid motion of the
  base (w, t), a shift d of each frame in its own axes).  Re-parameterizations
  leave the kinematics unchanged (c = 0); moving the base or a tool is rigid
  (c = 0); a uniform scaling gives c = eps.
* `choose_gauge`: the null directions of the loop Jacobian (one per
  parameter the reduction drops) are tested for scale content.  None: the
  data (or a length the user fixed) set the size.  Otherwise each free length
  g, longest first, is put last in the reduction order; it is the gauge when
  it is then dropped with a null direction whose scale content is exactly
  its own (fixing g longer by eps * g scales the robot by 1 + eps) and no
  other dropped parameter carries any.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
import pinocchio as pin

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem

N_CONFIGS = 32  # x 6 rows per loop frame: far more rows than the 7 + 6F rigid unknowns
HELD_ERROR = 2e-3  # m: an error of a nominal length a model file may carry (a drawing against the part)
# At a solution (`sets_scale`), the held length's null direction counts as a uniform scaling when what is left
# of its kinematic change besides the scaling and the rigid motions is under this share of it
# (`scale_content`'s second value).  At a nominal geometry (axes parallel or square, frames on them) the share
# is round-off (1e-14..1e-11), and `choose_gauge` reads the gauge there.  At a solution the joint frames carry
# the corrections: a length held beside the gauge then stands for a few millimetres (a UR5's elbow_joint.x, 0
# nominally, 5.1 mm calibrated), which does not scale with the robot, and the change is a scaling up to
# 9e-3 (a calibrated UR5 with a point contact; a camera head 6e-3).  A direction that is no scaling leaves
# 0.29 or more (a Panda weld, a UR5 socket).
PURE_SCALING = 0.05


def random_configurations(problem: CalibrationProblem, n: int = N_CONFIGS, seed: int = 0) -> np.ndarray:
    """n configurations of the full model with the problem's joints drawn within their ranges."""
    rng = np.random.default_rng(seed)
    angles = np.empty((n, len(problem.joints)))
    for j, name in enumerate(problem.joints):
        info = problem.robot.joint(name)
        lo, hi = max(info.lower, -np.pi), min(info.upper, np.pi)
        if not hi > lo:
            lo, hi = -np.pi, np.pi
        angles[:, j] = rng.uniform(lo, hi, n)
    return problem.robot.configurations(angles, problem.joints)


def kinematic_changes(
    problem: CalibrationProblem, x: np.ndarray, V: np.ndarray, q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pose changes of the loops' robot frames per unit step along each column of V, and the regressor.

    Returns dP (rows, k): the first-order changes of the open-chain positions
    and orientations (world rotation vectors) at configurations q, and A
    (rows, 7 + 6F): the motions every robot can make without changing shape,
    scaling first: positions [p | w x p | t | R_f d_f | 0], orientations
    [0 | w | 0 | 0 | R_f e_f] (module docstring; e_f turns frame f in place).
    Analytic: a step dx of the geometric parameters moves frame f by the LOCAL
    twist (K_f G + G_f) dx (`parameters` module docstring: Pinocchio's frame
    kinematic regressor K_f and the placements' generators G), which is
    (R_f v, R_f w) in the world.  The sensor parameters do not move a frame at
    given joint positions q.
    """
    frames = sorted({problem.robot.frame_id(f) for b in problem.blocks for f in b.loop.frames} - {0})
    if not frames:
        return np.zeros((0, V.shape[1])), np.zeros((0, 7))
    state = problem.rp.apply(x[: problem.n_robot])
    model, data = state.model, state.data
    n, F = q.shape[0], len(frames)
    P0 = np.empty((n, F, 3))
    R0 = np.empty((n, F, 3, 3))
    K = np.empty((n, F, 6, state.G.shape[0]))
    for i, qi in enumerate(q):
        pin.forwardKinematics(model, data, qi)
        for k, f in enumerate(frames):
            M = pin.updateFramePlacement(model, data, f)
            P0[i, k], R0[i, k] = M.translation, M.rotation
            K[i, k] = pin.computeFrameKinematicRegressor(model, data, f, pin.LOCAL)
    Vr = V[: problem.n_robot]
    twist = K @ (state.G @ Vr)  # (n, F, 6, k): each frame's LOCAL twist per column of V
    for k, f in enumerate(frames):
        if f in state.G_frames:
            twist[:, k] += state.G_frames[f] @ Vr
    dP = np.stack([R0 @ twist[:, :, :3], R0 @ twist[:, :, 3:]], axis=2)  # (n, F, 2, 3, k) in the world
    A = np.zeros((n, F, 2, 3, 7 + 6 * F))
    A[:, :, 0, :, 0] = P0
    A[..., 0, 0, 2], A[..., 0, 0, 3] = P0[..., 2], -P0[..., 1]  # w x p
    A[..., 0, 1, 1], A[..., 0, 1, 3] = -P0[..., 2], P0[..., 0]
    A[..., 0, 2, 1], A[..., 0, 2, 2] = P0[..., 1], -P0[..., 0]
    A[:, :, 0, :, 4:7] = np.eye(3)
    A[:, :, 1, :, 1:4] = np.eye(3)
    for k in range(F):
        A[:, k, 0, :, 7 + 6 * k : 10 + 6 * k] = R0[:, k]
        A[:, k, 1, :, 10 + 6 * k : 13 + 6 * k] = R0[:, k]
    return dP.reshape(-1, V.shape[1]), A.reshape(-1, 7 + 6 * F)


def scale_content(dP: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scaling c of each column of dP (fitted with the rigid motions), and how far it is from a pure scaling.

    The second value is |dP - c p| / |c p|: 0 for a uniform scaling (up to
    the rigid motions), large for a change that is mostly not one (a rigid
    motion, a re-parameterization, a change of shape).
    """
    sol, *_ = np.linalg.lstsq(A, dP, rcond=None)
    scaled = np.abs(sol[0]) * np.linalg.norm(A[:, 0])
    return sol[0], np.linalg.norm(A @ sol - dP, axis=0) / np.maximum(scaled, 1e-300)


def size_per_parameter(problem: CalibrationProblem, x: np.ndarray, est: list[int]) -> np.ndarray:
    """c (len(est)): the robot's relative size change per unit of each estimated parameter at x, 0 for loop
    parameters: the uniform scaling content (`scale_content`) of a prior-sized step of each robot parameter in
    the open-chain kinematics of the loops' frames at random configurations, divided by the step."""
    robot = [i for i, k in enumerate(est) if k < problem.n_robot]
    c = np.zeros(len(est))
    if not robot:
        return c
    prior = np.array([problem.params[est[i]].prior for i in robot])
    V = np.zeros((len(problem.params), len(robot)))
    V[[est[i] for i in robot], np.arange(len(robot))] = prior
    c_scaled, _ = scale_content(*kinematic_changes(problem, x, V, random_configurations(problem, 48)))
    c[robot] = c_scaled / prior
    return c


def contains_scaling(dP: np.ndarray, A: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether some combination of the columns of dP is a uniform scaling (up to rigid motions)."""
    if dP.shape[1] == 0 or A.shape[0] == 0:
        return False
    M = np.column_stack([dP, -A[:, 1:]])
    z, *_ = np.linalg.lstsq(M, A[:, 0], rcond=None)
    return bool(np.linalg.norm(M @ z - A[:, 0]) <= tol * np.linalg.norm(A[:, 0]))


def null_directions(R: np.ndarray, kept: list[int], dropped: list[int]) -> np.ndarray:
    """One null vector per dropped column: e_d - (least-squares fit of column d by the kept columns)."""
    V = np.zeros((R.shape[1], len(dropped)))
    V[dropped, np.arange(len(dropped))] = 1.0
    if kept and dropped:
        coef, *_ = np.linalg.lstsq(R[:, kept], R[:, dropped], rcond=None)  # every dropped column at once
        V[np.ix_(np.asarray(kept, dtype=int), np.arange(len(dropped)))] = -coef
    return V


def choose_gauge(
    problem: CalibrationProblem,
    x: np.ndarray,
    free: list[int],
    R: np.ndarray,
    reduce: Callable[[list[int]], tuple[list[int], list]],
    order: list[int],
    prefer: int | None = None,
) -> tuple[int | None, list[int], list, bool, float]:
    """The gauge (a column of R, or None), the kept columns and drops with it, whether the size is free,
    and the length L the gauge stands for (`short_gauge_warning` says when it is too short to trust).

    R: the compressed, prior-scaled loop Jacobian over `free`; `reduce(order)`
    the greedy reduction in that order, returning (kept columns, Dropped
    list).  The reduction runs with the longest nominal robot length last
    (`prefer` instead, if given): the thesis holds one link length (3.3).
    Each dropped parameter's null direction is then mapped to a kinematic
    change; one that is a pure uniform scaling (`scale_content`) holds the
    size, with the length L = d value / (size change) it stands for.  The
    gauge named is the longest such (no longer than the robot).
    """
    params = problem.params
    prior = np.array([params[k].prior for k in free])
    names = [problem.names[k] for k in free]
    lengths = [i for i in range(len(free)) if params[free[i]].kind != "loop" and params[free[i]].unit == "m"]
    g0 = prefer if prefer in lengths else max(lengths, key=lambda i: abs(length_of(problem, x, free[i])), default=None)
    q = random_configurations(problem)
    reach = robot_reach(problem, x)
    first: tuple[list[int], list] | None = None  # the first order's reduction
    orders = [order] if g0 is None else [[i for i in order if i != g0] + [g0], order]
    for attempt in orders:  # the longest length last (the thesis's choice), else the plain priority order
        kept, dropped = reduce(attempt)
        if not dropped:
            return None, kept, dropped, False, 0.0
        cols = [names.index(d.name) for d in dropped]
        V = np.zeros((len(params), len(cols)))
        V[free] = null_directions(R, kept, cols) * prior[:, None]  # scaled -> parameter units
        dP, A = kinematic_changes(problem, x, V, q)
        if not contains_scaling(dP, A):
            return None, kept, dropped, False, 0.0
        first = first or (kept, dropped)
        c, res = scale_content(dP, A)
        length = prior[cols] / np.maximum(np.abs(c), 1e-300)
        scaling = [j for j in range(len(cols)) if res[j] < 1e-3 and cols[j] in lengths and 0.01 <= length[j] <= reach]
        if scaling:
            best = max(scaling, key=lambda j: (round(float(length[j]), 4), -cols[j]))  # equal lengths: the first
            found = (cols[best], kept, dropped, float(length[best]))
            break
    else:
        found = None
    if found is None or found[3] < 0.1:  # a short or no held length: try each long one last in turn
        for g in sorted(lengths, key=lambda i: -abs(length_of(problem, x, free[i])))[:8]:
            kept_g, dropped_g = reduce([i for i in order if i != g] + [g])
            if names[g] not in [d.name for d in dropped_g]:
                continue
            Vg = np.zeros((len(params), 1))
            Vg[free] = null_directions(R, kept_g, [g]) * prior[:, None]
            c, res = scale_content(*kinematic_changes(problem, x, Vg, q))
            L = float(prior[g] / max(abs(c[0]), 1e-300))
            # longer by more than round-off (equal lengths: the first, whatever the last digits say)
            if res[0] < 1e-3 and 0.01 <= L <= reach and (found is None or L > found[3] * (1.0 + 1e-9)):
                found = (g, kept_g, dropped_g, L)
    if found is None:
        assert first is not None  # `orders` is never empty: its first reduction got this far
        return None, first[0], first[1], True, 0.0
    g, kept, dropped, L = found
    return g, kept, [d for d in dropped if d.name != names[g]], True, L


def short_gauge_warning(name: str, length: float, scale_suspect: float) -> str | None:
    """The warning that the size is held by a short length, or None: a HELD_ERROR in the nominal value of the
    gauge `name`, which stands for `length` (m), changes the size by more than `scale_suspect` (the size change
    that makes a result suspect, `VerdictRules.scale_suspect`: a held length under 67 mm by default)."""
    if length <= 0.0 or HELD_ERROR / length <= scale_suspect:
        return None
    return (
        f"the overall size is held by {name}, which stands for a length of only {length * 1e3:.3g} mm: an "
        f"error of {HELD_ERROR * 1e3:g} mm in its nominal value changes the identified size by {HELD_ERROR / length:.1%}"
    )


def robot_reach(problem: CalibrationProblem, x: np.ndarray) -> float:
    """The sum of the joint-origin distances along the loops' chains: no link is longer."""
    model = problem.rp.apply(x[: problem.n_robot]).model
    return float(sum(np.linalg.norm(model.jointPlacements[j].translation) for j in range(1, model.njoints)))


def length_of(problem: CalibrationProblem, x: np.ndarray, k: int) -> float:
    """The length a parameter stands for at x (its change per unit relative scaling), 0 for angles."""
    p = problem.params[k]
    if p.unit != "m" or p.kind == "loop":
        return 0.0
    if p.kind == "placement":  # t_local + p (the joint origin in its own frame, moved by p)
        return p.scales_with_length + float(x[k])
    return float(x[k])  # D-H s, a


def sets_scale(
    problem: CalibrationProblem, x: np.ndarray, free: list[int], R: np.ndarray, kept: list[int], g: int
) -> bool:
    """Whether the one null direction of R (over `free`) on columns kept + [g] is g's own uniform scaling (up to
    `PURE_SCALING`: at a solution the lengths held beside g do not scale with it)."""
    cols = kept + [g]
    _, S, Vt = np.linalg.svd(R[:, cols])
    if S.size < len(cols) or S[-1] > 1e-10 * S[0] or (len(S) > 1 and S[-2] <= 1e-10 * S[0]):
        return False
    prior = np.array([problem.params[k].prior for k in free])
    v = np.zeros(len(problem.params))
    v[[free[c] for c in cols]] = Vt[-1] * prior[cols]
    c, res = scale_content(*kinematic_changes(problem, x, v[:, None], random_configurations(problem)))
    return bool(res[0] < PURE_SCALING)
