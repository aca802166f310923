"""A-optimal exchange for pose selection (Fedorov 1972; Cook & Nachtsheim 1980): see `exchange_a`."""

from __future__ import annotations

import numpy as np

from closedloop.design.optimal import Selection, greedy_d_optimal, information
from closedloop.errors import OptionError


def exchange_a(
    B: np.ndarray,
    k: int,
    prior_weight: float = 1.0,
    base: np.ndarray | None = None,
    start: list[int] | None = None,
    max_passes: int = 200,
    tol: float = 1e-9,
    continuation: tuple[float, ...] = (0.1, 0.01),
) -> Selection:
    """A-optimal exchange (Fedorov 1972; modified, one point at a time: Cook & Nachtsheim 1980).

    Minimises tr A(S)^-1, A(S) = w I + base + sum_{i in S} B_i^T B_i, over designs of k distinct
    blocks of B (Npool, m, L), from the greedy A-optimal design (prior `prior_weight`) or `start`.

    A pass visits the design points in order of increasing removal cost tr(U_j^-1 B_j M^2 B_j^T)
    (M = A^-1, U_j = I - B_j M B_j^T).  For each j: downdate j out,
    M_j = M + M B_j^T U_j^-1 B_j M, find the free candidate i of largest trace decrease
    g_i = tr(S_i^-1 B_i M_j^2 B_i^T), S_i = I + B_i M_j B_i^T, and swap j for i when
    tr M_j - g_i < (1 - tol) tr M; otherwise keep j.  Passes repeat until none swaps (or
    max_passes); every swap lowers the trace, so this ends in a design no single exchange improves.

    Continuation: the exchange runs with w = prior_weight, then again from that design with
    w = c * prior_weight for each c in `continuation`.  The prior only makes the greedy start
    possible; the estimator's covariance has none, and near the smallest k (k m ~ L) a prior of
    the size of the weakest direction's information steers the design away from the trace the
    estimator will have.  The weak-prior criterion is rugged there, so it is entered from the
    strong-prior optimum rather than directly.  `trace` / `logdet` of the result are at the last w
    (`trace_history` runs through all stages).  continuation=() keeps w = prior_weight.

    Implementation: P = B M (all candidates) is kept; B_i M_j = P_i + C_i V_j with
    C_i = P_i B_j^T and V_j = U_j^-1 P_j, so a visit costs O(Npool m^2 L) and touches only m x m
    arrays per candidate.  The bounds ||B_i M_j||_F^2 / (1 + tr B_i M_j B_i^T) <= g_i <=
    ||B_i M_j||_F^2 (S_i >= I; lambda_max(S_i) <= 1 + tr(S_i - I)), expanded in those m x m
    terms, skip visits where no candidate can improve and restrict the exact m x m solves to
    candidates that can be the best (the 16 largest upper bounds first, then those whose bound
    beats the best exact gain found).
    """
    N = B.shape[0]
    if k > N:
        raise OptionError(f"cannot choose {k} configurations from a pool of {N}")
    if start is None:
        design = [int(i) for i in greedy_d_optimal(B, k, prior_weight, base, criterion="A").indices]
    else:
        design = [int(i) for i in start]
        if len(design) != k or len(set(design)) != k:
            raise OptionError(f"start must hold {k} distinct indices")
    hist: list[float] = []
    thist: list[float] = []
    exchanges = 0
    for w in (prior_weight, *(c * prior_weight for c in continuation)):
        design, logdet, trace, n_ex = _exchange_a(B, design, w, base, max_passes, tol, hist, thist)
        exchanges += n_ex
    return Selection(np.array(sorted(design), dtype=int), logdet, hist, exchanges, trace, thist, "A")


def _best_entrant(
    P: np.ndarray,
    C: np.ndarray,
    V: np.ndarray,
    Bt: np.ndarray,
    ub: np.ndarray,
    lb: np.ndarray,
    need: float,
    top: np.ndarray,
) -> tuple[float, int, np.ndarray | None, np.ndarray | None]:
    """The candidate of largest exact trace gain g_i = tr(S_i^-1 T_i T_i^T) (T_i = B_i M_j, S_i = I + T_i B_i^T):
    first among `top` (the largest upper bounds `ub`), then among the rest whose bound still beats the best
    gain so far, `need` and every lower bound `lb`.  Returns (g, i, T_i, S_i); g = -inf if none."""
    Im = np.eye(P.shape[1])
    best_g, best_i, best_T, best_S = -np.inf, -1, None, None
    for cand in (top, None):
        if cand is None:  # the rest: only where the bound beats the best exact gain so far
            bar = max(need, best_g, float(np.nanmax(lb)))
            rest = ub * (1.0 + 1e-9) > bar
            rest[top] = False
            cand = np.flatnonzero(rest)
        if cand.size == 0:
            continue
        Tc = P[cand] + C[cand] @ V
        S = Im + Tc @ Bt[cand]
        g = np.einsum("nkl,nkl->n", np.linalg.solve(S, Tc), Tc)
        c = int(np.argmax(g))
        if g[c] > best_g:
            best_g, best_i, best_T, best_S = float(g[c]), int(cand[c]), Tc[c], S[c]
    return best_g, best_i, best_T, best_S


def _exchange_a(
    B: np.ndarray,
    design: list[int],
    prior_weight: float,
    base: np.ndarray | None,
    max_passes: int,
    tol: float,
    hist: list[float],
    thist: list[float],
):
    """Exchange passes at one prior weight (see `exchange_a`); appends to hist / thist."""
    N, m, L = B.shape
    k = len(design)
    design = list(design)
    n_top = 16
    Bf = B.reshape(N * m, L)
    Bt = np.swapaxes(B, 1, 2)
    Im = np.eye(m)
    A = prior_weight * np.eye(L) + (base if base is not None else 0.0) + information(B, design)
    M = np.linalg.inv(A)
    logdet = float(np.linalg.slogdet(A)[1])
    in_design = np.zeros(N, dtype=bool)
    in_design[design] = True
    hist.append(logdet)
    thist.append(float(np.trace(M)))
    exchanges = 0
    for _ in range(max_passes):
        M = 0.5 * (M + M.T)
        tr = float(np.trace(M))
        P = (Bf @ M).reshape(N, m, L)  # B_i M, fresh every pass (no drift)
        p2 = np.einsum("nkl,nkl->n", P, P)  # ||B_i M||_F^2
        pb = np.einsum("nkl,nkl->n", P, B)  # tr(B_i M B_i^T)
        Pd = P[design]
        U = Im - Pd @ Bt[design]
        loss = np.full(k, np.inf)
        ok = np.linalg.eigvalsh(U)[:, 0] > 1e-12
        loss[ok] = np.einsum("nkl,nkl->n", np.linalg.solve(U[ok], Pd[ok]), Pd[ok])
        swapped = False
        for t in np.argsort(loss, kind="stable"):  # position t holds its pass-start point until visited
            if not np.isfinite(loss[t]):
                continue
            j = design[t]
            W = P[j]  # B_j M
            Uj = Im - W @ B[j].T
            if np.linalg.eigvalsh(Uj)[0] <= 1e-12:  # j alone carries a direction (possible without a prior)
                continue
            V = np.linalg.solve(Uj, W)  # U_j^-1 B_j M;  M_j = M + W^T V
            tr_j = tr + float(np.sum(W * V))  # tr M_j
            need = tr_j - (1.0 - tol) * tr  # a swap must gain more than this
            # B_i M_j = P_i + C_i V, C_i = B_i M B_j^T; its squared norm and tr(B_i M_j B_i^T) in m x m terms
            Z = (Bf @ np.hstack([W.T, M @ V.T, V.T])).reshape(N, m, 3 * m)  # one BLAS call
            C, Q, R = Z[:, :, :m], Z[:, :, m : 2 * m], Z[:, :, 2 * m :]  # B_i M B_j^T, B_i M V^T, B_i V^T
            ub = p2 + np.einsum("nkl,nkl->n", 2.0 * Q + C @ (V @ V.T), C)
            ub[in_design] = -np.inf
            if ub.max() * (1.0 + 1e-9) <= need:
                continue
            # exact gains first for the few largest upper bounds, then for whoever could still beat them
            lb = ub / (1.0 + pb + np.einsum("nkl,nkl->n", C, R))
            top = np.argpartition(-ub, min(n_top, N - 1))[:n_top]
            top = top[ub[top] * (1.0 + 1e-9) > need]
            best_g, best_i, best_T, best_S = _best_entrant(P, C, V, Bt, ub, lb, need, top)
            if best_g <= need:
                continue
            assert best_T is not None and best_S is not None  # a gain above `need` came with its entrant
            i, Ti, Si = best_i, best_T, best_S
            X = np.linalg.solve(Si, Ti)  # S_i^-1 B_i M_j
            M = M + W.T @ V - Ti.T @ X
            T = P + C @ V  # B M_j
            P = T - ((T.reshape(N * m, L) @ B[i].T) @ X).reshape(N, m, L)
            p2 = np.einsum("nkl,nkl->n", P, P)
            pb = np.einsum("nkl,nkl->n", P, B)
            tr = tr_j - best_g
            logdet += float(np.linalg.slogdet(Uj)[1] + np.linalg.slogdet(Si)[1])
            design[t] = i
            in_design[j], in_design[i] = False, True
            exchanges += 1
            swapped = True
            hist.append(logdet)
            thist.append(tr)
        if not swapped:
            break
    return design, logdet, float(np.trace(M)), exchanges
