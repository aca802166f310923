"""Variable projection of passive joints, batched over configurations (thesis 3.4.2-3.4.3).

The closure pose of frame A in frame B depends on k unmeasured task joint values phi,
X = X(phi).  Per configuration i, with M_i = T_B^-1 T_A (eq. 3.18, exact),

    r_i(phi) = log6( X(phi)^-1 M_i ),     E_i := X(phi)^-1 M_i,

and phi_i* = argmin |r_i(phi)|^2 is found by Gauss-Newton on every configuration at once:

    J_phi = dr/dphi = -Jlog6(E) Ad(E^-1) dX/dphi       (right twists, dX/dphi: 6 x k)
    dphi  = -J_phi^+ r          (k = 1: -(J^T r) / (J^T J); k > 1: -R^-1 Q^T r, J = QR thin,
                                 the SVD pseudo-inverse where J is ill-conditioned)

with step halving per configuration (masks: a configuration whose cost does not
decrease halves its own step, down to 2^-14; a large step that never descends ends
that configuration's iteration), full steps once |dphi| < 1e-6 (the cost is at
rounding there), and convergence when the step computed is below 1e-13 (|dphi|_inf: it is not taken;
the closure and its Jacobian are those of the last point evaluated) or a step taken was
(|t dphi|_inf, a step cut by the halving).  Only the configurations
still iterating are evaluated in each pass, so a pass costs what the slowest ones need.

A configuration far from closing (a corrupted reading) has a large residual, where Gauss-Newton
converges only linearly (J^T J is not the cost's curvature): one angle (k = 1, phi additive) then
takes the secant step on the gradient g = J^T r instead, dphi = -g / h with h = (g - g') / (phi - phi')
from the previous iterate, the cost's own curvature along phi (superlinear: a handful of iterations
where Gauss-Newton took forty), wherever h is positive and the step within `SECANT_REACH` Gauss-Newton
steps (the same direction as Gauss-Newton's); the step halving guards it as it guards Gauss-Newton's.

The residual handed to the core is P r_i(phi_i*) with the projector

    P = I - J_phi J_phi^+           (k = 1:  I - j j^T / (j^T j))

which removes the directions the passive joints close; the reduced Jacobians are
P dr/dx (see `hinge`'s docstring for the envelope-theorem argument).

The SE(3) algebra is `closedloop.model.se3`'s batched log6 / Jlog6 / adjoint, which follow
Pinocchio's formulas branch for branch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from closedloop.model.se3 import adjoint, log6, rigid_inverse

#: pose(phi (n, nq)) -> X (n, 4, 4), dX/dphi as right twists (n, 6, k)
BatchPoseFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: integrate(phi (n, nq), dphi (n, k)) -> phi (n, nq)
IntegrateFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class Elimination:
    """The eliminated passive values and the closure at them, per configuration."""

    phi: np.ndarray  # (N, nq) phi*
    r: np.ndarray  # (N, 6) log6(E) at phi* (not yet projected)
    Jl: np.ndarray  # (N, 6, 6) Jlog6(E)
    E: np.ndarray  # (N, 4, 4) X(phi*)^-1 M
    Jphi: np.ndarray  # (N, 6, k) dr/dphi
    iterations: np.ndarray  # (N,) Gauss-Newton iterations


def closure_error(M: np.ndarray, X: np.ndarray, jacobian: bool = False):
    """E = X^-1 M, r = log6(E), the cost |r|^2 and (on request, else None) Jlog6(E) for stacks (n, 4, 4)."""
    E = rigid_inverse(X) @ M
    r, Jl = log6(E, jacobian)
    return E, r, np.einsum("ij,ij->i", r, r), Jl


def start_costs(M: np.ndarray, pose: BatchPoseFn, starts: list[np.ndarray]) -> np.ndarray:
    """|r_i(start)|^2 (n_starts, N); rows of NaN in a start (no such start there) cost inf."""
    out = np.full((len(starts), M.shape[0]), np.inf)
    for s, phi in enumerate(starts):
        ok = np.flatnonzero(np.all(np.isfinite(phi), axis=1))
        if ok.size:
            out[s, ok] = closure_error(M[ok], pose(phi[ok])[0])[2]
    return out


def _orthonormalise(J: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin QR of a stack (n, 6, k) by modified Gram-Schmidt, each column orthogonalised twice.

    Returns Q (n, 6, k), R (n, k, k) and a mask (n,) of the well-conditioned matrices
    (min_i |R_ii| > 1e-4 max_i |J e_i|), on which Q, R are accurate to rounding times the condition;
    the others are left to the SVD (`np.linalg.pinv`), which truncates small singular values.
    """
    n, _, k = J.shape
    Q = np.array(J, dtype=float)
    R = np.zeros((n, k, k))
    for i in range(k):
        for _ in range(2):
            for m in range(i):
                c = np.einsum("nj,nj->n", Q[:, :, m], Q[:, :, i])
                Q[:, :, i] -= c[:, None] * Q[:, :, m]
                R[:, m, i] += c
        R[:, i, i] = np.sqrt(np.einsum("nj,nj->n", Q[:, :, i], Q[:, :, i]))
        with np.errstate(divide="ignore", invalid="ignore"):
            Q[:, :, i] /= R[:, i, i][:, None]
    scale = np.sqrt(np.einsum("nji,nji->ni", J, J)).max(axis=1)
    good = np.diagonal(R, axis1=1, axis2=2).min(axis=1) > 1e-4 * scale
    return Q, R, good


def _lstsq_step(J: np.ndarray, r: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """-J^+ r for stacks J (n, 6, k), r (n, 6): the least-squares Gauss-Newton step (n, k).

    k = 1 in closed form; k > 1 by a thin QR, x = -R^-1 Q^T r (back substitution), on the
    well-conditioned rows, and by the SVD-based pseudo-inverse (`rcond`) on the others."""
    n, _, k = J.shape
    if k == 1:
        j = J[:, :, 0]
        jj = np.einsum("ij,ij->i", j, j)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(jj > 0.0, -np.einsum("ij,ij->i", j, r) / jj, 0.0)
        return s[:, None]
    Q, R, good = _orthonormalise(J)
    y = -np.einsum("nji,nj->ni", Q, r)
    x = np.empty((n, k))
    for i in range(k - 1, -1, -1):
        with np.errstate(divide="ignore", invalid="ignore"):
            x[:, i] = (y[:, i] - np.einsum("nm,nm->n", R[:, i, i + 1 :], x[:, i + 1 :])) / R[:, i, i]
    bad = np.flatnonzero(~good)
    if bad.size:
        x[bad] = -np.einsum("nkj,nj->nk", np.linalg.pinv(J[bad], rcond=rcond), r[bad])
    return x


#: a secant step (`_secant_step`) is taken where it is at most this many Gauss-Newton steps long
SECANT_REACH = 100.0


def _secant_step(
    J: np.ndarray, r: np.ndarray, phi: np.ndarray, phi_prev: np.ndarray, g_prev: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The step of one angle (J (n, 6, 1), r (n, 6), phi (n,)) and the gradient g = J^T r (n,): the secant
    step -g / h, h = (g - g_prev) / (phi - phi_prev), where h > 0 and the step is within `SECANT_REACH`
    Gauss-Newton steps; the Gauss-Newton step -g / (J^T J) elsewhere (no previous iterate: NaN)."""
    j = J[:, :, 0]
    jj = np.einsum("ij,ij->i", j, j)
    g = np.einsum("ij,ij->i", j, r)
    with np.errstate(divide="ignore", invalid="ignore"):
        gn = np.where(jj > 0.0, -g / jj, 0.0)
        h = (g - g_prev) / (phi - phi_prev)
        sec = -g / h
    use = np.isfinite(h) & (h > 0.0) & np.isfinite(sec) & (np.abs(sec) <= SECANT_REACH * np.abs(gn))
    return np.where(use, sec, gn)[:, None], g


def projector(Jphi: np.ndarray) -> np.ndarray:
    """I - J_phi J_phi^+ for a stack (n, 6, k) -> (n, 6, 6): removes what the passive joints close.

    k = 1: I - j j^T / (j^T j); k > 1: I - Q Q^T (thin QR) where J is well conditioned, the
    SVD-based pseudo-inverse (rcond 1e-10) elsewhere."""
    n, _, k = Jphi.shape
    P = np.broadcast_to(np.eye(6), (n, 6, 6)).copy()
    if k == 0:
        return P
    if k == 1:
        j = Jphi[:, :, 0]
        jj = np.einsum("ij,ij->i", j, j)
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.where(jj > 0.0, 1.0 / jj, 0.0)
        return P - (w[:, None] * j)[:, :, None] * j[:, None, :]
    Q, _, good = _orthonormalise(Jphi)
    P -= Q @ np.swapaxes(Q, 1, 2)
    bad = np.flatnonzero(~good)
    if bad.size:
        P[bad] = np.eye(6) - Jphi[bad] @ np.linalg.pinv(Jphi[bad], rcond=1e-10)
    return P


def _jphi(Jl: np.ndarray, E: np.ndarray, Xd: np.ndarray) -> np.ndarray:
    """J_phi = -Jlog6(E) Ad(E^-1) dX/dphi."""
    return -Jl @ (adjoint(rigid_inverse(E)) @ Xd)


#: up to this many start rows in all, the starts' Jlog6 are formed with their closures in one pass (a short
#: stack's cost is the calls', not the rows'); above it, at the starts chosen only
STACKED_STARTS = 1024


def _start_state(M: np.ndarray, pose: BatchPoseFn, starts: list[np.ndarray]) -> list[np.ndarray]:
    """[phi, dX/dphi, E, r, |r|^2, Jlog6(E)] at the start of least cost per configuration (first on ties;
    NaN rows of a start are not starts there; every configuration needs one finite start).  Every start's
    finite rows are evaluated in one stack; Jlog6 (a function of E alone) with them while the stack is short
    (`STACKED_STARTS`), else once, at the starts chosen."""
    oks = [np.flatnonzero(np.all(np.isfinite(phi), axis=1)) for phi in starts]
    rows = np.concatenate(oks)
    phis = np.concatenate([np.asarray(phi[ok], dtype=float) for phi, ok in zip(starts, oks)])
    X, Xd = pose(phis)
    with_jl = rows.size <= STACKED_STARTS
    E, r, c, Jl = closure_error(M[rows], X, with_jl)
    pick, cost = np.full(M.shape[0], -1), np.full(M.shape[0], np.inf)
    at = 0
    for ok in oks:  # in order: a later start is taken only where it costs less
        better = np.flatnonzero(c[at : at + ok.size] < cost[ok])
        pick[ok[better]], cost[ok[better]] = at + better, c[at + better]
        at += ok.size
    if np.all(pick >= 0):
        state = [phis[pick], Xd[pick], E[pick], r[pick], c[pick]]
    else:  # configurations with no finite start: zeros, at infinite cost
        seen = np.flatnonzero(pick >= 0)
        state = []
        for a in (phis, Xd, E, r, c):
            b = np.zeros((M.shape[0],) + a.shape[1:])
            b[seen] = a[pick[seen]]
            state.append(b)
        state[4][pick < 0] = np.inf
    Jl = Jl[pick] if Jl is not None and np.all(pick >= 0) else log6(state[2], True)[1]
    assert Jl is not None  # asked for
    return state + [Jl]


def gauss_newton(
    M: np.ndarray,
    pose: BatchPoseFn,
    phi0: np.ndarray | list[np.ndarray],
    integrate: IntegrateFn | None = None,
    tol: float = 1e-13,
    max_iter: int = 100,
) -> Elimination:
    """phi* = argmin |log6(X(phi)^-1 M_i)|^2 from phi0 (N, nq), or the best of a list of starts, every
    configuration at once."""
    integ = integrate if integrate is not None else (lambda a, d: a + d)
    phi, Xd, E, r, c, Jl = _start_state(M, pose, phi0 if isinstance(phi0, list) else [phi0])
    Jphi = _jphi(Jl, E, Xd)
    N, k = phi.shape[0], Xd.shape[2]
    its = np.zeros(N, dtype=int)
    active = np.arange(N) if k else np.zeros(0, dtype=int)
    if not k:
        its[:] = min(1, max_iter)
    secant = k == 1 and phi.shape[1] == 1 and integrate is None  # one additive angle (module docstring)
    phi_prev, g_prev = np.full(N, np.nan), np.full(N, np.nan)
    for it in range(1, max_iter + 1):
        if not active.size:
            break
        a = active
        if secant:
            step, g = _secant_step(Jphi[a], r[a], phi[a, 0], phi_prev[a], g_prev[a])
        else:
            step = _lstsq_step(Jphi[a], r[a])
        go = np.max(np.abs(step), axis=1) >= tol  # else converged here: the step is below tol, not taken
        if not go.all():
            a, step = a[go], step[go]
            if secant:
                g = g[go]
            if not a.size:
                break
        its[a] = it
        small = np.max(np.abs(step), axis=1) < 1e-6  # near the solution: full steps (cost is at rounding)
        t = np.ones(a.size)
        phin, Xdn, En, Jln = np.empty_like(phi[a]), np.empty_like(Xd[a]), np.empty_like(E[a]), np.empty_like(Jl[a])
        rn, cn = np.empty_like(r[a]), np.empty(a.size)
        pend = np.arange(a.size)
        while pend.size:  # step halving, per configuration
            ph = integ(phi[a[pend]], t[pend, None] * step[pend])
            Xp, Xdp = pose(ph)
            Ep, rp, cp, Jlp = closure_error(M[a[pend]], Xp, True)
            phin[pend], Xdn[pend], En[pend], rn[pend], cn[pend], Jln[pend] = ph, Xdp, Ep, rp, cp, Jlp
            done = small[pend] | (cp <= c[a[pend]]) | (t[pend] < 1e-4)
            t[pend[~done]] *= 0.5
            pend = pend[~done]
        acc = small | (cn <= c[a])  # else: no descent along a large step, give up on this one
        ai = a[acc]
        if secant:
            phi_prev[ai], g_prev[ai] = phi[ai, 0], g[acc]
        phi[ai], Xd[ai], E[ai], r[ai], c[ai], Jl[ai] = phin[acc], Xdn[acc], En[acc], rn[acc], cn[acc], Jln[acc]
        Jphi[ai] = _jphi(Jl[ai], E[ai], Xd[ai])
        conv = np.max(np.abs(t[acc, None] * step[acc]), axis=1) < tol
        active = ai[~conv]
    return Elimination(phi, r, Jl, E, Jphi, its)


def eliminate(
    M: np.ndarray,
    pose: BatchPoseFn,
    starts: list[np.ndarray],
    integrate: IntegrateFn | None = None,
    tol: float = 1e-13,
    max_iter: int = 100,
    snap: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Elimination:
    """phi* by Gauss-Newton from the best of `starts` (each (N, nq); NaN rows: not a start there).

    `snap` (for warm starts): the converged phi is rounded by `snap` and the
    iteration rerun from there, so that the result is a function of M and the
    model only, bit for bit, not of the start (the solver compares costs of
    repeated evaluations at the same parameters; start-dependent rounding,
    amplified by the noise weighting, would keep it from terminating).
    """
    out = gauss_newton(M, pose, list(starts), integrate, tol, max_iter)
    if snap is not None:
        out = gauss_newton(M, pose, snap(out.phi), integrate, tol, max_iter)
    return out


def _spread(changed: np.ndarray, width: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows j in (c, c + width] after each changed row c (< N), each with its nearest such c."""
    idx = (changed[:, None] + np.arange(1, width + 1)[None]).ravel()
    src = np.repeat(changed, width)
    keep = idx < N
    idx, src = idx[keep], src[keep]
    order = np.lexsort((src, idx))
    idx, src = idx[order], src[order]
    last = np.r_[idx[1:] != idx[:-1], True]
    return idx[last], src[last]


def eliminate_along(
    M: np.ndarray,
    pose: BatchPoseFn,
    warm: np.ndarray | None,
    q0: np.ndarray,
    integrate: IntegrateFn | None = None,
    snap: Callable[[np.ndarray], np.ndarray] | None = None,
    max_speculative_sweeps: int = 24,
) -> Elimination:
    """phi* for rows that follow a path, as a row-by-row sweep would find them: row i from the best of
    `warm[i]` (the previous evaluation's solution), phi*_{i-1} (the previous row's) and `q0` (first on ties).

    All rows are solved together from the best of warm and q0; then sweeps settle the previous-row
    starts, re-solving only the rows whose chosen start changed.  Where a solution changed (e.g. the
    rows past a half turn from q0 follow the path only from their predecessors), the rows after it are
    also tried from it (speculatively, over a window doubling at each sweep, on the rows that start
    from their predecessor or where it is cheaper; verified at the next sweep), so that a change runs
    down a path in O(log N) sweeps, not N.  The result is the sweep's (with `snap`, a row's result depends on its start only through
    the basin it lies in); the loop ends at the sweep's fixed point.
    """
    N, nq = M.shape[0], q0.size
    none = np.full((N, nq), np.nan)
    cand = [warm if warm is not None else none, none.copy(), np.broadcast_to(q0, (N, nq))]
    costs = start_costs(M, pose, [cand[0], none, cand[2]])

    def pick(rows):
        w = np.argmin(costs[:, rows], axis=0)
        return np.stack([c[rows] for c in cand])[w, np.arange(rows.size)], costs[w, rows], w

    chosen, ccost, which = pick(np.arange(N))
    el = eliminate(M, pose, [chosen], integrate, snap=snap)

    def resolve(rows):  # re-solve `rows` from `chosen`; the rows whose solution changed
        sub = eliminate(M[rows], pose, [chosen[rows]], integrate, snap=snap)
        moved = rows[np.any(sub.phi != el.phi[rows], axis=1)]
        for f in ("phi", "r", "Jl", "E", "Jphi", "iterations"):
            getattr(el, f)[rows] = getattr(sub, f)
        return moved

    width, sweep = 1, 0
    while True:
        prev = np.vstack([none[:1], el.phi[:-1]])
        rows = np.flatnonzero(np.any(prev != cand[1], axis=1) & np.all(np.isfinite(prev), axis=1))
        if not rows.size:
            return el
        cand[1][rows] = prev[rows]
        costs[1, rows] = start_costs(M[rows], pose, [prev[rows]])[0]
        new, ncost, nwhich = pick(rows)
        which[rows] = nwhich
        moved = np.any(new != chosen[rows], axis=1)
        if not moved.any():
            return el
        redo = rows[moved]
        chosen[redo], ccost[redo] = new[moved], ncost[moved]
        changed = resolve(redo)
        sweep += 1
        if changed.size and sweep <= max_speculative_sweeps:
            idx, src = _spread(changed, width, N)
            c = start_costs(M[idx], pose, [el.phi[src]])[0]
            better = (which[idx] == 1) | (c < ccost[idx])  # rows that follow their predecessor, or cheaper
            idx, src = idx[better], src[better]
            if idx.size:
                chosen[idx], ccost[idx], which[idx] = el.phi[src], c[better], 1
                cand[1][idx] = np.nan  # verified against the true previous row at the next sweep
                resolve(idx)
            width *= 2
