"""Helpers shared by loop types: their parameter records, the relative point, refining a loop's own parameters.

The SE(3) algebra and the parsing of user poses are in `closedloop.model.se3`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import LoopEval
from closedloop.model.parameters import DEFAULT_PRIORS, Parameter
from closedloop.model.se3 import parse_vec, pose_of, skew

TIP_FIELDS = ("tip_x", "tip_y", "tip_z")
POINT_FIELDS = ("px", "py", "pz")
POSE_FIELDS = ("x", "y", "z", "rx", "ry", "rz")


def relative_point(TA: np.ndarray, TB: np.ndarray, tip: np.ndarray):
    """y = T_B^-1 T_A tip (N, 3) and R_BA = R_B^T R_A (N, 3, 3).

    With right perturbations of T_A and T_B (T <- T exp6((v, w))):

        dy/d(delta_A) = R_BA [ I  -[tip]x ]          (the tip moves with A)
        dy/d(delta_B) =      [ -I   [y]x  ]          (B moving is y moving back)
        dy/d(tip)     = R_BA
    """
    RB = np.swapaxes(TB[:, :3, :3], 1, 2)
    RBA = RB @ TA[:, :3, :3]
    y = np.einsum("nij,nj->ni", RB, TA[:, :3, 3] + TA[:, :3, :3] @ tip - TB[:, :3, 3])
    N = TA.shape[0]
    dA = np.empty((N, 3, 6))
    dA[:, :, :3] = RBA
    dA[:, :, 3:] = -RBA @ skew(tip)
    dB = np.empty((N, 3, 6))
    dB[:, :, :3] = -np.eye(3)
    dB[:, :, 3:] = skew(y)
    return y, RBA, dA, dB


def point_parameters(
    loop: str, fields: tuple[str, ...], values: np.ndarray, order0: int = 0, prior: float | None = None
) -> list[Parameter]:
    """Three unknown coordinates of a point (metres, they scale with length)."""
    prior = DEFAULT_PRIORS["loop_m"] if prior is None else prior
    return [
        Parameter(
            f"{loop}.{f}",
            "loop",
            loop,
            f,
            float(values[k]),
            "m",
            prior,
            scales_with_length=float(values[k]),
            priority=1,
            order=order0 + k,
        )
        for k, f in enumerate(fields)
    ]


def face_parameters(loop: str, fields: tuple[str, ...], order0: int = 0, prior: float | None = None) -> list[Parameter]:
    """A face's unknowns, starting at zero: direction angles (rad) and a distance ``d`` (m, the loop's
    length prior, or `prior`), none scaling with length (the plane loop's ``nrx nry d``, the face loop's)."""
    out = []
    for k, f in enumerate(fields):
        unit = "m" if f == "d" else "rad"
        p = DEFAULT_PRIORS["loop_m" if unit == "m" else "loop_rad"]
        if unit == "m" and prior is not None:
            p = prior
        out.append(
            Parameter(
                f"{loop}.{f}", "loop", loop, f, 0.0, unit, p, scales_with_length=0.0, priority=1, order=order0 + k
            )
        )
    return out


def pose_parameters(loop: str, fields: tuple[str, ...], X: pin.SE3, order0: int = 0) -> list[Parameter]:
    """Six unknown pose coordinates (x, y, z in m, scaling with length; rx, ry, rz rotation vector in rad)."""
    vals = np.concatenate([X.translation, pin.log3(X.rotation)])
    out = []
    for k, f in enumerate(fields):
        unit = "m" if k < 3 else "rad"
        out.append(
            Parameter(
                f"{loop}.{f}",
                "loop",
                loop,
                f,
                float(vals[k]),
                unit,
                DEFAULT_PRIORS["loop_m" if k < 3 else "loop_rad"],
                scales_with_length=float(vals[k]) if k < 3 else 0.0,
                priority=1,
                order=order0 + k,
            )
        )
    return out


def refine_own(
    evaluate: Callable[[np.ndarray], LoopEval],
    residual: Callable[[np.ndarray], np.ndarray],
    normalize: Callable[[np.ndarray], np.ndarray],
    p: np.ndarray,
    free: np.ndarray,
    iters: int = 30,
    halvings: int = 10,
) -> np.ndarray:
    """Gauss-Newton on the loop's own parameters ``p[free]`` (the robot's poses held inside the callables).

    Minimum-norm (truncated SVD, rcond 1e-9) steps, so a direction the data
    do not determine stays at its starting value; a step is kept only if it
    lowers |r|^2 (else halved, at most `halvings` times).  Deterministic.
    """

    def cost_of(q):
        r = residual(q)
        return float(np.sum(r * r)) if np.all(np.isfinite(r)) else np.inf

    cost = cost_of(p)
    for _ in range(iters):
        ev = evaluate(p)
        r = ev.r.reshape(-1)
        J = ev.dp.reshape(r.size, -1)[:, free]
        U, S, Vt = np.linalg.svd(J, full_matrices=False)
        keep = S > 1e-9 * max(S[0] if S.size else 0.0, 1e-300)
        step = -(Vt[keep].T @ ((U[:, keep].T @ r) / S[keep]))
        lam = 1.0
        for _h in range(halvings):
            q = p.copy()
            q[free] += lam * step
            q = normalize(q)
            c = cost_of(q)
            if c <= cost:
                break
            lam *= 0.5
        else:
            break
        small = np.abs(lam * step).max() < 1e-13 or cost - c <= 1e-15 * max(cost, 1e-300)
        p, cost = q, c
        if small:
            break
    return p


def opt_float(kw: dict[str, str], key: str) -> float | None:
    """An optional number of a loop spec (``--loop TYPE:key=value``); None when absent."""
    if key not in kw:
        return None
    try:
        return float(kw[key])
    except ValueError:
        raise LoopError(f"{key}='{kw[key]}' is not a number") from None


def opt_pose(kw: dict[str, str], key: str) -> pin.SE3 | None:
    """An optional pose of a loop spec: 'x y z rx ry rz', ``identity``; None when absent or ``unknown``."""
    if kw.get(key, "unknown") == "unknown":
        return None
    if kw[key] == "identity":
        return pin.SE3.Identity()
    return pose_of(parse_vec(kw[key], 6, key))


#: m: a point of the tool that moves more than this (RMS, at the nominal model) is no fixed point (a rough model
#: moves it a few mm), and one that travels more on a plane slides on it (`contact_fits`)
POINT_SPREAD = 0.02
#: a point of the tool stays on one plane (`contact_fits`) to within this share of the distance it travels on
#: it: a rough model leaves a few per cent
ON_PLANE = 0.05


def contact_fits(M: np.ndarray, iterations: int = 8) -> tuple[float, float, float]:
    """How well the relative poses M (N, 4, 4) = T_B^-1 T_A fit the contacts a tool point makes, read before any
    fit: (RMS distance of the best fixed point of A from one point of B (a pivot fit, R_i t - p = -d_i); RMS
    distance of the best point of A from one plane of B (alternating: the plane of the points, then the point
    on the plane, from the pivot's point); RMS distance that point travels).  Metres."""
    R, d = M[:, :3, :3], M[:, :3, 3]
    n = M.shape[0]
    A = np.concatenate([R, np.broadcast_to(-np.eye(3), (n, 3, 3))], axis=2).reshape(-1, 6)
    sol = np.linalg.lstsq(A, -d.reshape(-1), rcond=None)[0]
    pivot = float(np.sqrt(np.mean(np.sum((A @ sol + d.reshape(-1)).reshape(n, 3) ** 2, axis=1))))
    t = sol[:3]
    off = np.inf
    for _ in range(iterations):
        p = R @ t + d
        c = p.mean(axis=0)
        normal = np.linalg.svd(p - c, full_matrices=n < 3)[2][2]  # (not U: n x n)
        B = np.column_stack([(normal @ R), -np.ones(n)])  # normal . (R_i t + d_i) = c0
        tc = np.linalg.lstsq(B, -(d @ normal), rcond=None)[0]
        t = tc[:3]
        off = float(np.sqrt(np.mean((B @ tc + d @ normal) ** 2)))
    p = R @ t + d
    travel = float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
    return pivot, off, travel
