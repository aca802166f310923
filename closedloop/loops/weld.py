"""The weld loop: frame A is rigidly attached to frame B (thesis 3.3, 4.2.3)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from ..errors import LoopError
from ..parameters import DEFAULT_PRIORS, Parameter
from .base import Loop, LoopEval

CLOSURE_FIELDS = ("x", "y", "z", "rx", "ry", "rz")


class WeldLoop(Loop):
    """Six closure equations per configuration.

    Residual (the exact SE(3) form of eqs. 3.18 and 4.7, no small-angle vee):

        r = log6( X^-1  T_B^-1  T_A ),        E := X^-1 T_B^-1 T_A

    where X is the pose of A in B when the loop is closed.  A half-turn error
    reads as pi, never as zero.  With right perturbations:

        dr/d(delta_A) =  Jlog6(E)
        dr/d(delta_B) = -Jlog6(E) Ad(T_A^-1 T_B)
        dr/d(delta_X) = -Jlog6(E) Ad(E^-1)

    X is either known (``closure=`` a pin.SE3, e.g. identity for a D-H chain
    that closes on itself) or unknown with six parameters ``<loop>.x..rz``:
    X = (exp3(r), t), translation t exactly and rotation vector r, so
    d t -> delta_X = (R^T dt, 0) and d r -> delta_X = (0, Jexp3(r) dr).
    """

    translation_rows = (0, 1, 2)
    rotation_rows = (3, 4, 5)

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe",
                 closure: pin.SE3 | None = None, initial: pin.SE3 | None = None):
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
        vals = np.concatenate([X.translation, pin.log3(X.rotation)])
        out = []
        for k, f in enumerate(CLOSURE_FIELDS):
            unit = "m" if k < 3 else "rad"
            out.append(Parameter(f"{self.name}.{f}", "loop", self.name, f, float(vals[k]), unit,
                                 DEFAULT_PRIORS["loop_m" if k < 3 else "loop_rad"],
                                 scales_with_length=float(vals[k]) if k < 3 else 0.0, priority=1, order=k))
        return out

    def initialize(self, TA: np.ndarray, TB: np.ndarray) -> np.ndarray | None:
        """X from the first configuration: X = T_B^-1 T_A (the nominal model's guess)."""
        if self.known is not None or self.initial is not None:
            return None
        X = pin.SE3(np.linalg.solve(TB[0], TA[0]))
        return np.concatenate([X.translation, pin.log3(X.rotation)])

    def normalize(self, p: np.ndarray) -> np.ndarray:
        if self.known is not None:
            return p
        return np.concatenate([p[:3], pin.log3(pin.exp3(p[3:6]))])

    def describe(self) -> dict:
        return super().describe() | {"closure": "unknown" if self.known is None else
                                     np.concatenate([self.known.translation, pin.log3(self.known.rotation)]).tolist()}

    def closure(self, p: np.ndarray) -> pin.SE3:
        if self.known is not None:
            return self.known
        return pin.SE3(pin.exp3(p[3:6]), p[0:3].copy())

    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> np.ndarray:
        E = self.closure(p).inverse().homogeneous @ (rigid_inverse(TB) @ TA)
        return np.array([pin.log6(pin.SE3(Ei)).vector for Ei in E]).reshape(-1, 6)

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
        N = TA.shape[0]
        X = self.closure(p)
        Y = rigid_inverse(TB) @ TA  # T_B^-1 T_A
        E = X.inverse().homogeneous @ Y
        r = np.empty((N, 6))
        Jl = np.empty((N, 6, 6))
        for i in range(N):  # the nonlinear part, per configuration, in Pinocchio
            Ei = pin.SE3(E[i])
            r[i] = pin.log6(Ei).vector
            Jl[i] = pin.Jlog6(Ei)
        dB = -Jl @ adjoint(rigid_inverse(Y))
        if self.known is not None:
            return LoopEval(r, Jl, dB, np.zeros((N, 6, 0)))
        gen = np.zeros((6, 6))
        gen[:3, :3] = X.rotation.T
        gen[3:, 3:] = pin.Jexp3(p[3:6])
        dX = -Jl @ adjoint(rigid_inverse(E))
        return LoopEval(r, Jl, dB, dX @ gen)


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a stack of homogeneous transforms (..., 4, 4)."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """Stacked SE(3) adjoints [[R, [p]x R], [0, R]] (Pinocchio's `SE3.action`, batched)."""
    R, p = T[..., :3, :3], T[..., :3, 3]
    px = np.zeros(p.shape[:-1] + (3, 3))
    px[..., 0, 1], px[..., 0, 2], px[..., 1, 2] = -p[..., 2], p[..., 1], -p[..., 0]
    px[..., 1, 0], px[..., 2, 0], px[..., 2, 1] = p[..., 2], -p[..., 1], p[..., 0]
    Ad = np.zeros(T.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., :3, 3:] = px @ R
    Ad[..., 3:, 3:] = R
    return Ad


def identity_closure() -> pin.SE3:
    return pin.SE3.Identity()


def parse_pose(text: str) -> pin.SE3:
    """'x y z rx ry rz' (rotation vector) -> SE3."""
    try:
        v = np.array([float(t) for t in text.replace(",", " ").split()])
    except ValueError:
        raise LoopError(f"closure '{text}': expected six numbers 'x y z rx ry rz'") from None
    if v.size != 6 or not np.all(np.isfinite(v)):
        raise LoopError(f"closure '{text}': expected six finite numbers 'x y z rx ry rz'")
    return pin.SE3(pin.exp3(v[3:]), v[:3])
