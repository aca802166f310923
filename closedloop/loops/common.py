"""Helpers shared by loop types: refining a loop's own parameters with the robot held."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .base import LoopEval


def refine_own(evaluate: Callable[[np.ndarray], LoopEval], residual: Callable[[np.ndarray], np.ndarray],
               normalize: Callable[[np.ndarray], np.ndarray], p: np.ndarray, free: np.ndarray,
               iters: int = 30, halvings: int = 10) -> np.ndarray:
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
