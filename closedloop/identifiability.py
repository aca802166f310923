"""What the data can and cannot identify (thesis 3.2.2, 3.3, 4.2.2, 4.2.6).

Three questions, answered on the column-scaled Jacobian C D (D: the
parameters' expected error magnitudes):

1. Structural redundancy.  Evaluated on the logged configurations projected
   onto the current model's closure manifold, so that the gauge freedoms that
   only hold for closed loops (tool and base transforms against an unknown
   closure, the overall length scale of thesis 3.3) are exact.  Parameters
   are taken greedily in priority order (loop geometry, offsets, scales, then
   link geometry from the tip to the base) and one is dropped when its column
   lies in the span of those already kept (relative residual < tol); the
   least-squares coefficients of that fit say what absorbed it.
2. The length gauge (3.3): when a uniform scaling of every length lies in the
   null space, one length must be fixed; the longest free one is.
3. Data identifiability at the solution: singular directions of the whitened,
   scaled Jacobian that the noise swamps (s_i < snr * sigma) are reported with
   the parameters they involve (Singularity 2, insufficient excitation).

Mobility (Lemma 4): a loop is mobile iff the columns of its joint Jacobian
J_theta are dependent; joint j can move (Lemma 6) iff some vector of the null
space of J_theta has a non-zero j-th component.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Dropped:
    """A parameter removed before solving, and why."""

    name: str
    reason: str
    absorbed_into: list[tuple[str, float]] = field(default_factory=list)

    def describe(self) -> str:
        if not self.absorbed_into:
            return f"{self.name}: {self.reason}"
        parts = " ".join(f"{c:+.3g}*{n}" for n, c in self.absorbed_into)
        return f"{self.name}: {self.reason}; its effect equals {parts}"


@dataclass
class Combination:
    """A direction of parameter space that the data do not determine."""

    singular_value: float
    terms: list[tuple[str, float]]  # (name, coefficient) of the unit null direction (scaled units)

    def describe(self) -> str:
        names = [n for n, _ in self.terms]
        if len(self.terms) == 1:
            return f"{names[0]} is not identifiable with this data"
        if len(self.terms) == 2:
            (n1, c1), (n2, c2) = self.terms
            sign = "-" if c1 * c2 > 0 else "+"
            return (f"{n1} and {n2} are identifiable only together, as {n1} {sign} {n2} "
                    f"(in prior-scaled units); the direction {c1:+.2f}*{n1} {c2:+.2f}*{n2} is not")
        dirn = " ".join(f"{c:+.2f}*{n}" for n, c in self.terms)
        return f"{', '.join(names)} are not separately identifiable: the combination {dirn} is not determined"


def compress(C: np.ndarray) -> np.ndarray:
    """The R factor of C = QR: same column dependencies and singular values, P rows."""
    if C.shape[0] > C.shape[1]:
        return np.linalg.qr(C, mode="r")
    return C


def greedy_reduction(C: np.ndarray, names: list[str], order: list[int], tol: float = 1e-6,
                     max_terms: int = 6) -> tuple[list[int], list[Dropped]]:
    """Keep columns of C in `order` while they add rank; explain the others.

    C is the column-scaled Jacobian (M, P).  Returns kept column indices and
    the dropped ones with the kept parameters that absorb them.
    """
    C = compress(C)
    M = C.shape[0]
    Q = np.zeros((M, 0))
    kept: list[int] = []
    dropped: list[Dropped] = []
    norms = np.linalg.norm(C, axis=0)
    cmax = norms.max() if norms.size else 0.0
    for k in order:
        c = C[:, k]
        if norms[k] <= 1e-12 * max(cmax, 1e-300):
            dropped.append(Dropped(names[k], "has no effect on any loop with this data"))
            continue
        v = c - Q @ (Q.T @ c)
        v = v - Q @ (Q.T @ v)  # re-orthogonalise
        res = np.linalg.norm(v) / norms[k]
        if res > tol:
            Q = np.column_stack([Q, v / np.linalg.norm(v)])
            kept.append(k)
            continue
        coef, *_ = np.linalg.lstsq(C[:, kept], c, rcond=None)
        big = np.argsort(-np.abs(coef))
        terms = [(names[kept[i]], float(coef[i])) for i in big[:max_terms]
                 if abs(coef[i]) > 1e-3 * np.abs(coef).max()]
        dropped.append(Dropped(names[k], "structurally redundant with this loop", terms))
    return kept, dropped


def null_space(C: np.ndarray, rtol: float = 1e-7) -> np.ndarray:
    """Orthonormal basis (P, k) of the numerical null space of C."""
    if C.size == 0:
        return np.zeros((C.shape[1], 0))
    C = compress(C)
    if C.shape[0] < C.shape[1]:
        C = np.vstack([C, np.zeros((C.shape[1] - C.shape[0], C.shape[1]))])
    _, S, Vt = np.linalg.svd(C)
    rank = int(np.sum(S > rtol * S[0])) if S.size else 0
    return Vt[rank:].T


def length_gauge(C: np.ndarray, scale_dir: np.ndarray, length_mask: np.ndarray,
                 rtol: float = 1e-7, fit_tol: float = 1e-3) -> bool:
    """True when scaling every length uniformly (with any compensation) leaves the loops closed.

    `scale_dir` is d(value)/d(eps) under lengths -> (1+eps) lengths, in the
    scaled coordinates of C; only its length components (`length_mask`) are
    required to be reproduced by a null vector, the rest may compensate.
    """
    N = null_space(C, rtol)
    s = scale_dir[length_mask]
    if N.shape[1] == 0 or np.linalg.norm(s) == 0:
        return False
    NL = N[length_mask]
    c, *_ = np.linalg.lstsq(NL, s, rcond=None)
    return bool(np.linalg.norm(NL @ c - s) <= fit_tol * np.linalg.norm(s))


def weak_directions(S: np.ndarray, Vt: np.ndarray, threshold: float, names: list[str],
                    max_terms: int = 6) -> list[Combination]:
    """Singular directions below `threshold`, each with its main parameters."""
    out = []
    for s, v in zip(S, Vt):
        if s >= threshold:
            continue
        order = np.argsort(-np.abs(v))
        terms = [(names[i], float(v[i])) for i in order[:max_terms] if abs(v[i]) > 0.1 * np.abs(v).max()]
        out.append(Combination(float(s), terms))
    # Null directions beyond the number of rows (more parameters than equations).
    for v in Vt[S.size:]:
        order = np.argsort(-np.abs(v))
        terms = [(names[i], float(v[i])) for i in order[:max_terms] if abs(v[i]) > 0.1 * np.abs(v).max()]
        out.append(Combination(0.0, terms))
    return out


def loop_mobility(Jq: np.ndarray, rtol: float = 1e-8) -> tuple[int, np.ndarray]:
    """Mobility of a loop and which joints can move (Lemmas 4 and 6).

    Jq: (N, m, n) derivatives of the closure error w.r.t. the joint readings.
    Returns the largest nullity over configurations and, per joint, whether
    some null vector moves it at some configuration.
    """
    N, m, n = Jq.shape
    mobility = 0
    moves = np.zeros(n, dtype=bool)
    for i in range(min(N, 25)):
        _, S, Vt = np.linalg.svd(Jq[i], full_matrices=True)
        rank = int(np.sum(S > rtol * max(S[0], 1e-300))) if S.size else 0
        Nul = Vt[rank:]
        mobility = max(mobility, Nul.shape[0])
        if Nul.shape[0]:
            moves |= np.linalg.norm(Nul, axis=0) > 1e-6
    return mobility, moves
