"""Pure-kinematic closed-chain data: walk a loop's self-motion exactly.

Given parameter values (the "truth"), configurations are generated on the
closure manifold of one loop: from a start, step along the null space of
J_theta (the self-motion, Lemma 4), then pull back onto closure by
Gauss-Newton on the readings.  Directions persist between steps so the walk
covers the manifold instead of diffusing; it turns back at joint limits.
The output is joint READINGS, i.e. what the sensors of eq. 4.4 report.
"""

from __future__ import annotations

import numpy as np

from closedloop.errors import NotIdentifiableError
from closedloop.model.robot import limit_margins
from closedloop.problem.problem import CalibrationProblem


def close(
    problem: CalibrationProblem,
    values: np.ndarray,
    theta: np.ndarray,
    block: int = 0,
    iters: int = 20,
    tol: float = 1e-13,
) -> tuple[np.ndarray, float]:
    """Readings near `theta` (1, n) that close loop `block` at `values`."""
    th, err, _ = _close(problem, values, theta, block, iters, tol)
    return th, err


def _close(
    problem: CalibrationProblem, values: np.ndarray, theta: np.ndarray, block: int, iters: int, tol: float
) -> tuple[np.ndarray, float, np.ndarray | None]:
    """`close`, and the readings' Jacobian J_theta (m, n) at the readings returned where it was evaluated there
    (None: the last step moved them after it)."""
    thetas = [b.theta[:1] for b in problem.blocks]
    th = theta.copy()
    err = np.inf
    for _ in range(iters):
        thetas[block] = th
        ev = problem.evaluate(values, True, thetas, columns=[])[block]  # Jq alone
        assert ev.Jq is not None  # evaluated with Jacobians
        err = float(np.abs(ev.r).max())
        if err < tol:
            return th, err, ev.Jq[0]
        th = th - np.linalg.lstsq(ev.Jq[0], ev.r[0], rcond=None)[0][None, :]
    return th, err, None


def self_motion(
    problem: CalibrationProblem,
    values: np.ndarray,
    theta0: np.ndarray,
    n: int,
    rng: np.random.Generator,
    step: float = 0.04,
    stride: int = 3,
    block: int = 0,
    margin: float = 0.05,
) -> np.ndarray:
    """`n` configurations (readings, (n, n_joints)) along loop `block`'s self-motion."""
    lo = np.array([problem.robot.joint(j).lower for j in problem.joints])
    hi = np.array([problem.robot.joint(j).upper for j in problem.joints])
    m = limit_margins(lo, hi, margin)  # in each joint's own unit (a 4 cm finger keeps 36 mm)
    lo, hi = lo + m, hi - m
    rp = problem.rp
    k = values[rp.scale_index()]
    off = values[rp.offset_index()]
    th, err, Jq_at_th = _close(problem, values, np.atleast_2d(theta0), block, 20, 1e-13)
    if err > 1e-9:
        raise NotIdentifiableError(f"cannot close loop {problem.blocks[block].loop.name} from the start pose")
    start = th[0] * k + off
    outside = [j for j, a, l, h in zip(problem.joints, start, lo, hi) if not l <= a <= h]
    if outside:
        raise NotIdentifiableError(
            "the start pose is within the margin of (or beyond) the limits of joint(s) "
            + ", ".join(
                f"{j} ({m[k]:.3g} {problem.robot.joint(j).unit} of [{lo[k] - m[k]:.4g}, {hi[k] + m[k]:.4g}])"
                for k, j in enumerate(problem.joints)
                if j in outside
            )
            + ": the walk could not move"
        )
    thetas = [b.theta[:1] for b in problem.blocks]
    direction = None
    out: list[np.ndarray] = []
    walked = 0
    attempts = 0
    while len(out) < n:
        attempts += 1
        if attempts > 50 * n * stride + 100:
            raise NotIdentifiableError(
                f"self-motion walk of loop {problem.blocks[block].loop.name} is stuck "
                f"after {len(out)} of {n} configurations (joint limits)"
            )
        if Jq_at_th is None:  # the closing stopped on its step count: J_theta not yet evaluated at th
            thetas[block] = th
            Jq_all = problem.evaluate(values, True, thetas, columns=[])[block].Jq
            assert Jq_all is not None  # evaluated with Jacobians
            Jq_at_th = Jq_all[0]
        _, S, Vt = np.linalg.svd(Jq_at_th)
        rank = int(np.sum(S > 1e-9 * S[0]))
        Nul = Vt[rank:]
        if Nul.shape[0] == 0:
            raise NotIdentifiableError(f"loop {problem.blocks[block].loop.name} is immobile: no self-motion")
        if direction is None:
            direction = Nul.T @ rng.normal(size=Nul.shape[0])
        d = Nul.T @ (Nul @ direction) + 0.3 * Nul.T @ rng.normal(size=Nul.shape[0]) / np.sqrt(Nul.shape[0])
        d /= np.linalg.norm(d) + 1e-300
        cand, err, Jq_at_cand = _close(problem, values, th + step * d[None, :], block, 20, 1e-13)
        model_angles = cand[0] * k + off
        if err > 1e-10 or np.any(model_angles < lo) or np.any(model_angles > hi):
            direction = -d + 0.5 * Nul.T @ rng.normal(size=Nul.shape[0])
            continue
        th, direction, Jq_at_th = cand, d, Jq_at_cand
        walked += 1
        if walked % stride == 0:
            out.append(th[0].copy())
    return np.array(out)
