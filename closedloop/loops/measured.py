"""Open-loop calibration as a loop: an external sensor measures the tool (thesis 3.2).

A tracker, camera or CMM measures, at every configuration, the pose (or only
the position) of a tool in the sensor's own frame S.  The sensor frame is
placed in frame B (normally the robot base / universe) by an unknown pose
X = T_BS, and the tool by an unknown pose Y = T_A,tool (or only a tip point t).
The chain base -> robot -> tool -> sensor -> base is then a loop whose one
"joint" is the measurement, so the open-loop method of 3.2 (eqs. 3.4-3.12)
is the special case of a loop that measures its own closure.

Measurements come from extra log columns (``measurements``), one row per
configuration, named after the loop, and are passed to ``evaluate`` and
``initialize`` (the loop keeps none):

    <loop>:x, <loop>:y, <loop>:z          measured position (m), sensor frame
    <loop>:rx, <loop>:ry, <loop>:rz       measured rotation vector (rad), pose only

The measurement is an absolute length reference, so ``scale_free = False``
(no length is fixed, thesis 3.3 does not apply).  A measurement noise std
(``sigma_t`` in m, ``sigma_r`` in rad) sets ``measurement_cov``, which the
core adds to the covariance propagated from joint noise.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import (
    POSE_FIELDS,
    TIP_FIELDS,
    opt_float,
    opt_pose,
    point_parameters,
    pose_parameters,
    refine_own,
    relative_point,
)
from closedloop.loops.spec import register
from closedloop.model.parameters import Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import as_se3, generators, hand_eye, kabsch, parse_vec, pose_of, skew, vec3, vec_of

TOOL_FIELDS = tuple(f"tool_{f}" for f in POSE_FIELDS)
POSITION_COLS = ("x", "y", "z")
ROTATION_COLS = ("rx", "ry", "rz")


def _gauss_newton(
    loop: Loop, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, free: np.ndarray, meas: np.ndarray, iters: int = 30
) -> np.ndarray:
    """Refine the loop's own parameters ``p[free]`` with the robot held (TA, TB fixed); `common.refine_own`."""
    return refine_own(
        lambda q: loop.evaluate(TA, TB, q, meas),
        lambda q: loop.evaluate(TA, TB, q, meas).r,
        loop.normalize,
        p,
        free,
        iters,
    )


class _Measured(Loop):
    """Shared parts: the sensor base X, the measurement columns, the noise."""

    scale_free = False
    _cols: tuple[str, ...] = POSITION_COLS

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        base=None,
        initial_base=None,
        sigma_t: float | None = None,
        sigma_r: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.base = None if base is None else as_se3(base, "base")
        self.initial_base = pin.SE3.Identity() if initial_base is None else as_se3(initial_base, "initial_base")
        self.sigma_t = sigma_t
        self.sigma_r = sigma_r
        for s, what in ((sigma_t, "sigma_t"), (sigma_r, "sigma_r")):
            if s is not None and not (np.isfinite(s) and s > 0):
                raise LoopError(f"loop '{name}': {what} must be positive and finite")

    @property
    def n_base(self) -> int:
        return 0 if self.base is not None else 6

    def columns(self) -> list[str]:
        return [f"{self.name}:{c}" for c in self._cols]

    def measurements(self, extra: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
        missing = [c for c in self.columns() if c not in extra]
        if missing:
            raise LoopError(f"loop '{self.name}': the log has no measurement column(s) {', '.join(missing)}")
        M = np.column_stack([np.asarray(extra[c], dtype=float)[rows] for c in self.columns()])
        bad = np.flatnonzero(~np.all(np.isfinite(M), axis=1))
        if bad.size:
            raise LoopError(
                f"loop '{self.name}': measurement missing or not a number in row(s) "
                f"{', '.join(str(b + 1) for b in bad[:5])} of this loop"
            )
        return M

    def _checked(self, meas: np.ndarray | None, N: int) -> np.ndarray:
        """`meas` (N, columns), checked against the N configurations it is evaluated at."""
        if meas is None:
            raise LoopError(f"loop '{self.name}': no measurements given (log columns {', '.join(self.columns())})")
        meas = np.asarray(meas, dtype=float)
        if meas.shape != (N, len(self._cols)):
            raise LoopError(
                f"loop '{self.name}': {N} configurations but measurements of shape {meas.shape} "
                f"(expected ({N}, {len(self._cols)}))"
            )
        return meas

    def base_pose(self, p: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        v = vec_of(self.base) if self.base is not None else p[:6]
        return pose_of(v), v

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = p.copy()
        if self.base is None:
            out[3:6] = pin.log3(pin.exp3(p[3:6]))
        return out

    def describe(self) -> dict:
        return super().describe() | {
            "base": "unknown" if self.base is None else vec_of(self.base).tolist(),
            "columns": self.columns(),
        }


class MeasuredPoseLoop(_Measured):
    """The measured tool pose (6 equations per configuration, eqs. 3.4, 3.7).

    With M_i the measured pose of the tool in the sensor frame, X = T_BS the
    sensor base (``<loop>.x..rz``) and Y = T_A,tool the tool frame
    (``<loop>.tool_x..tool_rz``), the residual is the exact SE(3) error

        r = log6(E),   E = M_i^-1 X^-1 T_B^-1 T_A Y

    (translation rows 0-2 in m, rotation rows 3-5 in rad, in the tool frame).
    With right perturbations and Z = X^-1 T_B^-1 T_A Y:

        dr/d(delta_A) =  Jlog6(E) Ad(Y^-1)
        dr/d(delta_B) = -Jlog6(E) Ad((T_B^-1 T_A Y)^-1)
        dr/d(delta_X) = -Jlog6(E) Ad(Z^-1)
        dr/d(delta_Y) =  Jlog6(E)

    and the pose parameters map to delta as in WeldLoop (translation: R^T dt,
    rotation vector: Jexp3(r) dr).  The measurement noise, sigma_t (m) on
    position and sigma_r (rad) on rotation, is taken isotropic, so to first
    order (Jlog6 ~ I near closure) its covariance in r is
    diag(sigma_t^2 I3, sigma_r^2 I3) whatever the frame it is expressed in.
    """

    translation_rows = (0, 1, 2)
    rotation_rows = (3, 4, 5)
    _cols = POSITION_COLS + ROTATION_COLS

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        base=None,
        tool=None,
        initial_base=None,
        initial_tool=None,
        sigma_t: float | None = None,
        sigma_r: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b, base, initial_base, sigma_t, sigma_r)
        if (sigma_t is None) != (sigma_r is None):
            raise LoopError(f"loop '{name}': give both sigma_t and sigma_r for a pose measurement, or neither")
        self.tool = None if tool is None else as_se3(tool, "tool")
        self.initial_tool = pin.SE3.Identity() if initial_tool is None else as_se3(initial_tool, "initial_tool")
        self._fit_tool = initial_tool is None  # initialize() estimates an unknown tool with no initial value
        self.measurement_cov = (
            None if sigma_t is None or sigma_r is None else np.diag(np.array([sigma_t**2] * 3 + [sigma_r**2] * 3))
        )

    @property
    def dim(self) -> int:
        return 6

    def parameters(self) -> list[Parameter]:
        out = []
        if self.base is None:
            out += pose_parameters(self.name, POSE_FIELDS, self.initial_base)
        if self.tool is None:
            out += pose_parameters(self.name, TOOL_FIELDS, self.initial_tool, order0=6)
        return out

    def tool_pose(self, p: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        k = self.n_base
        v = vec_of(self.tool) if self.tool is not None else p[k : k + 6]
        return pose_of(v), v

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """The unknown sensor base X and tool frame Y fitted to every configuration given.

        With W_i = T_B^-1 T_A at the nominal robot, W_i Y = X M_i.  When the
        tool is unknown and no ``initial_tool`` was given, both are estimated:
        the rotations from the null vector of R_Wi R_Y = R_X R_Mi (linear in
        vec(R_X), vec(R_Y), robot-world hand-eye), the translations by linear
        least squares, then a few Gauss-Newton steps on the loop residual.
        Otherwise the tool stays at its given value and X starts from the
        first configuration, X = W_1 Y M_1^-1, refined on all of them.
        """
        fit_tool = self.tool is None and self._fit_tool
        if self.base is not None and not fit_tool:
            return None
        N = TA.shape[0]
        meas = self._checked(meas, N)
        M = self._measured_poses(meas)
        W = [pin.SE3(TB[i]).actInv(pin.SE3(TA[i])) for i in range(N)]
        X = self.base if self.base is not None else None
        Y = self.tool if self.tool is not None else self.initial_tool
        if fit_tool and X is None and N >= 2:
            XY = hand_eye(W, M)
            if XY is not None:
                X, Y = XY
        if X is None:
            X = W[0] * Y * M[0].inverse()
        elif fit_tool and self.base is not None:
            Y = W[0].inverse() * X * M[0]
        p = np.concatenate(
            ([] if self.base is not None else [vec_of(X)]) + ([] if self.tool is not None else [vec_of(Y)])
        )
        free = np.arange(p.size) if fit_tool else np.arange(6)  # a given tool stays as given
        return _gauss_newton(self, TA, TB, p, free, meas)

    @staticmethod
    def _measured_poses(m: np.ndarray) -> list[pin.SE3]:
        return [pose_of(row) for row in m]

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = super().normalize(p)
        if self.tool is None:
            k = self.n_base
            out[k + 3 : k + 6] = pin.log3(pin.exp3(p[k + 3 : k + 6]))
        return out

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        N = TA.shape[0]
        Ms = self._measured_poses(self._checked(meas, N))
        X, xv = self.base_pose(p)
        Y, yv = self.tool_pose(p)
        Xinv = X.inverse()
        Yinv_act = Y.inverse().action
        r = np.empty((N, 6))
        dA = np.empty((N, 6, 6))
        dB = np.empty((N, 6, 6))
        dX = np.empty((N, 6, 6))
        dY = np.empty((N, 6, 6))
        for i in range(N):
            TBA = pin.SE3(TB[i]).actInv(pin.SE3(TA[i]))
            W = TBA * Y  # tool in B
            Z = Xinv * W  # tool in the sensor frame (the model's prediction of M_i)
            E = Ms[i].inverse() * Z
            r[i] = pin.log6(E).vector
            Jl = pin.Jlog6(E)
            dA[i] = Jl @ Yinv_act
            dB[i] = -Jl @ W.inverse().action
            dX[i] = -Jl @ Z.inverse().action
            dY[i] = Jl
        blocks = []
        if self.base is None:
            blocks.append(dX @ generators(xv))
        if self.tool is None:
            blocks.append(dY @ generators(yv))
        dp = np.concatenate(blocks, axis=2) if blocks else np.zeros((N, 6, 0))
        return LoopEval(r, dA, dB, dp)

    def describe(self) -> dict:
        return super().describe() | {"tool": "unknown" if self.tool is None else vec_of(self.tool).tolist()}


class MeasuredPointLoop(_Measured):
    """The measured tool point (3 equations per configuration, the position rows of 3.7).

    With m_i the measured position in the sensor frame, X = (R_X, t_X) the
    sensor base (``<loop>.x..rz``) and t the tip in frame A
    (``<loop>.tip_x/y/z``):

        r = X^-1 T_B^-1 T_A t - m_i = R_X^T (y - t_X) - m_i,   y = T_B^-1 T_A t

    (3 rows, m, sensor frame).  With z = X^-1 y and point.relative_point:

        dr/d(delta_A) = R_X^T R_BA [I  -[t]x],   dr/d(delta_B) = R_X^T [-I  [y]x],
        dr/dt = R_X^T R_BA,                      dr/d(delta_X) = [-I  [z]x].

    sigma_t (m) gives measurement_cov = sigma_t^2 I3.
    """

    translation_rows = (0, 1, 2)
    rotation_rows = ()
    _cols = POSITION_COLS

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        base=None,
        tip=None,
        initial_base=None,
        initial_tip=None,
        sigma_t: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b, base, initial_base, sigma_t, None)
        self.tip = None if tip is None else vec3(tip, "tip")
        self.initial_tip = np.zeros(3) if initial_tip is None else vec3(initial_tip, "initial_tip")
        self._fit_tip = initial_tip is None  # initialize() estimates an unknown tip with no initial value
        self.measurement_cov = None if sigma_t is None else sigma_t**2 * np.eye(3)

    @property
    def dim(self) -> int:
        return 3

    def parameters(self) -> list[Parameter]:
        out = []
        if self.base is None:
            out += pose_parameters(self.name, POSE_FIELDS, self.initial_base)
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, self.initial_tip, order0=6)
        return out

    def tip_point(self, p: np.ndarray) -> np.ndarray:
        k = self.n_base
        return self.tip if self.tip is not None else p[k : k + 3]

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """The unknown sensor base and tool point fitted to every configuration given.

        With the robot held at the configurations given, m_i = X^-1 T_i t
        (T_i = T_B^-1 T_A).  The base: the rigid fit T_i t = R_X m_i + t_X
        (Kabsch / Horn) of the measured points to the current tip positions;
        fewer than three non-collinear points: the initial base rotation,
        translated so that the first point matches.  When the tip is unknown
        and no ``initial_tip`` was given, it is estimated as well (so that
        identifiability is not decided with the tip at the frame origin, which
        may lie on a joint axis): alternately the linear least squares
        R_i t - t_X = R_X m_i - p_i (for t and t_X) and the rigid fit, then a
        few Gauss-Newton steps on (X, t).  Otherwise the tip stays at its
        given value.
        """
        fit_tip = self.tip is None and self._fit_tip
        if self.base is not None and not fit_tip:
            return None
        N = TA.shape[0]
        m = self._checked(meas, N)
        tip = self.tip if self.tip is not None else self.initial_tip
        p0, RBA, *_ = relative_point(TA, TB, np.zeros(3))
        if self.base is not None:
            R, t = self.base.rotation, self.base.translation
        else:
            R, t = kabsch(m, p0 + RBA @ tip, self.initial_base.rotation)
        if fit_tip and N >= 3:
            I3 = np.broadcast_to(np.eye(3), (N, 3, 3))
            for _ in range(3):
                # linear in (tip, t_X) given R_X: R_i tip - t_X = R_X m_i - p_i (min-norm change)
                A = (np.concatenate([RBA, -I3], axis=2) if self.base is None else RBA).reshape(3 * N, -1)
                x = np.concatenate([tip, t]) if self.base is None else tip
                b = (m @ R.T - p0 + (0.0 if self.base is None else t)).reshape(-1)
                dx, *_ = np.linalg.lstsq(A, b - A @ x, rcond=1e-9)
                if not np.all(np.isfinite(dx)):
                    break
                tip = tip + dx[:3]
                if self.base is None:
                    R, t = kabsch(m, p0 + RBA @ tip, R)
        p = np.concatenate(
            ([] if self.base is not None else [vec_of(pin.SE3(R, t))]) + ([] if self.tip is not None else [tip])
        )
        if fit_tip and N >= 3:
            p = _gauss_newton(self, TA, TB, p, np.arange(p.size), m)
        return p

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        N = TA.shape[0]
        m = self._checked(meas, N)
        X, xv = self.base_pose(p)
        tip = self.tip_point(p)
        y, RBA, dyA, dyB = relative_point(TA, TB, tip)
        RXt = X.rotation.T
        z = (y - X.translation) @ X.rotation  # rows: R_X^T (y - t_X)
        r = z - m
        dA = RXt @ dyA
        dB = RXt @ dyB
        blocks = []
        if self.base is None:
            dX = np.empty((N, 3, 6))
            dX[:, :, :3] = -np.eye(3)
            dX[:, :, 3:] = skew(z)
            blocks.append(dX @ generators(xv))
        if self.tip is None:
            blocks.append(RXt @ RBA)
        dp = np.concatenate(blocks, axis=2) if blocks else np.zeros((N, 3, 0))
        return LoopEval(r, dA, dB, dp)

    def describe(self) -> dict:
        return super().describe() | {"tip": "unknown" if self.tip is None else self.tip.tolist()}


@register("measured_pose", {"frame", "to", "base", "base0", "tool", "sigma_t", "sigma_r"})
def _measured_pose(kw: dict[str, str], robot: RobotModel) -> Loop:
    """measured_pose:frame=tool[,to=frame_b][,base=|base0="x y z rx ry rz"][,tool=...][,sigma_t=m,sigma_r=rad].

    base: the known sensor pose; base0: only a starting guess of an unknown one.
    """
    if "frame" not in kw:
        raise LoopError("measured_pose loop needs frame=<tool frame>")
    return MeasuredPoseLoop(
        kw.get("name", "measured_pose"),
        kw["frame"],
        kw.get("to", "universe"),
        base=opt_pose(kw, "base"),
        tool=opt_pose(kw, "tool"),
        initial_base=opt_pose(kw, "base0"),
        sigma_t=opt_float(kw, "sigma_t"),
        sigma_r=opt_float(kw, "sigma_r"),
    )


@register("measured_point", {"frame", "to", "base", "base0", "tip", "sigma_t"})
def _measured_point(kw: dict[str, str], robot: RobotModel) -> Loop:
    """measured_point:frame=tool[,to=frame_b][,base=|base0="x y z rx ry rz"][,tip="x y z"][,sigma_t=m]."""
    if "frame" not in kw:
        raise LoopError("measured_point loop needs frame=<tool frame>")
    tip = parse_vec(kw["tip"], 3, "tip") if kw.get("tip", "unknown") != "unknown" else None
    return MeasuredPointLoop(
        kw.get("name", "measured_point"),
        kw["frame"],
        kw.get("to", "universe"),
        base=opt_pose(kw, "base"),
        tip=tip,
        initial_base=opt_pose(kw, "base0"),
        sigma_t=opt_float(kw, "sigma_t"),
    )
