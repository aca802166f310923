"""The camera model: pinhole with lens distortion, its inverse, and the linear start (DLT / PnP).

Pinhole (thesis 5.2.2, eqs. 5.3-5.4, the image offsets as the principal
point), with OpenCV's distortion model (Brown-Conrady; the "more refined
parametric models including lens distortions" of 5.2.2):

    (xn, yn) = (px / pz, py / pz),  r2 = xn^2 + yn^2
    radial   = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = xn radial + 2 p1 xn yn + p2 (r2 + 2 xn^2)
    yd = yn radial + p1 (r2 + 2 yn^2) + 2 p2 xn yn
    (u, v) = (fx xd + cx, fy yd + cy)

k = (fx, fy, cx, cy), d = (k1, k2, p1, p2, k3) (OpenCV's order).  Every
function returns its analytic Jacobians; ``tests/test_camera_distortion.py``
checks them against finite differences.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

INTRINSIC_FIELDS = ("fx", "fy", "cx", "cy")
DIST_FIELDS = ("k1", "k2", "p1", "p2", "k3")
NO_DIST = np.zeros(5)


def distort(xn: np.ndarray, yn: np.ndarray, d: np.ndarray):
    """Distorted normalised coordinates and their Jacobians.

    Returns xd, yd (N,), Dn = d(xd, yd)/d(xn, yn) (N, 2, 2) and
    Dd = d(xd, yd)/d(k1, k2, p1, p2, k3) (N, 2, 5):

        d xd/d xn = radial + 2 xn^2 R' + 2 p1 yn + 6 p2 xn,  d xd/d yn = 2 xn yn R' + 2 p1 xn + 2 p2 yn
        d yd/d xn = 2 xn yn R' + 2 p1 xn + 2 p2 yn,          d yd/d yn = radial + 2 yn^2 R' + 6 p1 yn + 2 p2 xn
        R' = k1 + 2 k2 r2 + 3 k3 r2^2
    """
    k1, k2, p1, p2, k3 = d
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = xn * yn
    xd = xn * radial + 2 * p1 * xy + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xy
    N = xn.shape[0]
    Rp = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    Dn = np.empty((N, 2, 2))
    Dn[:, 0, 0] = radial + 2 * xn * xn * Rp + 2 * p1 * yn + 6 * p2 * xn
    Dn[:, 0, 1] = Dn[:, 1, 0] = 2 * xy * Rp + 2 * p1 * xn + 2 * p2 * yn
    Dn[:, 1, 1] = radial + 2 * yn * yn * Rp + 6 * p1 * yn + 2 * p2 * xn
    Dd = np.empty((N, 2, 5))
    Dd[:, 0, 0], Dd[:, 1, 0] = xn * r2, yn * r2
    Dd[:, 0, 1], Dd[:, 1, 1] = xn * r2 * r2, yn * r2 * r2
    Dd[:, 0, 2], Dd[:, 1, 2] = 2 * xy, r2 + 2 * yn * yn
    Dd[:, 0, 3], Dd[:, 1, 3] = r2 + 2 * xn * xn, 2 * xy
    Dd[:, 0, 4] = xn * r2**3
    Dd[:, 1, 4] = yn * r2**3
    return xd, yd, Dn, Dd


def project(pc: np.ndarray, k: np.ndarray, jacobian: bool = True):
    """Pinhole projection without distortion: uv, d uv/d pc (N, 2, 3), d uv/d k (N, 2, 4)."""
    uv, Jp, Jk, _ = project_lens(pc, k, None, jacobian)
    return uv, Jp, Jk


def project_lens(pc: np.ndarray, k: np.ndarray, d: np.ndarray | None, jacobian: bool = True):
    """Projection of camera-frame points pc (N, 3) through intrinsics k and distortion d (None: none).

    uv = (fx xd + cx, fy yd + cy).  Jacobians (N, 2, .):

        d uv / d pc = diag(fx, fy) Dn [[1/pz, 0, -xn/pz], [0, 1/pz, -yn/pz]]
        d uv / d k  = [[xd, 0, 1, 0], [0, yd, 0, 1]]
        d uv / d d  = diag(fx, fy) Dd                  (None without distortion)
    """
    iz = 1.0 / pc[:, 2]
    xn, yn = pc[:, 0] * iz, pc[:, 1] * iz
    if d is None:
        xd, yd, Dn, Dd = xn, yn, None, None
    else:
        xd, yd, Dn, Dd = distort(xn, yn, d)
    uv = np.column_stack([k[0] * xd + k[2], k[1] * yd + k[3]])
    if not jacobian:
        return uv, None, None, None
    N = pc.shape[0]
    Jn = np.zeros((N, 2, 3))  # d(xn, yn)/d pc
    Jn[:, 0, 0] = Jn[:, 1, 1] = iz
    Jn[:, 0, 2] = -xn * iz
    Jn[:, 1, 2] = -yn * iz
    F = np.array([k[0], k[1]])[None, :, None]
    Jp = F * (Jn if Dn is None else Dn @ Jn)
    Jk = np.zeros((N, 2, 4))
    Jk[:, 0, 0], Jk[:, 1, 1] = xd, yd
    Jk[:, 0, 2] = Jk[:, 1, 3] = 1.0
    return uv, Jp, Jk, (None if Dd is None else F * Dd)


def undistort(xd: np.ndarray, yd: np.ndarray, d: np.ndarray, iters: int = 30):
    """(xn, yn) with distort(xn, yn) = (xd, yd), by Newton's method from (xd, yd); and its Jacobians.

    By the implicit function theorem d(xn, yn)/d(xd, yd) = Dn^-1 and
    d(xn, yn)/d d = -Dn^-1 Dd at the solution.  Converges to machine
    precision for the distortion of real lenses (Dn well conditioned).
    """
    xn, yn = xd.copy(), yd.copy()
    for _ in range(iters):
        ex, ey, Dn, _ = distort(xn, yn, d)
        e = np.column_stack([ex - xd, ey - yd])
        step = np.linalg.solve(Dn, e[:, :, None])[:, :, 0]
        xn, yn = xn - step[:, 0], yn - step[:, 1]
        if np.all(np.abs(step) < 1e-15 * (1 + np.abs(np.column_stack([xn, yn])))):
            break
    _, _, Dn, Dd = distort(xn, yn, d)
    Dinv = np.linalg.inv(Dn)
    return xn, yn, Dinv, -Dinv @ Dd


def image_ray(uv: np.ndarray, k: np.ndarray, d: np.ndarray | None):
    """The line of sight of pixels uv (N, 2): ray (xn, yn, 1) in the camera frame, and its Jacobians.

    Returns ray (N, 3), d ray/d uv (N, 3, 2), d ray/d k (N, 3, 4), d ray/d d (N, 3, 5) or None.
    (xd, yd) = ((u - cx)/fx, (v - cy)/fy); d(xd)/d fx = -xd/fx, d(xd)/d cx = -1/fx.
    """
    N = uv.shape[0]
    xd, yd = (uv[:, 0] - k[2]) / k[0], (uv[:, 1] - k[3]) / k[1]
    Gk = np.zeros((N, 2, 4))  # d(xd, yd)/d k
    Gk[:, 0, 0], Gk[:, 1, 1] = -xd / k[0], -yd / k[1]
    Gk[:, 0, 2], Gk[:, 1, 3] = -1.0 / k[0], -1.0 / k[1]
    Gu = np.zeros((N, 2, 2))
    Gu[:, 0, 0], Gu[:, 1, 1] = 1.0 / k[0], 1.0 / k[1]
    if d is None:
        xn, yn, A, Bd = xd, yd, None, None
    else:
        xn, yn, A, Bd = undistort(xd, yd, d)
    ray = np.column_stack([xn, yn, np.ones(N)])
    Ru = np.zeros((N, 3, 2))
    Rk = np.zeros((N, 3, 4))
    Ru[:, :2] = Gu if A is None else A @ Gu
    Rk[:, :2] = Gk if A is None else A @ Gk
    Rd = None
    if Bd is not None:
        Rd = np.zeros((N, 3, 5))
        Rd[:, :2] = Bd
    return ray, Ru, Rk, Rd


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
        from scipy.linalg import rq  # scipy.linalg costs ~0.2 s to import: only when a camera is fitted

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


PLACEHOLDER_K = np.array([1000.0, 1000.0, 0.0, 0.0])  # unknown intrinsics with no guess: replaced by the DLT
