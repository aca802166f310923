"""The plane loop: a tool tip touching an unknown plane (5 passive DOF, 1 equation)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import TIP_FIELDS, face_parameters, point_parameters, relative_point
from closedloop.loops.spec import register
from closedloop.model.parameters import Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import parse_vec, skew, vec3

PLANE_FIELDS = ("nrx", "nry", "d")
EZ = np.array([0.0, 0.0, 1.0])


class PlaneLoop(Loop):
    """One closure equation per configuration: the tip of A lies on a plane fixed in B.

    The extension of thesis 3.4 to t = 5 passive task DOF (sliding in two
    directions, three free rotations): of the six closure equations only the
    distance to the plane survives the elimination of the unsensed DOF,

        r = n^T (T_B^-1 T_A t) - d                    (1 row, metres)

    with t the tip in frame A (``<loop>.tip_x/y/z``, or known ``tip=``) and the
    plane {y : n^T y = d} in frame B.

    Parameterisation of the normal (minimal, 2 angles + 1 distance):

        n(w) = R0 exp3(w) e_z,   w = (nrx, nry, 0)

    R0 is a FIXED reference rotation with R0 e_z = n_ref (``normal=``, default
    the z axis of frame B).  w is a rotation vector perpendicular to e_z, so
    exp3(w) tilts e_z by |w| towards the direction e_z x w; the map w -> n is a
    diffeomorphism for |w| < pi and singular only at |w| = pi (the whole circle
    |w| = pi maps to -n_ref).  That singularity is never approached: n and -n
    (with d -> -d) describe the same plane, ``initialize`` fits the plane to
    the data (SVD of the tip points) and picks the sign with n . n_ref >= 0,
    i.e. |w| <= pi/2, and ``normalize`` flips back into that hemisphere after
    the solve.  A plane perpendicular to n_ref (|w| = pi/2) is still regular.
    The reference is fixed, not taken from the data, so the parameter values
    of two loop instances are comparable.

    Jacobians (right perturbations, y = T_B^-1 T_A t, see point.relative_point):

        dr/d(delta_A) = n^T R_BA [I  -[t]x],   dr/d(delta_B) = n^T [-I  [y]x],
        dr/dt = n^T R_BA,   dr/dd = -1,
        dr/dw = y^T dn/dw,  dn/dw = -R0 exp3(w) [e_z]x Jexp3(w)   (first two columns)

    Sessions: one PlaneLoop per physical plane and tool.  Touches of the same
    plane with the same tip, even from separate sessions, are rows of the
    SAME loop (the log's ``loop`` column names it); touches of different
    planes are different loops, each with its own plane parameters.  Two loops
    never share a plane parameter, so a plane touched with two different tools
    must be modelled as two planes (the core has no shared loop parameters).

    Identifiability: each plane hides the robot's base translation within the
    plane and its rotation about n; the core drops those parameters on the data.
    Enough distinct touches with varied tip orientation are needed for the tip.
    ``prior`` (m) is the expected error magnitude of the tip and d (see PointLoop).
    """

    translation_rows = (0,)
    rotation_rows = ()

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        tip: np.ndarray | None = None,
        normal: np.ndarray | None = None,
        initial_tip: np.ndarray | None = None,
        prior: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.prior = prior
        self.tip = None if tip is None else vec3(tip, "tip")
        self.initial_tip = np.zeros(3) if initial_tip is None else vec3(initial_tip, "initial_tip")
        n_ref = EZ if normal is None else vec3(normal, "normal")
        if np.linalg.norm(n_ref) < 1e-12:
            raise LoopError(f"plane loop '{name}': reference normal must be non-zero")
        self.n_ref = n_ref / np.linalg.norm(n_ref)
        self.R0 = pin.Quaternion.FromTwoVectors(EZ, self.n_ref).matrix()

    @property
    def dim(self) -> int:
        return 1

    @property
    def n_tip(self) -> int:
        return 0 if self.tip is not None else 3

    # ------------------------------------------------------------ the plane
    def normal(self, w2: np.ndarray) -> np.ndarray:
        return self.R0 @ pin.exp3(np.array([w2[0], w2[1], 0.0])) @ EZ

    def angles(self, n: np.ndarray) -> np.ndarray:
        """(nrx, nry) of a unit normal n (the inverse of `normal`, |w| in [0, pi])."""
        m = self.R0.T @ (n / np.linalg.norm(n))
        axis = np.cross(EZ, m)  # (-m_y, m_x, 0)
        s = np.linalg.norm(axis)
        ang = np.arctan2(s, m[2])
        if s < 1e-15:
            return np.zeros(2) if m[2] > 0 else np.array([np.pi, 0.0])
        return (ang / s) * axis[:2]

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(tip, w, d) from the loop's parameter vector."""
        k = self.n_tip
        tip = self.tip if self.tip is not None else p[:3]
        return np.asarray(tip, dtype=float), p[k : k + 2], float(p[k + 2])

    def parameters(self) -> list[Parameter]:
        out = []
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, self.initial_tip, prior=self.prior)
        out += face_parameters(self.name, PLANE_FIELDS, order0=3, prior=self.prior)
        return out

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """Plane through the tip points of the nominal model (least squares), normal towards n_ref.

        With fewer than three points (or collinear ones) the normal is n_ref and
        the plane passes through their centroid.
        """
        tip = self.tip if self.tip is not None else self.initial_tip
        y, *_ = relative_point(TA, TB, tip)
        c = y.mean(axis=0)
        n = self.n_ref
        if y.shape[0] >= 3:
            _, S, Vt = np.linalg.svd(y - c, full_matrices=False)
            if S.size == 3 and S[1] > 1e-9 * max(S[0], 1e-300):
                n = Vt[2] if Vt[2] @ self.n_ref >= 0 else -Vt[2]
        plane = np.concatenate([self.angles(n), [n @ c]])
        return plane if self.tip is not None else np.concatenate([self.initial_tip, plane])

    def normalize(self, p: np.ndarray) -> np.ndarray:
        """Keep the normal in the hemisphere of n_ref (|w| <= pi/2), flipping (n, d) -> (-n, -d)."""
        tip, w, d = self.split(p)
        if np.linalg.norm(w) <= np.pi / 2:
            return p
        n = self.normal(w)
        out = p.copy()
        k = self.n_tip
        out[k : k + 2] = self.angles(-n)
        out[k + 2] = -d
        return out

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        tip, w2, d = self.split(p)
        w = np.array([w2[0], w2[1], 0.0])
        Rw = pin.exp3(w)
        n = self.R0 @ Rw @ EZ
        y, RBA, dyA, dyB = relative_point(TA, TB, tip)
        N = TA.shape[0]
        r = (y @ n - d)[:, None]
        dA = np.einsum("i,nij->nj", n, dyA)[:, None, :]
        dB = np.einsum("i,nij->nj", n, dyB)[:, None, :]
        dn_dw = -self.R0 @ Rw @ skew(EZ) @ pin.Jexp3(w)  # (3, 3), columns for w_x, w_y, w_z
        blocks = []
        if self.tip is None:
            blocks.append(np.einsum("i,nij->nj", n, RBA)[:, None, :])
        blocks.append((y @ dn_dw[:, :2])[:, None, :])
        blocks.append(np.full((N, 1, 1), -1.0))
        return LoopEval(r, dA, dB, np.concatenate(blocks, axis=2))

    def describe(self) -> dict:
        return super().describe() | {
            "tip": "unknown" if self.tip is None else self.tip.tolist(),
            "reference_normal": self.n_ref.tolist(),
        }


@register("plane", {"frame", "to", "tip", "normal"})
def _plane(kw: dict[str, str], robot: RobotModel) -> Loop:
    """plane:frame=tool[,to=frame_b][,tip="x y z"][,normal="nx ny nz"]  (normal: reference direction)."""
    if "frame" not in kw:
        raise LoopError("plane loop needs frame=<tool frame>")
    tip = parse_vec(kw["tip"], 3, "tip") if kw.get("tip", "unknown") != "unknown" else None
    normal = parse_vec(kw["normal"], 3, "normal") if "normal" in kw else None
    return PlaneLoop(kw.get("name", "plane"), kw["frame"], kw.get("to", "universe"), tip=tip, normal=normal)
