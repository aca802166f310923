"""Choosing the most informative configurations (issue 5, item 2).

From a pool of candidate configurations of one loop (readings, e.g. a dense
self-motion walk) choose K that make the information matrix of the estimated
parameters large,

    A(S) = A_0 + sum_{i in S} B_i^T B_i,

B_i (m, L) the whitened, prior-scaled Jacobian block of configuration i at the
current estimate (``observability.whitened_blocks``) and A_0 = prior_weight * I
the prior information (prior^-2 I in unscaled units), which lets greedy start
from zero configurations.  Two criteria:

* D-optimality: maximise log det A(S) (observability index O1 of Borm & Menq
  1991), the volume of the confidence ellipsoid;
* A-optimality: minimise tr A(S)^-1, the trace of the parameter covariance
  (prior-scaled units), i.e. the sum of the parameters' variances, which is
  how the accuracy of a design is measured here (``trace_covariance``).

Every update is rank m (one configuration), never a refactorisation.  With
M = A^-1, S_i = I_m + B_i M B_i^T and U_j = I_m - B_j M B_j^T:

* adding i:    (A + B_i^T B_i)^-1 = M - M B_i^T S_i^-1 B_i M  (Sherman-Morrison-
  Woodbury), log det gains log det S_i (matrix determinant lemma), the trace
  falls by tr(S_i^-1 B_i M^2 B_i^T);
* removing j:  (A - B_j^T B_j)^-1 = M + M B_j^T U_j^-1 B_j M, log det falls by
  -log det U_j, the trace rises by tr(U_j^-1 B_j M^2 B_j^T).

These are evaluated for every candidate at once (batched m x m systems).

Algorithms:

* Greedy (forward selection): add the candidate with the largest gain (log det,
  or trace decrease for criterion 'A').  log det A is carried along as a sum
  of gains.
* DETMAX (Mitchell, "An algorithm for the construction of D-optimal
  experimental designs", Technometrics 16(2):203-210, 1974), D-criterion:
  starting from the greedy design, make excursions: add the l best points,
  then remove the l points whose removal costs least; keep the new design if
  log det rose, otherwise try a longer excursion (l = 1 .. max_excursion).
  Designs already visited (Mitchell's failure set) are not revisited.
* A-optimal exchange (``exchange_a``): Fedorov's exchange (Fedorov, "Theory of
  Optimal Experiments", Academic Press 1972, ch. 3) in the "modified"
  one-point-at-a-time form of Cook & Nachtsheim ("A comparison of algorithms
  for constructing exact D-optimal designs", Technometrics 22(3):315-324,
  1980; Atkinson, Donev & Tobias, "Optimum Experimental Designs, with SAS",
  Oxford 2007, ch. 12), on the trace criterion: starting from the A-optimal
  greedy design, for each design point j (cheapest removal first) downdate
  it out, find the candidate i with the largest trace decrease from the
  downdated design, and swap when tr A^-1 falls, i.e. when
  tr(S_i'^-1 B_i M_j^2 B_i^T) > tr(U_j^-1 B_j M^2 B_j^T), M_j the downdated
  inverse and S_i' its S_i; passes repeat until no swap improves the trace
  (a local optimum for all single exchanges; each swap strictly lowers it,
  so it terminates).  The exchange is then continued with the prior weight
  lowered 10x and 100x, towards the prior-free covariance the estimator has.

A pool of distinct configurations is a design without replicates: a point is
chosen at most once.  The A-optimal design on a one-dimensional self-motion
sits on a few poses (about eight on the Panda weld: both joint-limit ends and
interior poses) with many measurements at each, which a pool can only offer
as neighbouring configurations: a dense pool matters.  And its gain is
bounded: the continuous (approximate) A-optimal design there is only ~2.03x
as efficient as configurations spread uniformly along the motion (general
equivalence theorem, Kiefer & Wolfowitz 1960; Atkinson et al. ch. 9-10), so
K = N/2 selected configurations reach the trace of N random ones up to
N ~ 200 only.  The trace weights each parameter by its prior; the expected
closure error along the same motion (I-criterion) is not what it lowers
(README, "Pose selection"; benchmarks/bench_pose_selection.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibration import CalibrationResult
from .identifiability import greedy_reduction
from .observability import resolve, whitened_blocks
from .problem import CalibrationProblem


@dataclass
class Selection:
    """The chosen configurations and the information they carry."""

    indices: np.ndarray  # into the pool, in the order chosen (greedy) / sorted (detmax, exchange_a)
    logdet: float  # log det A(S) in prior-scaled units, A_0 included
    logdet_history: list[float] = field(default_factory=list)
    exchanges: int = 0
    trace: float = float("nan")  # tr A(S)^-1 in prior-scaled units, A_0 included
    trace_history: list[float] = field(default_factory=list)  # criterion 'A': after each step / exchange
    criterion: str = "D"


# --------------------------------------------------------------------------- information
class _Design:
    """A^-1 and log det A under rank-m updates (Woodbury; determinant lemma)."""

    def __init__(self, B: np.ndarray, prior_weight: float, base: np.ndarray | None = None):
        self.B = B  # (Npool, m, L)
        L = B.shape[2]
        A0 = prior_weight * np.eye(L) + (base if base is not None else 0.0)
        self.Ainv = np.linalg.inv(A0)
        sign, self.logdet = np.linalg.slogdet(A0)  # the starting point only
        self.m = B.shape[1]

    def gains(self) -> np.ndarray:
        """log det(I + B_i A^-1 B_i^T) for every candidate (what adding it gains)."""
        T = self.B @ self.Ainv  # (N, m, L)
        G = T @ np.swapaxes(self.B, 1, 2) + np.eye(self.m)
        return np.linalg.slogdet(G)[1]

    def trace_gains(self) -> np.ndarray:
        """tr A^-1 - tr (A + B_i^T B_i)^-1 = tr(S_i^-1 B_i A^-2 B_i^T), S_i = I + B_i A^-1 B_i^T (A-optimality)."""
        T = self.B @ self.Ainv  # (N, m, L): B_i A^-1
        S = T @ np.swapaxes(self.B, 1, 2) + np.eye(self.m)
        return np.einsum("nkl,nkl->n", np.linalg.solve(S, T), T)  # tr(S^-1 T T^T)

    @property
    def trace(self) -> float:
        """tr A^-1 (read off the carried inverse)."""
        return float(np.trace(self.Ainv))

    def losses(self, idx: np.ndarray) -> np.ndarray:
        """-log det(I - B_i A^-1 B_i^T) for design points (what removing each costs, >= 0)."""
        Bi = self.B[idx]
        G = np.eye(self.m) - Bi @ self.Ainv @ np.swapaxes(Bi, 1, 2)
        sign, ld = np.linalg.slogdet(G)
        return np.where(sign > 0, -ld, np.inf)

    def add(self, i: int) -> float:
        B = self.B[i]
        AB = self.Ainv @ B.T  # (L, m)
        S = np.eye(self.m) + B @ AB
        g = np.linalg.slogdet(S)[1]
        self.Ainv = self.Ainv - AB @ np.linalg.solve(S, AB.T)
        self.Ainv = 0.5 * (self.Ainv + self.Ainv.T)
        self.logdet += g
        return g

    def remove(self, i: int) -> float:
        B = self.B[i]
        AB = self.Ainv @ B.T
        S = np.eye(self.m) - B @ AB
        g = np.linalg.slogdet(S)[1]
        self.Ainv = self.Ainv + AB @ np.linalg.solve(S, AB.T)
        self.Ainv = 0.5 * (self.Ainv + self.Ainv.T)
        self.logdet += g
        return g


def greedy_d_optimal(B: np.ndarray, k: int, prior_weight: float = 1.0, base: np.ndarray | None = None,
                     start: list[int] | None = None, criterion: str = "D") -> Selection:
    """Greedy D-optimal (or, criterion='A', trace-minimising) choice of k blocks of B (Npool, m, L).

    Each step adds the free candidate with the largest gain, log det(I + B_i A^-1 B_i^T) (D) or
    tr(S_i^-1 B_i A^-2 B_i^T) (A), then updates A^-1 by Woodbury.  `start`: indices taken first.
    """
    if criterion not in ("D", "A"):
        raise ValueError(f"criterion must be 'D' or 'A', not '{criterion}'")
    N = B.shape[0]
    if k > N:
        raise ValueError(f"cannot choose {k} configurations from a pool of {N}")
    d = _Design(B, prior_weight, base)
    chosen: list[int] = []
    free = np.ones(N, dtype=bool)
    hist = [d.logdet]
    for i in start or []:
        d.add(i)
        chosen.append(i)
        free[i] = False
    thist = [d.trace]
    while len(chosen) < k:
        g = d.gains() if criterion == "D" else d.trace_gains()
        g[~free] = -np.inf
        i = int(np.argmax(g))
        d.add(i)
        chosen.append(i)
        free[i] = False
        hist.append(d.logdet)
        thist.append(d.trace)
    return Selection(np.array(chosen, dtype=int), d.logdet, hist, trace=d.trace, trace_history=thist,
                     criterion=criterion)


def detmax(B: np.ndarray, k: int, prior_weight: float = 1.0, base: np.ndarray | None = None,
           start: list[int] | None = None, max_excursion: int = 4, max_rounds: int = 500,
           tol: float = 1e-9) -> Selection:
    """Mitchell's DETMAX exchange from a greedy (or given) design of k blocks."""
    sel = greedy_d_optimal(B, k, prior_weight, base) if start is None else None
    design = list(sel.indices) if sel is not None else list(start)
    d = _Design(B, prior_weight, base)
    for i in design:
        d.add(i)
    hist = [d.logdet]
    failures: set[frozenset] = set()
    exchanges = 0
    for _ in range(max_rounds):
        improved = False
        for ell in range(1, max_excursion + 1):
            trial = list(design)
            in_design = np.zeros(B.shape[0], dtype=bool)
            in_design[trial] = True
            saved_Ainv, saved_ld = d.Ainv.copy(), d.logdet
            for _ in range(ell):  # excursion up: add the l best points
                g = d.gains()
                g[in_design] = -np.inf
                i = int(np.argmax(g))
                d.add(i)
                trial.append(i)
                in_design[i] = True
            for _ in range(ell):  # back down: remove the l cheapest
                loss = d.losses(np.array(trial))
                j = int(np.argmin(loss))
                d.remove(trial[j])
                in_design[trial[j]] = False
                trial.pop(j)
            key = frozenset(trial)
            if d.logdet > saved_ld + tol and key not in failures:
                design = trial
                exchanges += 1
                hist.append(d.logdet)
                improved = True
                break
            failures.add(key)
            d.Ainv, d.logdet = saved_Ainv, saved_ld
        if not improved:
            break
    return Selection(np.array(sorted(design), dtype=int), d.logdet, hist, exchanges)


def exchange_a(B: np.ndarray, k: int, prior_weight: float = 1.0, base: np.ndarray | None = None,
               start: list[int] | None = None, max_passes: int = 200, tol: float = 1e-9,
               continuation: tuple[float, ...] = (0.1, 0.01)) -> Selection:
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
        raise ValueError(f"cannot choose {k} configurations from a pool of {N}")
    if start is None:
        design = [int(i) for i in greedy_d_optimal(B, k, prior_weight, base, criterion="A").indices]
    else:
        design = [int(i) for i in start]
        if len(design) != k or len(set(design)) != k:
            raise ValueError(f"start must hold {k} distinct indices")
    hist: list[float] = []
    thist: list[float] = []
    exchanges = 0
    for w in (prior_weight, *(c * prior_weight for c in continuation)):
        design, logdet, trace, n_ex = _exchange_a(B, design, w, base, max_passes, tol, hist, thist)
        exchanges += n_ex
    return Selection(np.array(sorted(design), dtype=int), logdet, hist, exchanges, trace, thist, "A")


def _exchange_a(B: np.ndarray, design: list[int], prior_weight: float, base: np.ndarray | None,
                max_passes: int, tol: float, hist: list[float], thist: list[float]):
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
            C, Q, R = Z[:, :, :m], Z[:, :, m:2 * m], Z[:, :, 2 * m:]  # B_i M B_j^T, B_i M V^T, B_i V^T
            ub = p2 + np.einsum("nkl,nkl->n", 2.0 * Q + C @ (V @ V.T), C)
            ub[in_design] = -np.inf
            if ub.max() * (1.0 + 1e-9) <= need:
                continue
            # exact gains first for the few largest upper bounds, then for whoever could still beat them
            lb = ub / (1.0 + pb + np.einsum("nkl,nkl->n", C, R))
            top = np.argpartition(-ub, min(n_top, N - 1))[:n_top]
            top = top[ub[top] * (1.0 + 1e-9) > need]
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
            if best_g <= need:
                continue
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


# --------------------------------------------------------------------------- on a problem
def pool_blocks(result_or_problem: CalibrationResult | CalibrationProblem, values: np.ndarray | None,
                pool_thetas: np.ndarray, block: int = 0, params=None, noise=None,
                weighting: str = "noise") -> tuple[np.ndarray, list[int]]:
    """Whitened, prior-scaled Jacobian blocks (Npool, m, L) of the pool and the parameter indices used.

    With a bare problem and no `params`, the parameters are a structural
    reduction of the pool's own Jacobian (``identifiability.greedy_reduction``,
    calibrate's priority order): redundant directions carry no information and
    would only measure the prior.  Pool readings should close the loop (e.g.
    a self-motion walk) for that reduction to be exact.
    """
    problem, vals, idx, sigma_q = resolve(result_or_problem, values, params, noise)
    thetas = [b.theta for b in problem.blocks]
    thetas[block] = np.asarray(pool_thetas, float)
    if params is None and not isinstance(result_or_problem, CalibrationResult):
        _, J = whitened_blocks(problem, vals, idx, sigma_q, weighting, thetas, blocks=[block])[0]
        C = J.reshape(-1, J.shape[2])
        prm = problem.params
        order = sorted(range(len(idx)), key=lambda i: (prm[idx[i]].priority,
                                                       -prm[idx[i]].order if prm[idx[i]].kind in ("placement", "dh")
                                                       else prm[idx[i]].order, idx[i]))
        kept, _ = greedy_reduction(C, [problem.names[k] for k in idx], order)
        idx = sorted(idx[i] for i in kept)
    _, J = whitened_blocks(problem, vals, idx, sigma_q, weighting, thetas, blocks=[block])[0]
    return J, idx


METHODS = ("greedy", "detmax", "greedy-a", "exchange-a")


def select_poses(result_or_problem: CalibrationResult | CalibrationProblem, values: np.ndarray | None,
                 pool_thetas: np.ndarray, k: int, method: str = "greedy", block: int = 0, params=None,
                 noise=None, weighting: str = "noise", prior_weight: float = 1.0,
                 include_existing: bool = False, return_selection: bool = False):
    """Indices of the k most informative rows of `pool_thetas` (readings of loop `block`).

    result_or_problem: a `CalibrationResult` (its estimated parameters, values
      and noise are the defaults) or a `CalibrationProblem` (pass `values`).
    method: 'greedy' (D-optimal forward selection), 'detmax' (greedy, then
      Mitchell's exchange), 'greedy-a' (forward selection minimising the
      trace of the covariance, A-optimality, with the same Woodbury updates),
      or 'exchange-a' (greedy-a, then Fedorov's exchange on the trace:
      `exchange_a`; the best for the covariance trace, what
      benchmarks/bench_pose_selection.py measures).
    prior_weight: A_0 = prior_weight * I in prior-scaled units.
    include_existing: count the problem's own configurations as already taken
      (choose the k that best complement the data in hand).
    Returns the indices (np.ndarray), or a `Selection` if return_selection.
    """
    B, idx = pool_blocks(result_or_problem, values, pool_thetas, block, params, noise, weighting)
    base = None
    if include_existing:
        problem, vals, _, sigma_q = resolve(result_or_problem, values, idx, noise)
        C = np.vstack([J.reshape(-1, len(idx)) for _, J in whitened_blocks(problem, vals, idx, sigma_q, weighting)])
        base = C.T @ C
    if method == "greedy":
        sel = greedy_d_optimal(B, k, prior_weight, base)
    elif method == "greedy-a":
        sel = greedy_d_optimal(B, k, prior_weight, base, criterion="A")
    elif method == "detmax":
        sel = detmax(B, k, prior_weight, base)
    elif method == "exchange-a":
        sel = exchange_a(B, k, prior_weight, base)
    else:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, not '{method}'")
    return sel if return_selection else sel.indices


def information(B: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """sum_i B_i^T B_i over `rows` of the blocks B (N, m, L) (no prior)."""
    Bs = B if rows is None else B[np.asarray(rows)]
    C = Bs.reshape(-1, Bs.shape[2])
    return C.T @ C


def trace_covariance(B: np.ndarray, rows: np.ndarray | None = None, unscale: np.ndarray | None = None) -> float:
    """Trace of (sum B_i^T B_i)^-1 (prior-scaled units, or physical with `unscale` = the priors).

    inf when the information is singular (too few configurations for the parameters).
    """
    A = information(B, rows)
    ev = np.linalg.eigvalsh(A)
    if ev[0] <= 1e-13 * ev[-1]:
        return float("inf")
    cov = np.linalg.inv(A)
    if unscale is not None:
        cov = cov * np.outer(unscale, unscale)
    return float(np.trace(cov))
