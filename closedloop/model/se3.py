"""SE(3) algebra, batched, and the parsing of poses and vectors given by a user.

Every loop's residual is an exact SE(3) or R^3 closure error; this module holds
the geometry they share, so that a loop's file holds only its own equations:

* `log3`, `log6` (with Jlog6): Pinocchio's formulas over a stack of poses
  (n, 4, 4), branch for branch (thesis eqs. 3.18, 4.7 use their small-angle
  form); `rigid_inverse`, `adjoint` (Ad(T) = [[R, [p]x R], [0, R]]), `skew`;
* `pose_of` / `vec_of`: a pose as (x, y, z, rx, ry, rz) (translation,
  rotation vector) and back, `generators`: d delta / d v of that chart under
  right perturbations, delta = (R^T dt, Jexp3(r) dr);
* `kabsch` (the rigid fit y ~ R m + t), `project_so3`, `hand_eye` (W_i Y = X M_i);
* `as_se3`, `vec3`, `parse_vec`, `parse_pose`: a user's pose or vector
  (an SE3, a 4x4 matrix, numbers or text), refused with a `LoopError` naming it.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x for a batch (..., 3) -> (..., 3, 3): [v]x u = v x u."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


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
    """a x b for stacks (n, 3) (np.cross's arithmetic without its axis handling; written into one array:
    `np.stack`'s own cost is most of a short stack's)."""
    out = np.empty((a.shape[0], 3))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _unskew(M: np.ndarray) -> np.ndarray:
    """(M - M^T)/2 as a vector, for a stack (n, 3, 3)."""
    out = np.empty((M.shape[0], 3))
    out[:, 0] = M[:, 2, 1] - M[:, 1, 2]
    out[:, 1] = M[:, 0, 2] - M[:, 2, 0]
    out[:, 2] = M[:, 1, 0] - M[:, 0, 1]
    return 0.5 * out


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
    Rn = np.empty((R.shape[0], 3, 3))
    Rn[:, :, 0], Rn[:, :, 1], Rn[:, :, 2] = _cross(c1, c2), c1, c2
    tr = _trace3(Rn)
    cos = (tr - 1.0) / 2.0
    acos_exp = np.sqrt(2.0 * (1.0 - cos) + _EPS * _EPS)
    theta = np.where(
        tr <= 3.0 - _PREC2,
        np.where(tr >= -1.0 + _PREC2, np.arccos(np.clip(cos, -1.0, 1.0)), np.pi - acos_exp),
        acos_exp,
    )
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
    them in tests/test_se3.py).  With (w, theta) = log3(R), p the
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
    A = (a3[:, None] * w)[:, :, None] * w[:, None, :] + skew(0.5 * w)
    A[:, _DIAG[0], _DIAG[1]] += d3[:, None]
    v3 = (bdot * wp)[:, None] * w - (th2 * bdot + 2.0 * b)[:, None] * p
    C = v3[:, :, None] * w[:, None, :] + (b[:, None] * w)[:, :, None] * p[:, None, :] + skew(0.5 * p)
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


def relative(TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
    """T_B^-1 T_A for stacks (N, 4, 4); TA itself where TB is the base's pose (the identity broadcast along the
    stack, as `CalibrationProblem.frame_kinematics` gives frame 0)."""
    if TB.ndim == 3 and TB.strides[0] == 0 and np.array_equal(TB[0], np.eye(4)):
        return TA
    return rigid_inverse(TB) @ TA


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


def poses_from_adjoints(Ad: np.ndarray, P: np.ndarray) -> np.ndarray:
    """T = P X^-1 (N, 4, 4) for stacked adjoints Ad(X) (N, 6, 6) and a pose P (4, 4).

    X is read off its adjoint [[R, [p]x R], [0, R]]: R, then [p]x = (upper right) R^T.  With
    X = T^-1 P: T = (R_P R^T, p_P - R_P R^T p).
    """
    R = Ad[:, 3:, 3:]
    px = Ad[:, :3, 3:] @ np.swapaxes(R, 1, 2)
    p = np.stack([px[:, 2, 1], px[:, 0, 2], px[:, 1, 0]], axis=1)
    T = np.zeros((Ad.shape[0], 4, 4))
    T[:, :3, :3] = P[:3, :3] @ np.swapaxes(R, 1, 2)
    T[:, :3, 3] = P[:3, 3] - np.einsum("nij,nj->ni", T[:, :3, :3], p)
    T[:, 3, 3] = 1.0
    return T


def pose_of(v: np.ndarray) -> pin.SE3:
    """(x, y, z, rx, ry, rz) -> SE3 (translation, rotation vector): X = (exp3(r), t)."""
    return pin.SE3(pin.exp3(v[3:6]), np.asarray(v[0:3], dtype=float).copy())


def vec_of(X: pin.SE3) -> np.ndarray:
    """SE3 -> (x, y, z, rx, ry, rz), the inverse of `pose_of` (rotation vector within pi)."""
    return np.concatenate([X.translation, pin.log3(X.rotation)])


def generators(v: np.ndarray) -> np.ndarray:
    """d delta / d v for X = pose_of(v) under right perturbations: blockdiag(R^T, Jexp3(r)) (as in WeldLoop)."""
    g = np.zeros((6, 6))
    g[:3, :3] = pin.exp3(v[3:6]).T
    g[3:, 3:] = pin.Jexp3(v[3:6])
    return g


def kabsch(m: np.ndarray, y: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid fit y_i ~ R m_i + t (Kabsch / Horn); R0 when the points are (nearly) collinear.

    H = sum (m_i - m̄)(y_i - ȳ)^T = U S V^T, R = V diag(1, 1, det(V U^T)) U^T, t = ȳ - R m̄.
    """
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


def project_so3(A: np.ndarray) -> np.ndarray:
    """The rotation nearest to A (Frobenius): U diag(1, 1, det(U V^T)) V^T with A = U S V^T."""
    U, _, Vt = np.linalg.svd(A)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def hand_eye(W: list[pin.SE3], M: list[pin.SE3]) -> tuple[pin.SE3, pin.SE3] | None:
    """Closed-form X, Y of W_i Y = X M_i, robot-world hand-eye (None when the rotations do not determine them).

    Rotations: the null vector of [I (x) R_Wi, -R_Mi^T (x) I] [vec R_Y; vec R_X] = 0 stacked over i
    (column-major vec), each block projected on SO(3); translations: the least squares
    R_Wi t_Y - t_X = R_X t_Mi - t_Wi.
    """
    I3 = np.eye(3)
    A = np.concatenate([np.hstack([np.kron(I3, w.rotation), -np.kron(m.rotation.T, I3)]) for w, m in zip(W, M)])
    _, S, Vt = np.linalg.svd(A, full_matrices=A.shape[0] < A.shape[1])  # (not U: 9n x 9n)
    if not S[-2] > 1e-6 * S[0]:
        return None
    v = Vt[-1]
    RY, RX = v[:9].reshape(3, 3, order="F"), v[9:].reshape(3, 3, order="F")
    if np.linalg.det(RY) < 0:
        RY, RX = -RY, -RX
    RY, RX = project_so3(RY), project_so3(RX)
    # translations: R_Wi t_Y - t_X = R_X t_Mi - t_Wi
    B = np.concatenate([np.hstack([w.rotation, -I3]) for w in W])
    b = np.concatenate([RX @ m.translation - w.translation for w, m in zip(W, M)])
    t, *_ = np.linalg.lstsq(B, b, rcond=1e-9)
    if not np.all(np.isfinite(t)):
        return None
    return pin.SE3(RX, t[3:]), pin.SE3(RY, t[:3])


def as_se3(X, what: str) -> pin.SE3:
    """A user's pose: a pin.SE3, a 4x4 matrix or six numbers (x y z rx ry rz); LoopError naming `what`."""
    if isinstance(X, pin.SE3):
        return X
    a = np.asarray(X, dtype=float)
    if a.shape == (4, 4):
        return pin.SE3(a)
    a = a.reshape(-1)
    if a.size != 6 or not np.all(np.isfinite(a)):
        raise LoopError(f"{what}: expected an SE3, a 4x4 matrix or six numbers 'x y z rx ry rz'")
    return pose_of(a)


def vec3(v, what: str) -> np.ndarray:
    """A user's 3-vector (three finite numbers); LoopError naming `what`."""
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.size != 3 or not np.all(np.isfinite(a)):
        raise LoopError(f"{what}: expected three finite numbers, got {v!r}")
    return a


def parse_vec(text: str, n: int, what: str) -> np.ndarray:
    """'x y z' (spaces or commas) -> array of n finite numbers."""
    try:
        v = np.array([float(t) for t in text.replace(",", " ").split()])
    except ValueError:
        raise LoopError(f"{what} '{text}': expected {n} numbers") from None
    if v.size != n or not np.all(np.isfinite(v)):
        raise LoopError(f"{what} '{text}': expected {n} finite numbers")
    return v


def parse_pose(text: str) -> pin.SE3:
    """'x y z rx ry rz' (rotation vector) -> SE3."""
    try:
        v = np.array([float(t) for t in text.replace(",", " ").split()])
    except ValueError:
        raise LoopError(f"closure '{text}': expected six numbers 'x y z rx ry rz'") from None
    if v.size != 6 or not np.all(np.isfinite(v)):
        raise LoopError(f"closure '{text}': expected six finite numbers 'x y z rx ry rz'")
    return pin.SE3(pin.exp3(v[3:]), v[:3])
