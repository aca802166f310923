"""The design algorithms of pose selection on Jacobian blocks (numpy only): information, greedy, DETMAX.

The information of a design S is A(S) = A_0 + sum_{i in S} B_i^T B_i (B_i the whitened,
prior-scaled Jacobian block of configuration i); every update is rank m (Woodbury, the matrix
determinant lemma).  The full derivation, the criteria (D: log det A; A: tr A^-1) and the
references are in the docstring of :mod:`closedloop.design.poses`; the A-optimal exchange is in
:mod:`closedloop.design.exchange`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from closedloop.errors import OptionError


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


def greedy_d_optimal(
    B: np.ndarray,
    k: int,
    prior_weight: float = 1.0,
    base: np.ndarray | None = None,
    start: list[int] | None = None,
    criterion: str = "D",
) -> Selection:
    """Greedy D-optimal (or, criterion='A', trace-minimising) choice of k blocks of B (Npool, m, L).

    Each step adds the free candidate with the largest gain, log det(I + B_i A^-1 B_i^T) (D) or
    tr(S_i^-1 B_i A^-2 B_i^T) (A), then updates A^-1 by Woodbury.  `start`: indices taken first.
    """
    if criterion not in ("D", "A"):
        raise OptionError(f"criterion must be 'D' or 'A', not '{criterion}'")
    N = B.shape[0]
    if k > N:
        raise OptionError(f"cannot choose {k} configurations from a pool of {N}")
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
    return Selection(
        np.array(chosen, dtype=int), d.logdet, hist, trace=d.trace, trace_history=thist, criterion=criterion
    )


def detmax(
    B: np.ndarray,
    k: int,
    prior_weight: float = 1.0,
    base: np.ndarray | None = None,
    start: list[int] | None = None,
    max_excursion: int = 4,
    max_rounds: int = 500,
    tol: float = 1e-9,
) -> Selection:
    """Mitchell's DETMAX exchange from a greedy (or given) design of k blocks."""
    sel = greedy_d_optimal(B, k, prior_weight, base) if start is None else None
    design = list(sel.indices) if sel is not None else list(start or [])
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


def information(B: np.ndarray, rows: np.ndarray | list[int] | None = None) -> np.ndarray:
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
