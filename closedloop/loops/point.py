"""The point loop: a tool tip held at a fixed point (ball joint / point contact, thesis 3.4.1)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import (
    POINT_FIELDS,
    TIP_FIELDS,
    point_parameters,
    relative_point,
)
from closedloop.loops.spec import register
from closedloop.model.axes import AXIS_TOLERANCE, BlindJoint, blind_joints
from closedloop.model.parameters import Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import parse_vec, vec3

#: a contact point a pivot puts closer than this to the last joint's axis (m) is taken to lie on it
CONTACT_TOLERANCE = 3e-3


class PointLoop(Loop):
    """Three closure equations per configuration: a point of A coincides with a point of B.

    Residual (the position part of the closure, eq. 3.19 with x_c = p_c, eqs. 3.27):

        r = T_B^-1 T_A t - p              (3 rows, metres, in frame B)

    t is the tool tip in frame A (``<loop>.tip_x/y/z``), p the contact point
    in frame B (``<loop>.px/py/pz``, world coordinates when B is the
    universe).  Either may be known (``tip=``, ``point=``), e.g. a calibrated
    probe ball, or a known fixture.  The orientation of A relative to B is
    free (the three passive rotations of the ball joint), so the loop only
    sees the partial velocity vectors of eq. 3.27.  Jacobians:

        dr/d(delta_A) = R_BA [I  -[t]x],   dr/d(delta_B) = [-I  [y]x],
        dr/dt = R_BA,                      dr/dp = -I,

    with y = T_B^-1 T_A t and R_BA = R_B^T R_A.  Which robot parameters the
    data cannot identify (Theorem 4, eq. 3.28: the orientation of the base
    about the contact point, the tool orientation, one length when the point
    is unknown) is decided by the core on the data; nothing is removed here.

    B may be any frame of the model, including another branch (two fingers
    touching, the two grippers of a two-armed robot joined at a point).

    ``initial_tip`` / ``initial_point`` are starting values of unknown ones
    (the point is otherwise initialised from the data); ``prior`` (m) is the
    expected magnitude of their errors, used to scale the Jacobian columns
    and to report unidentifiable combinations (default DEFAULT_PRIORS
    ["loop_m"]; give the robot's length prior when the tip is a link length).
    """

    translation_rows = (0, 1, 2)
    rotation_rows = ()

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        tip: np.ndarray | None = None,
        point: np.ndarray | None = None,
        initial_tip: np.ndarray | None = None,
        initial_point: np.ndarray | None = None,
        prior: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.prior = prior
        self.tip = None if tip is None else vec3(tip, "tip")
        self.point = None if point is None else vec3(point, "point")
        self.initial_tip = np.zeros(3) if initial_tip is None else vec3(initial_tip, "initial_tip")
        self.initial_point = None if initial_point is None else vec3(initial_point, "initial_point")

    @property
    def dim(self) -> int:
        return 3

    @property
    def n_tip(self) -> int:
        return 0 if self.tip is not None else 3

    def parameters(self) -> list[Parameter]:
        out = []
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, self.initial_tip, prior=self.prior)
        if self.point is None:
            p0 = self.initial_point if self.initial_point is not None else np.zeros(3)
            out += point_parameters(self.name, POINT_FIELDS, p0, order0=3, prior=self.prior)
        return out

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tip, point) from the loop's parameter vector."""
        k = self.n_tip
        tip = self.tip if self.tip is not None else p[:3]
        point = self.point if self.point is not None else p[k : k + 3]
        return np.asarray(tip, dtype=float), np.asarray(point, dtype=float)

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """Unknown tip and point from the data (a pivot calibration), else the point from the given tip.

        With both unknown and no initial tip given: R_i t - p = -d_i for every
        configuration (T_B^-1 T_A = (R_i, d_i)), linear least squares in
        (t, p) when the rotations R_i span enough axes, used when it puts the
        tip over 2 cm from frame A's origin (a start there, on a joint axis,
        would be far from the data; within 2 cm the frame is taken at its
        word); otherwise the point is the mean of T_B^-1 T_A t.
        """
        if self.point is not None or self.initial_point is not None:
            return None
        tip = self.tip if self.tip is not None else self.initial_tip
        if self.tip is None and not np.any(self.initial_tip):
            sol = pivot(np.linalg.solve(TB, TA))
            if sol is not None and np.linalg.norm(sol[:3]) > 0.02:  # the data put the tip away from the origin
                return sol
        y, *_ = relative_point(TA, TB, tip)
        p = y.mean(axis=0)
        return p if self.tip is not None else np.concatenate([tip, p])

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        tip, point = self.split(p)
        y, RBA, dA, dB = relative_point(TA, TB, tip)
        N = TA.shape[0]
        blocks = []
        if self.tip is None:
            blocks.append(RBA)
        if self.point is None:
            blocks.append(np.broadcast_to(-np.eye(3), (N, 3, 3)))
        dp = np.concatenate(blocks, axis=2) if blocks else np.zeros((N, 3, 0))
        return LoopEval(y - point, dA, dB, dp)

    def describe(self) -> dict:
        return super().describe() | {
            "tip": "unknown" if self.tip is None else self.tip.tolist(),
            "point": "unknown" if self.point is None else self.point.tolist(),
        }


def pivot(M: np.ndarray) -> np.ndarray | None:
    """A pivot calibration: (tip, point) solving ``R_i t - p = -d_i`` by linear least squares over the
    poses ``M_i = (R_i, d_i)`` (N, 4, 4) of frame A in frame B; None when there are fewer than 3 poses
    or their rotations do not span enough axes to fix the tip (smallest singular value below 1e-3 of
    the largest)."""
    if M.shape[0] < 3:
        return None
    A = np.concatenate([M[:, :3, :3], np.broadcast_to(-np.eye(3), (M.shape[0], 3, 3))], axis=2)
    A, b = A.reshape(-1, 6), -M[:, :3, 3].reshape(-1)
    S = np.linalg.svd(A, compute_uv=False)
    if not S[-1] > 1e-3 * S[0]:
        return None
    return np.linalg.lstsq(A, b, rcond=None)[0]


def contact_on_axis(robot: RobotModel, loop: PointLoop, angles: np.ndarray, joints: list[str]) -> list[BlindJoint]:
    """The last joints whose axes the loop's contact point lies on (`closedloop.model.axes`), before a fit.

    The contact point is the given tip, else where a pivot calibration on the nominal model puts it
    from the readings `angles` (N, len(`joints`)) of the loop's rows (:func:`pivot`; the fit starts
    there or, within 2 cm, at the frame's origin), judged within `CONTACT_TOLERANCE` (the nominal
    model's errors move a pivot by millimetres).  Empty for a loop to another robot frame, when the
    pivot cannot fix the tip, or when the last joint moves the point.
    """
    if loop.frame_b not in ("universe", "world"):
        return []
    model = robot.model
    fid = robot.frame_id(loop.frame_a)
    if loop.tip is not None:  # the given tip, at the neutral configuration
        tip, q0, tol = loop.tip, None, AXIS_TOLERANCE
    else:  # the pivot's, at the first reading
        finite = np.all(np.isfinite(angles), axis=1) & np.all(np.abs(angles) < 1e3, axis=1)
        angles = angles[finite]
        if len(angles) > 200:  # evenly spread rows: the pivot needs the rotations, not every row
            angles = angles[np.linspace(0, len(angles) - 1, 200).astype(int)]
        q = robot.configurations(angles, joints)
        data = model.createData()
        M = np.empty((len(q), 4, 4))
        for i, qi in enumerate(q):
            pin.framesForwardKinematics(model, data, qi)
            M[i] = data.oMf[fid].homogeneous
        sol = pivot(M)
        if sol is None:
            return []
        tip, q0, tol = (sol[:3] if np.linalg.norm(sol[:3]) > 0.02 else np.zeros(3)), q[0], CONTACT_TOLERANCE
    return blind_joints(model, fid, tip, q0, tol=tol)


@register("point", {"frame", "to", "tip", "point"})
def _point(kw: dict[str, str], robot: RobotModel) -> Loop:
    """point:frame=tool[,to=frame_b][,tip="x y z"][,point="x y z"]  (tip/point: unknown if absent)."""
    if "frame" not in kw:
        raise LoopError("point loop needs frame=<tool frame>")
    tip = parse_vec(kw["tip"], 3, "tip") if kw.get("tip", "unknown") != "unknown" else None
    point = parse_vec(kw["point"], 3, "point") if kw.get("point", "unknown") != "unknown" else None
    return PointLoop(kw.get("name", "point"), kw["frame"], kw.get("to", "universe"), tip=tip, point=point)
