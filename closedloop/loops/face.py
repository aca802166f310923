"""The face loop: a flat face of frame A sliding on a flat face of frame B (3 passive DOF, 3 equations).

A palm pressed flat on a table, a gripper's flat pad on the other hand's pad, a tool's base plate on a
wall: the faces slide over each other in two directions and turn about their common normal, and nothing
else moves.  A point touching a plane is the `plane` loop (5 passive DOF); a face on a face also keeps
the two faces parallel.
"""

from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import face_parameters, relative_point
from closedloop.loops.spec import register
from closedloop.model.parameters import Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import parse_vec, skew, vec3

#: the fields of the loop's own parameters: A's face normal (2 angles), B's face plane (2 angles, offset);
#: B's fields are the plane loop's, so ``normal=@GROUP`` shares a table between a plane loop and a face loop
FACE_FIELDS = ("mrx", "mry")
PLANE_FIELDS = ("nrx", "nry", "d")
EZ = np.array([0.0, 0.0, 1.0])
#: rad RMS: a face of A that stays parallel to one plane of B at the nominal model tilts from it by less
#: than this (a rough model: a few degrees); more is a point or a ball on the face, not a face
FACE_TILT = 0.6


def _chart(ref: np.ndarray) -> np.ndarray:
    """The fixed rotation R0 with R0 e_z = ref (unit)."""
    return pin.Quaternion.FromTwoVectors(EZ, ref).matrix()


def _direction(R0: np.ndarray, w2: np.ndarray) -> np.ndarray:
    return R0 @ pin.exp3(np.array([w2[0], w2[1], 0.0])) @ EZ


def _angles(R0: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(rx, ry) of a unit direction n in the chart R0 exp3((rx, ry, 0)) e_z (|w| in [0, pi])."""
    m = R0.T @ (n / np.linalg.norm(n))
    axis = np.cross(EZ, m)
    s = np.linalg.norm(axis)
    if s < 1e-15:
        return np.zeros(2) if m[2] > 0 else np.array([np.pi, 0.0])
    return (np.arctan2(s, m[2]) / s) * axis[:2]


def fixed_direction(R: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit direction m of frame A that the rotations R (N, 3, 3) = R_B^-1 R_A carry to one direction of
    B, and how far they tilt it from that direction (rad RMS): the least eigenvector of
    sum_i (R_i - R_mean)^T (R_i - R_mean), i.e. min over |m| = 1 of sum_i |R_i m - R_mean m|^2.  Rotations
    that do not turn (every direction fixed) give `ref`."""
    D = R - R.mean(axis=0)
    lam, V = np.linalg.eigh(np.einsum("nki,nkj->ij", D, D))
    m = V[:, 0] if lam[1] > 1e-18 * R.shape[0] else ref
    v = R @ m
    c = v.mean(axis=0)
    c = c / max(np.linalg.norm(c), 1e-300)
    tilt = float(np.sqrt(np.mean(np.arccos(np.clip(v @ c, -1.0, 1.0)) ** 2)))
    return m, tilt


class FaceLoop(Loop):
    """Three closure equations per configuration: a flat face of A lies flat on a flat face of B.

    The extension of thesis 3.4 to t = 3 passive task DOF (two slides in the plane and a turn about its
    normal).  Of the six closure equations, the three that move the faces along their passive DOF are
    eliminated; what is left is the tilt of A's face from B's plane (2 rows, rad) and its distance from
    it (1 row, m).  A's face has the outward normal m in A and passes through the point t of A; B's face
    is the plane {y : n^T y = d} of B with outward normal n; in contact, R_BA m = -n and n^T y = d with
    y = T_B^-1 T_A t.  With (e1, e2, n) = R_n the columns of B's normal chart, v = R_BA m and
    s = R_n^T v:

        r = ( s_1,  s_2,  n^T y - d )                 (rad, rad, m)

    s_1 = e1^T v and s_2 = e2^T v are the tilt of A's face from B's plane about e2 and e1 (they vanish
    when v = -n; v = +n is the other branch, which `initialize` and `normalize` keep away from).

    Parameters (minimal): A's normal m(wa) = Ra0 exp3(wa) e_z, B's normal n(wb) = Rb0 exp3(wb) e_z with
    wa = (mrx, mry, 0), wb = (nrx, nry, 0) and fixed reference rotations Ra0 e_z = m_ref (``face=``,
    default A's z axis) and Rb0 e_z = n_ref (``normal=``, default B's z axis), and the offset d.  The
    point t is given (``tip=``, default A's origin) and not a parameter: only m^T t enters the closure
    (n^T R_BA t = -m^T t in contact), and d absorbs it.  Each chart is singular only at |w| = pi; the
    pair (m, n, d) and (-m, -n, -d) closes the same contact, and `normalize` takes whichever has the
    smaller |wa| + |wb| (then both are below pi).

    Jacobians (right perturbations; y, R_BA and dy/d(delta) as in `common.relative_point`;
    J_r(w) = Jexp3(w) the right Jacobian of exp3):

        ds/d(delta_A) = R_n^T [0  -R_BA [m]x],     ds/d(delta_B) = R_n^T [0  [v]x],
        ds/dwa = R_n^T R_BA dm/dwa,  dm/dwa = -Ra0 exp3(wa) [e_z]x J_r(wa),
        ds/dwb = [s]x J_r(wb),
        d(n^T y - d)/d(delta_A, delta_B) = n^T dy/d(delta_A, delta_B),
        d(n^T y - d)/dwb = y^T dn/dwb,  dn/dwb = -Rb0 exp3(wb) [e_z]x J_r(wb),   d/dd = -1

    (first two columns of each chart derivative).  Identifiability: each face hides the robot's base
    translation within the plane and its rotation about n, and A's turn about m (the core drops those
    on the data); the contact does not see the robot's size (thesis 3.3).
    """

    translation_rows = (2,)
    rotation_rows = (0, 1)

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        tip: np.ndarray | None = None,
        face: np.ndarray | None = None,
        normal: np.ndarray | None = None,
        prior: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.prior = prior
        self.tip = np.zeros(3) if tip is None else vec3(tip, "tip")
        refs = []
        for key, v in (("face", face), ("normal", normal)):
            r = EZ if v is None else vec3(v, key)
            if not np.isfinite(r).all() or np.linalg.norm(r) < 1e-12:
                raise LoopError(f"face loop '{name}': {key}= must be a non-zero direction")
            refs.append(r / np.linalg.norm(r))
        self.m_ref, self.n_ref = refs
        self.Ra0, self.Rb0 = _chart(self.m_ref), _chart(self.n_ref)

    @property
    def dim(self) -> int:
        return 3

    # ------------------------------------------------------------ the faces
    def face_normal(self, wa: np.ndarray) -> np.ndarray:
        """A's outward face normal m, in A."""
        return _direction(self.Ra0, wa)

    def normal(self, wb: np.ndarray) -> np.ndarray:
        """B's outward face normal n, in B."""
        return _direction(self.Rb0, wb)

    def angles(self, m: np.ndarray, n: np.ndarray, d: float) -> np.ndarray:
        """The loop's parameter vector (mrx, mry, nrx, nry, d) of the faces m (in A), {n^T y = d} (in B)."""
        return np.concatenate([_angles(self.Ra0, m), _angles(self.Rb0, n), [d]])

    def parameters(self) -> list[Parameter]:
        return face_parameters(self.name, FACE_FIELDS + PLANE_FIELDS, prior=self.prior)

    def _faces(self, TA: np.ndarray, TB: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(m in A, n in B with n . n_ref >= 0, offset d, tilt in rad RMS) read off the poses: the fixed direction
        of the relative rotations and the plane through the points y_i = T_B^-1 T_A t."""
        RBA = np.swapaxes(TB[:, :3, :3], 1, 2) @ TA[:, :3, :3]
        m, tilt = fixed_direction(RBA, self.m_ref) if RBA.shape[0] >= 2 else (self.m_ref, 0.0)
        n = -(RBA @ m).mean(axis=0)
        n /= max(np.linalg.norm(n), 1e-300)
        if n @ self.n_ref < 0:
            m, n = -m, -n
        y, *_ = relative_point(TA, TB, self.tip)
        return m, n, float(np.mean(y @ n)), tilt

    def prepare(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> "FaceLoop":
        """A copy with the reference of A's face normal turned round when it points into A's face (the data's
        m, with B's normal towards its reference, lies more than 90 deg from ``face=``), so that both charts
        start in their hemisphere; otherwise `self`.  The sign of a reference is a convention: the contact
        is the same."""
        m, _, _, _ = self._faces(TA, TB)
        if m @ self.m_ref >= 0:
            return self
        other = copy.copy(self)
        other.m_ref = -self.m_ref
        other.Ra0 = _chart(other.m_ref)
        return other

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """The faces read off the data at the nominal model (`_faces`)."""
        m, n, d, _ = self._faces(TA, TB)
        return self.normalize(self.angles(m, n, d))

    def normalize(self, p: np.ndarray) -> np.ndarray:
        """The pair (m, n, d) or (-m, -n, -d), whichever is nearer its references (smaller |wa| + |wb|)."""
        if np.linalg.norm(p[0:2]) + np.linalg.norm(p[2:4]) <= np.pi:
            return p
        return self.angles(-self.face_normal(p[0:2]), -self.normal(p[2:4]), -float(p[4]))

    def mismatch(self, Ts: list[np.ndarray], meas: np.ndarray | None = None) -> str | None:
        """A face of A that does not stay parallel to any plane of B (it tilts by over `FACE_TILT` rad RMS at the
        nominal model) is no face on a face: a point or a ball touches there."""
        if Ts[0].shape[0] < 3:
            return None
        _, _, _, tilt = self._faces(Ts[0], Ts[1])
        if tilt <= FACE_TILT:
            return None
        spec = self.spec("plane")
        return (
            f"loop '{self.name}' (face on {self.frame_a}): no direction of the frame stays fixed relative to "
            f"{self.frame_b} (the best one tilts by {np.degrees(tilt):.0f} deg RMS at the nominal model, more than "
            f"any rough model explains): is a point of it touching a plane? --loop {spec}"
        )

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        wa = np.array([p[0], p[1], 0.0])
        wb = np.array([p[2], p[3], 0.0])
        d = float(p[4])
        Ea, Eb = pin.exp3(wa), pin.exp3(wb)
        m = self.Ra0 @ Ea @ EZ
        Rn = self.Rb0 @ Eb
        n = Rn[:, 2]
        y, RBA, dyA, dyB = relative_point(TA, TB, self.tip)
        v = RBA @ m
        s = v @ Rn  # (N, 3): R_n^T v
        N = TA.shape[0]
        r = np.empty((N, 3))
        r[:, :2] = s[:, :2]
        r[:, 2] = y @ n - d
        RnT2 = Rn[:, :2].T  # (2, 3)
        dA = np.zeros((N, 3, 6))
        dB = np.zeros((N, 3, 6))
        dA[:, :2, 3:] = -np.einsum("ij,njk,kl->nil", RnT2, RBA, skew(m))
        dB[:, :2, 3:] = np.einsum("ij,njk->nik", RnT2, _skews(v))
        dA[:, 2, :] = np.einsum("i,nij->nj", n, dyA)
        dB[:, 2, :] = np.einsum("i,nij->nj", n, dyB)
        dm_dwa = (-self.Ra0 @ Ea @ skew(EZ) @ pin.Jexp3(wa))[:, :2]
        Jb = pin.Jexp3(wb)[:, :2]
        dn_dwb = (-self.Rb0 @ Eb @ skew(EZ) @ pin.Jexp3(wb))[:, :2]
        dp = np.zeros((N, 3, 5))
        dp[:, :2, 0:2] = np.einsum("ij,njk,kl->nil", RnT2, RBA, dm_dwa)
        dp[:, :2, 2:4] = (_skews(s) @ Jb)[:, :2, :]
        dp[:, 2, 2:4] = y @ dn_dwb
        dp[:, 2, 4] = -1.0
        return LoopEval(r, dA, dB, dp)

    def describe(self) -> dict:
        return super().describe() | {
            "tip": self.tip.tolist(),
            "reference_face_normal": self.m_ref.tolist(),
            "reference_normal": self.n_ref.tolist(),
        }


def _skews(v: np.ndarray) -> np.ndarray:
    """[v_i]x for each row of v (N, 3) -> (N, 3, 3)."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


@register("face", {"frame", "to", "tip", "face", "normal"})
def _face(kw: dict[str, str], robot: RobotModel) -> Loop:
    """face:frame=A[,to=B][,tip="x y z"][,face="mx my mz"][,normal="nx ny nz"]  (face, normal: default z axes).

    A flat face of A on a flat face of B; tip: a point of A's face (default A's origin); face, normal: reference
    directions of the faces' outward normals in A and in B."""
    if "frame" not in kw:
        raise LoopError("face loop needs frame=<frame A>")
    tip = parse_vec(kw["tip"], 3, "tip") if "tip" in kw else None
    face = parse_vec(kw["face"], 3, "face") if "face" in kw else None
    normal = parse_vec(kw["normal"], 3, "normal") if "normal" in kw else None
    return FaceLoop(kw.get("name", "face"), kw["frame"], kw.get("to", "universe"), tip=tip, face=face, normal=normal)
