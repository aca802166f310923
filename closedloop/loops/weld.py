"""The weld loop: frame A is rigidly attached to frame B (thesis 3.3, 4.2.3).

With the batched SE(3) algebra it runs on: Pinocchio's log3, log6 and Jlog6
over a stack of configurations (`log3`, `log6`), `rigid_inverse`, `adjoint`.
"""

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
        dr/d(delta_X) = -Jlog6(E) Ad(E^-1) = dr/d(delta_B) Ad(X)

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
        """The rotation vector within pi (a shorter one is returned as it is, bit for bit)."""
        if self.known is not None or np.linalg.norm(p[3:6]) < np.pi:
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
        return log6(E)[0]

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
        N = TA.shape[0]
        X = self.closure(p)
        Y = rigid_inverse(TB) @ TA  # T_B^-1 T_A
        r, Jl = log6(X.inverse().homogeneous @ Y, jacobian=True)
        dB = -Jl @ adjoint(rigid_inverse(Y))
        if self.known is not None:
            return LoopEval(r, Jl, dB, np.zeros((N, 6, 0)))
        gen = np.zeros((6, 6))
        gen[:3, :3] = X.rotation.T
        gen[3:, 3:] = pin.Jexp3(p[3:6])
        return LoopEval(r, Jl, dB, dB @ (X.action @ gen))  # Ad(E^-1) = Ad(Y^-1) Ad(X)


# Pinocchio's TaylorSeriesExpansion<double>::precision<k>() = eps^(1/(k+1)): its branch thresholds.
_EPS = float(np.finfo(float).eps)
_PREC2 = _EPS ** (1.0 / 3.0)
_PREC3 = _EPS ** (1.0 / 4.0)
_DIAG = ([0, 1, 2], [0, 1, 2])

# Sums in Eigen's order (a vector's squared norm or dot product: (x0 + x1) + x2; a trace: d0 + (d1 + d2)),
# so that log3 near pi, where theta / sin(theta) amplifies the last bit of the trace, matches Pinocchio.


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a . b for stacks (n, 3)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _trace3(M: np.ndarray) -> np.ndarray:
    """tr M for a stack (n, 3, 3)."""
    return M[:, 0, 0] + (M[:, 1, 1] + M[:, 2, 2])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for stacks (n, 3) (np.cross's arithmetic without its axis handling)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _unskew(M: np.ndarray) -> np.ndarray:
    """(M - M^T)/2 as a vector, for a stack (n, 3, 3)."""
    return 0.5 * np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], axis=1)


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x for a stack (n, 3) -> (n, 3, 3)."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return S


def log3(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors w (n, 3) and angles theta in [0, pi] (n,) of a stack of rotations (n, 3, 3).

    Pinocchio's log3, batched, branch for branch: R is re-orthonormalised,
    cos(theta) = (tr R - 1)/2 and, away from pi, w = theta / sin(theta) * unskew(R)
    (Taylor series at small angles).  Within eps^(1/3) of pi the axis comes from
    the symmetric part: the index i0 of the largest 2 R_ii - tr R + 1 gives
    s = +-sqrt(that), axis_i0 = s/2, axis_k = (R_k,i0 + R_i0,k)/(2s) and
    theta = 2 atan2(|axis|, (R_i2,i1 - R_i1,i2)/(2s)).
    """
    c0 = R[:, :, 0] / np.sqrt(_dot3(R[:, :, 0], R[:, :, 0]))[:, None]
    c1 = R[:, :, 1] / np.sqrt(_dot3(R[:, :, 1], R[:, :, 1]))[:, None]
    c2 = _cross(c0, c1)
    Rn = np.stack([_cross(c1, c2), c1, c2], axis=2)
    tr = _trace3(Rn)
    cos = (tr - 1.0) / 2.0
    acos_exp = np.sqrt(2.0 * (1.0 - cos) + _EPS * _EPS)
    theta = np.where(tr <= 3.0 - _PREC2,
                     np.where(tr >= -1.0 + _PREC2, np.arccos(np.clip(cos, -1.0, 1.0)), np.pi - acos_exp), acos_exp)
    a = _unskew(Rn)
    t2 = _dot3(a, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(theta >= _PREC2, theta / np.sin(theta), 1.0 + t2 / 6.0 + t2 * t2 * 3.0 / 40.0)
    w = t[:, None] * a
    sing = np.flatnonzero(cos < -1.0 + _PREC2)
    if sing.size:
        Rs = Rn[sing]
        val = 2.0 * np.diagonal(Rs, axis1=1, axis2=2) - tr[sing, None] + 1.0
        i0 = np.argmax(val, axis=1)  # ties to the lowest index, as Pinocchio's comparisons
        i1, i2 = (i0 + 1) % 3, (i0 + 2) % 3
        n = np.arange(sing.size)
        s = np.sqrt(val[n, i0] + _EPS + _EPS * _EPS) * np.where(Rs[n, i2, i1] >= Rs[n, i1, i2], 1.0, -1.0)
        axis = np.empty((sing.size, 3))
        axis[n, i0] = s / 2.0
        axis[n, i1] = 1.0 / (2.0 * s) * (Rs[n, i1, i0] + Rs[n, i0, i1])
        axis[n, i2] = 1.0 / (2.0 * s) * (Rs[n, i2, i0] + Rs[n, i0, i2])
        wq = 1.0 / (2.0 * s) * (Rs[n, i2, i1] - Rs[n, i1, i2])
        norm = np.sqrt(_dot3(axis, axis))
        theta[sing] = 2.0 * np.arctan2(norm, wq)
        w[sing] = theta[sing, None] * (axis / norm[:, None])
    return w, theta


def log6(T: np.ndarray, jacobian: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """log6 (n, 6) of a stack of poses (n, 4, 4) and, on request, Jlog6 (n, 6, 6).

    Pinocchio's log6 and Jlog6, batched, branch for branch (checked against
    them in tests/test_se3_batched.py).  With (w, theta) = log3(R), p the
    translation and st, ct = sin, cos(theta):

        v = alpha p - 1/2 w x p + beta (w.p) w,
        alpha = theta st / (2 (1 - ct)),  beta = 1/theta^2 - st / (2 theta (1 - ct))

    (Taylor series near tr R = 3), and Jlog6 = [[A, C A], [0, A]] with A the
    right Jacobian of log3,

        A = a w w^T + d I + [w]x / 2,   a = beta,  d = theta st / (2 (1 - ct)),
        C = (b' (w.p) w - (theta^2 b' + 2 beta) p) w^T + beta w p^T + beta (w.p) I + [p]x / 2,

    b' = (d beta / d theta) / theta (Taylor series below theta = eps^(1/4)).
    """
    R, p = T[:, :3, :3], T[:, :3, 3]
    w, th = log3(R)
    st, ct = np.sin(th), np.cos(th)
    a = _unskew(R)
    t2 = _dot3(a, a)
    wp = _dot3(w, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        series = _trace3(R) >= 3.0 - _PREC2
        alpha = np.where(series, 1.0 - t2 / 12.0 - t2 * t2 / 720.0, th * st / (2.0 * (1.0 - ct)))
        beta = np.where(series, 1.0 / 12.0 + t2 / 720.0, 1.0 / (th * th) - st / (2.0 * th * (1.0 - ct)))
    r = np.concatenate([alpha[:, None] * p - 0.5 * _cross(w, p) + (beta * wp)[:, None] * w, w], axis=1)
    if not jacobian:
        return r, None
    small = th < _PREC3
    th2 = th * th
    with np.errstate(divide="ignore", invalid="ignore"):
        st_1mct = st / (1.0 - ct)
        tinv = 1.0 / th
        t2inv = tinv * tinv
        inv_2_2ct = 1.0 / (2.0 * (1.0 - ct))
        a3 = np.where(small, 1.0 / 12.0 + th2 / 720.0, 1.0 / th2 - st_1mct / (2.0 * th))
        d3 = np.where(small, 0.5 * (2.0 - th2 / 6.0), 0.5 * (th * st_1mct))
        b = np.where(small, 1.0 / 12.0 + th2 / 720.0, t2inv - st * tinv * inv_2_2ct)
        bdot = np.where(small, 1.0 / 360.0, -2.0 * t2inv * t2inv + (1.0 + st * tinv) * t2inv * inv_2_2ct)
    A = (a3[:, None] * w)[:, :, None] * w[:, None, :] + _skew(0.5 * w)
    A[:, _DIAG[0], _DIAG[1]] += d3[:, None]
    v3 = (bdot * wp)[:, None] * w - (th2 * bdot + 2.0 * b)[:, None] * p
    C = v3[:, :, None] * w[:, None, :] + (b[:, None] * w)[:, :, None] * p[:, None, :] + _skew(0.5 * p)
    C[:, _DIAG[0], _DIAG[1]] += (wp * b)[:, None]
    Jl = np.zeros((T.shape[0], 6, 6))
    Jl[:, :3, :3] = A
    Jl[:, 3:, 3:] = A
    Jl[:, :3, 3:] = C @ A
    return r, Jl


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
