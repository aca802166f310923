"""Predicted accuracy over the workspace: how far the calibrated robot's frames are from the true robot's.

A calibration's closure on its own rows says how well the loops close; a user wants how accurate the
robot is where it works.  This module answers the second question to first order, from what the fit
knows: the parameters' covariance and what the data could not see.

**Propagation.**  At a joint reading theta_i, a followed frame (a loop's tool point, or its frame for a
pose loop) moves by e_i = J_i dx for a parameter error dx, J_i = d(position, rotation)/dx of the
calibrated model at theta_i (thesis eqs. 4.11-4.14 evaluated at a configuration of the workspace, not
of the log; here by forward differences of the Pinocchio kinematics through the sensor model of
eq. 4.4).  The error of the calibrated parameters is modelled as dx = L z, z ~ N(0, I), with

    L L^T = Sigma_est  +  Sigma_unseen,

* Sigma_est: the covariance of the estimated parameters the report trusts (the noise model's,
  s^2 (J^T J)^-1 truncated as in eq. 4.17, or the sandwich where the residual is not the assumed
  noise);
* Sigma_unseen: what the data cannot see.  A parameter error the loop residual does not change is
  not corrected by the fit, whatever the data; it stays in the calibrated model at the size the nominal
  model had it.  With C the data Jacobian over the parameters the fit considered (estimated, dropped,
  unidentifiable), each column scaled by its prior scale p_k, and V_u the right singular vectors of its
  u smallest singular values (u = the dropped parameters plus the undetermined combinations, the
  directions the fit did not estimate; on a log of more than `UNSEEN_SAMPLE` configurations per loop, C
  of an evenly spaced sample of that many: which directions are least seen is the geometry's, not the row
  count's), the nominal model's tolerance T = diag(t_k)
  (`PriorTolerance`) projected on them gives  Sigma_unseen = P V_u V_u^T P^-1 T^2 P^-1 V_u V_u^T P,
  P = diag(p_k).  A weld with a 1-DOF self-motion sees the arm along its motion only: parameters
  redundant there are dropped, and over the joint ranges they move the tool; a structural redundancy
  (a joint offset and the rotation about its axis) moves nothing once the gauge below is removed.
  What the data cannot see the fit cannot have corrected: where the solution has moved the robot's
  parameters along those directions anyway (a weak direction followed before the truncation of eq. 4.17
  set it aside, on noise), that move d_u = P V_u V_u^T P^-1 (x - x_0) is an error of its own, independent
  of the nominal's: Sigma_unseen + d_u d_u^T.

**Gauge.**  What no loop can see is not an error of the robot: a rigid transform of the base (one for
the loops closed to the world, one per loop between two robot frames, in its second frame), a constant
tool transform per pose loop, and the overall size where the data do not measure it (thesis 3.3).  With
G the stacked derivatives of the frames' errors along these freedoms over the workspace, and W the
weights 1/tol_m, 1/tol_rad of `closedloop check`, the predicted error is the part of W e that G cannot
explain: e_perp = W^-1 (I - W G (W G)^+) W J L z, the first-order image of check's fit of the same
freedoms, so that prediction and check's observation are comparable.

**Figures.**  Per frame and configuration, the expected squared position error is the trace of the
3x3 position block of e_perp's covariance, sigma_i^2 = ||E_i||_F^2 (E_i the rows of configuration i).
RMS over the workspace: sqrt(mean sigma_i^2); 95th percentile: of sigma_i; max: the expected largest
error over the configurations, E[max_i |e_i|], by Monte Carlo over z (the errors of one calibrated robot
are correlated across configurations: its largest is one draw's maximum, which `check` observes).  The
same in rad for a pose loop's rotation.  The worst configuration is the reading with the largest
sigma_i.

**Model error.**  Joint noise alone leaves the errors-in-variables estimate (eq. 3.17 weighting) and the
plain loop-closure estimate (eq. 3.8) within their noise of each other; a residual the kinematics cannot
explain (a loop's compliance, a contact's deformation, gearing) biases them differently, and the weighting
amplifies it where joint noise barely acts (a residual direction J_theta Sigma J_theta^T hardly produces).
The plain fit is linearized at the calibration (`estimate.model_error.plain_linearization`): its
Gauss-Newton step from there is their difference d = x_plain - x_fit to first order (where the step lowers
the plain closure by at least half the decrease it predicts: else the plain fit is not linear over it and
nothing is judged), and moves the frames by e_d = J d (gauge removed, weighted by W).  Under the noise model d has the covariance
Sigma_d = Sigma_plain - Sigma_fit (Hausman's: the weighted estimator is the efficient one), so
E|e_d|^2 = tr(M), M = W J Sigma_d J^T W, a weighted chi-square of (tr M)^2 / tr(M^2) effective degrees of
freedom nu.  Where R = |e_d|^2 / tr(M) exceeds 1 + 3 sqrt(2 / nu), the share of d beyond the noise,
b = sqrt(1 - 1 / R) d, is taken as a systematic error of the calibrated parameters: it moves the frames by
e_b = J b (gauge removed), a fixed offset beside the random L z.  Its size, not its sign, is what the
disagreement measures.
**The size.**  Where the data do not measure the overall size, `closedloop check` removes it before
comparing the frames and compares it on a row of its own; the prediction does the same.  The size the
gauge fit above assigns to the errors e (its coefficient of the size column of G, c_s = row of
(W G)^+ W e) has a variance from L like the frames'; and the length held to set the size (thesis 3.3) is
held at its nominal value, whose error t over the length L_g it stands for moves the size by t / L_g
whatever the data (t = `closedloop.analysis.gauge.HELD_ERROR`, 2 mm, the error a model file's nominal
length may carry, the figure the short-gauge warning quotes; the nominal lengths' tolerance where one
above it is given, ``--prior-tolerance length=...``).  Their sum, sigma_s^2 = |c_s(L)|^2 +
(t / L_g)^2, is the predicted relative size error (`WorkspaceAccuracy.size_std`); the expected |error|
sigma_s sqrt(2 / pi) is the figure beside check's observed one, 1.96 sigma_s its 95 % bound.

**Against the nominal model.**  The nominal model's own expected error is the tolerance of every
parameter considered, T, propagated the same way (L = T): where the calibrated model's RMS is not below
it, calibrating did not make the robot better in expectation (`better_than_nominal`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from closedloop.analysis.gauge import HELD_ERROR
from closedloop.errors import InputError
from closedloop.estimate.qr import scaled_r_factor_of_blocks
from closedloop.problem.problem import even_sample
from closedloop.records import ParamStatus

#: loop types whose tool point is followed, and those whose frame pose is (`closedloop check` alike)
POINT_LOOPS = ("PointLoop", "PlaneLoop", "MeasuredPointLoop", "point", "plane", "measured_point")
MEASURED_POINT = ("MeasuredPointLoop", "measured_point")  # a point measured in a tracker's frame
PLANE = ("PlaneLoop", "plane")
HINGE = ("HingeLoop", "hinge")
POSE_LOOPS = ("WeldLoop", "HingeLoop", "MeasuredPoseLoop", "weld", "hinge", "measured_pose")
#: loops that close at any overall size: with only these the size is not measured
SIZE_BLIND = ("PointLoop", "PlaneLoop", "FaceLoop", "WeldLoop", "HingeLoop", "point", "plane", "face", "weld", "hinge")
N_WORKSPACE = 200  # configurations the workspace is sampled at (as many as `closedloop check` compares)
TOL_M, TOL_RAD = 1e-3, 5e-3  # check's default tolerances: the weights of position and rotation in the gauge fit
MAX_DRAWS = 400  # Monte Carlo draws of the expected largest error
FD_STEP = 1e-7  # forward-difference step of the frame Jacobians (m, rad or 1): relative error ~1e-7


@dataclass(frozen=True)
class PriorTolerance:
    """The nominal model's own uncertainty (one standard deviation per parameter), the prior of what the
    data cannot see: a maker's tolerance on link lengths and angles, and on the encoders' zero.

    Attributes:
        length_m: a placement's translation, a D-H length, a tool point's coordinate (m).
        angle_rad: a placement's rotation, a D-H angle (rad).
        offset_rad: a joint's zero (rad; a prismatic joint's zero takes `length_m`).
        scale: a joint's gear ratio error, relative.
    """

    length_m: float = 1e-3
    angle_rad: float = 1e-3
    offset_rad: float = 0.01
    scale: float = 1e-3

    def of(self, kind: str, unit: str) -> float:
        """The tolerance of a parameter of `kind` and `unit` (0: compliances and multipliers, not geometry)."""
        if kind == "offset":
            return self.offset_rad if unit == "rad" else self.length_m
        if kind in ("scale", "mimic"):
            return self.scale if kind == "scale" else 0.0
        if unit == "m":
            return self.length_m
        if unit == "rad":
            return self.angle_rad
        return 0.0


@dataclass(frozen=True)
class FrameAccuracy:
    """The predicted error of one followed frame over the workspace (m, rad; None where not a pose)."""

    loop: str
    frame: str
    kind: str  # 'point' (its tool point's position) or 'pose' (its frame's position and rotation)
    rms_m: float
    p95_m: float
    max_m: float
    rms_rad: float | None
    p95_rad: float | None
    max_rad: float | None
    max95_m: float  # 95 % of calibrated robots have their largest position error below this (m)
    max95_rad: float | None
    #: the chance that one calibrated robot's largest position error lies within 0.5-2 times max_m (over the
    #: Monte Carlo draws): how closely a single calibration can be expected to follow the prediction
    max_within_2x: float
    unseen_rms_m: float  # the share of rms_m from what the data cannot see (the prior)
    unseen_rms_rad: float | None
    nominal_rms_m: float  # the nominal model's expected error: its tolerance over the same parameters, same gauge
    nominal_rms_rad: float | None
    model_rms_m: float  # the share of rms_m from the model error (`ModelError`; 0 where none is found)
    model_rms_rad: float | None
    worst: dict[str, float]  # the joint readings of the configuration with the largest expected error
    sigma_m: np.ndarray = field(repr=False)  # (n,) expected position error per configuration
    sigma_rad: np.ndarray | None = field(repr=False, default=None)
    reach: np.ndarray | None = field(repr=False, default=None)  # (n,) distance of the point from the base (m)
    # the same at the calibration's readings (an even sample of `UNSEEN_SAMPLE` of them on a long log)
    training_reach: np.ndarray | None = field(repr=False, default=None)


@dataclass(frozen=True)
class Disagreement:
    """The plain loop-closure estimate against the errors-in-variables calibration (`disagreement`)."""

    shift: np.ndarray = field(repr=False)  # (P,) x_plain - x_fit over the problem's parameters (0: not estimated)
    estimated: tuple[int, ...]  # the columns both estimated
    noise_cov: np.ndarray = field(repr=False)  # Sigma_plain - Sigma_fit over `estimated`: the shift's covariance
    # under the noise model


@dataclass(frozen=True)
class ModelError:
    """The estimators' disagreement over the workspace, judged against the noise (module docstring)."""

    ratio: float  # R = |e_d|^2 / E|e_d|^2 under the noise model (weighted as check weighs)
    dof: float  # the effective degrees of freedom of |e_d|^2 under the noise model
    limit: float  # 1 + 3 sqrt(2 / dof): above it the disagreement is more than the noise
    share: float  # sqrt(1 - 1 / R) above the limit, else 0

    @property
    def found(self) -> bool:
        return self.share > 0.0


@dataclass(frozen=True)
class WorkspaceAccuracy:
    """The predicted accuracy of every followed frame over a set of joint readings (module docstring)."""

    frames: tuple[FrameAccuracy, ...]
    joints: tuple[str, ...]
    readings: np.ndarray = field(repr=False)  # (n, joints) the workspace's joint readings
    source: str  # where the readings come from: 'random within the joint ranges', a log, a box
    error_bars: str  # the covariance propagated (`NoiseRecord.error_bars`): the noise model's or the sandwich
    prior: PriorTolerance
    size_removed: bool  # the overall size removed as the data do not measure it
    training: np.ndarray | None = field(repr=False, default=None)  # (m, joints) the calibration's readings
    default_readings: bool = False  # the readings are `random_readings`' default: those `closedloop check` uses
    parameters: tuple[str, ...] = ()  # the parameters whose uncertainty moves a followed frame
    #: the loops' other unknowns the calibration considered, which move no followed frame (a plane's normal
    #: and distance, a socket's position): known only as well as the data fix them, and correlated with
    #: `parameters`, so that new rows of a loop resolve them too (`closedloop.design.next_poses`)
    loop_parameters: tuple[str, ...] = ()
    #: L L^T (estimated and unseen) over `parameters` then `loop_parameters`, cross terms included
    full_covariance: np.ndarray | None = field(repr=False, default=None)
    #: (len(parameters),) the systematic error b the model error adds (zeros where none is found): data
    #: reduce L L^T, never b
    bias: np.ndarray | None = field(repr=False, default=None)
    #: (3 n per frame, len(parameters)) the frames' position errors per parameter over the readings, gauge
    #: removed (e_perp = design @ dx): what a design of new configurations is judged by (`closedloop.design`)
    design: np.ndarray | None = field(repr=False, default=None)
    model_error: ModelError | None = None  # the estimators' disagreement, where it was tested

    @property
    def covariance(self) -> np.ndarray | None:
        """L L^T over `parameters` (estimated and unseen): the block of `full_covariance` of what moves a frame."""
        if self.full_covariance is None:
            return None
        m = len(self.parameters)
        return self.full_covariance[:m, :m]

    @property
    def error_covariance(self) -> np.ndarray | None:
        """The parameters' mean-square error L L^T + b b^T: what `closedloop evaluate` propagates."""
        if self.covariance is None:
            return None
        return self.covariance if self.bias is None else self.covariance + np.outer(self.bias, self.bias)

    #: the predicted relative error of the overall size, one standard deviation, where the data do not measure
    #: it (module docstring, "The size"): from the fit's uncertainty and from the held length's tolerance
    size_std: float | None = None
    size_held_std: float | None = None  # the held length's share: its possible error over the length it stands for

    @property
    def size_predicted(self) -> float | None:
        """The expected |relative size error| (what `closedloop check` observes on its size row), or None."""
        return None if self.size_std is None else float(self.size_std * np.sqrt(2.0 / np.pi))

    @property
    def max_m(self) -> float:
        """The largest expected position error over the frames (m)."""
        return max((f.max_m for f in self.frames), default=0.0)

    @property
    def max_rad(self) -> float | None:
        vals = [f.max_rad for f in self.frames if f.max_rad is not None]
        return max(vals) if vals else None

    @property
    def max95_m(self) -> float:
        """The largest 95 % bound of the largest position error over the frames (m): 95 % of calibrated
        robots keep every frame below it (`FrameAccuracy.max95_m`)."""
        return max((f.max95_m for f in self.frames), default=0.0)

    @property
    def max95_rad(self) -> float | None:
        vals = [f.max95_rad for f in self.frames if f.max95_rad is not None]
        return max(vals) if vals else None

    @property
    def better_than_nominal(self) -> bool:
        """Whether every frame's predicted RMS position error is below the nominal model's."""
        return all(f.rms_m < f.nominal_rms_m for f in self.frames)

    def frame(self, loop: str) -> FrameAccuracy:
        for f in self.frames:
            if f.loop == loop:
                return f
        raise KeyError(loop)


# --------------------------------------------------------------------------- the workspace's readings
def joint_ranges(robot, joints: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper readings of `joints`: the model's limits within +/- pi (a full turn where none)."""
    lo = np.array([max(robot.joint(j).lower, -np.pi) for j in joints])
    hi = np.array([min(robot.joint(j).upper, np.pi) for j in joints])
    bad = ~(hi > lo)
    lo[bad], hi[bad] = -np.pi, np.pi
    return lo, hi


def random_readings(robot, joints: list[str], n: int = N_WORKSPACE, seed: int = 0, box=None) -> np.ndarray:
    """`n` readings drawn uniformly within the joint ranges (`joint_ranges`), or within `box`
    ({joint: (lo, hi)}, each inside its range; the other joints over their ranges)."""
    lo, hi = joint_ranges(robot, joints)
    for j, (a, b) in (box or {}).items():
        if j not in joints:
            raise InputError(f"--workspace: joint '{j}' is not one of the calibrated joints ({', '.join(joints)})")
        k = joints.index(j)
        if not (a < b):
            raise InputError(f"--workspace: joint '{j}': the range {a:g}..{b:g} is empty")
        lo[k], hi[k] = max(lo[k], a), min(hi[k], b)
        if not (lo[k] < hi[k]):
            raise InputError(f"--workspace: joint '{j}': {a:g}..{b:g} lies outside its limits")
    return np.random.default_rng(seed).uniform(lo, hi, (n, len(joints)))


# --------------------------------------------------------------------------- the frames followed
@dataclass(frozen=True)
class Followed:
    """One followed frame: the loop, its frames and its tool point's parameters."""

    loop: str
    kind: str  # 'point' or 'pose'
    frame_a: str
    frame_b: str | None  # None: the world
    tip: np.ndarray  # the tool point in frame_a (zeros for a pose)
    tip_columns: tuple[int, ...]  # the problem's columns of tip_x, tip_y, tip_z (empty if fixed)


def followed_frames(problem, values: np.ndarray) -> list[Followed]:
    """The frames `closedloop check` follows, one per point or pose loop of the problem."""
    out = []
    for b in problem.blocks:
        d = b.loop.describe()
        typ = d.get("type")
        if typ not in POINT_LOOPS + POSE_LOOPS or getattr(b.loop, "parameter_only", False):
            continue
        fb = d.get("frame_b")
        frame_b = None if fb in (None, "universe", "world") else str(fb)
        point = typ in POINT_LOOPS
        names = [f"{b.loop.name}.tip_{a}" for a in "xyz"]
        cols: tuple[int, ...] = ()
        tip = np.zeros(3)
        if point and all(n in problem.index for n in names):
            cols = tuple(problem.index[n] for n in names)
            tip = np.array([values[k] for k in cols], dtype=float)
        elif point and isinstance(d.get("tip"), (list, tuple)) and len(d["tip"]) == 3:
            tip = np.asarray(d["tip"], dtype=float)
        out.append(Followed(b.loop.name, "point" if point else "pose", str(d["frame_a"]), frame_b, tip, cols))
    return out


def size_blind(problem) -> bool:
    """Whether every loop closes at any overall size (the data then do not measure it)."""
    return all(b.loop.describe().get("type") in SIZE_BLIND for b in problem.blocks)


def _poses(problem, x: np.ndarray, readings: np.ndarray, items: list[Followed]) -> list[np.ndarray]:
    """Per followed frame, its poses (n, 4, 4) at `readings` (in frame_b where it has one)."""
    state = problem.rp.apply(x[: problem.n_robot])
    names = sorted({f for it in items for f in (it.frame_a, it.frame_b) if f is not None})
    fids = {f: problem.robot.frame_id(f) for f in names}
    kin = problem.frame_kinematics(state, readings, list(fids.values()), False)
    out = []
    for it in items:
        T = kin[fids[it.frame_a]][0]
        if it.frame_b is not None:
            T = np.linalg.inv(kin[fids[it.frame_b]][0]) @ T
        out.append(T)
    return out


def _rotvec_small(D: np.ndarray) -> np.ndarray:
    """The rotation vector of rotations D (n, 3, 3) near the identity, from their skew part."""
    return 0.5 * np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], axis=1)


def frame_jacobians(
    problem, values: np.ndarray, readings: np.ndarray, items: list[Followed], columns: list[int]
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """Positions (n, 3), rotations (n, 3, 3) and their derivatives (n, 3, C) with respect to the problem's
    `columns` of every followed frame at `readings`: the world-frame (or frame_b) variation of the tool
    point R tip + t and of the rotation (dR R^T), by forward differences of the kinematics for the robot's
    parameters, exactly (R) for the tool point's own coordinates; loop parameters that are not the tool
    point do not move a robot frame."""
    T0 = _poses(problem, values, readings, items)
    pos = [T[:, :3, :3] @ it.tip + T[:, :3, 3] for T, it in zip(T0, items)]
    rot = [T[:, :3, :3] for T in T0]
    n, C = readings.shape[0], len(columns)
    Jp = [np.zeros((n, 3, C)) for _ in items]
    Jr = [np.zeros((n, 3, C)) for _ in items]
    for c, k in enumerate(columns):
        if k >= problem.n_robot:
            for i, it in enumerate(items):
                if k in it.tip_columns:
                    Jp[i][:, :, c] = rot[i][:, :, it.tip_columns.index(k)]
            continue
        xp = values.copy()
        xp[k] += FD_STEP
        Tp = _poses(problem, xp, readings, items)
        for i, it in enumerate(items):
            pp = Tp[i][:, :3, :3] @ it.tip + Tp[i][:, :3, 3]
            Jp[i][:, :, c] = (pp - pos[i]) / FD_STEP
            Jr[i][:, :, c] = _rotvec_small(Tp[i][:, :3, :3] @ np.swapaxes(rot[i], 1, 2)) / FD_STEP
    return pos, rot, Jp, Jr


# --------------------------------------------------------------------------- the parameters' uncertainty
def unseen_factor(
    problem,
    values: np.ndarray,
    considered: list[int],
    n_unseen: int,
    prior: PriorTolerance,
    moved: np.ndarray | None = None,
    evaluations: list | None = None,
) -> np.ndarray:
    """A factor (len(considered), len(considered) + 1) of Sigma_unseen (module docstring) over `considered`:
    the nominal tolerance projected on the `n_unseen` directions the data see least, and, as its last column,
    the part along them of `moved` (the solution's move from the nominal, over `considered`; 0 where None).
    `evaluations`: the problem's at `values` with the Jacobian over `considered` (None: evaluated here)."""
    if n_unseen <= 0 or not considered:
        return np.zeros((len(considered), 0))
    p = np.array([problem.params[k].prior for k in considered], dtype=float)
    t = np.array([prior.of(problem.params[k].kind, problem.params[k].unit) for k in considered], dtype=float)
    return tolerance_factor(least_seen(data_triangle(problem, values, considered, evaluations), n_unseen), p, t, moved)


def data_triangle(problem, values: np.ndarray, considered: list[int], evaluations: list | None = None) -> np.ndarray:
    """The prior-scaled closure Jacobian C over `considered` at `values` (its finite rows) reduced to its
    triangle R (C = Q R, a chunk of rows at a time: the same right singular vectors); `evaluations` as in
    `unseen_factor`."""
    p = np.array([problem.params[k].prior for k in considered], dtype=float)
    evs = problem.evaluate(values, True, columns=considered) if evaluations is None else evaluations
    rows = [ev.jacobian().reshape(-1, len(considered)) for ev in evs if ev.J is not None and ev.J.size]
    rows = [J if np.isfinite(J).all() else J[np.all(np.isfinite(J), axis=1)] for J in rows]
    return scaled_r_factor_of_blocks(rows, p) if rows else np.zeros((0, len(considered)))


def least_seen(C: np.ndarray, n_unseen: int) -> np.ndarray:
    """The `n_unseen` right singular directions of the prior-scaled data C (rows, or their triangle) with the
    smallest singular values, as columns (prior-scaled units)."""
    if C.shape[0] < C.shape[1]:
        C = np.vstack([C, np.zeros((C.shape[1] - C.shape[0], C.shape[1]))])
    _, _, Vt = np.linalg.svd(C, full_matrices=False)
    return Vt[-min(n_unseen, Vt.shape[0]) :].T


def tolerance_factor(Vu: np.ndarray, p: np.ndarray, t: np.ndarray, moved: np.ndarray | None = None) -> np.ndarray:
    """Sigma_unseen's factor (module docstring) along the least-seen directions `Vu` (`least_seen`): the
    tolerances `t` projected on them, and the part of `moved` along them as a last column (0 where None);
    `p` the parameters' prior scales."""
    d_u = p * (Vu @ (Vu.T @ (moved / p))) if moved is not None else np.zeros(len(p))
    return np.hstack([(p[:, None] * Vu) @ (Vu.T * (t / p)), d_u[:, None]])


def _sqrt_psd(S: np.ndarray) -> np.ndarray:
    """A factor L with L L^T = S for a symmetric positive semi-definite S (negative round-off clipped)."""
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    keep = w > 0
    return V[:, keep] * np.sqrt(w[keep])


def disagreement(res, evaluated: tuple[list[int], list] | None = None) -> Disagreement | None:
    """The plain loop-closure fit (eq. 3.8) linearized at the errors-in-variables calibration `res`: its
    Gauss-Newton step from there, d = x_plain - x_fit to first order (a step, not a solve: on a self-motion
    the plain residual's long steps can reach a degenerate robot), and the covariance of d under the noise
    model, Sigma_plain - Sigma_fit (module docstring, Model error); None where the calibration is not the
    errors-in-variables fit (the plain one already: nothing to compare), did not converge, estimated
    nothing, or where the plain fit is not linear over its step (`_holds_to_first_order`).  `evaluated`:
    (columns, the problem's evaluations at the solution with the Jacobian over them, a superset of the
    estimated), shared with the caller (`plain_linearization`); None: evaluated here."""
    from closedloop.estimate.model_error import plain_linearization

    problem, fit = res.problem, res.fit
    est = list(fit.estimated)
    if not compared(res):
        return None
    x = np.asarray(fit.values, dtype=float)
    sigma_q = np.full(len(problem.joints), float(res.noise.sigma))
    step, plain, decrease = plain_linearization(problem, x, est, sigma_q, evaluated=evaluated)
    shift = np.zeros(len(problem.params))
    shift[est] = step
    if not _holds_to_first_order(problem, x, shift, decrease):
        return None
    cov = plain - np.nan_to_num(np.asarray(fit.covariance, dtype=float))
    return Disagreement(shift=shift, estimated=tuple(est), noise_cov=cov)


def compared(res) -> bool:
    """Whether `disagreement` compares the estimators on `res`: a converged errors-in-variables fit that
    estimated something with a joint noise above zero."""
    from closedloop.estimate.model_error import EIV

    fit = res.fit
    return bool(len(fit.estimated)) and fit.converged and res.noise.estimator == EIV and res.noise.sigma > 0


LINEAR_RATIO = 0.5  # the plain step's actual decrease of the closure against the one it predicts, at least


def _holds_to_first_order(problem, x: np.ndarray, shift: np.ndarray, predicted: float) -> bool:
    """Whether the plain fit's Gauss-Newton step from `x` lowers its squared closure by at least
    `LINEAR_RATIO` of the decrease it predicts (a trust-region ratio): where it does not, the plain fit is
    not linear over the step and the disagreement is no first-order figure (a weak direction the noise
    throws far, not a model error)."""

    def cost(v: np.ndarray) -> float:
        return float(sum(np.sum(np.nan_to_num(ev.r) ** 2) for ev in problem.evaluate(v, False)))

    if not predicted > 0.0:  # no step: nothing to judge, and nothing that disagrees
        return True
    return cost(x) - cost(x + shift) >= LINEAR_RATIO * predicted


def judge_disagreement(d: np.ndarray, noise: np.ndarray) -> ModelError:
    """`ModelError` of the weighted workspace errors `d` (rows) of the estimators' shift, against the factor
    `noise` (rows, r) of their covariance under the noise model: R = |d|^2 / tr(N N^T), the effective degrees
    of freedom (tr M)^2 / tr(M^2) of M = N N^T."""
    sv2 = np.linalg.svd(noise, compute_uv=False) ** 2 if noise.size else np.zeros(0)
    expected = float(sv2.sum())
    if not expected > 0.0:
        return ModelError(ratio=0.0, dof=0.0, limit=float("inf"), share=0.0)
    ratio = float(d @ d) / expected
    dof = expected**2 / float(np.sum(sv2**2))
    limit = 1.0 + 3.0 * np.sqrt(2.0 / dof)
    share = float(np.sqrt(1.0 - 1.0 / ratio)) if ratio > limit else 0.0
    return ModelError(ratio=ratio, dof=float(dof), limit=float(limit), share=share)


# --------------------------------------------------------------------------- the gauge
def gauge_basis(items: list[Followed], pos: list[np.ndarray], rot: list[np.ndarray], scaled: bool) -> np.ndarray:
    """G (rows, g): the stacked errors (per frame: positions n x 3, then a pose's rotations n x 3) that a
    base transform per group, a tool transform per pose loop and (`scaled`) the size make, to first order."""
    groups = sorted({it.frame_b or "" for it in items})
    n_tools = sum(it.kind == "pose" for it in items)
    g = 6 * len(groups) + 6 * n_tools + (1 if scaled else 0)
    blocks = []
    tool = 0
    for it, p, R in zip(items, pos, rot):
        n = p.shape[0]
        b = 6 * groups.index(it.frame_b or "")
        Gp = np.zeros((n, 3, g))
        Gp[:, :, b : b + 3] = np.eye(3)
        Gp[:, 0, b + 4], Gp[:, 0, b + 5] = p[:, 2], -p[:, 1]  # omega x p = -[p]x omega
        Gp[:, 1, b + 3], Gp[:, 1, b + 5] = -p[:, 2], p[:, 0]
        Gp[:, 2, b + 3], Gp[:, 2, b + 4] = p[:, 1], -p[:, 0]
        if scaled:
            Gp[:, :, -1] = p
        blocks.append(Gp.reshape(-1, g))
        if it.kind == "pose":
            t = 6 * len(groups) + 6 * tool
            Gp[:, :, t : t + 3] = R
            blocks[-1] = Gp.reshape(-1, g)
            Gr = np.zeros((n, 3, g))
            Gr[:, :, b + 3 : b + 6] = np.eye(3)
            Gr[:, :, t + 3 : t + 6] = R
            blocks.append(Gr.reshape(-1, g))
            tool += 1
    return np.vstack(blocks) if blocks else np.zeros((0, g))


# --------------------------------------------------------------------------- the prediction
#: configurations per loop above which what the data cannot see is read on an evenly spaced sample of this many
#: (`predict_from_result`; as the left-out prediction's, `estimate.model_error.LOO_SAMPLE`)
UNSEEN_SAMPLE = 8192


def considered_columns(problem, status: list, estimated: list[int], prior: PriorTolerance) -> list[int]:
    """The parameters whose error the prediction propagates: the estimated ones, and those dropped or
    unidentifiable that the nominal tolerance (`prior`) lets be off."""
    return [
        k
        for k, s in enumerate(status)
        if s in (ParamStatus.ESTIMATED, ParamStatus.DROPPED, ParamStatus.UNIDENTIFIABLE)
        and prior.of(problem.params[k].kind, problem.params[k].unit) > 0
        or k in estimated
    ]


def predict_accuracy(
    problem,
    values: np.ndarray,
    covariance: np.ndarray,
    estimated: list[int],
    status: list,
    n_weak: int,
    readings: np.ndarray,
    *,
    size_measured: bool,
    error_bars: str = "the noise model",
    prior: PriorTolerance | None = None,
    source: str = "random within the joint ranges",
    default_readings: bool = False,
    seed: int = 0,
    tol_m: float = TOL_M,
    tol_rad: float = TOL_RAD,
    disagreement: Disagreement | None = None,
    held_length: float = 0.0,
    initial: np.ndarray | None = None,
    evaluations: list | None = None,
) -> WorkspaceAccuracy | None:
    """The predicted error of every followed frame at `readings` (n, problem joints) (module docstring).

    `covariance` is over the `estimated` columns of the problem; `status` the parameters' statuses
    (`ParamStatus`); `n_weak` the number of combinations the fit left undetermined; `disagreement`
    the plain fit's against the calibration (`disagreement`): beyond the noise, model error, whose bias
    moves the frames beside the random error.  None when no loop
    has a frame to follow (a camera, a known distance).
    (`ParamStatus`); `n_weak` the number of combinations the fit left undetermined; `held_length` the length
    the parameter held to set the size stands for (m; 0: none held); `initial` the nominal values the fit
    started from (the move along what the data cannot see is an error: module docstring; None: not counted);
    `evaluations` the problem's at `values` with the Jacobian over `considered_columns` (None: evaluated
    where needed).  None when no loop has a frame to follow (a camera, a known distance).
    """
    prior = prior or PriorTolerance()
    items = followed_frames(problem, values)
    if not items:
        return None
    readings = np.asarray(readings, dtype=float)
    considered = considered_columns(problem, status, estimated, prior)
    n_dropped = sum(status[k] == ParamStatus.DROPPED for k in considered)
    moved = None
    if initial is not None:  # the robot's corrections (a loop's place has no nominal: its start is a guess)
        moved = np.array([values[k] - initial[k] if k < problem.n_robot else 0.0 for k in considered])
    L_u = unseen_factor(problem, values, considered, n_dropped + n_weak, prior, moved, evaluations)
    L_e = np.zeros((len(considered), 0))
    if len(estimated) and covariance.size:
        pos_of = {k: i for i, k in enumerate(considered)}
        F = _sqrt_psd(np.nan_to_num(np.asarray(covariance, dtype=float)))  # NaN: a bound held it, no spread
        L_e = np.zeros((len(considered), F.shape[1]))
        L_e[[pos_of[k] for k in estimated]] = F
    pos, rot, Jp, Jr = frame_jacobians(problem, values, readings, items, considered)
    # the stacked, weighted frame errors and the gauge they are judged modulo
    W, E = [], []
    for it, jp, jr in zip(items, Jp, Jr):
        W.append(np.full(jp.shape[0] * 3, 1.0 / tol_m))
        E.append(jp.reshape(-1, len(considered)))
        if it.kind == "pose":
            W.append(np.full(jr.shape[0] * 3, 1.0 / tol_rad))
            E.append(jr.reshape(-1, len(considered)))
    w = np.concatenate(W)
    J = np.vstack(E)
    G = gauge_basis(items, pos, rot, not size_measured) * w[:, None]
    Qg = np.linalg.qr(G)[0] if G.shape[1] else np.zeros((G.shape[0], 0))

    def projected(L: np.ndarray) -> np.ndarray:
        A = (J @ L) * w[:, None]
        return (A - Qg @ (Qg.T @ A)) / w[:, None]

    A_e, A_u = projected(L_e), projected(L_u)
    bias, model = np.zeros(len(considered)), None
    if disagreement is not None:  # model error: the estimators' disagreement beyond the noise, over the workspace
        pos_of = {k: i for i, k in enumerate(considered)}
        F = _sqrt_psd(disagreement.noise_cov)
        L_d = np.zeros((len(considered), F.shape[1]))
        L_d[[pos_of[k] for k in disagreement.estimated]] = F
        shift = np.asarray(disagreement.shift, dtype=float)[considered]
        model = judge_disagreement(projected(shift[:, None])[:, 0] * w, projected(L_d) * w[:, None])
        bias = model.share * shift
    B = projected(bias[:, None])[:, 0]  # the frames' systematic error, gauge removed
    size_std = size_held = None
    if not size_measured and G.shape[1]:  # the size's coefficient in the gauge fit, and the held length's tolerance
        row_s = np.linalg.pinv(G)[-1]
        c_s = row_s @ ((J @ np.hstack([L_e, L_u])) * w[:, None])
        # the held length is as good as the nominal model's lengths: 2 mm, or the tolerance given above it
        size_held = max(HELD_ERROR, prior.length_m) / held_length if held_length > 0 else 0.0
        size_std = float(np.sqrt(np.sum(c_s**2) + size_held**2))
    n_read = readings.shape[0]
    position_rows = np.concatenate(
        [np.arange(3 * n_read) + 3 * n_read * (i + sum(x.kind == "pose" for x in items[:i])) for i in range(len(items))]
    )
    tol = np.array([prior.of(problem.params[k].kind, problem.params[k].unit) for k in considered])
    A_n = projected(np.diag(tol))  # the nominal model: every considered parameter off by its tolerance
    tips = {k for it in items for k in it.tip_columns}
    moving = [i for i, k in enumerate(considered) if k < problem.n_robot or k in tips]  # what moves a frame
    others = sorted(set(range(len(considered))) - set(moving))  # a loop's place: moves no frame
    L_all = np.hstack([L_e, L_u])[moving + others]
    A = np.hstack([A_e, A_u])
    rng = np.random.default_rng(seed + 1)
    draws = A @ rng.standard_normal((A.shape[1], MAX_DRAWS)) if A.shape[1] else np.zeros((A.shape[0], MAX_DRAWS))
    draws += B[:, None]
    frames: list[FrameAccuracy] = []
    row = 0
    n = readings.shape[0]
    joints = tuple(problem.joints)
    training = np.vstack([b.theta for b in problem.blocks if b.theta.size]) if problem.blocks else None
    seen = None
    if training is not None and training.shape[0]:  # where the data are: a long log's even sample marks it as well
        where = training[even_sample(training.shape[0], UNSEEN_SAMPLE)]
        seen = [T[:, :3, :3] @ it.tip + T[:, :3, 3] for T, it in zip(_poses(problem, values, where, items), items)]
    for it in items:
        blocks = [("m", slice(row, row + 3 * n))]
        row += 3 * n
        if it.kind == "pose":
            blocks.append(("rad", slice(row, row + 3 * n)))
            row += 3 * n
        figs: dict[str, tuple] = {}
        for unit, sl in blocks:
            sig_b = np.linalg.norm(B[sl].reshape(n, 3), axis=1)
            sig = np.sqrt(np.sum(A[sl].reshape(n, -1) ** 2, axis=1) + sig_b**2)
            sig_u = np.sqrt(np.sum(A_u[sl].reshape(n, -1) ** 2, axis=1))
            largest = np.linalg.norm(draws[sl].reshape(n, 3, -1), axis=1).max(axis=0)
            figs[unit] = (
                sig,
                float(np.sqrt(np.mean(sig**2))),
                float(np.percentile(sig, 95)),
                float(largest.mean()),
                float(np.percentile(largest, 95)),
                float(np.mean((largest >= 0.5 * largest.mean()) & (largest <= 2.0 * largest.mean()))),
            )
            figs[unit + "_u"] = (float(np.sqrt(np.mean(sig_u**2))),)
            figs[unit + "_b"] = (float(np.sqrt(np.mean(sig_b**2))),)
            figs[unit + "_n"] = (float(np.sqrt(np.sum(A_n[sl] ** 2) / n)),)
        sm, rms_m, p95_m, max_m, max95_m, within_2x = figs["m"]
        worst = int(np.argmax(sm))
        pose = "rad" in figs
        frames.append(
            FrameAccuracy(
                loop=it.loop,
                frame=it.frame_a,
                kind=it.kind,
                rms_m=rms_m,
                p95_m=p95_m,
                max_m=max_m,
                rms_rad=figs["rad"][1] if pose else None,
                p95_rad=figs["rad"][2] if pose else None,
                max_rad=figs["rad"][3] if pose else None,
                max95_m=max95_m,
                max95_rad=figs["rad"][4] if pose else None,
                max_within_2x=within_2x,
                unseen_rms_m=figs["m_u"][0],
                unseen_rms_rad=figs["rad_u"][0] if pose else None,
                nominal_rms_m=figs["m_n"][0],
                nominal_rms_rad=figs["rad_n"][0] if pose else None,
                model_rms_m=figs["m_b"][0],
                model_rms_rad=figs["rad_b"][0] if pose else None,
                worst={j: float(v) for j, v in zip(joints, readings[worst])},
                sigma_m=sm,
                sigma_rad=figs["rad"][0] if pose else None,
                reach=np.linalg.norm(pos[len(frames)], axis=1),
                training_reach=None if seen is None else np.linalg.norm(seen[len(frames)], axis=1),
            )
        )
    return WorkspaceAccuracy(
        frames=tuple(frames),
        joints=joints,
        readings=readings,
        source=source,
        error_bars=error_bars,
        prior=prior,
        size_removed=not size_measured,
        training=training,
        default_readings=default_readings,
        parameters=tuple(problem.names[considered[i]] for i in moving),
        loop_parameters=tuple(problem.names[considered[i]] for i in others),
        full_covariance=L_all @ L_all.T,
        bias=bias[moving],
        design=projected(np.eye(len(considered))[:, moving])[position_rows],
        model_error=model,
        size_std=size_std,
        size_held_std=size_held,
    )


def predict_closure(problem, values: np.ndarray, names: list[str], covariance: np.ndarray) -> list[dict]:
    """The closure RMS the parameters' uncertainty predicts on the problem's own configurations, per loop
    (a calibration's `WorkspaceAccuracy.covariance` over `names`, propagated as in the module docstring at
    the readings of each block): what a closure on new data shows of the model's error, with the loop's
    place refitted (a point loop's point: a translation; a tracker's frame, where it measures the point,
    and a pose loop's fixture: a rigid transform of the base; a plane's tilt and offset, on the tip's
    distance to it, `_plane_closure`; a door's hinge line and grasp, on its own residual,
    `_refitted_closure`).  The readings' noise is not included.  Rows: loop, rms_m, rms_rad (None: not a followed loop)."""
    from closedloop.estimate.threads import blas_threads

    with blas_threads(None):
        return _predict_closure(problem, values, names, covariance)


def _predict_closure(problem, values: np.ndarray, names: list[str], covariance: np.ndarray) -> list[dict]:
    items = {it.loop: it for it in followed_frames(problem, values)}
    cols = [problem.index[n] for n in names if n in problem.index]
    keep = [i for i, n in enumerate(names) if n in problem.index]
    L = _sqrt_psd(np.asarray(covariance, dtype=float)[np.ix_(keep, keep)]) if keep else np.zeros((0, 0))
    out = []
    for bi, b in enumerate(problem.blocks):
        it = items.get(b.loop.name)
        if it is None or not b.theta.shape[0] or not cols:
            continue
        n, typ = b.theta.shape[0], b.loop.describe().get("type")
        if typ in HINGE:
            out.append(_refitted_closure(problem, values, bi, cols, L))
            continue
        pos, rot, Jp, Jr = frame_jacobians(problem, values, b.theta, [it], cols)
        if typ in PLANE:
            out.append(_plane_closure(b.loop, values[problem.loop_columns[bi]], pos[0], Jp[0] @ L, b.loop.name))
            continue
        pose = it.kind == "pose"
        J = np.vstack([Jp[0].reshape(-1, len(cols))] + ([Jr[0].reshape(-1, len(cols))] if pose else []))
        w = np.concatenate([np.full(3 * n, 1.0 / TOL_M)] + ([np.full(3 * n, 1.0 / TOL_RAD)] if pose else []))
        G = gauge_basis([it], pos, rot, False)
        # the refitted place: a base pose (a fixture), the tracker's frame (a rigid transform of the points it
        # measures), or a translation (a socket's point)
        G = G[:, :6] if pose else G[: 3 * n, :6] if typ in MEASURED_POINT else G[: 3 * n, :3]
        G = G * w[:, None]
        Qg = np.linalg.qr(G)[0]
        A = (J @ L) * w[:, None]
        A = (A - Qg @ (Qg.T @ A)) / w[:, None]
        rms_m = float(np.sqrt(np.sum(A[: 3 * n] ** 2) / n))
        rms_rad = float(np.sqrt(np.sum(A[3 * n :] ** 2) / n)) if pose else None
        out.append({"loop": b.loop.name, "rms_m": rms_m, "rms_rad": rms_rad})
    return out


def _refitted_closure(problem, values: np.ndarray, bi: int, cols: list[int], L: np.ndarray) -> dict:
    """`_predict_closure` through the loop's own residual (a door: the handle's pose about a hinge line, its
    angle eliminated per configuration): the residual's rows moved by the model's uncertainty (J L over the
    robot's columns), less what a new log's refit of the loop's own parameters (the hinge line, the grasp)
    absorbs; RMS over the translation and the rotation rows, as `validation.evaluate` observes them."""
    b = problem.blocks[bi]
    robot_cols = set(cols)
    own = [int(k) for k in problem.loop_columns[bi] if int(k) not in robot_cols]
    ev = problem.evaluate(values, True, columns=list(cols) + own)[bi]
    N, m, _ = ev.J.shape
    trans, rot = list(b.loop.translation_rows), list(b.loop.rotation_rows)
    w = np.ones(m)
    w[trans], w[rot] = 1.0 / TOL_M, 1.0 / TOL_RAD
    A = (ev.J[:, :, : len(cols)] @ L) * w[None, :, None]
    G = (ev.J[:, :, len(cols) :] * w[None, :, None]).reshape(N * m, -1)
    Q = np.linalg.qr(G)[0] if G.shape[1] else np.zeros((N * m, 0))
    A = A.reshape(N * m, -1)
    A = ((A - Q @ (Q.T @ A)).reshape(N, m, -1)) / w[None, :, None]
    rms = {k: float(np.sqrt(np.sum(A[:, rows] ** 2) / N)) if rows else None for k, rows in (("m", trans), ("rad", rot))}
    return {"loop": b.loop.name, "rms_m": rms["m"], "rms_rad": rms["rad"]}


def _plane_closure(loop, p: np.ndarray, pos: np.ndarray, JL: np.ndarray, name: str) -> dict:
    """`_predict_closure` for a plane loop: its closure is the tip's distance to the plane, r = n^T y - d, and
    a new log refits the plane, its tilt (dn, normal to n: r moves by dn^T y) and offset; what the model's
    uncertainty `JL` (n, 3, r: the tip's position per factor of the covariance) leaves of the distance once
    those three are refitted."""
    _, w, _ = loop.split(p)
    nrm = loop.normal(w)
    t1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(nrm, t1)
    A = np.einsum("j,ijr->ir", nrm, JL)
    Q = np.linalg.qr(np.column_stack([pos @ t1, pos @ t2, np.ones(pos.shape[0])]))[0]
    A = A - Q @ (Q.T @ A)
    return {"loop": name, "rms_m": float(np.sqrt(np.sum(A**2) / pos.shape[0])), "rms_rad": None}


def predict_from_result(
    res,
    readings: np.ndarray | None = None,
    *,
    n: int = N_WORKSPACE,
    seed: int = 0,
    prior: PriorTolerance | None = None,
    source: str | None = None,
    size_measured: bool | None = None,
    model_error: bool = True,
) -> WorkspaceAccuracy | None:
    """`predict_accuracy` for a `CalibrationResult` (its problem, values, trusted covariance, statuses),
    at `readings`, or `n` readings drawn within the joint ranges (`random_readings`, `seed`); BLAS threads
    limited by size (`closedloop.estimate.threads.blas_threads`).  `model_error`: the calibration tested
    for model error (`disagreement`); False leaves it out."""
    problem = res.problem
    default = readings is None and n == N_WORKSPACE and seed == 0
    if readings is None:
        readings = random_readings(problem.robot, problem.joints, n, seed)
        source = source or f"{n} random readings within the joint ranges (seed {seed})"
    if size_measured is None:
        ev = res.verdict.evidence if res.verdict is not None else {}
        size_measured = bool(ev["size_measured"]) if "size_measured" in ev else not size_blind(problem)
    from closedloop.estimate.threads import blas_threads

    values = np.asarray(res.fit.values, dtype=float)
    prior = prior or PriorTolerance()
    # The passes over the log at the solution (the costly part): on a short log one evaluation with the
    # Jacobian over the considered columns serves both the plain fit's linearization and what the data cannot
    # see.  On a long log the plain fit's reads the fit's own last evaluation (the problem's memo), and what the
    # data cannot see, the geometry's least-seen directions, is read on an evenly spaced sample of
    # `UNSEEN_SAMPLE` configurations per loop.
    considered = considered_columns(problem, list(res.fit.status), list(res.fit.estimated), prior)
    unseen = len(res.identifiability.weak) + sum(res.fit.status[k] == ParamStatus.DROPPED for k in considered)
    evaluations = shared = None
    if considered and (unseen > 0 or (model_error and compared(res))) and followed_frames(problem, values):
        if any(b.theta.shape[0] > UNSEEN_SAMPLE for b in problem.blocks):
            evaluations = problem.sampled(UNSEEN_SAMPLE).evaluate(values, True, columns=considered) if unseen else None
        else:
            evaluations = problem.evaluate(values, True, columns=considered)
            shared = (considered, evaluations)
    with blas_threads(None):  # small dense algebra: one thread
        found = disagreement(res, shared) if model_error else None
        return predict_accuracy(
            problem,
            values,
            np.asarray(res.fit.covariance, dtype=float),
            list(res.fit.estimated),
            list(res.fit.status),
            len(res.identifiability.weak),
            readings,
            size_measured=size_measured,
            error_bars=getattr(getattr(res, "noise", None), "error_bars", "the noise model"),  # `NoiseRecord`'s
            prior=prior,
            source=source or "the given readings",
            default_readings=default,
            seed=seed,
            disagreement=found,
            held_length=float(getattr(getattr(res, "scale", None), "gauge_length", 0.0) or 0.0),
            initial=np.asarray(res.fit.initial, dtype=float),
            evaluations=evaluations,
        )
