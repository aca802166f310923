"""The weld loop: frame A is rigidly attached to frame B (thesis 3.3, 4.2.3).

It runs on the batched SE(3) algebra of `closedloop.model.se3` (log6 with Jlog6 over
a stack of configurations, `rigid_inverse`, `adjoint`).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import ON_PLANE, POINT_SPREAD, POSE_FIELDS, contact_fits, pose_parameters
from closedloop.loops.spec import register
from closedloop.model.parameters import Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import adjoint, log3, log6, parse_pose, relative, rigid_inverse

CLOSURE_FIELDS = POSE_FIELDS

#: rad: RMS spread of a weld's relative orientation across rows, at the nominal model, above which no rough
#: model explains it (the thesis-sized starts of benchmarks/basin.py, offsets +-0.6 rad and twists +-0.3 rad,
#: spread it by at most 0.37 rad; the zoo's rough models, 2 cm / 0.02 rad / 0.2 rad offsets, by 0.11 rad)
WELD_ROTATION_SPREAD = 0.6
#: a point of the tool stays fixed (a pivot fit) to within this share of the rotation spread times the
#: tool's distance from frame B: rough models leave 0.016 and more, a point contact 0.003 (2.6 mm at 1 rad
#: and 0.5 m)
POINT_CONSISTENCY = 0.008
#: the rotations spread about one axis (a hinge) when the second largest singular value of the rotation
#: vectors about their mean is below this share of the largest
HINGE_PLANARITY = 0.05
#: rad: RMS spread about ONE axis above which a weld's data are a door's when a point of the tool (on that
#: axis) stays put: a door opened by 60 deg spreads it by 0.28 rad; rough models turn it about no single axis
HINGE_ROTATION_SPREAD = 0.15
#: ... and when that point stays within this share of the distance frame A's origin travels (RMS): a door of
#: the UR5 simulation, 2 mm / 2 mrad / 0.02 rad off at the nominal model, 0.04 (2.8 mm against 76 mm)
HINGE_CONSISTENCY = 0.1


class WeldLoop(Loop):
    """Six closure equations per configuration.

    Residual (the exact SE(3) form of eqs. 3.18 and 4.7, no small-angle vee):

        r = log6( X^-1  T_B^-1  T_A ),        E := X^-1 T_B^-1 T_A

    where X is the pose of A in B when the loop is closed.  A half-turn error
    reads as pi, never as zero.  With right perturbations:

        dr/d(delta_A) =  Jlog6(E)
        dr/d(delta_B) = -Jlog6(E) Ad(T_A^-1 T_B)
        dr/d(delta_X) = -Jlog6(E) Ad(E^-1) = dr/d(delta_B) Ad(X)

    X is either known (``closure=`` a pin.SE3, e.g. identity for a D-H chain
    that closes on itself) or unknown with six parameters ``<loop>.x..rz``:
    X = (exp3(r), t), translation t exactly and rotation vector r, so
    d t -> delta_X = (R^T dt, 0) and d r -> delta_X = (0, Jexp3(r) dr).
    """

    translation_rows = (0, 1, 2)
    rotation_rows = (3, 4, 5)

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        closure: pin.SE3 | None = None,
        initial: pin.SE3 | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.known = closure
        self.initial = initial

    @property
    def dim(self) -> int:
        return 6

    def parameters(self) -> list[Parameter]:
        if self.known is not None:
            return []
        X = self.initial if self.initial is not None else pin.SE3.Identity()
        return pose_parameters(self.name, CLOSURE_FIELDS, X)

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """X from the first configuration: X = T_B^-1 T_A (the nominal model's guess)."""
        if self.known is not None or self.initial is not None:
            return None
        X = pin.SE3(np.linalg.solve(TB[0], TA[0]))
        return np.concatenate([X.translation, pin.log3(X.rotation)])

    def normalize(self, p: np.ndarray) -> np.ndarray:
        """The rotation vector within pi (a shorter one is returned as it is, bit for bit)."""
        if self.known is not None or np.linalg.norm(p[3:6]) < np.pi:
            return p
        return np.concatenate([p[:3], pin.log3(pin.exp3(p[3:6]))])

    def normalize_jacobian(self, p: np.ndarray) -> np.ndarray:
        """d p / d p' (`Loop.normalize_jacobian`): the rotation vectors r and r' = log3(exp3(r)) name one
        rotation, so under right perturbations Jr(r) dr = Jr(r') dr' (Jr: `pin.Jexp3`)."""
        T = np.eye(6)
        if self.known is None and np.linalg.norm(p[3:6]) >= np.pi:
            T[3:, 3:] = np.linalg.solve(pin.Jexp3(p[3:6]), pin.Jexp3(pin.log3(pin.exp3(p[3:6]))))
        return T

    def mismatch(self, Ts: list[np.ndarray], meas: np.ndarray | None = None) -> str | None:
        """A weld fixes the whole pose of A in B: `Loop.mismatch` when its orientation spreads across the rows
        by over `WELD_ROTATION_SPREAD` RMS while one point of A stays put (a pivot fit, as
        `PointLoop.initialize`: R_i t - p = -d_i) to within `POINT_CONSISTENCY` of that spread times A's
        distance from B: a point contact, or a hinge when the rotations are about one axis; or when it
        spreads by over `HINGE_ROTATION_SPREAD` about one axis while a point stays within
        `HINGE_CONSISTENCY` of the distance A's origin travels: a hinge (a door turns by less)."""
        M = np.linalg.solve(Ts[1], Ts[0])
        n = M.shape[0]
        if n < 6:
            return None
        R, d = M[:, :3, :3], M[:, :3, 3]
        U, _, Vt = np.linalg.svd(R.sum(axis=0))  # the chordal mean rotation
        Rm = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        w = log3(Rm.T @ R)[0]
        # a few corrupted rows (a cell of another unit, a glitch) are the outlier screen's, not a loop type's:
        # rows turned by over 5 times the median turn are left out here, and the rest judged
        turn = np.linalg.norm(w, axis=1)
        typical = turn <= 5.0 * float(np.median(turn)) + 1e-12
        if not typical.all():
            M = M[typical]
            n = M.shape[0]
            if n < 6:
                return None
            R, d = M[:, :3, :3], M[:, :3, 3]
            U, _, Vt = np.linalg.svd(R.sum(axis=0))
            Rm = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
            w = log3(Rm.T @ R)[0]
        spread = float(np.sqrt(np.mean(np.sum(w**2, axis=1))))
        if not spread > HINGE_ROTATION_SPREAD:
            return None
        S = np.linalg.svd(w - w.mean(axis=0), compute_uv=False)
        hinge = S[1] < HINGE_PLANARITY * S[0]
        if not (spread > WELD_ROTATION_SPREAD or hinge):
            return None
        A = np.concatenate([R, np.broadcast_to(-np.eye(3), (n, 3, 3))], axis=2).reshape(-1, 6)
        sol = np.linalg.lstsq(A, -d.reshape(-1), rcond=None)[0]
        off = float(np.sqrt(np.mean(np.sum((A @ sol + d.reshape(-1)).reshape(n, 3) ** 2, axis=1))))
        reach = max(float(np.mean(np.linalg.norm(d, axis=1))), 0.1)
        travel = float(np.sqrt(np.mean(np.sum((d - d.mean(axis=0)) ** 2, axis=1))))
        pivot = spread > WELD_ROTATION_SPREAD and off < POINT_CONSISTENCY * spread * reach
        door = hinge and off < HINGE_CONSISTENCY * travel  # the handle travels, a point on the axis stays
        if not (pivot or door):
            if spread > WELD_ROTATION_SPREAD:  # no rough model: does one point of the tool slide on a plane?
                _, on_plane, slide = contact_fits(M)
                if on_plane < ON_PLANE * slide and slide > POINT_SPREAD:
                    return (
                        f"loop '{self.name}' (weld on {self.frame_a}): the frame's orientation is not fixed across "
                        f"the rows (it spreads by {np.degrees(spread):.0f} deg RMS at the nominal model) while one "
                        f"point of it stays within {on_plane * 1e3:.3g} mm RMS of a plane: is this a plane "
                        f"contact? --loop {self.spec('plane')}"
                    )
            return None
        kind, what = ("hinge", "a hinge (it turns about one axis)") if hinge else ("point", "a point contact")
        return (
            f"loop '{self.name}' (weld on {self.frame_a}): the frame's orientation is not fixed across the rows "
            f"(it spreads by {np.degrees(spread):.0f} deg RMS at the nominal model, more than any rough model "
            f"explains) while one point of it stays within {off * 1e3:.3g} mm RMS of a fixed point: is this "
            f"{what}? --loop {self.spec(kind)}"
        )

    def describe(self) -> dict:
        return super().describe() | {
            "closure": "unknown"
            if self.known is None
            else np.concatenate([self.known.translation, pin.log3(self.known.rotation)]).tolist()
        }

    def closure(self, p: np.ndarray) -> pin.SE3:
        if self.known is not None:
            return self.known
        return pin.SE3(pin.exp3(p[3:6]), p[0:3].copy())

    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        E = self.closure(p).inverse().homogeneous @ relative(TA, TB)
        return log6(E)[0]

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        N = TA.shape[0]
        X = self.closure(p)
        Y = relative(TA, TB)  # T_B^-1 T_A
        r, Jl = log6(X.inverse().homogeneous @ Y, jacobian=True)
        assert Jl is not None  # asked for
        dB = -Jl @ adjoint(rigid_inverse(Y))
        if self.known is not None:
            return LoopEval(r, Jl, dB, np.zeros((N, 6, 0)))
        gen = np.zeros((6, 6))
        gen[:3, :3] = X.rotation.T
        gen[3:, 3:] = pin.Jexp3(p[3:6])
        dp = (dB.reshape(-1, 6) @ (X.action @ gen)).reshape(N, 6, 6)  # Ad(E^-1) = Ad(Y^-1) Ad(X): one product
        return LoopEval(r, Jl, dB, dp)


@register("weld", {"frame", "to", "closure"})
def _weld(kw: dict[str, str], robot: RobotModel) -> Loop:
    """weld:frame=tool[,to=frame_b][,closure=identity|"x y z rx ry rz"]  (closure: unknown if absent)."""
    if "frame" not in kw:
        raise LoopError("weld loop needs frame=<tool frame>")
    closure = kw.get("closure", "unknown")
    known = None
    if closure == "identity":
        known = parse_pose("0 0 0 0 0 0")
    elif closure != "unknown":
        known = parse_pose(closure)
    return WeldLoop(kw.get("name", "weld"), kw["frame"], kw.get("to", "universe"), closure=known)
