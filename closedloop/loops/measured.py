"""Open-loop calibration as a loop: an external sensor measures the tool (thesis 3.2).

A tracker, camera or CMM measures, at every configuration, the pose (or only
the position) of a tool in the sensor's own frame S.  The sensor frame is
placed in frame B (normally the robot base / universe) by an unknown pose
X = T_BS, and the tool by an unknown pose Y = T_A,tool (or only a tip point t).
The chain base -> robot -> tool -> sensor -> base is then a loop whose one
"joint" is the measurement, so the open-loop method of 3.2 (eqs. 3.4-3.12)
is the special case of a loop that measures its own closure.

Measurements come from extra log columns (``bind``), one row per
configuration, named after the loop:

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

from ..errors import LoopError
from ..parameters import DEFAULT_PRIORS, Parameter
from ..robot import RobotModel
from .common import refine_own
from .base import Loop, LoopEval
from .point import TIP_FIELDS, _vec3, parse_vec, point_parameters, relative_point, skew
from .spec import register

POSE_FIELDS = ("x", "y", "z", "rx", "ry", "rz")
TOOL_FIELDS = tuple(f"tool_{f}" for f in POSE_FIELDS)
POSITION_COLS = ("x", "y", "z")
ROTATION_COLS = ("rx", "ry", "rz")


def pose_parameters(loop: str, fields: tuple[str, ...], X: pin.SE3, order0: int = 0) -> list[Parameter]:
    vals = np.concatenate([X.translation, pin.log3(X.rotation)])
    out = []
    for k, f in enumerate(fields):
        unit = "m" if k < 3 else "rad"
        out.append(Parameter(f"{loop}.{f}", "loop", loop, f, float(vals[k]), unit,
                             DEFAULT_PRIORS["loop_m" if k < 3 else "loop_rad"],
                             scales_with_length=float(vals[k]) if k < 3 else 0.0, priority=1, order=order0 + k))
    return out


def pose_of(v: np.ndarray) -> pin.SE3:
    """(x, y, z, rx, ry, rz) -> SE3 (translation, rotation vector)."""
    return pin.SE3(pin.exp3(v[3:6]), np.asarray(v[0:3], dtype=float).copy())


def vec_of(X: pin.SE3) -> np.ndarray:
    return np.concatenate([X.translation, pin.log3(X.rotation)])


def generators(v: np.ndarray) -> np.ndarray:
    """d delta / d v for X = pose_of(v) under right perturbations (as in WeldLoop)."""
    g = np.zeros((6, 6))
    g[:3, :3] = pin.exp3(v[3:6]).T
    g[3:, 3:] = pin.Jexp3(v[3:6])
    return g


def _as_se3(X, what: str) -> pin.SE3:
    if isinstance(X, pin.SE3):
        return X
    a = np.asarray(X, dtype=float)
    if a.shape == (4, 4):
        return pin.SE3(a)
    a = a.reshape(-1)
    if a.size != 6 or not np.all(np.isfinite(a)):
        raise LoopError(f"{what}: expected an SE3, a 4x4 matrix or six numbers 'x y z rx ry rz'")
    return pose_of(a)


def _kabsch(m: np.ndarray, y: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid fit y_i ~ R m_i + t (Kabsch / Horn); R0 when the points are (nearly) collinear."""
    R = R0
    if m.shape[0] >= 3:
        cy, cm = y.mean(axis=0), m.mean(axis=0)
        H = (m - cm).T @ (y - cy)
        U, S, Vt = np.linalg.svd(H)
        if S[1] > 1e-9 * max(S[0], 1e-300):
            D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
            R = Vt.T @ D @ U.T
        return R, cy - R @ cm
    return R, y[0] - R @ m[0]


def _project_so3(A: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(A)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def _gauss_newton(loop: Loop, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, free: np.ndarray,
                  iters: int = 30) -> np.ndarray:
    """Refine the loop's own parameters ``p[free]`` with the robot held (TA, TB fixed); `common.refine_own`."""
    if loop.meas is None or loop.meas.shape[0] != TA.shape[0]:
        return p  # evaluate() needs one measurement per configuration given
    return refine_own(lambda q: loop.evaluate(TA, TB, q), lambda q: loop.evaluate(TA, TB, q).r, loop.normalize,
                      p, free, iters)


class _Measured(Loop):
    """Shared parts: the sensor base X, the measurement columns, the noise."""

    scale_free = False
    _cols: tuple[str, ...] = POSITION_COLS

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe", base=None, initial_base=None,
                 sigma_t: float | None = None, sigma_r: float | None = None):
        super().__init__(name, frame_a, frame_b)
        self.base = None if base is None else _as_se3(base, "base")
        self.initial_base = pin.SE3.Identity() if initial_base is None else _as_se3(initial_base, "initial_base")
        self.sigma_t = sigma_t
        self.sigma_r = sigma_r
        self.meas: np.ndarray | None = None  # (N, len(_cols))
        for s, what in ((sigma_t, "sigma_t"), (sigma_r, "sigma_r")):
            if s is not None and not (np.isfinite(s) and s > 0):
                raise LoopError(f"loop '{name}': {what} must be positive and finite")

    @property
    def n_base(self) -> int:
        return 0 if self.base is not None else 6

    def columns(self) -> list[str]:
        return [f"{self.name}:{c}" for c in self._cols]

    def bind(self, extra: dict[str, np.ndarray]) -> None:
        missing = [c for c in self.columns() if c not in extra]
        if missing:
            raise LoopError(f"loop '{self.name}': the log has no measurement column(s) {', '.join(missing)}")
        M = np.column_stack([np.asarray(extra[c], dtype=float) for c in self.columns()])
        bad = np.flatnonzero(~np.all(np.isfinite(M), axis=1))
        if bad.size:
            raise LoopError(f"loop '{self.name}': measurement missing or not a number in row(s) "
                            f"{', '.join(str(b + 1) for b in bad[:5])} of this loop")
        self.meas = M

    def _measurements(self, N: int) -> np.ndarray:
        if self.meas is None:
            raise LoopError(f"loop '{self.name}': no measurements bound (log columns {', '.join(self.columns())})")
        if self.meas.shape[0] != N:
            raise LoopError(f"loop '{self.name}': {N} configurations but {self.meas.shape[0]} measurements")
        return self.meas

    def base_pose(self, p: np.ndarray) -> tuple[pin.SE3, np.ndarray]:
        v = vec_of(self.base) if self.base is not None else p[:6]
        return pose_of(v), v

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = p.copy()
        if self.base is None:
            out[3:6] = pin.log3(pin.exp3(p[3:6]))
        return out

    def describe(self) -> dict:
        return super().describe() | {"base": "unknown" if self.base is None else vec_of(self.base).tolist(),
                                     "columns": self.columns()}


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

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe", base=None, tool=None,
                 initial_base=None, initial_tool=None, sigma_t: float | None = None, sigma_r: float | None = None):
        super().__init__(name, frame_a, frame_b, base, initial_base, sigma_t, sigma_r)
        if (sigma_t is None) != (sigma_r is None):
            raise LoopError(f"loop '{name}': give both sigma_t and sigma_r for a pose measurement, or neither")
        self.tool = None if tool is None else _as_se3(tool, "tool")
        self.initial_tool = pin.SE3.Identity() if initial_tool is None else _as_se3(initial_tool, "initial_tool")
        self._fit_tool = initial_tool is None  # initialize() estimates an unknown tool with no initial value
        self.measurement_cov = (None if sigma_t is None else
                                np.diag([sigma_t ** 2] * 3 + [sigma_r ** 2] * 3))

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
        v = vec_of(self.tool) if self.tool is not None else p[k:k + 6]
        return pose_of(v), v

    def initialize(self, TA: np.ndarray, TB: np.ndarray) -> np.ndarray | None:
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
        M = self._measured_poses(self.meas[:N] if self.meas is not None else self._measurements(N))
        W = [pin.SE3(TB[i]).actInv(pin.SE3(TA[i])) for i in range(N)]
        X = self.base if self.base is not None else None
        Y = self.tool if self.tool is not None else self.initial_tool
        if fit_tool and X is None and N >= 2:
            XY = self._hand_eye(W, M)
            if XY is not None:
                X, Y = XY
        if X is None:
            X = W[0] * Y * M[0].inverse()
        elif fit_tool and self.base is not None:
            Y = W[0].inverse() * X * M[0]
        p = np.concatenate(([] if self.base is not None else [vec_of(X)])
                           + ([] if self.tool is not None else [vec_of(Y)]))
        free = np.arange(p.size) if fit_tool else np.arange(6)  # a given tool stays as given
        return _gauss_newton(self, TA, TB, p, free)

    @staticmethod
    def _hand_eye(W: list[pin.SE3], M: list[pin.SE3]) -> tuple[pin.SE3, pin.SE3] | None:
        """Closed-form X, Y of W_i Y = X M_i (None when the rotations do not determine them)."""
        I3 = np.eye(3)
        A = np.concatenate([np.hstack([np.kron(I3, w.rotation), -np.kron(m.rotation.T, I3)])
                            for w, m in zip(W, M)])
        _, S, Vt = np.linalg.svd(A)
        if not S[-2] > 1e-6 * S[0]:
            return None
        v = Vt[-1]
        RY, RX = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
        if np.linalg.det(RY) < 0:
            RY, RX = -RY, -RX
        RY, RX = _project_so3(RY), _project_so3(RX)
        # translations: R_Wi t_Y - t_X = R_X t_Mi - t_Wi
        B = np.concatenate([np.hstack([w.rotation, -I3]) for w in W])
        b = np.concatenate([RX @ m.translation - w.translation for w, m in zip(W, M)])
        t, *_ = np.linalg.lstsq(B, b, rcond=1e-9)
        if not np.all(np.isfinite(t)):
            return None
        return pin.SE3(RX, t[3:]), pin.SE3(RY, t[:3])

    @staticmethod
    def _measured_poses(m: np.ndarray) -> list[pin.SE3]:
        return [pose_of(row) for row in m]

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = super().normalize(p)
        if self.tool is None:
            k = self.n_base
            out[k + 3:k + 6] = pin.log3(pin.exp3(p[k + 3:k + 6]))
        return out

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
        N = TA.shape[0]
        Ms = self._measured_poses(self._measurements(N))
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

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe", base=None, tip=None,
                 initial_base=None, initial_tip=None, sigma_t: float | None = None):
        super().__init__(name, frame_a, frame_b, base, initial_base, sigma_t, None)
        self.tip = None if tip is None else _vec3(tip, "tip")
        self.initial_tip = np.zeros(3) if initial_tip is None else _vec3(initial_tip, "initial_tip")
        self._fit_tip = initial_tip is None  # initialize() estimates an unknown tip with no initial value
        self.measurement_cov = None if sigma_t is None else sigma_t ** 2 * np.eye(3)

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
        return self.tip if self.tip is not None else p[k:k + 3]

    def initialize(self, TA: np.ndarray, TB: np.ndarray) -> np.ndarray | None:
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
        m = (self.meas[:N] if self.meas is not None else self._measurements(N))
        tip = self.tip if self.tip is not None else self.initial_tip
        p0, RBA, *_ = relative_point(TA, TB, np.zeros(3))
        if self.base is not None:
            R, t = self.base.rotation, self.base.translation
        else:
            R, t = _kabsch(m, p0 + RBA @ tip, self.initial_base.rotation)
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
                    R, t = _kabsch(m, p0 + RBA @ tip, R)
        p = np.concatenate(([] if self.base is not None else [vec_of(pin.SE3(R, t))])
                           + ([] if self.tip is not None else [tip]))
        if fit_tip and N >= 3:
            p = _gauss_newton(self, TA, TB, p, np.arange(p.size))
        return p

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
        N = TA.shape[0]
        m = self._measurements(N)
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


def _opt_float(kw: dict[str, str], key: str) -> float | None:
    if key not in kw:
        return None
    try:
        return float(kw[key])
    except ValueError:
        raise LoopError(f"{key}='{kw[key]}' is not a number") from None


def _opt_pose(kw: dict[str, str], key: str) -> pin.SE3 | None:
    if kw.get(key, "unknown") == "unknown":
        return None
    if kw[key] == "identity":
        return pin.SE3.Identity()
    return pose_of(parse_vec(kw[key], 6, key))


@register("measured_pose", {"frame", "to", "base", "base0", "tool", "sigma_t", "sigma_r"})
def _measured_pose(kw: dict[str, str], robot: RobotModel) -> Loop:
    """measured_pose:frame=tool[,to=frame_b][,base=|base0="x y z rx ry rz"][,tool=...][,sigma_t=m,sigma_r=rad].

    base: the known sensor pose; base0: only a starting guess of an unknown one.
    """
    if "frame" not in kw:
        raise LoopError("measured_pose loop needs frame=<tool frame>")
    return MeasuredPoseLoop(kw.get("name", "measured_pose"), kw["frame"], kw.get("to", "universe"),
                            base=_opt_pose(kw, "base"), tool=_opt_pose(kw, "tool"),
                            initial_base=_opt_pose(kw, "base0"),
                            sigma_t=_opt_float(kw, "sigma_t"), sigma_r=_opt_float(kw, "sigma_r"))


@register("measured_point", {"frame", "to", "base", "base0", "tip", "sigma_t"})
def _measured_point(kw: dict[str, str], robot: RobotModel) -> Loop:
    """measured_point:frame=tool[,to=frame_b][,base=|base0="x y z rx ry rz"][,tip="x y z"][,sigma_t=m]."""
    if "frame" not in kw:
        raise LoopError("measured_point loop needs frame=<tool frame>")
    tip = parse_vec(kw["tip"], 3, "tip") if kw.get("tip", "unknown") != "unknown" else None
    return MeasuredPointLoop(kw.get("name", "measured_point"), kw["frame"], kw.get("to", "universe"),
                             base=_opt_pose(kw, "base"), tip=tip, initial_base=_opt_pose(kw, "base0"),
                             sigma_t=_opt_float(kw, "sigma_t"))
