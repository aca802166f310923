"""The stereo-triangulation closure of the camera loop (thesis 5.2.2-5.2.3, eqs. 5.11-5.13).

Everything is expressed in camera 1's frame C1 (the thesis's left camera).
With the lines of sight d1 (camera 1) and d2 (camera 2) of the observed
pixels (``camera.model.image_ray``: (xn, yn, 1), distortion removed), camera
2's pose in C1, Q = X_1^-1 T_F1^-1 T_F2 X_2, its focal point p = t_Q (the
thesis's **p**, left to right focal point) and its ray u2 = R_Q d2:

    x~ = c d1,   c = Gamma(p) = ((u2 x d1) . (u2 x p)) / |u2 x d1|^2          (5.11, 5.12)
    r  = x~ - x^,   x^ = X_1^-1 T_F1^-1 T_A t  (the arm's point, eq. 5.2)      (5.13)

x~ is the point of camera 1's ray nearest to camera 2's ray, exact (no small
error form).  With a = u2 x d1, b = u2 x p:

    dc/dp  = a^T [u2]x / |a|^2
    dc/du2 = (-b^T [d1]x - a^T [p]x + 2 c a^T [d1]x) / |a|^2
    dc/dd1 = (b^T [u2]x - 2 c a^T [u2]x) / |a|^2
    dr/dp = d1 dc/dp,  dr/du2 = d1 dc/du2,  dr/dd1 = c I + d1 dc/dd1,  dr/dx^ = -I

and the perturbations move p, u2, x^ as points / directions expressed in C1:
a right perturbation delta of T_F1 moves what is not attached to F1 by
S [-I [z]x] (points z in F1) and S [0 [w]x] (directions), S = R_X1^T; one of
T_F2 moves camera 2 by S R_F1F2 [I -[o]x] and S R_F1F2 [0 -[w]x] (o, w in F2);
one of X_1 moves everything by [-I [z]x] / [0 [u]x] in C1; one of X_2 moves
camera 2 by R_Q [I 0] and R_Q [0 -[d2]x].  The pixels' covariance
sigma_px^2 (G1 G1^T + G2 G2^T) (G_c = dr/d uv_c) is returned in LoopEval.cov.
"""

from __future__ import annotations

import numpy as np

from closedloop.loops.base import LoopEval
from closedloop.loops.camera.model import image_ray
from closedloop.loops.common import relative_point
from closedloop.model.se3 import generators, skew


def _perturb(S: np.ndarray, z: np.ndarray, sign: float, direction: bool) -> np.ndarray:
    """(N, 3, 6) S [sign I  -sign [z]x] for points (sign -1: [-I [z]x]), S [0 -sign [z]x] for directions."""
    N = z.shape[0]
    out = np.zeros((N, 3, 6))
    if not direction:
        out[:, :, :3] = sign * np.eye(3)
    out[:, :, 3:] = -sign * skew(z)
    return S @ out


def triangulation_eval(loop, Ts: list[np.ndarray], p: np.ndarray, m: np.ndarray, jac: bool) -> LoopEval:
    """Residual (N, 3) and Jacobians of the triangulation closure of a two-camera `loop` (CameraLoop).

    `m` (N, 4): the pixels u1, v1, u2, v2 per configuration (NaN: out of view).
    """
    N = Ts[0].shape[0]
    uv1, uv2 = np.nan_to_num(m[:, 0:2], nan=0.0), np.nan_to_num(m[:, 2:4], nan=0.0)
    f1, f2 = loop._fidx
    TF1, TF2, TA = Ts[f1], Ts[f2], Ts[0]
    X1, X2 = loop.camera_pose(p, 0), loop.camera_pose(p, 1)
    k1, k2 = loop.intrinsics(p, 0), loop.intrinsics(p, 1)
    dd1, dd2 = loop.distortion(p, 0), loop.distortion(p, 1)
    d1, D1u, D1k, D1d = image_ray(uv1, k1, dd1)
    d2, D2u, D2k, D2d = image_ray(uv2, k2, dd2)
    S = X1.rotation.T
    RF1t = np.swapaxes(TF1[:, :3, :3], 1, 2)
    R12 = RF1t @ TF2[:, :3, :3]
    o2F1 = np.einsum("nij,nj->ni", RF1t, TF2[:, :3, 3] - TF1[:, :3, 3]) + R12 @ X2.translation
    w2F2 = d2 @ X2.rotation.T  # rows: R_X2 d2
    w2F1 = np.einsum("nij,nj->ni", R12, w2F2)
    pp = (o2F1 - X1.translation) @ S.T
    u2 = w2F1 @ S.T
    y, RFA, dyA, dyF = relative_point(TA, TF1, loop.tip_point(p))
    xh = (y - X1.translation) @ S.T
    a = np.cross(u2, d1)
    b = np.cross(u2, pp)
    aa = np.einsum("ni,ni->n", a, a)
    c = np.einsum("ni,ni->n", a, b) / aa
    r = c[:, None] * d1 - xh
    if not jac:
        return LoopEval(r, None, None, np.zeros((N, 3, 0)))
    ia = (1.0 / aa)[:, None]
    A = a[:, None, :]
    dc_dp = (A @ skew(u2))[:, 0] * ia
    dc_du2 = ((-b[:, None, :] @ skew(d1) - A @ skew(pp) + 2 * c[:, None, None] * (A @ skew(d1)))[:, 0]) * ia
    dc_dd1 = ((b[:, None, :] @ skew(u2) - 2 * c[:, None, None] * (A @ skew(u2)))[:, 0]) * ia
    Rp = d1[:, :, None] * dc_dp[:, None, :]
    Ru = d1[:, :, None] * dc_du2[:, None, :]
    Rd = c[:, None, None] * np.eye(3) + d1[:, :, None] * dc_dd1[:, None, :]
    dF = [np.zeros((N, 3, 6)) for _ in loop.frames]
    dF[0] += -S @ dyA
    dF[f1] += -S @ dyF + Rp @ _perturb(S, o2F1, -1.0, False) + Ru @ _perturb(S, w2F1, -1.0, True)
    SR12 = S @ R12
    dF[f2] += Rp @ _perturb(SR12, np.broadcast_to(X2.translation, (N, 3)), 1.0, False) + Ru @ _perturb(
        SR12, w2F2, 1.0, True
    )
    I3 = np.broadcast_to(np.eye(3), (N, 3, 3))
    dX1 = -_perturb(I3, xh, -1.0, False) + Rp @ _perturb(I3, pp, -1.0, False) + Ru @ _perturb(I3, u2, -1.0, True)
    RQ = SR12 @ X2.rotation
    dX2 = Rp @ _perturb(RQ, np.zeros((N, 3)), 1.0, False) + Ru @ _perturb(RQ, d2, 1.0, True)
    dp = np.zeros((N, 3, loop.n_own))
    if loop.rig is not None:
        dX1 = dX1 + dX2 @ loop.rig.inverse().action
    for c_, dX in ((0, dX1), (1, dX2)):
        sl = loop.sl[f"pose{c_}"]
        if sl is not None:
            dp[:, :, sl] = dX @ generators(p[sl])
    Gu2 = Ru @ RQ  # dr/d(ray 2 in C2)
    for c_, G, Dk, Dd in ((0, Rd, D1k, D1d), (1, Gu2, D2k, D2d)):
        if loop.sl[f"K{c_}"] is not None:
            dp[:, :, loop.sl[f"K{c_}"]] = G @ Dk
        if loop.sl[f"D{c_}"] is not None:
            dp[:, :, loop.sl[f"D{c_}"]] = (G @ Dd)[:, :, loop._dist_idx]
    if loop.sl["tip"] is not None:
        dp[:, :, loop.sl["tip"]] = -S @ RFA
    cov = None
    if loop.sigma_px is not None:
        G1, G2 = Rd @ D1u, Gu2 @ D2u
        cov = loop.sigma_px**2 * (G1 @ np.swapaxes(G1, 1, 2) + G2 @ np.swapaxes(G2, 1, 2))
    two = len(loop.frames) == 2
    return LoopEval(r, dF[0] if two else None, dF[1] if two else None, dp, dF=dF, cov=cov)
