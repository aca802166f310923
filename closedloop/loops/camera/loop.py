"""The camera loop: a marker on the tool seen by cameras, each on any robot frame (thesis 3.2, 5.2-5.4).

A marker at an unknown point t of frame A (the tool) is imaged by one or more
pinhole cameras (``camera.model``: intrinsics and optional lens distortion).
Camera c sits at an unknown (or known) pose X_c in its own robot frame F_c:
the world, a fixed head, or a frame moved by the camera's own sensed joint
(the thesis's verging head, 5.2.2: each camera on its own rotation).  The
closure is either

* ``reprojection`` (default): the image-plane error in every camera, the
  first formulation of 5.1.4, 2 rows (pixels) per camera; or
* ``triangulation`` (two cameras): the thesis's own choice, the point given
  by the stereo pair (eqs. 5.11-5.12) minus the arm's point (eq. 5.2), 3 rows
  (metres, in camera 1's frame, eq. 5.13); see ``stereo.py``.

Both are exact, with analytic Jacobians.  Measurements come from log
columns ``<loop>:u<c>``, ``<loop>:v<c>`` (c = 1, 2, ...).  A pixel pair that is
NaN in both coordinates is a missing observation (the marker out of view):
its residual and Jacobian rows are zero and ``LoopEval.valid`` marks them.

Identifiability (5.4, eq. 5.27): scaling every length leaves every pixel
unchanged unless a camera position or the rig baseline is known, so the
loop is ``scale_free`` otherwise and the core fixes one robot length.  A
camera on its own pan joint absorbs that joint's offset and the placement
components along its axis (the core's reduction drops and names them);
parallel pan axes leave one more redundancy (5.4, eq. 5.26), found the same way.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.camera.model import (  # noqa: F401
    DIST_FIELDS,
    INTRINSIC_FIELDS,
    PLACEHOLDER_K,
    camera_from_dlt,
    dlt,
    project,
    project_lens,
)
from closedloop.loops.common import POSE_FIELDS, TIP_FIELDS, point_parameters, pose_parameters, relative_point
from closedloop.model.parameters import Parameter
from closedloop.model.se3 import as_se3, generators, pose_of, skew, vec3, vec_of

PIXEL_COLS = ("u", "v")
CLOSURES = ("reprojection", "triangulation")
DEFAULT_PRIOR_PX = 100.0  # expected error of an intrinsics guess (px): column scaling, data identifiability
DEFAULT_PRIOR_DIST = 0.1  # expected error of a distortion guess


class CameraLoop(Loop):
    """Image points of a tool marker in pinhole cameras, each on its own frame.

    With t the marker in frame A (``<loop>.tip_x/y/z``), y_c = T_Fc^-1 T_A t
    its position in camera c's frame F_c, X_c = (R_c, t_c) the camera's pose
    in F_c (``<loop>.cam<c>.x..rz``), k_c its intrinsics
    (``<loop>.cam<c>.fx..cy``) and d_c its distortion (``<loop>.cam<c>.k1..``
    for the coefficients in ``dist``):

        p_c = X_c^-1 y_c = R_c^T (y_c - t_c),   r_c = pi(k_c, d_c, p_c) - (u_c, v_c)

    With Jpi = d pi / d p (``camera.model.project_lens``), point.relative_point:

        dr_c/d(delta_A)  = Jpi R_c^T R_FA [I  -[t]x]      dr_c/d(delta_Fc) = Jpi R_c^T [-I  [y_c]x]
        dr_c/d t         = Jpi R_c^T R_FA                 dr_c/d(delta_Xc) = Jpi [-I  [p_c]x]
        dr_c/d k_c       = [[xd, 0, 1, 0], [0, yd, 0, 1]] dr_c/d d_c       = diag(fx, fy) Dd

    the pose parameters mapping to delta_Xc as in the measured loops.  A known
    ``rig`` (camera 2 at G in camera 1, both on one frame): X_2 = X_1 G and
    dr_2/d(delta_X1) = Jpi [-I [p_2]x] Ad(G^-1).  ``frames`` is (A, F_1, F_2,
    ...) without repeats; a frame's derivative sums over its cameras.
    ``sigma_px`` gives measurement_cov = sigma_px^2 I (reprojection).
    """

    translation_rows: tuple[int, ...] = ()
    rotation_rows: tuple[int, ...] = ()

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        cameras: int | None = None,
        K: Sequence | None = None,
        initial_K: Sequence | None = None,
        poses: Sequence | None = None,
        initial_poses: Sequence | None = None,
        rig=None,
        tip=None,
        initial_tip=None,
        sigma_px: float | None = None,
        prior_px: float = DEFAULT_PRIOR_PX,
        camera_frames: Sequence[str] | None = None,
        dist: Sequence[str] = (),
        D: Sequence | None = None,
        closure: str = "reprojection",
    ):
        frames = list(camera_frames) if camera_frames else None
        n = len(frames) if frames else (cameras or 1)
        if cameras is not None and frames and cameras != len(frames):
            raise LoopError(f"camera loop '{name}': cameras={cameras} but {len(frames)} camera frames")
        if n < 1 or (not frames and n > 2):
            raise LoopError(
                f"camera loop '{name}': cameras={n!r}: expected 1 or 2 on one frame "
                "(more cameras: one frame each, to=F1+F2+F3)"
            )
        super().__init__(name, frame_a, frames[0] if frames else frame_b)
        self.cameras = n
        self.camera_frames = frames or [frame_b] * n
        if frame_a in self.camera_frames:
            raise LoopError(f"camera loop '{name}': the marker frame '{frame_a}' is also a camera frame")
        self._frames = tuple(dict.fromkeys([frame_a] + self.camera_frames))
        self._fidx = [self._frames.index(f) for f in self.camera_frames]
        what = f"camera loop '{name}'"
        self.K = self._per_camera(K, "K{}", lambda v, w: _intrinsics(v, f"{what}: {w}"))
        self.initial_K = self._per_camera(initial_K, "K{}_0", lambda v, w: _intrinsics(v, f"{what}: {w}"))
        self.poses = self._per_camera(poses, "known pose{}", lambda v, w: _se3(v, name, w))
        self.initial_poses = self._per_camera(initial_poses, "pose{}", lambda v, w: _se3(v, name, w))
        Dv = self._per_camera(D, "D{}", lambda v, w: _distortion(v, f"{what}: {w}"))
        self.D = [np.zeros(5) if x is None else x for x in Dv]
        bad = [f for f in dist if f not in DIST_FIELDS]
        if bad:
            raise LoopError(
                f"{what}: dist='{'+'.join(dist)}': unknown coefficient '{bad[0]}' (known: {'+'.join(DIST_FIELDS)})"
            )
        self.dist = tuple(f for f in DIST_FIELDS if f in dist)
        self._dist_idx = np.array([DIST_FIELDS.index(f) for f in self.dist], dtype=int)
        for c in range(n):
            if self.K[c] is not None and self.initial_K[c] is not None:
                raise LoopError(f"{what}: camera {c + 1} has known intrinsics and a guess; give one")
            if self.poses[c] is not None and self.initial_poses[c] is not None:
                raise LoopError(f"{what}: camera {c + 1} has a known pose and a guess; give one")
        self.rig = None if rig is None else _se3(rig, name, "rig")
        if self.rig is not None:
            if n != 2 or self.camera_frames[0] != self.camera_frames[1]:
                raise LoopError(f"{what}: rig (camera 2 in camera 1) needs two cameras on one frame")
            if self.poses[1] is not None or self.initial_poses[1] is not None:
                raise LoopError(f"{what}: with a rig, camera 2's pose follows camera 1's; give no pose for camera 2")
        if closure not in CLOSURES:
            raise LoopError(f"{what}: closure='{closure}': expected one of {', '.join(CLOSURES)}")
        if closure == "triangulation" and n != 2:
            raise LoopError(f"{what}: closure=triangulation needs exactly two cameras, not {n}")
        self.closure = closure
        self.tip = None if tip is None else vec3(tip, f"{what}: tip")
        self.initial_tip = np.zeros(3) if initial_tip is None else vec3(initial_tip, f"{what}: initial_tip")
        self._fit_tip = initial_tip is None  # initialize() estimates an unknown tip with no initial value
        for s, w in ((sigma_px, "sigma_px"), (prior_px, "prior_px")):
            if s is not None and not (np.isfinite(s) and s > 0):
                raise LoopError(f"{what}: {w}={s!r} must be positive and finite")
        self.sigma_px = sigma_px
        self.prior_px = prior_px
        tri = closure == "triangulation"
        self.translation_rows = (0, 1, 2) if tri else ()
        self.pixel_rows = () if tri else tuple(range(2 * n))
        # with triangulation the pixel noise enters through a per-configuration covariance (LoopEval.cov)
        self.measurement_cov = None if sigma_px is None or tri else sigma_px**2 * np.eye(2 * n)
        # the length scale is fixed only by a known baseline or a known camera position
        known_t = [X.translation for X in self.poses if X is not None]
        if self.rig is not None:
            known_t.append(self.rig.translation)
        self.scale_free = not any(np.linalg.norm(t) > 0 for t in known_t)
        self._layout()

    def _per_camera(self, v, what: str, conv) -> list:
        if v is None:
            return [None] * self.cameras
        v = list(v)
        if len(v) != self.cameras:
            raise LoopError(
                f"camera loop '{self.name}': {what.format('')} has {len(v)} entries for {self.cameras} camera(s)"
            )
        return [None if x is None else conv(x, what.format(c + 1)) for c, x in enumerate(v)]

    def _layout(self) -> None:
        """Slices of the own parameter vector: poses, intrinsics, distortion, tip (only the unknown ones)."""
        self.sl: dict[str, slice | None] = {}
        k = 0
        for c in range(self.cameras):
            unknown = self.poses[c] is None and not (c == 1 and self.rig is not None)
            self.sl[f"pose{c}"] = slice(k, k + 6) if unknown else None
            k += 6 if unknown else 0
        for c in range(self.cameras):
            self.sl[f"K{c}"] = slice(k, k + 4) if self.K[c] is None else None
            k += 4 if self.K[c] is None else 0
        nd = len(self.dist)
        for c in range(self.cameras):
            self.sl[f"D{c}"] = slice(k, k + nd) if nd else None
            k += nd
        self.sl["tip"] = slice(k, k + 3) if self.tip is None else None
        self.n_own = k + (3 if self.tip is None else 0)

    @property
    def dim(self) -> int:
        return 3 if self.closure == "triangulation" else 2 * self.cameras

    @property
    def frames(self) -> tuple[str, ...]:
        return self._frames

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
                out += [
                    Parameter(
                        f"{self.name}.cam{c + 1}.{f}",
                        "loop",
                        self.name,
                        f"cam{c + 1}.{f}",
                        float(k0[i]),
                        "px",
                        self.prior_px,
                        priority=1,
                        order=len(out) + i,
                    )
                    for i, f in enumerate(INTRINSIC_FIELDS)
                ]
        for c in range(self.cameras):
            out += [
                Parameter(
                    f"{self.name}.cam{c + 1}.{f}",
                    "loop",
                    self.name,
                    f"cam{c + 1}.{f}",
                    float(self.D[c][DIST_FIELDS.index(f)]),
                    "1",
                    DEFAULT_PRIOR_DIST,
                    priority=1,
                    order=len(out) + i,
                )
                for i, f in enumerate(self.dist)
            ]
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, self.initial_tip, order0=len(out))
        return out

    # ------------------------------------------------------------- measurements
    def measurements(self, extra: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
        """The pixels (len(rows), 2 cameras) at the log's `rows`: u1, v1, u2, v2, ... (NaN: out of view)."""
        missing = [c for c in self.columns() if c not in extra]
        if missing:
            raise LoopError(f"camera loop '{self.name}': the log has no pixel column(s) {', '.join(missing)}")
        M = np.column_stack([np.asarray(extra[c], dtype=float)[rows] for c in self.columns()])
        fin = np.isfinite(M)
        half = np.flatnonzero(np.any(fin[:, 0::2] != fin[:, 1::2], axis=1) | np.any(np.isinf(M), axis=1))
        if half.size:
            raise LoopError(
                f"camera loop '{self.name}': pixel coordinates missing or not a number in row(s) "
                f"{', '.join(str(b + 1) for b in half[:5])} of this loop (a marker out of view "
                "is NaN in both u and v)"
            )
        return M

    def checked(self, meas: np.ndarray | None, N: int) -> np.ndarray:
        """The pixels `meas` (N, 2 cameras), checked against the N configurations they are evaluated at."""
        if meas is None:
            raise LoopError(f"camera loop '{self.name}': no pixels given (log columns {', '.join(self.columns())})")
        meas = np.asarray(meas, dtype=float)
        if meas.shape != (N, 2 * self.cameras):
            raise LoopError(
                f"camera loop '{self.name}': {N} configurations but pixels of shape {meas.shape} "
                f"(expected ({N}, {2 * self.cameras}))"
            )
        return meas

    def observed(self, meas: np.ndarray) -> np.ndarray:
        """(N, cameras) True where camera c saw the marker (its pixel pair in `meas` is not NaN)."""
        return np.isfinite(np.asarray(meas, dtype=float)[:, 0::2])

    def valid_rows(self, meas: np.ndarray) -> np.ndarray:
        """(N, dim) True for residual rows that carry an observation (``LoopEval.valid``)."""
        seen = self.observed(meas)
        if self.closure == "triangulation":
            return np.repeat(np.all(seen, axis=1, keepdims=True), 3, axis=1)
        return np.repeat(seen, 2, axis=1)

    def valid_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        valid = self.valid_rows(self.checked(meas, Ts[0].shape[0]))
        return None if np.all(valid) else valid

    # ------------------------------------------------------------- parameters
    def camera_pose(self, p: np.ndarray, c: int) -> pin.SE3:
        """X_c, the pose of camera c (0-based) in its frame F_c."""
        if c == 1 and self.rig is not None:
            return self.camera_pose(p, 0) * self.rig
        sl = self.sl[f"pose{c}"]
        return self.poses[c] if sl is None else pose_of(p[sl])

    def intrinsics(self, p: np.ndarray, c: int) -> np.ndarray:
        sl = self.sl[f"K{c}"]
        return self.K[c] if sl is None else p[sl]

    def distortion(self, p: np.ndarray, c: int) -> np.ndarray | None:
        """(k1, k2, p1, p2, k3) of camera c; None for an ideal pinhole (nothing identified, all zero)."""
        sl = self.sl[f"D{c}"]
        if sl is None:
            return self.D[c] if np.any(self.D[c]) else None
        d = self.D[c].copy()
        d[self._dist_idx] = p[sl]
        return d

    def tip_point(self, p: np.ndarray) -> np.ndarray:
        return self.tip if self.tip is not None else p[self.sl["tip"]]

    def normalize(self, p: np.ndarray) -> np.ndarray:
        out = p.copy()
        for c in range(self.cameras):
            sl = self.sl[f"pose{c}"]
            if sl is not None:
                out[sl.start + 3 : sl.stop] = pin.log3(pin.exp3(p[sl.start + 3 : sl.stop]))
        return out

    # ------------------------------------------------------------- residual
    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        return self.residual_frames([TA, TB], p, meas)

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        return self.evaluate_frames([TA, TB], p, meas)

    def residual_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        return self._eval(Ts, p, meas, False).r

    def evaluate_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        return self._eval(Ts, p, meas, True)

    def _eval(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None, jac: bool) -> LoopEval:
        if len(Ts) != len(self._frames):
            raise LoopError(f"camera loop '{self.name}': {len(Ts)} frame poses for frames {self._frames}")
        meas = self.checked(meas, Ts[0].shape[0])
        if self.closure == "triangulation":
            from closedloop.loops.camera.stereo import triangulation_eval

            ev = triangulation_eval(self, Ts, p, meas, jac)
        else:
            ev = self._reprojection(Ts, p, meas, jac)
        valid = self.valid_rows(meas)
        if not np.all(valid):
            ev.r = np.where(valid, ev.r, 0.0)
            if jac and ev.dF is not None:
                ev.dF = [np.where(valid[:, :, None], d, 0.0) for d in ev.dF]
                ev.dp = np.where(valid[:, :, None], ev.dp, 0.0)
                if ev.cov is not None:
                    ev.cov = np.where(valid[:, :, None] & valid[:, None, :], ev.cov, 0.0)
            ev.valid = valid
        return ev

    def _reprojection(self, Ts: list[np.ndarray], p: np.ndarray, m: np.ndarray, jac: bool) -> LoopEval:
        N = Ts[0].shape[0]
        tip = self.tip_point(p)
        r = np.empty((N, self.dim))
        dF = [np.zeros((N, self.dim, 6)) for _ in self._frames] if jac else []
        dp = np.zeros((N, self.dim, self.n_own if jac else 0))
        for c in range(self.cameras):
            rows = slice(2 * c, 2 * c + 2)
            y, RFA, dyA, dyF = relative_point(Ts[0], Ts[self._fidx[c]], tip)
            X = self.camera_pose(p, c)
            pc = (y - X.translation) @ X.rotation  # rows: R_c^T (y - t_c)
            uv, Jp, Jk, Jd = project_lens(pc, self.intrinsics(p, c), self.distortion(p, c), jac)
            r[:, rows] = uv - m[:, rows]
            if not jac:
                continue
            JpR = Jp @ X.rotation.T  # d uv / d y
            dF[0][:, rows] += JpR @ dyA
            dF[self._fidx[c]][:, rows] += JpR @ dyF
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
            if self.sl[f"D{c}"] is not None:
                dp[:, rows, self.sl[f"D{c}"]] = Jd[:, :, self._dist_idx]
            if self.sl["tip"] is not None:
                dp[:, rows, self.sl["tip"]] = JpR @ RFA
        if not jac:
            return LoopEval(r, None, None, dp)
        two = len(self._frames) == 2
        return LoopEval(r, dF[0] if two else None, dF[1] if two else None, dp, dF=dF)

    # ------------------------------------------------------------- start
    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        return self.initialize_frames([TA, TB], meas)

    def initialize_frames(self, Ts: list[np.ndarray], meas: np.ndarray | None = None) -> np.ndarray | None:
        """Unknown camera poses, intrinsics, distortion and marker from the pixels `meas` (``camera_start``)."""
        from closedloop.loops.camera.start import initialize_camera_loop

        return initialize_camera_loop(self, Ts, meas)

    def describe(self) -> dict:
        cams = []
        for c in range(self.cameras):
            pose = (
                "rig"
                if c == 1 and self.rig is not None
                else "unknown"
                if self.poses[c] is None
                else vec_of(self.poses[c]).tolist()
            )
            cams.append(
                {
                    "frame": self.camera_frames[c],
                    "pose": pose,
                    "K": "unknown" if self.K[c] is None else self.K[c].tolist(),
                    "distortion": dict(zip(DIST_FIELDS, self.D[c].tolist())),
                    "identified_distortion": list(self.dist),
                }
            )
        return super().describe() | {
            "cameras": cams,
            "closure": self.closure,
            "rig": None if self.rig is None else vec_of(self.rig).tolist(),
            "tip": "unknown" if self.tip is None else self.tip.tolist(),
            "sigma_px": self.sigma_px,
            "columns": self.columns(),
            "residual_unit": "m" if self.closure == "triangulation" else "px",
        }


def _intrinsics(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size != 4 or not np.all(np.isfinite(a)) or a[0] <= 0 or a[1] <= 0:
        got = " ".join(f"{x:g}" for x in a) if np.issubdtype(a.dtype, np.number) else repr(v)
        raise LoopError(f"{what}: expected four numbers 'fx fy cx cy' (pixels, fx and fy > 0), got '{got}'")
    return a


def _distortion(v, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size != 5 or not np.all(np.isfinite(a)):
        raise LoopError(f"{what}: expected five finite numbers 'k1 k2 p1 p2 k3', got {v!r}")
    return a


def _se3(v, name: str, what: str) -> pin.SE3:
    try:
        return as_se3(v, what)
    except LoopError as exc:
        raise LoopError(f"camera loop '{name}': {exc}") from None
