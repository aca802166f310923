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
   null space, one length must be held; it is named by what the robot does
   (`gauge.choose_gauge`).  Both are decided at the start and checked again
   at the solution (`structure_holds`).
3. Data identifiability at the solution: singular directions of the whitened,
   scaled Jacobian that the noise swamps (s_i < snr * sigma) are reported with
   the parameters they involve (Singularity 2, insufficient excitation).

Mobility (Lemma 4): a loop is mobile iff the columns of its joint Jacobian
J_theta are dependent; joint j can move (Lemma 6) iff some vector of the null
space of J_theta has a non-zero j-th component.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from closedloop.analysis.gauge import choose_gauge, sets_scale
from closedloop.estimate.noise import cholesky_inverse
from closedloop.estimate.qr import r_factor, scaled_r_factor_of_blocks
from closedloop.records import Combination, Dropped

STRUCTURE_ROWS = 768  # residual rows per loop the structural analysis reads (`closure_jacobian`), whole configurations
STRUCTURE_CONFIGS = (64, 512)  # the configurations that makes per loop: at least, at most

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem

log = logging.getLogger(__name__)


def compress(C: np.ndarray) -> np.ndarray:
    """The R factor of C = QR: same column dependencies and singular values, P rows (blocked QR)."""
    if C.shape[0] > C.shape[1]:
        return r_factor(C)
    return C


def greedy_reduction(
    C: np.ndarray,
    names: list[str],
    order: list[int],
    tol: float = 1e-6,
    max_terms: int = 6,
    scale: np.ndarray | None = None,
) -> tuple[list[int], list[Dropped]]:
    """Keep columns of C in `order` while they add rank; explain the others.

    C is the column-scaled Jacobian (M, P), C = J diag(s) with s the
    parameters' priors (`scale`; None: C is J itself).  Returns kept column
    indices and the dropped ones with the kept parameters that absorb them.
    A dropped column c_k = sum_j a_j c_j (least squares on the kept ones) is
    reported in the parameters' own units: J_k = sum_j (a_j s_j / s_k) J_j,
    so a change d of parameter k has the effect of changes (a_j s_j / s_k) d
    of the kept ones (m per m, rad per rad, m per rad ...).
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
        big = np.argsort(-np.abs(coef))  # the largest in scaled units: the terms that carry the effect
        phys = coef if scale is None else coef * scale[kept] / scale[k]
        terms = [(names[kept[i]], float(phys[i])) for i in big[:max_terms] if abs(coef[i]) > 1e-3 * np.abs(coef).max()]
        dropped.append(Dropped(names[k], "structurally redundant with this loop", terms, float(res)))
    return kept, dropped


def reduction_margin(C: np.ndarray, kept: list[int], dropped: list[int]) -> tuple[float, float]:
    """How far a reduction of C's columns is from `greedy_reduction`'s tolerance: (largest dropped, smallest kept).

    The first value is the largest relative residual of a dropped column on the
    span of the kept ones, the second the smallest relative residual of a kept
    column on the span of the other kept ones (order-free, so never larger
    than the residual the greedy pass saw).  A reduction read at the nominal
    geometry has round-off (~1e-13) against columns of 1e-3 or more (the
    stereo head with parallel pan axes): noise in the readings cannot move
    either value across the 1e-6 tolerance.
    """
    C = compress(C)
    A = C[:, kept]
    norms = np.linalg.norm(C, axis=0)
    if not kept:
        return (1.0 if dropped else 0.0), np.inf
    Q, Rk = np.linalg.qr(A)
    worst_dropped = 0.0
    for k in dropped:
        if norms[k] > 0:
            v = C[:, k] - Q @ (Q.T @ C[:, k])
            worst_dropped = max(worst_dropped, float(np.linalg.norm(v) / norms[k]))
    # distance of kept column j from the span of the others: 1 / |row j of A^+|, A^+ = Rk^-1 Q^T
    with np.errstate(all="ignore"):
        rows = np.linalg.norm(np.linalg.pinv(Rk, rcond=1e-15), axis=1)
        weakest = float(np.min(1.0 / (rows * norms[kept])))
    return worst_dropped, weakest


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


def weak_directions(
    S: np.ndarray, Vt: np.ndarray, threshold: float, names: list[str], max_terms: int = 6
) -> list[Combination]:
    """Singular directions below `threshold`, each with its main parameters."""
    out = []
    for s, v in zip(S, Vt):
        if s >= threshold:
            continue
        order = np.argsort(-np.abs(v))
        terms = [(names[i], float(v[i])) for i in order[:max_terms] if abs(v[i]) > 0.1 * np.abs(v).max()]
        out.append(Combination(float(s), terms))
    # Null directions beyond the number of rows (more parameters than equations).
    for v in Vt[S.size :]:
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


# --------------------------------------------------------------------------- structure and gauge
@dataclass
class Structure:
    """The structural reduction of a problem: what is estimated, dropped, and what sets the scale.

    kept: indices of the parameters to estimate (sorted);
    dropped: the structurally redundant ones, with what absorbs them;
    gauge: index of the length fixed to set the overall size (thesis 3.3), or
    None (the loops see the size, a user's fixed length sets it, or no length
    is free); gauge_note: the sentence the report gives about the scale.
    """

    kept: list[int]
    dropped: list[Dropped]
    gauge: int | None = None
    gauge_note: str | None = None
    scale_free: bool = False  # the loops cannot see the overall size
    gauge_length: float = 0.0  # the length the gauge stands for (m)
    rechecked: bool = False  # decided at a solution
    provisional: bool = False  # the start closed too few configurations to decide: everything kept until the solution

    def nearly_redundant(self, index: dict[str, int]) -> list[int]:
        """The dropped parameters whose columns lie in the kept ones' span only to 1e-11..1e-6, not to round-off.

        On closure an exact redundancy leaves ~1e-16 (the door's base and tool
        transforms), a weak but real column of a single self-motion 1e-8 to 1e-6
        (the door's j1.a, j5.s); an ill-conditioned arm's exact ones can show
        1e-8 too (a UR5's parallel axes), so the tolerance cannot tell them
        apart.  These are freed when a fit stalls (`solve.solve_with_restarts`).
        """
        return sorted(index[d.name] for d in self.dropped if d.residual > 1e-11 and d.name in index)


def _min_norm_inverse(Jq: np.ndarray) -> np.ndarray:
    """Per configuration the minimum-norm right inverse of Jq (N, m, n): Jq^T (Jq Jq^T)^-1 (N, n, m).

    Through the inverse Cholesky factor L^-1 of Jq Jq^T where it is well conditioned (kappa of
    `cholesky_inverse` below 1e6); elsewhere the SVD pseudo-inverse (rcond 1e-10).
    """
    with np.errstate(all="ignore"):
        Linv, kappa = cholesky_inverse(Jq @ np.swapaxes(Jq, 1, 2))
        P = np.einsum("nji,njk->nik", Jq, np.einsum("nji,njk->nik", Linv, Linv))  # Jq^T L^-T L^-1
    ill = np.flatnonzero(kappa >= 1e6)
    if ill.size:
        P[ill] = np.linalg.pinv(Jq[ill], rcond=1e-10)
    return P


def project_to_closure(
    problem: CalibrationProblem, values: np.ndarray, iters: int = 12
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Joint readings moved onto the closure manifold of the model at `values`, and which converged.

    Gauss-Newton on the readings, theta <- theta - J_theta^+ r per configuration, with the
    minimum-norm inverse J_theta^+ of `_min_norm_inverse`.  Used only to make structural
    redundancies exact.  Near closure (largest residual below 1e-6) the steps keep the last
    J_theta^+ (chord steps: residual-only evaluations, ~5x cheaper than one with J_theta); each
    contracts the residual by about the distance moved since J_theta was taken (~1e-4 for data
    at 1e-4 rad), and J_theta is taken again when one contracts it less than 100-fold.
    Returns the readings per block and, per block, a mask of the configurations whose closure
    error fell below 1e-10 (or 1e-8 of where it started) or stopped moving (the readings cannot
    close a stereo pair's epipolar error: the closest point is taken).
    """
    thetas = [b.theta.copy() for b in problem.blocks]
    last = [np.full(b.theta.shape[0], np.inf) for b in problem.blocks]
    first: list[np.ndarray] = []
    moved = [np.full(b.theta.shape[0], np.inf) for b in problem.blocks]
    inverses: list[np.ndarray | None] = [None] * len(problem.blocks)
    fresh, before = True, np.inf  # J_theta taken in this iteration; the previous largest residual
    for it in range(iters):
        evals = problem.evaluate(values, fresh, thetas, columns=[])
        worst = 0.0
        for k, ev in enumerate(evals):
            last[k] = np.abs(ev.r).max(axis=1) if ev.r.size else np.zeros(0)
            if it == 0:
                first.append(last[k].copy())
            if fresh:
                assert ev.Jq is not None  # evaluated with the Jacobians (fresh)
                inverses[k] = _min_norm_inverse(ev.Jq)
            inv = inverses[k]
            assert inv is not None  # the first iteration is fresh: every block has its inverse
            with np.errstate(all="ignore"):
                step = np.einsum("nij,nj->ni", inv, ev.r)
            step = np.where(np.isfinite(step), step, 0.0)
            moved[k] = np.abs(step).max(axis=1) if step.size else np.zeros(0)
            thetas[k] = thetas[k] - step
            worst = max(worst, float(last[k].max()) if last[k].size else 0.0)
        if worst < 1e-13:
            break
        fresh = not (worst < 1e-6 and (fresh or worst < 1e-2 * before))  # chord steps while they contract
        before = worst
    # closed, or as close as the readings can bring it (a stereo pair's epipolar error is not theirs to fix)
    return thetas, [
        np.isfinite(v) & ((v < np.maximum(1e-10, 1e-8 * f)) | (m < 1e-12)) for v, f, m in zip(last, first, moved)
    ]


def closure_jacobian(problem: CalibrationProblem, x: np.ndarray, free: list[int]) -> np.ndarray | None:
    """The prior-scaled Jacobian over `free` on the readings projected onto closure at `x`, compressed (R of QR).

    Configurations that do not reach closure (gross outliers) are left out;
    None when none does.  Per loop, the configurations of STRUCTURE_ROWS
    residual rows (128 of a weld, 256 of a point contact; STRUCTURE_CONFIGS
    bound the count), evenly spaced along the log (`CalibrationProblem.sampled`):
    the exact dependencies are the model's, and several hundred rows of
    generic configurations show them as well as 100,000: a column's relative
    residual against the others does not grow with more rows spread alike
    (what the data excite weakly is the truncation's business, decided on all
    rows at the solution).  The Panda weld at 1,000 configurations: the same
    structure, gauge and values to the bit with 512, 256 or 128
    configurations (0.084 -> 0.065 s CPU from 512 to 128).  R has the
    columns' dependencies, norms and singular values of the tall matrix.
    """
    scale = np.array([p.prior for p in problem.params])
    lo, hi = STRUCTURE_CONFIGS
    problem = problem.sampled([min(hi, max(lo, -(-STRUCTURE_ROWS // max(b.loop.dim, 1)))) for b in problem.blocks])
    thetas, ok = project_to_closure(problem, x)
    closed = sum(int(m.sum()) for m in ok)
    if closed < 0.5 * sum(m.size for m in ok) and closed * max(b.loop.dim for b in problem.blocks) < 2 * len(free):
        return None  # a model this far from the data closes too few of them: no structure to read there
    evals = problem.evaluate(x, True, thetas, columns=free)
    blocks = []
    for ev, m in zip(evals, ok):
        if m.any():
            assert ev.J is not None  # evaluated with the Jacobian
            blocks.append(ev.J if m.all() else ev.J[m])
    return scaled_r_factor_of_blocks(blocks, scale[free]) if blocks else None  # compress(stacked * scale)


def analyse_structure(
    problem: CalibrationProblem, x: np.ndarray, free: list[int], prefer: int | None = None, R: np.ndarray | None = None
) -> Structure:
    """Structural reduction and length gauge of the free parameters at `x`.

    On `closure_jacobian` (given as `R` when the caller has it).  A start
    that closes too few configurations gives a provisional structure (every
    free parameter kept: the solver's floor truncation takes the exact null
    directions) that `structure_holds` sends back for deciding at the
    solution: never a reduction read off a special point.  `prefer`: a
    gauge to keep if it still qualifies.  Returns indices into the
    problem's parameters.
    """
    names = problem.names
    params = problem.params
    if R is None:
        R = closure_jacobian(problem, x, free)
    if R is None:  # too far from closure to read exact dependencies: decided at the solution instead
        return Structure(list(free), [], provisional=True)
    order = sorted(
        range(len(free)),
        key=lambda i: (
            params[free[i]].priority,
            -params[free[i]].order if params[free[i]].kind in ("placement", "dh") else params[free[i]].order,
            free[i],
        ),
    )
    fnames = [names[k] for k in free]
    priors = np.array([params[k].prior for k in free])

    def reduce(order_: list[int]) -> tuple[list[int], list[Dropped]]:
        return greedy_reduction(R, fnames, order_, scale=priors)

    if not all(b.loop.scale_free for b in problem.blocks):
        kept, dropped = reduce(order)
        return Structure(sorted(free[i] for i in kept), dropped)
    g, kept, dropped, size_free, length = choose_gauge(
        problem, x, free, R, reduce, order, prefer=free.index(prefer) if prefer in free else None
    )
    note: str | None
    if g is not None:
        note = (
            f"the loops close at any overall size (thesis 3.3); {names[free[g]]} is held at its value to set "
            f"the length scale (it stands for a length of {length:.4g} m: holding it longer by d scales the "
            f"robot by 1 + d / {length:.4g})"
        )
        return Structure(sorted(free[i] for i in kept), dropped, free[g], note, True, length)
    note = (
        None
        if not size_free
        else (
            "the loops close at any overall size and no single length sets it: the scale is not determined by the data"
        )
    )
    return Structure(sorted(free[i] for i in kept), dropped, None, note, size_free)


def structure_holds(
    problem: CalibrationProblem, x: np.ndarray, structure: Structure, free: list[int], R: np.ndarray | None
) -> tuple[str | None, str | None]:
    """Why the reduction chosen at the start fails at `x` (a solution), or None; and a warning, or None.

    `R`: `closure_jacobian` at `x`.  The reduction fails when the kept
    parameters are structurally dependent there (rcond 1e-10: what the data
    cannot separate is the SVD truncation's business, not the reduction's),
    or when a parameter dropped for having no effect at the start has one at
    `x` (a tool point started on a joint axis, found off it), or when the
    start found no length to hold the size.  With a gauge g, the kept
    parameters and g must still have one null direction, g's own uniform
    scaling of the robot (`gauge.sets_scale`); if not, the size is not held
    by g alone, which is a warning (the data leave it to other held values).
    """
    if structure.provisional:
        return "the start was too far from closing the loops to decide the reduction", None
    if R is None:
        return None, "the reduction could not be re-checked at the solution (no configuration projects onto closure)"
    norms = np.linalg.norm(R, axis=0)  # the tall matrix's column norms
    for d in structure.dropped:
        if d.reason.startswith("has no effect") and d.name in problem.index:
            k = problem.index[d.name]
            if k in free and norms[free.index(k)] > 1e-9 * norms.max():
                return f"{d.name} has an effect at the solution", None
    kept = [free.index(k) for k in structure.kept]
    S = np.linalg.svd(R[:, kept], compute_uv=False)
    if S.size and S[-1] <= 1e-10 * S[0]:
        return "the estimated parameters are structurally dependent at the solution", None
    # The free parameters' columns beyond the span of the kept ones' (and the held length's): a dropped
    # parameter carries information at the solution if that part moves the closure by more than the
    # closure's own RMS per prior unit (a fit's noise breaks the exact symmetries of a nominal geometry by
    # far less).  Measured on the part orthogonal to the held span, not by counting singular values above
    # that floor: near-equal ones straddle it (a Panda weld of one self-motion, examples/fleet_drift.py,
    # counted one more at 1.03x the floor while its dropped columns lay in the held span to 3e-12x; the
    # re-solve on that reduction drifted along the scale, 7.5x); the door's start 12 adds 12x.
    held = kept + ([free.index(structure.gauge)] if structure.gauge in free else [])
    others = [i for i in range(R.shape[1]) if i not in set(held)]
    r = np.concatenate([ev.r.ravel() for ev in problem.evaluate(x, False)])
    scale_R = float(np.linalg.norm(R, 2)) if R.size else 0.0
    floor = max(1e-10 * scale_R, float(np.sqrt(np.mean(r**2)))) if r.size else np.inf
    if others:
        Q = np.linalg.qr(R[:, held])[0] if held else np.zeros((R.shape[0], 0))
        beyond = R[:, others] - Q @ (Q.T @ R[:, others])
        if np.linalg.norm(beyond, 2) > floor:
            return "a parameter dropped as redundant at the start is not redundant at the solution", None
    if structure.scale_free and structure.gauge is None and not structure.rechecked:
        return "no single length was found to set the scale at the start", None
    if structure.gauge is not None and not sets_scale(problem, x, free, R, kept, free.index(structure.gauge)):
        return None, (
            f"{problem.names[structure.gauge]} does not hold the length scale alone at the solution: "
            "the data leave part of the overall size to other held values"
        )
    return None, None


COLLAPSED = 1e-6  # a loop's response to its joints, over the nominal robot's, below which the fit is no robot
SENSITIVITY_CONFIGS = 16  # configurations per block that response is compared on (`collapsed`)


def collapsed(problem: CalibrationProblem, x: np.ndarray) -> bool:
    """A robot whose loops do not move with its joints: a degenerate fit, whose closure says nothing.

    With the tool point on every joint axis it passes through (links folded onto the axes) a point
    contact closes every configuration trivially: the closure is round-off, and so is the joint noise's
    effect on it, W_i = J_theta,i Sigma J_theta,i^T (eq. 3.17), so the weighted closure is 0/0, any
    number (its rounding decides whether such a fit looks like one within the noise).  Compared here is
    each block's median |J_theta,i| (Frobenius) over a few configurations (`SENSITIVITY_CONFIGS`, evenly
    spaced) at `x` with that of the nominal robot (the same loop parameters): a calibration moves lever
    arms by percent, a degenerate fit shrinks them to round-off (1e-11 and below); `COLLAPSED` lies
    orders of magnitude from both.  A block whose loop does not move with the joints at the nominal robot
    (a known distance) does not count.
    """
    sub = problem.sampled(SENSITIVITY_CONFIGS)
    ref = x.copy()
    ref[: problem.n_robot] = problem.nominal[: problem.n_robot]

    def response(values: np.ndarray) -> list[float]:
        out = []
        for ev in sub.evaluate(values, True, columns=[]):
            norms = np.linalg.norm(ev.Jq, axis=(1, 2)) if ev.Jq is not None and ev.Jq.size else np.zeros(0)
            out.append(float(np.median(norms)) if norms.size else 0.0)
        return out

    at_fit, at_nominal = response(x), response(ref)
    gone = [a < COLLAPSED * n for a, n in zip(at_fit, at_nominal) if n > 0.0 and np.isfinite(n)]
    if any(gone):
        log.info("the fit's loops do not move with its joints (a degenerate robot): it closes nothing")
    return any(gone)
