"""The camera loop's start: DLT / PnP per camera, then Gauss-Newton with the robot held (thesis 3.2).

Deterministic.  After the refinement a camera whose pixels the model still
misses by much more than their noise (e.g. a camera declared fixed in a frame
while it turns on its own joint) is reported in the log, with the cure.
"""

from __future__ import annotations

import logging

import numpy as np

from . import common

from .camera import PLACEHOLDER_K
from .camera_model import camera_from_dlt
from .measured import vec_of
from .point import relative_point

log = logging.getLogger(__name__)
MISFIT_PX = 20.0  # a camera's start RMS (px) above which its model is suspect


def initialize_camera_loop(loop, Ts: list[np.ndarray]) -> np.ndarray | None:
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
    given, the same refinement also starts from them alone and the start
    with the lower residual wins.  Deterministic.
    """
    if loop.n_own == 0:
        return None
    N = Ts[0].shape[0]
    if loop.meas is None or loop.meas.shape[0] != N:
        return None
    p_guess = np.array([q.nominal for q in loop.parameters()])
    tip = loop.tip if loop.tip is not None else loop.initial_tip
    seen = loop.observed(N)
    p_lin = p_guess.copy()
    for c in range(loop.cameras):
        y, *_ = relative_point(Ts[0], Ts[loop._fidx[c]], tip)
        uv = loop.meas[seen[:, c], 2 * c:2 * c + 2]
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
    best, best_cost = p_lin, np.inf
    for p0 in starts:
        p = refine_own(loop, Ts, loop.normalize(p0), free)
        r = loop.residual_frames(Ts, p)
        cost = float(np.sum(r * r)) if np.all(np.isfinite(r)) else np.inf
        if cost < best_cost:
            best, best_cost = p, cost
    _warn_misfit(loop, Ts, best, seen)
    return best


def _warn_misfit(loop, Ts: list[np.ndarray], p: np.ndarray, seen: np.ndarray) -> None:
    """Log a camera whose pixels the started model misses by > MISFIT_PX RMS (and 30 sigma_px)."""
    if loop.closure != "reprojection":
        return
    r = loop.residual_frames(Ts, p)
    for c in range(loop.cameras):
        e = np.linalg.norm(r[seen[:, c], 2 * c:2 * c + 2], axis=1)
        rms = float(np.sqrt(np.mean(e ** 2))) if e.size else 0.0
        if rms > max(MISFIT_PX, 30 * (loop.sigma_px or 0.0)):
            same = loop.camera_frames.count(loop.camera_frames[c]) > 1
            log.warning("camera loop '%s': camera %d is missed by %.3g px RMS at the start (robot at nominal)%s",
                        loop.name, c + 1, rms,
                        f": if it turns on its own joint, give each camera its frame (to={'+'.join(['F1', 'F2'])})"
                        if same else "")

def refine_own(loop, Ts: list[np.ndarray], p: np.ndarray, free: np.ndarray, iters: int = 40) -> np.ndarray:
    """Gauss-Newton on the own parameters p[free] with the robot held (`common.refine_own`)."""
    return common.refine_own(lambda q: loop.evaluate_frames(Ts, q), lambda q: loop.residual_frames(Ts, q),
                             loop.normalize, p, free, iters, halvings=12)

