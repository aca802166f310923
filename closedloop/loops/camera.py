"""The camera loop: a marker on the tool seen by one or two pinhole cameras (thesis 3.2, 5.2-5.4).

A marker at an unknown point t of frame A (the tool) is imaged by one camera,
or by a stereo pair, rigidly attached to frame B (the world by default, or a
robot frame such as a head).  As with the measured loops (``measured.py``),
the open-loop measurement equations of 3.2 (eq. 3.4: measured = model) become
a loop whose "joint" is the measurement; here the measurement is the image
point itself, so the residual is the image-plane error, the first of the two
formulations discussed in 5.1 (5.2.2: pinhole model, eqs. 5.3-5.4, with the
image offsets as the principal point).

Measurements come from log columns, one row per configuration:

    <loop>:u1, <loop>:v1     pixel coordinates in camera 1
    <loop>:u2, <loop>:v2     pixel coordinates in camera 2 (stereo pair)

Identifiability (5.4, eq. 5.27): the pinhole projection is invariant under
p -> s p, so scaling every length (robot, camera positions, marker) leaves
every pixel unchanged.  This holds for one camera or a stereo pair, with known
or unknown intrinsics, as long as the camera positions are unknown; only a
known baseline (``rig``: the pose of camera 2 in camera 1) or a known camera
position fixes the length scale.  The loop therefore says ``scale_free`` unless
one of those is given, and the core's length-gauge test decides on the data
(it fixes one robot length when the gauge is there).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pinocchio as pin
from scipy.linalg import rq

from ..errors import LoopError
from ..parameters import Parameter
from ..robot import RobotModel
from .base import Loop, LoopEval
from .measured import (POSE_FIELDS, _as_se3, _gauss_newton, _opt_float, generators, pose_of, pose_parameters,
                       vec_of)
from .point import TIP_FIELDS, _vec3, parse_vec, point_parameters, relative_point, skew
from .spec import register

INTRINSIC_FIELDS = ("fx", "fy", "cx", "cy")
PIXEL_COLS = ("u", "v")
DEFAULT_PRIOR_PX = 100.0  # expected error of an intrinsics guess (px): column scaling, data identifiability
PLACEHOLDER_K = np.array([1000.0, 1000.0, 0.0, 0.0])  # unknown intrinsics with no guess: replaced by the DLT


def project(pc: np.ndarray, k: np.ndarray, jacobian: bool = True):
    """Pinhole projection of camera-frame points and its Jacobians.

    uv = (fx px/pz + cx, fy py/pz + cy) for pc (N, 3), k = (fx, fy, cx, cy):

        d uv / d pc = [[fx/pz, 0, -fx px/pz^2], [0, fy/pz, -fy py/pz^2]]     (N, 2, 3)
        d uv / d k  = [[px/pz, 0, 1, 0], [0, py/pz, 0, 1]]                   (N, 2, 4)
    """
    iz = 1.0 / pc[:, 2]
    xn, yn = pc[:, 0] * iz, pc[:, 1] * iz
    uv = np.column_stack([k[0] * xn + k[2], k[1] * yn + k[3]])
    if not jacobian:
        return uv, None, None
    N = pc.shape[0]
    Jp = np.zeros((N, 2, 3))
    Jp[:, 0, 0] = k[0] * iz
    Jp[:, 0, 2] = -k[0] * xn * iz
    Jp[:, 1, 1] = k[1] * iz
    Jp[:, 1, 2] = -k[1] * yn * iz
    Jk = np.zeros((N, 2, 4))
    Jk[:, 0, 0], Jk[:, 1, 1] = xn, yn
    Jk[:, 0, 2] = Jk[:, 1, 3] = 1.0
    return uv, Jp, Jk


# --------------------------------------------------------------------------- linear start (DLT / PnP)
def dlt(Y: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """The 3x4 projection matrix P (uv ~ P [Y; 1]) by the normalised DLT; None when degenerate.

    Hartley normalisation of both point sets, the null vector of the 2N x 12
    system [Y^T 1 0 -u (Y^T 1); 0 Y^T 1 -v (Y^T 1)] p = 0, denormalised.
    Needs six or more points, not coplanar (a plane leaves a family of P).
    """
    N = Y.shape[0]
    if N < 6:
        return None
    cY, cu = Y.mean(axis=0), uv.mean(axis=0)
    dY = np.linalg.norm(Y - cY, axis=1).mean()
    du = np.linalg.norm(uv - cu, axis=1).mean()
    if not (dY > 0 and du > 0):
        return None
    sY, su = np.sqrt(3.0) / dY, np.sqrt(2.0) / du
    Yh = np.column_stack([(Y - cY) * sY, np.ones(N)])
    un = (uv - cu) * su
    A = np.zeros((2 * N, 12))
    A[0::2, 0:4] = Yh
    A[0::2, 8:12] = -un[:, :1] * Yh
    A[1::2, 4:8] = Yh
    A[1::2, 8:12] = -un[:, 1:] * Yh
    _, S, Vt = np.linalg.svd(A, full_matrices=False)
    if not S[-2] > 1e-9 * S[0]:
        return None
    T2inv = np.array([[1 / su, 0, cu[0]], [0, 1 / su, cu[1]], [0, 0, 1]])
    T3 = np.diag([sY, sY, sY, 1.0])
    T3[:3, 3] = -sY * cY
    return T2inv @ Vt[-1].reshape(3, 4) @ T3


def camera_from_dlt(Y: np.ndarray, uv: np.ndarray, k: np.ndarray | None) -> tuple[pin.SE3, np.ndarray] | None:
    """Camera pose in the points' frame (and intrinsics) from the DLT; None when it fails.

    Unknown intrinsics (k None): P = K [R | t] by RQ decomposition of P's left
    block (det > 0, positive diagonal, zero skew dropped).  Known intrinsics
    (linear PnP): A = K^-1 P, R the nearest rotation to its left block, the
    scale the mean of its singular values.  The camera pose in the points'
    frame is X = (R^T, -R^T t); the fit must put the points in front (pz > 0).
    """
    P = dlt(Y, uv)
    if P is None or not np.all(np.isfinite(P)):
        return None
    if k is None:
        if np.linalg.det(P[:, :3]) < 0:
            P = -P
        Kr, R = rq(P[:, :3])
        D = np.diag(np.sign(np.diag(Kr)))
        Kr, R = Kr @ D, D @ R
        t = np.linalg.solve(Kr, P[:, 3])
        Kn = Kr / Kr[2, 2]
        k = np.array([Kn[0, 0], Kn[1, 1], Kn[0, 2], Kn[1, 2]])
    else:
        K = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
        A = np.linalg.solve(K, P)
        if np.linalg.det(A[:, :3]) < 0:
            A = -A
        U, S, Vt = np.linalg.svd(A[:, :3])
        R = U @ Vt
        t = A[:, 3] / S.mean()
    depth = Y @ R[2] + t[2]
    if np.mean(depth > 0) < 0.5 or not (np.all(np.isfinite(k)) and k[0] > 0 and k[1] > 0):
        return None
    return pin.SE3(R.T, -R.T @ t), np.asarray(k, dtype=float)


# --------------------------------------------------------------------------- the loop
class CameraLoop(Loop):
    """Image points of a tool marker in one or two pinhole cameras (2 or 4 rows, pixels).

    With t the marker in frame A (``<loop>.tip_x/y/z``), y = T_B^-1 T_A t its
    position in B, X_c = (R_c, t_c) the pose of camera c in B
    (``<loop>.cam<c>.x..rz``: translation, rotation vector) and
    k_c = (fx, fy, cx, cy) its intrinsics (``<loop>.cam<c>.fx..cy``):

        p_c = X_c^-1 y = R_c^T (y - t_c)
        r_c = pi(k_c, p_c) - (u_c, v_c),   pi(k, p) = (fx px/pz + cx, fy py/pz + cy)

    exact (no small-angle form).  With Jpi = d pi / d p (``project``) and
    point.relative_point:

        dr_c/d(delta_A) = Jpi R_c^T R_BA [I  -[t]x]      dr_c/d(delta_B) = Jpi R_c^T [-I  [y]x]
        dr_c/d t        = Jpi R_c^T R_BA                 dr_c/d(delta_Xc) = Jpi [-I  [p_c]x]
        dr_c/d k_c      = [[px/pz, 0, 1, 0], [0, py/pz, 0, 1]]

    and the pose parameters map to delta_Xc as in the measured loops
    (translation R_c^T dt, rotation vector Jexp3(r) dr).  With a known rig
    (camera 2 at the fixed pose G in camera 1, X_2 = X_1 G) camera 2's rows
    depend on camera 1's pose: dr_2/d(delta_X1) = Jpi [-I [p_2]x] Ad(G^-1).

    Known quantities are fixed: ``K`` (per camera, intrinsics or None),
    ``poses`` (per camera, a known pose in B or None), ``tip``.  Unknown ones
    start from ``initial_K`` / ``initial_poses`` / ``initial_tip`` and from
    the data (``initialize``).  ``sigma_px`` (pixels) gives
    measurement_cov = sigma_px^2 I.

    Residual rows are pixels, neither metres nor radians, so
    translation_rows = rotation_rows = (); ``pixel_rows`` makes the report
    give the per-image-point error in pixels (``residual_stats``: rms_px, max_px).
    """

    translation_rows: tuple[int, ...] = ()
    rotation_rows: tuple[int, ...] = ()

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe", cameras: int = 1,
                 K: Sequence | None = None, initial_K: Sequence | None = None,
                 poses: Sequence | None = None, initial_poses: Sequence | None = None, rig=None,
                 tip=None, initial_tip=None, sigma_px: float | None = None, prior_px: float = DEFAULT_PRIOR_PX):
        super().__init__(name, frame_a, frame_b)
        if cameras not in (1, 2):
            raise LoopError(f"camera loop '{name}': cameras={cameras!r}: expected 1 or 2")
        self.cameras = cameras
        # labels as in the spec: K1 (known intrinsics of camera 1), K1_0 (a guess), pose1 (a guess)
        self.K = self._per_camera(K, "K{}", lambda v, w: _intrinsics(v, f"camera loop '{name}': {w}"))
        self.initial_K = self._per_camera(initial_K, "K{}_0",
                                          lambda v, w: _intrinsics(v, f"camera loop '{name}': {w}"))
        self.poses = self._per_camera(poses, "known pose{}", lambda v, w: _se3(v, name, w))
        self.initial_poses = self._per_camera(initial_poses, "pose{}", lambda v, w: _se3(v, name, w))
        for c in range(cameras):
            if self.K[c] is not None and self.initial_K[c] is not None:
                raise LoopError(f"camera loop '{name}': camera {c + 1} has known intrinsics and a guess; give one")
            if self.poses[c] is not None and self.initial_poses[c] is not None:
                raise LoopError(f"camera loop '{name}': camera {c + 1} has a known pose and a guess; give one")
        self.rig = None if rig is None else _se3(rig, name, "rig")
        if self.rig is not None:
            if cameras != 2:
                raise LoopError(f"camera loop '{name}': rig (camera 2 in camera 1) needs cameras=2")
            if self.poses[1] is not None or self.initial_poses[1] is not None:
                raise LoopError(f"camera loop '{name}': with a rig, camera 2's pose follows camera 1's; "
                                "give no pose for camera 2")
        self.tip = None if tip is None else _vec3(tip, f"camera loop '{name}': tip")
        self.initial_tip = np.zeros(3) if initial_tip is None else _vec3(initial_tip,
                                                                          f"camera loop '{name}': initial_tip")
        self._fit_tip = initial_tip is None  # initialize() estimates an unknown tip with no initial value
        for s, what in ((sigma_px, "sigma_px"), (prior_px, "prior_px")):
            if s is not None and not (np.isfinite(s) and s > 0):
                raise LoopError(f"camera loop '{name}': {what}={s!r} must be positive and finite")
        self.sigma_px = sigma_px
        self.prior_px = prior_px
        self.measurement_cov = None if sigma_px is None else sigma_px ** 2 * np.eye(2 * cameras)
        self.pixel_rows = tuple(range(2 * cameras))
        # the length scale is fixed only by a known baseline or a known camera position
        known_t = [X.translation for X in self.poses if X is not None]
        if self.rig is not None:
            known_t.append(self.rig.translation)
        self.scale_free = not any(np.linalg.norm(t) > 0 for t in known_t)
        self.meas: np.ndarray | None = None  # (N, 2 * cameras)
        self._layout()

    def _per_camera(self, v, what: str, conv) -> list:
        if v is None:
            return [None] * self.cameras
        v = list(v)
        if len(v) != self.cameras:
            raise LoopError(f"camera loop '{self.name}': {what.format('')} has {len(v)} entries for "
                            f"{self.cameras} camera(s)")
        return [None if x is None else conv(x, what.format(c + 1)) for c, x in enumerate(v)]

    def _layout(self) -> None:
        """Slices of the own parameter vector: pose c, intrinsics c, tip (only the unknown ones)."""
        self.sl: dict[str, slice | None] = {}
        k = 0
        for c in range(self.cameras):
            unknown = self.poses[c] is None and not (c == 1 and self.rig is not None)
            self.sl[f"pose{c}"] = slice(k, k + 6) if unknown else None
            k += 6 if unknown else 0
        for c in range(self.cameras):
            self.sl[f"K{c}"] = slice(k, k + 4) if self.K[c] is None else None
            k += 4 if self.K[c] is None else 0
        self.sl["tip"] = slice(k, k + 3) if self.tip is None else None
        self.n_own = k + (3 if self.tip is None else 0)

    @property
    def dim(self) -> int:
        return 2 * self.cameras

    def columns(self) -> list[str]:
        return [f"{self.name}:{a}{c + 1}" for c in range(self.cameras) for a in PIXEL_COLS]

    def parameters(self) -> list[Parameter]:
        out: list[Parameter] = []
        for c in range(self.cameras):
            if self.sl[f"pose{c}"] is not None:
                X = self.initial_poses[c] if self.initial_poses[c] is not None else pin.SE3.Identity()
                out += pose_parameters(self.name, tuple(f"cam{c + 1}.{f}" for f in POSE_FIELDS), X, order0=len(out))
        for c in range(self.cameras):
            if self.sl[f"K{c}"] is not None:
                k0 = self.initial_K[c] if self.initial_K[c] is not None else PLACEHOLDER_K
                out += [Parameter(f"{self.name}.cam{c + 1}.{f}", "loop", self.name, f"cam{c + 1}.{f}",
                                  float(k0[i]), "px", self.prior_px, priority=1, order=len(out) + i)
                        for i, f in enumerate(INTRINSIC_FIELDS)]
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, self.initial_tip, order0=len(out))
        return out

    # ------------------------------------------------------------- measurements
    def bind(self, extra: dict[str, np.ndarray]) -> None:
        missing = [c for c in self.columns() if c not in extra]
        if missing:
            raise LoopError(f"camera loop '{self.name}': the log has no pixel column(s) {', '.join(missing)}")
        M = np.column_stack([np.asarray(extra[c], dtype=float) for c in self.columns()])
        bad = np.flatnonzero(~np.all(np.isfinite(M), axis=1))
        if bad.size:
            raise LoopError(f"camera loop '{self.name}': pixel coordinates missing or not a number in row(s) "
                            f"{', '.join(str(b + 1) for b in bad[:5])} of this loop")
        self.meas = M

    def _measurements(self, N: int) -> np.ndarray:
        if self.meas is None:
            raise LoopError(f"camera loop '{self.name}': no pixels bound (log columns {', '.join(self.columns())})")
        if self.meas.shape[0] != N:
            raise LoopError(f"camera loop '{self.name}': {N} configurations but {self.meas.shape[0]} pixel rows")
        return self.meas

    # ------------------------------------------------------------- parameters
    def camera_pose(self, p: np.ndarray, c: int) -> pin.SE3:
        """X_c, the pose of camera c (0-based) in frame B."""
        if c == 1 and self.rig is not None:
            return self.camera_pose(p, 0) * self.rig
        sl = self.sl[f"pose{c}"]
        return self.poses[c] if sl is None else pose_of(p[sl])

    def intrinsics(self, p: np.ndarray, c: int) -> np.ndarray:
        sl = self.sl[f"K{c}"]
        return self.K[c] if sl is None else p[sl]

    def tip_point(self, p: np.ndarray) -> np.ndarray:
        return self.tip if self.tip is not None else p[self.sl["tip"]]

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = p.copy()
        for c in range(self.cameras):
            sl = self.sl[f"pose{c}"]
            if sl is not None:
                out[sl.start + 3:sl.stop] = pin.log3(pin.exp3(p[sl.start + 3:sl.stop]))
        return out

    # ------------------------------------------------------------- residual
    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> np.ndarray:
        m = self._measurements(TA.shape[0])
        y, *_ = relative_point(TA, TB, self.tip_point(p))
        r = np.empty((TA.shape[0], self.dim))
        for c in range(self.cameras):
            X = self.camera_pose(p, c)
            uv, _, _ = project((y - X.translation) @ X.rotation, self.intrinsics(p, c), jacobian=False)
            r[:, 2 * c:2 * c + 2] = uv - m[:, 2 * c:2 * c + 2]
        return r

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
        N = TA.shape[0]
        m = self._measurements(N)
        y, RBA, dyA, dyB = relative_point(TA, TB, self.tip_point(p))
        r = np.empty((N, self.dim))
        dA = np.empty((N, self.dim, 6))
        dB = np.empty((N, self.dim, 6))
        dp = np.zeros((N, self.dim, self.n_own))
        for c in range(self.cameras):
            rows = slice(2 * c, 2 * c + 2)
            X = self.camera_pose(p, c)
            pc = (y - X.translation) @ X.rotation  # rows: R_c^T (y - t_c)
            uv, Jp, Jk = project(pc, self.intrinsics(p, c))
            r[:, rows] = uv - m[:, rows]
            JpR = Jp @ X.rotation.T  # d uv / d y
            dA[:, rows] = JpR @ dyA
            dB[:, rows] = JpR @ dyB
            dX = np.empty((N, 2, 6))  # d uv / d(delta_Xc)
            dX[:, :, :3] = -Jp
            dX[:, :, 3:] = Jp @ skew(pc)
            if c == 1 and self.rig is not None:
                dX, owner = dX @ self.rig.inverse().action, self.sl["pose0"]
            else:
                owner = self.sl[f"pose{c}"]
            if owner is not None:
                dp[:, rows, owner] = dX @ generators(p[owner])
            if self.sl[f"K{c}"] is not None:
                dp[:, rows, self.sl[f"K{c}"]] = Jk
            if self.sl["tip"] is not None:
                dp[:, rows, self.sl["tip"]] = JpR @ RBA
        return LoopEval(r, dA, dB, dp)

    # ------------------------------------------------------------- start
    def initialize(self, TA: np.ndarray, TB: np.ndarray) -> np.ndarray | None:
        """Unknown camera poses, intrinsics and marker fitted with the robot held at TA, TB.

        Per camera with an unknown pose, a linear start from the marker
        positions y_i = T_B^-1 T_A t (t: the known tip, else its initial
        value) and the pixels: the normalised DLT decomposed into K [R | t]
        when the intrinsics are unknown and have no guess (also for a camera
        whose pose is known or follows the rig), else linear PnP with the
        known (or guessed) intrinsics (``camera_from_dlt``).  A camera whose
        DLT fails (fewer than six configurations, coplanar marker positions)
        keeps its ``initial_poses`` guess (and, with neither intrinsics nor a
        guess, f = 1000 px with the principal point at the mean pixel).  Then
        Gauss-Newton on the pixel residual over every unknown own parameter
        (the tip too, unless an ``initial_tip`` was given: that is kept).
        When guesses were given, the same refinement also starts from them
        alone and the start with the lower pixel error wins.  Deterministic.
        """
        if self.n_own == 0:
            return None
        N = TA.shape[0]
        if self.meas is None or self.meas.shape[0] != N:
            return None
        p_guess = np.array([q.nominal for q in self.parameters()])
        tip = self.tip if self.tip is not None else self.initial_tip
        y, *_ = relative_point(TA, TB, tip)
        p_lin = p_guess.copy()
        for c in range(self.cameras):
            uv = self.meas[:, 2 * c:2 * c + 2]
            sl, slk = self.sl[f"pose{c}"], self.sl[f"K{c}"]
            k_known = self.K[c] if slk is None else self.initial_K[c]
            if sl is None and k_known is not None:
                continue  # nothing linear to estimate (the pose is known or follows the rig)
            fit = camera_from_dlt(y, uv, k_known)
            if fit is not None:
                if sl is not None:
                    p_lin[sl] = vec_of(fit[0])
                if k_known is None:
                    p_lin[slk] = fit[1]
            elif k_known is None:  # no DLT, no guess: centre the principal point
                p_lin[slk] = np.concatenate([PLACEHOLDER_K[:2], uv.mean(axis=0)])
        keep_tip = self.sl["tip"] is not None and not self._fit_tip
        free = np.arange(self.sl["tip"].start if keep_tip else self.n_own)  # the tip is last
        if free.size == 0:
            return p_lin
        starts = [p_lin] + ([p_guess] if any(x is not None for x in self.initial_poses) else [])
        best, best_cost = p_lin, np.inf
        for p0 in starts:
            p = _gauss_newton(self, TA, TB, self.normalize(p0), free)
            r = self.residual(TA, TB, p)
            cost = float(np.sum(r * r)) if np.all(np.isfinite(r)) else np.inf
            if cost < best_cost:
                best, best_cost = p, cost
        return best

    def describe(self) -> dict:
        cams = []
        for c in range(self.cameras):
            pose = ("rig" if c == 1 and self.rig is not None else
                    "unknown" if self.poses[c] is None else vec_of(self.poses[c]).tolist())
            cams.append({"pose": pose, "K": "unknown" if self.K[c] is None else self.K[c].tolist()})
        return super().describe() | {
            "cameras": cams, "rig": None if self.rig is None else vec_of(self.rig).tolist(),
            "tip": "unknown" if self.tip is None else self.tip.tolist(), "sigma_px": self.sigma_px,
            "columns": self.columns(), "residual_unit": "px"}


def _intrinsics(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size != 4 or not np.all(np.isfinite(a)) or a[0] <= 0 or a[1] <= 0:
        got = " ".join(f"{x:g}" for x in a) if np.issubdtype(a.dtype, np.number) else repr(v)
        raise LoopError(f"{what}: expected four numbers 'fx fy cx cy' (pixels, fx and fy > 0), got '{got}'")
    return a


def _se3(v, name: str, what: str) -> pin.SE3:
    try:
        return _as_se3(v, what)
    except LoopError as exc:
        raise LoopError(f"camera loop '{name}': {exc}") from None


# --------------------------------------------------------------------------- spec
def _spec_vec(kw: dict[str, str], key: str, n: int, name: str) -> np.ndarray | None:
    if kw.get(key, "unknown") == "unknown":
        return None
    try:
        return parse_vec(kw[key], n, key)
    except LoopError as exc:
        raise LoopError(f"camera loop '{name}': {exc}") from None


@register("camera", {"frame", "to", "cameras", "K1", "K2", "K1_0", "K2_0", "pose1", "pose2", "rig", "tip", "tip0",
                     "sigma_px"})
def _camera(kw: dict[str, str], robot: RobotModel) -> Loop:
    """camera:frame=A[,to=B][,cameras=1|2][,K1=|K1_0="fx fy cx cy"][,K2=..|K2_0=..][,pose1="x y z rx ry rz"]
    [,pose2=..][,rig="x y z rx ry rz"][,tip=|tip0="x y z"][,sigma_px=px].

    K<c>: known intrinsics (fixed); K<c>_0: a guess of unknown ones (default: from the DLT).
    pose<c>: a starting guess of camera c's unknown pose in B (the data's DLT comes first).
    rig: the known pose of camera 2 in camera 1 (a calibrated stereo head; fixes the length scale).
    tip: the known marker point in A; tip0: a guess of an unknown one.
    """
    name = kw.get("name", "camera")
    if "frame" not in kw:
        raise LoopError(f"camera loop '{name}': needs frame=<tool frame>")
    try:
        cameras = int(kw.get("cameras", "1"))
    except ValueError:
        cameras = 0
    if cameras not in (1, 2):
        raise LoopError(f"camera loop '{name}': cameras='{kw['cameras']}': expected 1 or 2")
    if cameras == 1:
        extra = [k for k in ("K2", "K2_0", "pose2", "rig") if k in kw]
        if extra:
            raise LoopError(f"camera loop '{name}': {extra[0]} given but cameras=1 (add cameras=2)")
    for c in range(1, cameras + 1):
        if f"K{c}" in kw and f"K{c}_0" in kw:
            raise LoopError(f"camera loop '{name}': give K{c} (known intrinsics) or K{c}_0 (a guess), not both")
    if "tip" in kw and "tip0" in kw:
        raise LoopError(f"camera loop '{name}': give tip (known) or tip0 (a guess), not both")
    K = [_spec_vec(kw, f"K{c}", 4, name) for c in range(1, cameras + 1)]
    K0 = [_spec_vec(kw, f"K{c}_0", 4, name) for c in range(1, cameras + 1)]
    poses = [_spec_vec(kw, f"pose{c}", 6, name) for c in range(1, cameras + 1)]
    rig = _spec_vec(kw, "rig", 6, name)
    try:
        sigma = _opt_float(kw, "sigma_px")
    except LoopError as exc:
        raise LoopError(f"camera loop '{name}': {exc}") from None
    return CameraLoop(name, kw["frame"], kw.get("to", "universe"), cameras=cameras, K=K, initial_K=K0,
                      initial_poses=poses, rig=rig, tip=_spec_vec(kw, "tip", 3, name),
                      initial_tip=_spec_vec(kw, "tip0", 3, name), sigma_px=sigma)
