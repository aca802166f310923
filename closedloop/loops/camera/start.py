"""The camera loop's start: DLT / PnP per camera, then Gauss-Newton with the robot held (thesis 3.2).

Deterministic.  After the refinement a camera whose pixels the model still
misses by much more than their noise (e.g. a camera declared fixed in a frame
while it turns on its own joint) is reported in the log, with the cure.

A marker of unknown position seen by a camera of unknown pose (one board point
seen from a hand camera) gets a second start from its rays (`ray_start`): the
DLT alone must assume a marker position, and from a wrong one the refinement
can run off to a far-away minimum (a camera 3 km away seeing every pixel at
the image centre).
"""

from __future__ import annotations

import logging
from functools import lru_cache

import numpy as np
import pinocchio as pin

from closedloop.loops import common
from closedloop.loops.camera.model import PLACEHOLDER_K, camera_from_dlt
from closedloop.loops.common import relative_point
from closedloop.model.se3 import vec_of

log = logging.getLogger(__name__)
MISFIT_PX = 20.0  # a camera's start RMS (px) above which its model is suspect


def initialize_camera_loop(loop, Ts: list[np.ndarray], meas: np.ndarray | None) -> np.ndarray | None:
    """Unknown camera poses, intrinsics, distortion and marker fitted with the robot held.

    Per camera with an unknown pose, a linear start from the marker
    positions y_i = T_Fc^-1 T_A t in its frame (t: the known tip, else its
    initial value) and the pixels it saw: the normalised DLT decomposed
    into K [R | t] when the intrinsics are unknown and have no guess, else
    linear PnP with the known (or guessed) intrinsics (``camera_from_dlt``);
    the distortion starts at its given values (default 0).  A camera whose
    DLT fails (fewer than six views, coplanar marker positions) keeps its
    ``initial_poses`` guess (and, with neither intrinsics nor a guess,
    f = 1000 px with the principal point at the mean pixel).  Then
    Gauss-Newton on the residual over every unknown own parameter (the
    tip too, unless an ``initial_tip`` was given).  When pose guesses were
    given, the same refinement also starts from them alone, and for a tip
    with no initial value from the rays (`ray_start`); the start with the
    lowest residual wins.  Deterministic.  `meas`: the pixels (N, 2 cameras); None: nothing to fit.
    """
    if loop.n_own == 0:
        return None
    N = Ts[0].shape[0]
    if meas is None:
        return None
    meas = loop.checked(meas, N)
    p_guess = np.array([q.nominal for q in loop.parameters()])
    tip = loop.tip if loop.tip is not None else loop.initial_tip
    seen = loop.observed(meas)
    p_lin = p_guess.copy()
    for c in range(loop.cameras):
        y, *_ = relative_point(Ts[0], Ts[loop._fidx[c]], tip)
        uv = meas[seen[:, c], 2 * c : 2 * c + 2]
        y = y[seen[:, c]]
        sl, slk = loop.sl[f"pose{c}"], loop.sl[f"K{c}"]
        k_known = loop.K[c] if slk is None else loop.initial_K[c]
        if sl is None and k_known is not None:
            continue  # nothing linear to estimate (the pose is known or follows the rig)
        fit = camera_from_dlt(y, uv, k_known)
        if fit is not None:
            if sl is not None:
                p_lin[sl] = vec_of(fit[0])
            if k_known is None:
                p_lin[slk] = fit[1]
        elif k_known is None:  # no DLT, no guess: centre the principal point
            p_lin[slk] = np.concatenate([PLACEHOLDER_K[:2], uv.mean(axis=0) if len(uv) else [0.0, 0.0]])
    keep_tip = loop.sl["tip"] is not None and not loop._fit_tip
    free = np.arange(loop.sl["tip"].start if keep_tip else loop.n_own)  # the tip is last
    if free.size == 0:
        return p_lin
    starts = [p_lin] + ([p_guess] if any(x is not None for x in loop.initial_poses) else [])
    if loop._fit_tip and loop.sl["tip"] is not None:
        p_ray = ray_start(loop, Ts, meas, p_lin, seen)
        starts += [] if p_ray is None else [p_ray]
    best, best_cost = p_lin, np.inf
    for p0 in starts:
        p = refine_own(loop, Ts, meas, loop.normalize(p0), free)
        r = loop.residual_frames(Ts, p, meas)
        cost = float(np.sum(r * r)) if np.all(np.isfinite(r)) else np.inf
        if cost < best_cost:
            best, best_cost = p, cost
    _warn_misfit(loop, Ts, meas, best, seen)
    return best


@lru_cache(maxsize=1)
def _rotations(n_axes: int = 48, n_roll: int = 8) -> np.ndarray:
    """(n_axes * n_roll, 3, 3) rotations: optical axes on a Fibonacci sphere, each at n_roll roll angles."""
    k = np.arange(n_axes) + 0.5
    z = 1.0 - 2.0 * k / n_axes
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    e3 = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    ref = np.where(np.abs(e3[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(ref, e3)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(e3, e1)
    return np.concatenate(
        [
            np.stack([np.cos(a) * e1 + np.sin(a) * e2, np.cos(a) * e2 - np.sin(a) * e1, e3], axis=2)
            for a in np.arange(n_roll) * 2.0 * np.pi / n_roll
        ]
    )


def ray_fit(Rc: np.ndarray, RFA: np.ndarray, y0: np.ndarray, m: np.ndarray):
    """For each camera rotation Rc[j] in F, the marker t and camera position t_X nearest to the rays.

    The marker in F at view i is y_i = R_FA,i t + y0_i (`relative_point` with
    a zero tip), the ray's direction a_i = R m_i / |m_i| (m_i = K^-1 (u, v, 1)).
    With P_i = I - a_i a_i^T, the squared distance of y_i from the ray through
    t_X is |P_i (R_FA,i t + y0_i - t_X)|^2, linear least squares in w = (t, t_X):
    the normal equations M w = -g with M = sum A_i^T P_i A_i, g = sum A_i^T P_i y0_i,
    A_i = [R_FA,i  -I].  Returns the cost (sum of squared distances, m^2), t,
    t_X and the fraction of views with the marker in front (a_i . (y_i - t_X) > 0).
    """
    a = np.einsum("cij,nj->cni", Rc, m / np.linalg.norm(m, axis=1, keepdims=True))
    P = np.eye(3) - a[..., :, None] * a[..., None, :]
    PR = P @ RFA[None]
    M = np.empty(Rc.shape[:1] + (6, 6))
    M[:, :3, :3] = np.einsum("nki,cnkj->cij", RFA, PR)
    M[:, 3:, :3] = -PR.sum(axis=1)
    M[:, :3, 3:] = np.swapaxes(M[:, 3:, :3], 1, 2)
    M[:, 3:, 3:] = P.sum(axis=1)
    Py = np.einsum("cnij,nj->cni", P, y0)
    g = np.concatenate([np.einsum("nki,cnk->ci", RFA, Py), -Py.sum(axis=1)], axis=1)
    ridge = 1e-12 * np.trace(M, axis1=1, axis2=2)[:, None, None] * np.eye(6)
    w = -np.linalg.solve(M + ridge, g[..., None])[..., 0]
    v = np.einsum("nij,cj->cni", RFA, w[:, :3]) + y0[None] - w[:, None, 3:]
    cost = np.einsum("cni,cni->c", *(2 * [np.einsum("cnij,cnj->cni", P, v)]))
    return cost, w[:, :3], w[:, 3:], (np.einsum("cni,cni->cn", a, v) > 0).mean(axis=1)


def ray_start(loop, Ts: list[np.ndarray], meas: np.ndarray, p_lin: np.ndarray, seen: np.ndarray) -> np.ndarray | None:
    """A start for an unknown marker and unknown camera poses from the rays alone (no marker guess).

    Given a camera's rotation, its position and the marker follow linearly
    (`ray_fit`, distances of the marker from the rays); the rotation is the best
    of 384 spread over SO(3) (about 20 degrees apart), among those that put the
    marker in front of the camera in most views.  The marker is that of the
    camera whose rays it fits best (RMS distance); intrinsics from `p_lin`,
    distortion ignored.  None when no camera with an unknown pose saw the
    marker in six views.  The pixel refinement then starts from it.
    """
    rotations = _rotations()
    p = p_lin.copy()
    tip, best = None, np.inf
    for c in range(loop.cameras):
        sl, slk = loop.sl[f"pose{c}"], loop.sl[f"K{c}"]
        rows = seen[:, c]
        if sl is None or rows.sum() < 6:
            continue
        k = loop.K[c] if slk is None else p_lin[slk]
        y0, RFA, *_ = relative_point(Ts[0][rows], Ts[loop._fidx[c]][rows], np.zeros(3))
        uv = meas[rows, 2 * c : 2 * c + 2]
        m = np.column_stack([(uv[:, 0] - k[2]) / k[0], (uv[:, 1] - k[3]) / k[1], np.ones(len(uv))])
        cost, t, tX, front = ray_fit(rotations, RFA, y0, m)
        cost = np.where(front > 0.5, cost, np.inf)
        j = int(np.argmin(cost))
        if not np.isfinite(cost[j]):
            continue
        p[sl] = vec_of(pin.SE3(rotations[j], tX[j]))
        if cost[j] / rows.sum() < best:
            tip, best = t[j], cost[j] / rows.sum()
    if tip is None:
        return None
    p[loop.sl["tip"]] = tip
    return loop.normalize(p)


def _warn_misfit(loop, Ts: list[np.ndarray], meas: np.ndarray, p: np.ndarray, seen: np.ndarray) -> None:
    """Log a camera whose pixels the started model misses by > MISFIT_PX RMS (and 30 sigma_px)."""
    if loop.closure != "reprojection":
        return
    r = loop.residual_frames(Ts, p, meas)
    for c in range(loop.cameras):
        e = np.linalg.norm(r[seen[:, c], 2 * c : 2 * c + 2], axis=1)
        rms = float(np.sqrt(np.mean(e**2))) if e.size else 0.0
        if rms > max(MISFIT_PX, 30 * (loop.sigma_px or 0.0)):
            same = loop.camera_frames.count(loop.camera_frames[c]) > 1
            log.warning(
                "camera loop '%s': camera %d is missed by %.3g px RMS at the start (robot at nominal)%s",
                loop.name,
                c + 1,
                rms,
                f": if it turns on its own joint, give each camera its frame (to={'+'.join(['F1', 'F2'])})"
                if same
                else "",
            )


def refine_own(
    loop, Ts: list[np.ndarray], meas: np.ndarray, p: np.ndarray, free: np.ndarray, iters: int = 40
) -> np.ndarray:
    """Gauss-Newton on the own parameters p[free] with the robot held (`common.refine_own`)."""
    return common.refine_own(
        lambda q: loop.evaluate_frames(Ts, q, meas),
        lambda q: loop.residual_frames(Ts, q, meas),
        loop.normalize,
        p,
        free,
        iters,
        halvings=12,
    )
