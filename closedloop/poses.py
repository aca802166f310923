"""Choosing the most informative configurations (issue 5, item 2).

From a pool of candidate configurations of one loop (readings, e.g. a dense
self-motion walk) choose K that maximise the determinant of the information
matrix of the estimated parameters (D-optimality, i.e. observability index O1
of Borm & Menq 1991):

    A(S) = A_0 + sum_{i in S} B_i^T B_i,

B_i (m, L) the whitened, prior-scaled Jacobian block of configuration i at the
current estimate (``observability.whitened_blocks``) and A_0 = prior_weight * I
the prior information (prior^-2 I in unscaled units), which lets greedy start
from zero configurations.

* Greedy: add the candidate with the largest gain
  log det(A + B^T B) - log det A = log det(I_m + B A^-1 B^T)
  (matrix determinant lemma, evaluated for every candidate at once) and update
  A^-1 by Sherman-Morrison-Woodbury, a rank-m update.  No determinant is ever
  recomputed from scratch: log det A is carried along as a sum of gains.
* DETMAX (Mitchell, "An algorithm for the construction of D-optimal
  experimental designs", Technometrics 16(2):203-210, 1974): starting from the
  greedy design, make excursions: add the l best points, then remove the l
  points whose removal costs least (loss log det(I_m - B A^-1 B^T), again by
  the lemma, and a Woodbury downdate); keep the new design if log det rose,
  otherwise try a longer excursion (l = 1 .. max_excursion).  Designs already
  visited (Mitchell's failure set) are not revisited.
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

    indices: np.ndarray  # into the pool, in the order chosen (greedy) / sorted (detmax)
    logdet: float  # log det A(S) in prior-scaled units, A_0 included
    logdet_history: list[float] = field(default_factory=list)
    exchanges: int = 0


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
        T = self.B @ self.Ainv  # (N, m, L)
        S = T @ np.swapaxes(self.B, 1, 2) + np.eye(self.m)
        TT = T @ np.swapaxes(T, 1, 2)  # B A^-2 B^T
        return np.einsum("nii->n", np.linalg.solve(S, TT))

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
    """Greedy D-optimal (or, criterion='A', trace-minimising) choice of k blocks of B (Npool, m, L)."""
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
    while len(chosen) < k:
        g = d.gains() if criterion == "D" else d.trace_gains()
        g[~free] = -np.inf
        i = int(np.argmax(g))
        d.add(i)
        chosen.append(i)
        free[i] = False
        hist.append(d.logdet)
    return Selection(np.array(chosen, dtype=int), d.logdet, hist)


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


def select_poses(result_or_problem: CalibrationResult | CalibrationProblem, values: np.ndarray | None,
                 pool_thetas: np.ndarray, k: int, method: str = "greedy", block: int = 0, params=None,
                 noise=None, weighting: str = "noise", prior_weight: float = 1.0,
                 include_existing: bool = False, return_selection: bool = False):
    """Indices of the k most informative rows of `pool_thetas` (readings of loop `block`).

    result_or_problem: a `CalibrationResult` (its estimated parameters, values
      and noise are the defaults) or a `CalibrationProblem` (pass `values`).
    method: 'greedy' (D-optimal forward selection), 'detmax' (greedy, then
      Mitchell's exchange), or 'greedy-a' (forward selection minimising the
      trace of the covariance, A-optimality, with the same Woodbury updates).
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
    else:
        raise ValueError(f"method must be 'greedy', 'detmax' or 'greedy-a', not '{method}'")
    return sel if return_selection else sel.indices


def information(B: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """sum_i B_i^T B_i over `rows` of the blocks B (N, m, L) (no prior)."""
    Bs = B if rows is None else B[np.asarray(rows)]
    C = Bs.reshape(-1, Bs.shape[2])
    return C.T @ C


def trace_covariance(B: np.ndarray, rows: np.ndarray | None = None, unscale: np.ndarray | None = None) -> float:
    """Trace of (sum B_i^T B_i)^-1 (prior-scaled units, or physical with `unscale` = the priors)."""
    cov = np.linalg.inv(information(B, rows))
    if unscale is not None:
        cov = cov * np.outer(unscale, unscale)
    return float(np.trace(cov))
