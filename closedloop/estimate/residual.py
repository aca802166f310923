"""The residual functions of a reduced calibration problem, and one solve of each (a stage).

The solver (`lm.levenberg_marquardt`) minimises 1/2 |r(x)|^2 for any
residual function; this module builds those functions for a calibration
problem over its estimated parameters and solves each once (a stage; the order of
the stages and their starts are `closedloop.calibration.solve`'s) (thesis 3.2.3,
4.2.6, with the noise treated as errors in variables):

1. **Plain stage.**  The loop-closure residual itself (the thesis's criterion,
   eq. 3.8), truncated only at the numerical floor.  Far from the solution
   the errors-in-variables weights W_i^-1 (below) are those of a wrong model,
   and where a task axis lines up with a joint axis they discard residual
   directions altogether; the plain residual has neither problem.
2. **Weighted stage.**  From the plain solution, each configuration's
   closure error whitened by W_i = J_theta,i Sigma J_theta,i^T (+ the loop's
   measurement covariance) (Wampler, Hollerbach & Arai 1995), with the
   noise-aware SVD truncation of eq. 4.17.
3. **Guard.**  The weighting must not hide a residual: if at the weighted
   solution W_i has lost rank that it had at the plain solution (a fitted
   hinge slid onto a joint axis) while the unweighted closure grew, the plain
   solution is kept and the result says why.

On a long log (a block above `PRESOLVE_ABOVE` configurations) each stage is
first solved on an evenly spaced sample and finished on the whole log
(`presolved`).  `Restarts` (random starts within the parameters' priors) are
tried by the caller when a stage stalls far above any plausible noise.
"""

from __future__ import annotations

import copy
import logging
import weakref
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from closedloop.estimate.lm import SolverOptions, SolverResult, chord_projection, levenberg_marquardt, scaled_svd
from closedloop.estimate.noise import Roots, whiten
from closedloop.loops.base import Loop
from closedloop.problem.problem import BlockEval, CalibrationProblem

log = logging.getLogger(__name__)


@dataclass
class ResidualFunction:
    """r(x_est) and its Jacobian over the estimated parameters `est`, the others held at `x0`.

    Only the estimated columns of the Jacobian are formed.  The solver's
    functions whiten with the cheap square root of W_i^-1 (`whiten`,
    symmetric=False: the same least-squares problem); robust weights need
    the components of the symmetric W_i^-1/2 r (`symmetric`).  Evaluations
    are reused, never changed: the first trial point after a Jacobian call is
    evaluated with its Jacobian (Levenberg-Marquardt usually accepts it and
    asks for that next; its cost is still taken with the old W_i), and the
    last Jacobian evaluation is returned again for the same parameters.
    `row_weights` multiplies the rows (IRLS, outlier screening).  With `frozen` the W_i of the first
    evaluation are kept for every later one, Jacobians included: the function is then one fixed weighted
    least-squares problem, whose cost the solver's accepted steps lower monotonically (a reweighted pass,
    `outliers.robust_refit`; the errors-in-variables fit itself re-weights at each Jacobian).
    """

    problem: CalibrationProblem
    x0: np.ndarray
    est: list[int]
    sigma_q: np.ndarray
    weighting: str
    row_weights: np.ndarray | None = None
    symmetric: bool = False
    frozen: bool = False

    def __post_init__(self) -> None:
        self._W: Roots | None = None  # the weighting's roots at the last Jacobian (`whiten`)
        self._x: np.ndarray | None = None  # the last Jacobian's point
        self._rJ: tuple[np.ndarray, np.ndarray] | None = None  # (r, J) there
        self._trial: tuple[np.ndarray, list[BlockEval]] | None = None  # the first trial point, its evaluation
        self.deficit = 0  # residual directions the weighting discards (pseudo-inverse), at the last Jacobian
        self.missing = 0  # residual rows without an observation, at the last Jacobian
        self._charts: dict[int, Loop] = {}  # block -> its loop with a re-centred chart (`retract`)
        self._charted = self.problem  # the problem evaluated: with those loops
        self._x0c = self.x0  # x0 in those charts
        self._chartable: list[int] | None = None  # blocks `retract` may re-chart, found at its first call

    def full(self, xe: np.ndarray) -> np.ndarray:
        """The whole parameter vector, in the problem's own charts."""
        x = self._x0c.copy()
        x[self.est] = xe
        for bi, lp in self._charts.items():
            c = self.problem.loop_columns[bi]
            x[c] = lp.express(x[c], self.problem.blocks[bi].loop)
        return x

    def retract(self, xe: np.ndarray) -> np.ndarray:
        """`xe` after the loops' charts moved to it (`Loop.recentred`), in the new charts.

        Called by the solver after each accepted step: a loop whose parameters
        are coordinates on a manifold (the hinge's line) keeps its chart centred
        where the solver is, so that the steps are taken where it is nearly
        flat.  Loops whose parameters are not all estimated or are shared stay.
        """
        if self._chartable is None:  # the blocks whose loop has a chart to move, all of it estimated, unshared
            est, cols = set(self.est), self.problem.loop_columns
            self._chartable = [
                bi
                for bi, b in enumerate(self.problem.blocks)
                if type(b.loop).recentred is not Loop.recentred
                and cols[bi].size
                and est.issuperset(cols[bi].tolist())
                and not any(np.intersect1d(cols[bi], o).size for bj, o in enumerate(cols) if bj != bi)
            ]
        if not self._chartable:
            return xe
        x = self._x0c.copy()
        x[self.est] = xe
        moved = False
        for bi in self._chartable:
            c = self.problem.loop_columns[bi]
            lp = self._charts.get(bi, self.problem.blocks[bi].loop)
            moved_to = lp.recentred(x[c])
            if moved_to is not None:
                self._charts[bi], x[c] = moved_to
                moved = True
        if moved:
            blocks = [replace(b, loop=self._charts.get(bi, b.loop)) for bi, b in enumerate(self.problem.blocks)]
            self._charted = copy.copy(self.problem)
            self._charted.blocks = blocks
            self._x0c, self._x, self._rJ, self._trial = x, None, None, None
        return x[self.est]

    def settle(self, xe: np.ndarray) -> np.ndarray | None:
        """`xe` in the problem's own charts, the charts reset; None if none moved."""
        if not self._charts:
            return None
        x = self.full(xe)
        self._charts, self._charted, self._x0c = {}, self.problem, self.x0
        self._x, self._rJ, self._trial = None, None, None
        return x[self.est]

    def _local(self, xe: np.ndarray) -> np.ndarray:
        x = self._x0c.copy()
        x[self.est] = xe
        return x

    def __call__(self, xe: np.ndarray, jac: bool | None) -> tuple[np.ndarray, np.ndarray | None]:
        """r (and J if `jac`) at xe; `jac=None`: a probe (no Jacobian, not a trial point)."""
        if jac is None:
            evals = self._charted.evaluate(self._local(xe), self._W is None, columns=[])
            r, _, _ = whiten(evals, self.sigma_q, self.weighting, False, self.problem.noise, self._W, self.symmetric)
            return (r * self.row_weights if self.row_weights is not None else r), None
        if jac and self._x is not None and self._rJ is not None and np.array_equal(xe, self._x):
            return self._rJ
        kept = self._kept_roots(xe) if not jac and self._W is None else None  # another function's, same point
        if kept is not None:
            self._W = kept
        loops = self.problem.noise  # each block's measurement covariance (problem.BlockNoise)
        first_trial = not jac and self._W is not None and self._trial is None and kept is None
        if jac and self._trial is not None and np.array_equal(xe, self._trial[0]):
            evals = self._trial[1]
        else:
            full = jac or first_trial
            evals = self._charted.evaluate(self._local(xe), full or self._W is None, columns=self.est if full else [])
        roots = None if jac and not self.frozen else self._W
        r, J, used = whiten(
            evals, self.sigma_q, self.weighting, jac, loops, roots, self.symmetric, overwrite=True
        )  # evaluations are copies (a trial's is whitened once)
        if roots is None and self.weighting == "noise":
            self._keep_roots(xe, used)
        if jac or self._W is None or kept is not None:
            self._W = used
            self.deficit = sum(u[1] for u in used if u is not None)
            # rows with no observation (a marker out of view): zero, and no degree of freedom.  Without a
            # measurement covariance the weighting already drops them (they are in the deficit).
            self.missing = sum(
                int((~ev.valid).sum())
                for ev, lp in zip(evals, loops)
                if ev.valid is not None and (self.weighting != "noise" or lp.measurement_cov is not None)
            )
        if self.row_weights is not None:
            r = r * self.row_weights
            if J is not None and J.flags.writeable:
                J *= self.row_weights[:, None]  # J is whitening's own (or the evaluation's copy)
            elif J is not None:  # the evaluation itself, kept read-only by the problem (unweighted rows)
                J = J * self.row_weights[:, None]
        if jac and J is not None:
            self._x, self._rJ, self._trial = xe.copy(), (r, J), None
        elif first_trial:
            self._trial = (xe.copy(), evals)
        return r, J

    def _keep_roots(self, xe: np.ndarray, used: Roots) -> None:
        """Keep the weighting's roots at `xe` on the problem evaluated (one point), for `_kept_roots`."""
        self._charted.__dict__["_roots_kept"] = (self._local(xe).tobytes(), self.sigma_q.copy(), self.symmetric, used)

    def _kept_roots(self, xe: np.ndarray) -> Roots | None:
        """The roots of W_i^-1 at `xe` from another function of the same problem at the same point, where they
        are this function's: W_i = Jq_i Sigma Jq_i^T scales with Sigma, so a joint noise c times the one they
        were formed with gives them divided by c (the fit's weighting, the screen's and the closure level's at
        one solution: the same Jq).  None where a loop has a measurement covariance (W_i is then no multiple),
        for configurations whitened as groups, or another point, root or noise pattern."""
        kept = self._charted.__dict__.get("_roots_kept")
        if kept is None or self.weighting != "noise" or kept[2] != self.symmetric:
            return None
        key, sigma, _, used = kept
        if any(nz.measurement_cov is not None for nz in self.problem.noise) or len(used) != len(self.problem.blocks):
            return None
        c = float(self.sigma_q[0] / sigma[0]) if sigma.size and sigma[0] > 0.0 else 0.0
        if not (c > 0.0 and np.allclose(self.sigma_q, c * sigma, rtol=1e-12, atol=0.0)):
            return None
        if key != self._local(xe).tobytes():
            return None
        return [None if u is None else (u[0] / c, u[1]) for u in used]

    def keep_jacobian(self, xe: np.ndarray, r: np.ndarray) -> None:
        """The solver's chord step (`lm.SolverOptions.chord`): the linearisation at `xe` is the last Jacobian
        with `r`, the residual at `xe` (a probe's: the weighting of that Jacobian)."""
        if self._rJ is not None and self._x is not None:
            self._charted.relinearized(self._local(xe), self._local(self._x))  # for the stages after the solve
            kept = self._charted.__dict__.get("_roots_kept")
            if kept is not None and kept[0] == self._local(self._x).tobytes():  # and the weighting's roots
                self._charted.__dict__["_roots_kept"] = (self._local(xe).tobytes(),) + kept[1:]
            J = self._rJ[1]
            svd = self.__dict__.get("_svd")
            if svd is not None and svd[0]() is J:  # and its factorisation, with the projection of `r`
                S, Vt, _ = svd[3]
                g = chord_projection(J, r, np.frombuffer(svd[2], dtype=float), S, Vt)
                self.__dict__["_svd"] = (svd[0], weakref.ref(r), svd[2], (S, Vt, g))
            self._x, self._rJ, self._trial = xe.copy(), (r, J), None

    def linearized(self, xe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """r and its Jacobian J at `xe` (the call with `jac`; a ValueError if the problem gives no J)."""
        r, J = self(xe, True)
        if J is None:
            raise ValueError("the residual function has no Jacobian: the problem has no loop block")
        return r, J

    def factorised(self, xe: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """S, Vt and g = U^T r of the column-scaled Jacobian J D = U S V^T at `xe` (`lm.scaled_svd`), kept with
        that Jacobian: the solver's last iteration, its noise estimate, the model-error test and the analysis
        at the solution ask for the same factorisation, a pass over every row each on a long log."""
        r, J = self.linearized(xe)
        kept = self.__dict__.get("_svd")  # weak references: a Jacobian the function let go is not held
        key = np.asarray(scale, dtype=float).tobytes()
        if kept is not None and kept[0]() is J and kept[1]() is r and kept[2] == key:
            return kept[3]
        out = scaled_svd(J, r, scale)
        self.__dict__["_svd"] = (weakref.ref(J), weakref.ref(r), key, out)
        return out

    def normalized(self, x: np.ndarray) -> np.ndarray:
        """`x`, a full vector at this function's last Jacobian, with the loops in canonical form
        (`CalibrationProblem.normalized`: the same model), and that Jacobian carried there by the chain rule,
        J dp/dp' (`Loop.normalize_jacobian`), so that the analysis at the solution does not evaluate again.
        Where a loop knows no such Jacobian, or moves a value not estimated, the next call evaluates."""
        xn = self.problem.normalized(x)
        if (
            np.array_equal(xn, x)
            or self._charts
            or self._x is None
            or self._rJ is None
            or not np.array_equal(self._x, x[self.est])
        ):
            return xn
        col = {k: i for i, k in enumerate(self.est)}
        r, J = self._rJ
        J = J.copy()
        for b, cols in zip(self.problem.blocks, self.problem.loop_columns):
            if np.array_equal(xn[cols], x[cols]):
                continue
            T = b.loop.normalize_jacobian(x[cols])
            if T is None or not all(int(c) in col for c in cols):
                return xn
            idx = [col[int(c)] for c in cols]
            J[:, idx] = J[:, idx] @ T
        self._x, self._rJ, self._trial = xn[self.est].copy(), (r, J), None
        return xn

    def blocks(self, xe: np.ndarray, symmetric: bool = True) -> list[np.ndarray]:
        """The residual at `xe` per loop block, (N, m) each (no row weights).

        The symmetric whitening gives each component of a configuration's residual its meaning (a
        component's correlation along the log); `symmetric` False is for what any root F of W_i^-1 gives
        alike, at a fraction of the cost: norms per configuration, and components that are independent
        N(0, 1) under the noise model (the outlier screen's scale).
        """
        f = replace(self, row_weights=None, symmetric=symmetric)
        r, _ = f(xe, False)
        sizes = [b.theta.shape[0] * b.loop.dim for b in self.problem.blocks]
        parts = np.split(r, np.cumsum(sizes)[:-1])
        return [p.reshape(b.theta.shape[0], b.loop.dim) for p, b in zip(parts, self.problem.blocks)]


def unweighted_closure(problem: CalibrationProblem, x: np.ndarray) -> float:
    """RMS of the raw closure residual over all rows (metres and radians mixed: a convergence gauge)."""
    evals: list[BlockEval] = problem.evaluate(x, False)
    r = np.concatenate([e.r.ravel() for e in evals]) if evals else np.zeros(0)
    return float(np.sqrt(np.mean(r**2))) if r.size else 0.0


@dataclass
class StageResult:
    solution: SolverResult
    fun: ResidualFunction
    note: str | None = None
    deficit_start: int = 0  # residual directions the weighting discarded at the stage's start
    closure_level: float | None = None  # `solve._closure_level`, once computed


PRESOLVE_ROWS = 8192  # configurations per block of the sample a stage on a long log is first solved on
PRESOLVE_ABOVE = 32768  # configurations in a block from which a stage is presolved (`presolved`)


def presolved(
    fun: ResidualFunction,
    start: np.ndarray,
    scale: np.ndarray,
    sopt: SolverOptions,
    progress: Callable[[int, float], None] | None,
) -> tuple[np.ndarray, int]:
    """A start for `fun` (estimated values) from the same fit on an evenly spaced sample of a long log.

    Far from the solution, a log of 100,000 configurations says nothing 8,192 of them do not, at 12 times
    the cost per iteration: the fit is solved on at most `PRESOLVE_ROWS` configurations per block
    (`CalibrationProblem.sampled`), and the whole log then only finishes it (its least-squares minimum
    is a few sample standard errors away, one or two iterations).  The sample's solution is used only if
    its fit converged, finite, without its weighting discarding more residual directions than at `start`
    (the guard of `weighted_stage`); else `start` is returned.  Row weights (IRLS) are per row of the
    whole log: no presolve then.  Returns the start and the sample's iterations.
    """
    problem = fun.problem
    if fun.row_weights is not None or all(b.theta.shape[0] < PRESOLVE_ABOVE for b in problem.blocks):
        return start, 0
    sub = replace(fun, problem=problem.sampled(PRESOLVE_ROWS))
    sub(start, True)
    deficit = sub.deficit
    res = levenberg_marquardt(sub, start, scale, sopt, progress)
    sub(res.x, True)
    if res.status != "converged" or not np.isfinite(res.cost) or sub.deficit > deficit:
        log.info("the fit on a sample of the log did not converge cleanly (%s): solved on the whole log", res.message)
        return start, res.iterations
    log.info(
        "solved on %d configurations per loop in %d iterations; finishing on the whole log",
        PRESOLVE_ROWS,
        res.iterations,
    )
    # the loops' parameters in their canonical form (the same model): the whole log's fit then ends where the
    # analysis at the solution evaluates it
    return fun.problem.normalized(fun.full(res.x), fun.est)[fun.est], res.iterations


#: |dz| (prior units) below which the whole log's finish from its sample's solution keeps its Jacobian
#: (`lm.SolverOptions.chord`): that solution lies a few sample standard errors from the log's, hundredths of
#: a prior unit, over which the Jacobian changes by ~1e-4 of itself
FINISH_CHORD = 0.1


def _finishing(sopt: SolverOptions, near: np.ndarray, start: np.ndarray) -> SolverOptions:
    """The solver's options for the whole log from `near`: with chord steps where `near` is its sample's
    solution (`presolved`: not `start`)."""
    return replace(sopt, chord=FINISH_CHORD) if near is not start else sopt


def below_noise_reset(
    problem: CalibrationProblem,
    base: np.ndarray,
    at: np.ndarray,
    moved: np.ndarray,
    ref: np.ndarray,
    est: list[int],
    scale: np.ndarray,
    sigma_q: np.ndarray,
    snr: float,
) -> np.ndarray | None:
    """`moved` (estimated values) with its components along the directions the weighted fit truncates at `at`
    set back to those of `ref`: ref + V_k V_k^T (moved - ref) in prior-scaled coordinates, V_k the directions
    of the weighted, prior-scaled Jacobian at `at` (eq. 4.17) with s_k above `snr` noise units (and the
    numerical floor).  None where no direction lies below them there (nothing to set back).

    The weighted fit holds a truncated direction where its start puts it (eq. 4.17): a start that moved
    along one (a fit without truncation, or one that saw the data left out) would carry that move into the
    solution; set back, the direction keeps the value of `ref`, as a fit truncating it from `ref` would."""
    fun = ResidualFunction(problem, base, est, sigma_q, "noise")
    r, J = fun.linearized(at)
    S, Vt, _ = scaled_svd(J, r, scale[est])
    keep = S > max(SolverOptions().rcond * (S[0] if S.size else 0.0), snr)
    if keep.all():
        return None
    V = Vt[keep]
    d = (moved - ref) / scale[est]
    return ref + (V.T @ (V @ d)) * scale[est]


def plain_stage(
    problem: CalibrationProblem,
    x0: np.ndarray,
    start: np.ndarray,
    est: list[int],
    scale: np.ndarray,
    sopt: SolverOptions,
    progress: Callable[[int, float], None] | None,
    row_weights: np.ndarray | None = None,
) -> StageResult:
    """The loop-closure residual itself (eq. 3.8) from `start` (estimated values), floor truncation only.

    On a single self-motion many robots close the same curve, and its long
    Gauss-Newton steps may reach a degenerate one (a forearm of zero length):
    the caller compares it with the weighted fit (`solve._better`).
    """
    fun = ResidualFunction(problem, x0, est, np.ones(len(problem.joints)), "none", row_weights)
    sopt = replace(sopt, noise=0.0)
    near, pre = presolved(fun, start, scale[est], sopt, progress)
    res = levenberg_marquardt(fun, near, scale[est], _finishing(sopt, near, start), progress)
    res.iterations += pre
    return StageResult(res, fun)


def weighted_stage(
    problem: CalibrationProblem,
    x0: np.ndarray,
    start: np.ndarray,
    est: list[int],
    scale: np.ndarray,
    sigma_q: np.ndarray,
    weighting: str,
    sopt: SolverOptions,
    progress: Callable[[int, float], None] | None,
    row_weights: np.ndarray | None = None,
) -> StageResult:
    """The errors-in-variables stage from `start` (a plain solution), guarded against hidden residuals."""
    fun = ResidualFunction(problem, x0, est, sigma_q, weighting, row_weights)
    near, pre = presolved(fun, start, scale[est], sopt, progress)
    fun(near, True)
    deficit_start = fun.deficit  # the weighting at the start (the solver's first call reuses this evaluation)
    res = levenberg_marquardt(fun, near, scale[est], _finishing(sopt, near, start), progress)
    res.iterations += pre
    if weighting != "noise":
        return StageResult(res, fun)
    fun(res.x, True)
    if fun.deficit > deficit_start:
        before, after = unweighted_closure(problem, fun.full(start)), unweighted_closure(problem, fun.full(res.x))
        if after > 2.0 * before + 1e-12:
            note = (
                f"the noise weighting became singular at the weighted fit ({fun.deficit - deficit_start} more "
                f"residual directions discarded: a task axis on a joint axis) while the unweighted closure "
                f"grew from {before:.3g} to {after:.3g}; the plain loop-closure fit is kept"
            )
            log.info(note)  # the stage's note: the verdict's reason where this stage is the calibration's
            plain = ResidualFunction(problem, x0, est, np.ones(len(problem.joints)), "none", row_weights)
            kept = levenberg_marquardt(plain, start, scale[est], sopt, progress)
            return StageResult(kept, plain, note, deficit_start)
    return StageResult(res, fun, None, deficit_start)


def random_start(
    x0: np.ndarray, est: list[int], scale: np.ndarray, rng: np.random.Generator, size: float
) -> np.ndarray:
    """x0 with the estimated parameters moved by `size` times their prior magnitudes (normal draws)."""
    x = x0.copy()
    x[est] = x[est] + size * scale[est] * rng.standard_normal(len(est))
    return x


@dataclass
class Fit:
    """A solved reduced problem: the full parameter vector and how it was reached."""

    x: np.ndarray
    stage: StageResult
    est: list[int]
    sigma_q: np.ndarray
    known: bool
    iterations: int
    warnings: list[str]
    #: restarts gave up: every start stalled alike far above any noise (`solve.solve_with_restarts`)
    hopeless: bool = False
