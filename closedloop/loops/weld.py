"""The weld loop: frame A is rigidly attached to frame B (thesis 3.3, 4.2.3).

It runs on the batched SE(3) algebra of `closedloop.model.se3` (log6 with Jlog6 over
a stack of configurations, `rigid_inverse`, `adjoint`).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import POSE_FIELDS, pose_parameters
from closedloop.model.parameters import Parameter
from closedloop.model.se3 import adjoint, log6, parse_pose, rigid_inverse  # noqa: F401  (parse_pose: spec.py's)

CLOSURE_FIELDS = POSE_FIELDS


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
        E = self.closure(p).inverse().homogeneous @ (rigid_inverse(TB) @ TA)
        return log6(E)[0]

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        N = TA.shape[0]
        X = self.closure(p)
        Y = rigid_inverse(TB) @ TA  # T_B^-1 T_A
        r, Jl = log6(X.inverse().homogeneous @ Y, jacobian=True)
        assert Jl is not None  # asked for
        dB = -Jl @ adjoint(rigid_inverse(Y))
        if self.known is not None:
            return LoopEval(r, Jl, dB, np.zeros((N, 6, 0)))
        gen = np.zeros((6, 6))
        gen[:3, :3] = X.rotation.T
        gen[3:, 3:] = pin.Jexp3(p[3:6])
        return LoopEval(r, Jl, dB, dB @ (X.action @ gen))  # Ad(E^-1) = Ad(Y^-1) Ad(X)
