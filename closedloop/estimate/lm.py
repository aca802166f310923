"""Levenberg-Marquardt with noise-aware SVD truncation (thesis 3.2.3, 4.2.6).

The solver knows nothing of robots or loops: it minimises 1/2 |r(x)|^2 for a
callable returning the (already whitened) residual r and Jacobian J.

Each iteration solves the modified criterion of eq. 3.17 / 4.17,

    min |r + J dx|^2 + lambda |dx|^2,

in column-scaled coordinates dx = D dz (D: the parameters' expected error
magnitudes), through the SVD J D = U S V^T:

    dz = - sum_{i kept} s_i / (s_i^2 + lambda) (u_i^T r) v_i.

Truncation (4.2.6) follows the noise rather than a fixed ratio: direction i is
kept when the data determine it better than its prior, s_i > snr * sigma, with
sigma the known noise level of r (1 when r is whitened by a known noise) or, if
unknown, the current residual RMS (large while the model is far off, like the
thesis's large p at the start; the noise level at convergence).

Globalisation (thesis-sized starting errors).  The first step is
Gauss-Newton (lambda = 0, or `damping` x s_max^2); a trial is accepted when
its gain ratio rho = (actual decrease) / (the linear model's decrease) exceeds
1e-4, and lambda follows Nielsen's rule (x max(1/3, 1 - (2 rho - 1)^3) on
success, x nu with nu doubling on failure; the thesis halves the step, 4.2.6).
Every step carries Transtrum and Sethna's geodesic acceleration, v + a/2 with
a = -(J^T J + lambda)^-1 J^T r''(v): in the narrow curved valleys of a single
self-motion it cuts the iterations several-fold and finds the solution from
starts where plain Gauss-Newton reaches a wrong minimum (one more residual
evaluation per iteration; taking it only after a poorly predicted step halved
Example 1's recovery rate).  When the linear
model predicts a relative decrease below ftol the solver stops without trying
(at the minimum the trial costs differ only by round-off); it also stops where
the cost itself has stopped falling over several accepted steps (`STALL_ITERATIONS`):
the trials may keep "succeeding" (a weighting that moves with the step, round-off).  A step made
short by the damping after rejected trials is not convergence while the
undamped step is long (both must be below `xtol`), and where no damped step
lowers the cost although the linear model says the undamped one would remove
most of it (the stop is no minimum), that step is tried shortened
(`_line_search`); a solve that only such cut steps move, a percent of the cost at a time, is crawling on
a slope its Jacobian does not give, and stops 'stalled' (`CRAWL_ITERATIONS`).  With bounds
the step is a bounded least-squares problem solved by qpsolvers/OSQP in the
kept subspace.

Chord steps (`SolverOptions.chord`, for a solve that starts next to its minimum: a long log finished from
its sample's solution).  An undamped step no longer than `chord` in the
parameters' prior units, and after such a step a tenth of it at most (the iteration contracts: `_chord`),
keeps the Jacobian: the trial is evaluated without one, and once accepted the next linear model is the last
Jacobian J_0 with the new residual, g = U^T r = S^-1 V^T D J_0^T r (the chord, or simplified Newton,
method: Kelley 1995, ch. 5).  J changes over such a step by about the step times the model's curvature, a
few 1e-4 of itself where a prior unit is a millimetre or a milliradian on links of decimetres; the chord's
minimum, where J_0^T r vanishes, lies about that share of a standard error from the minimum's.  The
solver's Jacobian is then J_0, the linearisation of a point within `chord` of its solution; a function
with a `keep_jacobian` hook is told so (its next Jacobian call at the solution returns J_0 with the
residual there).  No geodesic correction then: a step that short has no curvature to correct.  A damped
step, or a chord that does not contract (a valley whose Jacobian turns along it), takes a new Jacobian.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from closedloop.estimate.qr import scaled_r_factor

log = logging.getLogger(__name__)

#: r(x, jac): jac True, with its Jacobian; False, a trial point; None, a probe (no Jacobian)
ResidualFn = Callable[[np.ndarray, bool | None], tuple[np.ndarray, np.ndarray | None]]


@dataclass
class SolverOptions:
    max_iter: int = 100
    ftol: float = (
        1e-10  # stop when the relative cost decrease is below this (x sqrt(2 ftol chi2) sigma from the minimum)
    )
    xtol: float = 1e-9  # stop when |dz| (step in units of the parameters' priors) is below this
    noise: float | None = None  # known noise level of r; None: estimate from the residual
    snr: float = 1.0  # keep directions with s_i > snr * sigma
    rcond: float = 1e-10  # numerical rank floor, relative to s_max
    geodesic: float = 0.75  # geodesic acceleration (Transtrum & Sethna 2012) if > 0: max 2|a|/|v|
    damping: float = 0.0  # initial lambda relative to s_max^2 (Nielsen's tau); 0: Gauss-Newton first
    chord: float = 0.0  # steps of at most this |dz| keep the Jacobian (module docstring); 0: never
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None


@dataclass
class SolverResult:
    x: np.ndarray
    cost: float
    iterations: int
    status: str  # 'converged' | 'max_iter' | 'stalled'
    message: str
    residual: np.ndarray = field(repr=False)  # fun at x
    jacobian: np.ndarray = field(repr=False)  # its Jacobian at x
    history: list[float] = field(default_factory=list)
    truncated: int = 0  # directions truncated in the last iteration


def rms(r: np.ndarray, dof: int | None = None) -> float:
    n = r.size if dof is None else max(dof, 1)
    return float(np.sqrt(np.dot(r, r) / n)) if r.size else 0.0


def levenberg_marquardt(
    fun: ResidualFn,
    x0: np.ndarray,
    scale: np.ndarray,
    options: SolverOptions | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> SolverResult:
    """Minimise 1/2 |fun(x)|^2 from x0; `scale` are the parameters' error magnitudes.

    With a known noise level, directions below snr * noise are truncated
    throughout.  With an unknown one, a first solve truncates only at the
    numerical floor; the noise is then estimated from its residual and, if some
    direction lies below it, the problem is solved again from x0 with that
    level fixed (a residual-based threshold while far from the solution would
    freeze the very directions that must move).  A first solve that stops
    short of its minimum (a long valley, or wandering along directions the
    noise hides) is continued once; if the truncated fit then closes well
    below the level it was truncated at, that level was the first solve's
    misfit, not noise: it is lowered to the new residual and the fit resumed.
    """
    opt = options or SolverOptions()
    if opt.noise is not None:
        return _solve(fun, x0, scale, opt, progress)
    memo: dict = {}
    first = _solve(fun, x0, scale, replace(opt, noise=0.0), progress, memo)
    if first.status == "max_iter":  # a long valley: once more from where it stopped (not after a crawl)
        first = _after(first, _solve(fun, first.x, scale, replace(opt, noise=0.0), progress, memo))
    r = first.residual
    # the last iteration's factorisation when it was of this Jacobian (a solve that ends on
    # "no step lowers the cost"), else one more QR pass
    at_x = "x" in memo and np.array_equal(memo["x"], first.x)
    S = memo["S"] if at_x else scaled_svd(first.jacobian, r, scale)[0]
    sigma = rms(r, r.size - int(np.sum(S > opt.rcond * S[0])))
    if not np.any(S <= opt.snr * sigma):
        return first
    log.info("re-solving with SVD truncation at the estimated noise %.3e", sigma)
    second = _solve(fun, x0, scale, replace(opt, noise=sigma), progress)
    for _ in range(4):  # a first solve stopped short of its minimum over-estimates the noise: lower it
        s2 = rms(second.residual, second.residual.size - x0.size)
        if s2 >= 0.5 * sigma:
            break
        log.info("the truncated fit closes to %.3e, below the noise estimated before (%.3e): re-solving", s2, sigma)
        sigma = s2
        second = _after(second, _solve(fun, second.x, scale, replace(opt, noise=sigma), progress))
    second = _after(first, second)
    # Truncating directions that lie below the noise raises the cost by about their number times
    # sigma^2, a small fraction of it.  Far more means the "noise" was model misfit (a stage that
    # holds most parameters fixed): keep the untruncated solution then.
    if second.cost > 4.0 * first.cost:  # (info: a stage's or restart's inner decision; the verdict judges the end)
        log.info(
            "noise-level truncation raised the cost %.3g-fold (model misfit, not noise): "
            "keeping the untruncated solution",
            second.cost / max(first.cost, 1e-300),
        )
        first.iterations = second.iterations
        first.history = second.history
        return first
    return second


def _after(before: SolverResult, after: SolverResult) -> SolverResult:
    """`after` (a solve that followed `before`) counting `before`'s iterations and history too."""
    after.iterations += before.iterations
    after.history = before.history + after.history
    return after


def _solve(
    fun: ResidualFn,
    x0: np.ndarray,
    scale: np.ndarray,
    opt: SolverOptions,
    progress: Callable[[int, float], None] | None,
    memo: dict | None = None,
) -> SolverResult:
    """One Levenberg-Marquardt run at a fixed truncation level; `memo` gets the last (J, S)."""
    memo = {} if memo is None else memo
    assert opt.noise is not None, "a solve at a fixed truncation level"  # levenberg_marquardt sets it
    sigma = opt.noise
    bounded = opt.lower is not None or opt.upper is not None
    x = np.array(x0, dtype=float)
    r, J = _with_jacobian(fun, x)
    cost = 0.5 * float(r @ r)
    history = [cost]
    if progress:
        progress(0, cost)
    lam, nu = 0.0, 2.0
    lowest, still = cost, 0  # the lowest cost reached, and the accepted steps since it last fell by ftol
    crawl = 0  # cut undamped steps since the cost last fell by a useful share (`CRAWL_ITERATIONS`)
    retract = getattr(fun, "retract", None) if not bounded else None
    status, message, truncated = "max_iter", f"no convergence in {opt.max_iter} iterations", 0
    it = 0
    factorised = getattr(fun, "factorised", None)  # a function that keeps its factorisation shares it
    chorded = False  # the last accepted step kept the Jacobian: J is J_0's, r is x's (module docstring)
    last_chord = 0.0  # that step's |dz|
    S, Vt = np.zeros(0), np.zeros((0, x.size))  # the factorisation of J (formed at the first iteration)
    keep_jacobian = getattr(fun, "keep_jacobian", None)
    for it in range(1, opt.max_iter + 1):
        if chorded:
            g = chord_projection(J, r, scale, S, Vt)
        else:
            S, Vt, g = factorised(x, scale) if factorised is not None else scaled_svd(J, r, scale)
        memo["x"], memo["S"] = x.copy(), S
        if sigma == 0.0 and it > 1 and _determined_converged(S, g, r, opt):
            status, message = "converged", "what the noise does not hide has converged; the rest lies below it"
            break
        Js = J * scale if bounded else None  # the bounded step works on the rows themselves
        floor = opt.rcond * (S[0] if S.size else 0.0)
        keep = S > max(floor, opt.snr * sigma)
        if not keep.any():  # everything below the noise: take the numerically safe part
            keep = S > floor
        truncated = int(S.size - keep.sum())
        accepted = False
        if lam == 0.0 and opt.damping > 0.0 and S.size:
            lam = opt.damping * float(S[0] ** 2)
        gn = np.where(keep, g, 0.0) / np.where(keep, S, 1.0)  # minus the undamped step, along the rows of Vt
        chord = False
        while True:
            dz = _step(S, Vt, g, keep, lam, x, scale, opt, Js, r)
            predicted = _model_decrease(S, Vt, g, dz)
            if predicted <= opt.ftol * cost:
                break  # even if the trial succeeded, its decrease would stop the iteration: at the minimum
            chord = _chord(opt, bounded, dz, lam, S[keep], last_chord if chorded else None)
            if opt.geodesic and not bounded and not chord:
                dz = _geodesic(fun, x, r, J, scale, S, Vt, keep, lam, dz, opt.geodesic)
            x_new = x + dz * scale
            r_new, _ = fun(x_new, None if chord else False)  # a chord's trial: no Jacobian (a probe)
            cost_new = 0.5 * float(r_new @ r_new)
            rho = (cost - cost_new) / predicted if np.isfinite(cost_new) else -np.inf
            if rho > 1e-4:
                accepted = True
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                break
            lam = lam * nu if lam > 0 else 1e-6 * float(S[0] ** 2) if S.size else 1.0
            nu *= 2.0
            if nu > 2.0**40:
                break
        found = None if accepted or bounded else _line_search(fun, x, r, g, keep, -(Vt.T @ gn), scale)  # a minimum?
        alpha = 1.0
        if found is not None:
            (dz, x_new, cost_new, alpha), accepted, lam, nu = found, True, 0.0, 2.0
        if not accepted:
            status, message = "converged", "no step lowers the cost: at a minimum"
            break
        if cost - cost_new >= CRAWL_PROGRESS * cost:
            crawl = 0
        elif found is not None and alpha <= CRAWL_ALPHA:
            crawl += 1
        step_norm = float(np.linalg.norm(dz))
        decrease = cost - cost_new
        x = x_new
        if retract is not None:
            x = retract(x)  # the parameters' charts follow the solution (`residual.ResidualFunction.retract`)
        chorded = chord and found is None and np.array_equal(x, x_new)  # (a chart that moved re-linearises)
        if chorded:
            last_chord = step_norm
            r = r_new
            if keep_jacobian is not None:
                keep_jacobian(x, r)
        else:
            r, J = _with_jacobian(fun, x)
        cost = 0.5 * float(r @ r)
        history.append(cost)
        if progress:
            progress(it, cost)
        log.debug("LM it %d cost %.6e step %.3e truncated %d", it, cost, step_norm, truncated)
        if cost <= 1e-28 * r.size:  # RMS residual at the level of round-off (1e-14)
            status, message = "converged", "residual is zero to round-off"
            break
        # a step made short by the damping is no convergence while the undamped one is long: both below xtol
        if decrease <= opt.ftol * max(cost + decrease, 1e-300) or max(step_norm, float(np.linalg.norm(gn))) < opt.xtol:
            status, message = "converged", "cost and step converged"
            break
        # The trial's cost is taken with the weighting of the step's start, the new point's with its own
        # (`residual.ResidualFunction`): where the two differ by more than the decrease, the trials keep
        # "succeeding" while the cost itself stays (round-off, or weights that move with the step).
        still = 0 if cost < lowest * (1.0 - opt.ftol) else still + 1
        lowest = min(lowest, cost)
        if still >= STALL_ITERATIONS:
            status, message = "converged", f"the cost stopped falling ({still} iterations without a decrease)"
            break
        if crawl >= CRAWL_ITERATIONS:
            status = "stalled"
            message = f"crawling: {crawl} steps cut to {CRAWL_ALPHA:g} of the Gauss-Newton step or less, little gain"
            break
    # a function with charts (`retract`) settles them at the end (`residual.ResidualFunction.settle`)
    settled = getattr(fun, "settle")(x) if retract is not None else None
    if settled is not None:  # back in the problem's own charts
        x = settled
        r, J = _with_jacobian(fun, x)
    return SolverResult(
        x=x,
        cost=cost,
        iterations=it,
        status=status,
        message=message,
        residual=r,
        jacobian=J,
        history=history,
        truncated=truncated,
    )


def _with_jacobian(fun: ResidualFn, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`fun`'s residual and Jacobian at `x` (a Jacobian is asked for, so one is given)."""
    r, J = fun(x, True)
    if J is None:
        raise ValueError("the residual function returned no Jacobian where one was asked for")
    return r, J


#: a floor-truncated solve stops where every direction above the residual's own level is within this many of
#: its standard errors of the linear model's minimum (`_determined_converged`)
DETERMINED = 0.01


def _determined_converged(S: np.ndarray, g: np.ndarray, r: np.ndarray, opt: SolverOptions) -> bool:
    """Whether a solve at the numerical floor (no noise level known) has converged in every direction the
    residual's own level does not hide, while some lie below it.

    With sigma the residual's RMS over its degrees of freedom, direction i of J D = U S V^T (eq. 4.17) is
    above the noise when s_i > snr sigma; the undamped step along it, g_i / s_i, is |g_i| / sigma of its
    standard error sigma / s_i.  Where those are all below `DETERMINED`, what the solve still gains comes from
    directions below the noise: a crawl of hundreds of iterations along a valley the data barely see (a
    contact point on a joint axis, the errors-in-variables weighting moving with the parameters), each
    lowering the cost by 1e-7 of itself, which the solve at the noise level truncates anyway
    (`levenberg_marquardt`)."""
    if not S.size:
        return False
    dof = r.size - int(np.sum(S > opt.rcond * S[0]))
    sigma = rms(r, dof)
    above = S > opt.snr * sigma
    if not (sigma > 0.0 and above.any()) or above.all():
        return False
    return bool(np.all(np.abs(g[above]) <= DETERMINED * sigma))


#: a chord step's damping at most this share of the smallest kept squared singular value (an undamped step)
CHORD_DAMPING = 1e-3
#: a chord step after a chord step at most this share of its length (the chord iteration contracts)
CHORD_CONTRACTION = 0.1


def _chord(
    opt: SolverOptions, bounded: bool, dz: np.ndarray, lam: float, S_kept: np.ndarray, last: float | None
) -> bool:
    """Whether the trial step `dz` keeps the Jacobian (`SolverOptions.chord`, module docstring): no longer than
    `opt.chord`, undamped (`CHORD_DAMPING`), and after a chord step (`last`, its length) a `CHORD_CONTRACTION`
    of it.  A damped step is one the linear model is not trusted for, and a chord that does not contract is
    crawling along a valley whose Jacobian turns (the minimum it would reach is the stale Jacobian's)."""
    if opt.chord <= 0.0 or bounded or not S_kept.size or lam > CHORD_DAMPING * float(S_kept[-1]) ** 2:
        return False
    n = float(np.linalg.norm(dz))
    return n <= opt.chord and (last is None or n <= CHORD_CONTRACTION * last)


def _geodesic(fun, x, r, J, scale, S, Vt, keep, lam, v, alpha, h: float = 0.1):
    """v + a/2 with the geodesic acceleration a = -(J^T J + lam)^-1 J^T r'' (Transtrum & Sethna 2012).

    r'' is the second directional derivative of r along v, by a finite
    difference: r'' ~ 2/h ((r(x + h v) - r(x))/h - J v).  The correction is
    kept only while 2 |a| <= alpha |v| (the step's curvature is small).
    """
    r_h, _ = fun(x + h * v * scale, None)
    Jv = J @ (scale * v)
    rpp = (2.0 / h) * ((r_h - r) / h - Jv)
    c = Vt @ (scale * (J.T @ rpp))  # V^T (J D)^T r'' = S U^T r''
    a = -(Vt.T @ np.where(keep, c / (S**2 + lam), 0.0))
    if not np.all(np.isfinite(a)) or 2.0 * np.linalg.norm(a) > alpha * np.linalg.norm(v):
        return v
    return v + 0.5 * a


#: accepted steps in a row that leave the cost where it was (no relative decrease of ftol below the lowest
#: reached) after which the solve stops at a minimum: the cost's fall, not the trials', decides (`_solve`).
#: A larger fall over a window would stop slow but real progress (the Rosenbrock valleys of
#: tests/test_solver_linalg.py, b down to 1e-4, crawl by 1e-6 of their cost per step towards zero).
STALL_ITERATIONS = 8

STOPPED_SHORT = 0.5  # share of the cost the linear model removes above which a stop is no minimum (`_line_search`)

#: A solve that took `CRAWL_ITERATIONS` steps by `_line_search` at `CRAWL_ALPHA` of the undamped step or less
#: while no step lowered the cost by `CRAWL_PROGRESS` of it is crawling, and stops ('stalled'): no damped step
#: lowered the cost there, so the gradient the Jacobian gives is not the cost's (a weighting that moves with
#: the parameters as much as the closure, a hair above zero on exact data); its cut steps gain a percent of
#: the cost each and the damped steps between them next to nothing, for as long as the iteration cap allows.
#: Its caller takes another route (`calibration.solve.solve_staged`: the plain loop-closure residual).  A
#: long valley the line search serves takes steps of a useful fraction, or lowers the cost between them.
CRAWL_ALPHA = 1.0 / 64.0
CRAWL_ITERATIONS = 8
CRAWL_PROGRESS = 0.1


def reducible_share(r: np.ndarray, g: np.ndarray, keep: np.ndarray) -> float:
    """|U_k^T r|^2 / |r|^2 (g = U^T r, `scaled_svd`; k the kept directions): the share of the cost the
    undamped Gauss-Newton step removes in the linear model.  ~0 at a minimum, where r is orthogonal to the
    columns of J (at a round-off residual anything: it is no least-squares residual)."""
    rr = float(r @ r)
    gk = g[keep]
    return float(gk @ gk) / rr if rr > 0 else 0.0


def _line_search(fun, x, r, g, keep, step, scale, halvings: int = 12):
    """The undamped Gauss-Newton `step`, halved until the cost falls (Armijo), where no damped step did.

    Only when it would remove more than `STOPPED_SHORT` of the cost (`reducible_share`): then the stop is
    no minimum.  The trials were rejected along a direction the closure barely sees (the long, curved
    valleys of a weak direction) and the damped steps were too short to move along it; the verdict
    checks the same share at the solution (`verdict._minimum`).  Returns (dz, x_new, cost_new, the fraction
    of `step` taken) or None.
    """
    share = reducible_share(r, g, keep)
    if share <= STOPPED_SHORT:
        return None
    cost = 0.5 * float(r @ r)
    model = 2.0 * share * cost  # |U_k^T r|^2
    alpha = 1.0
    for _ in range(halvings):
        x_new = x + alpha * step * scale
        r_new, _ = fun(x_new, False)
        cost_new = 0.5 * float(r_new @ r_new)
        if np.isfinite(cost_new) and cost - cost_new >= 1e-4 * 0.5 * (2.0 * alpha - alpha**2) * model:
            log.info("no damped step lowered the cost %.3e; the undamped step x %g did (%.3e)", cost, alpha, cost_new)
            return alpha * step, x_new, cost_new, alpha
        alpha *= 0.5
    return None


def chord_projection(J: np.ndarray, r: np.ndarray, scale: np.ndarray, S: np.ndarray, Vt: np.ndarray) -> np.ndarray:
    """g = U^T r for another residual `r` of the Jacobian J whose scaled factorisation J D = U S V^T is
    (S, Vt) (`scaled_svd`), without U: (J D)^T r = V S U^T r, so U^T r = S^-1 V^T D J^T r (zero where S is)."""
    return np.where(S > 0.0, Vt @ (scale * (J.T @ r)) / np.where(S > 0.0, S, 1.0), 0.0)


def scaled_svd(J: np.ndarray, r: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S, Vt and g = U^T r of the column-scaled J D = U S V^T (D = diag(scale)), without forming U.

    The cost is one pass over the rows (QR of [J D | r], formed a chunk at a
    time: no copy of J) and an SVD of the (n+1)-square triangle.  Also for the
    analysis at a solution (standard errors V S^-2 V^T, weak directions), which
    needs no U: `np.linalg.svd` of the tall J D would form U (rows x n) and run
    threaded LAPACK on it.
    """
    n = J.shape[1]
    if J.shape[0] > 2 * n:  # R = [R_J | Q^T r] with R_J = U_R S V^T: U^T r = U_R^T (Q^T r)
        Ra = scaled_r_factor(J, r, scale)
        U_R, S, Vt = np.linalg.svd(Ra[:n, :n])
        return S, Vt, U_R.T @ Ra[:n, n]
    U, S, Vt = np.linalg.svd(J * scale, full_matrices=False)
    return S, Vt, U.T @ r


def _model_decrease(S: np.ndarray, Vt: np.ndarray, g: np.ndarray, dz: np.ndarray) -> float:
    """Decrease of the linear model's cost, 1/2 |r|^2 - 1/2 |r + Js dz|^2, for Js = U S V^T, g = U^T r.

    With w = S V^T dz (Js dz = U w): -g.w - |w|^2 / 2.  Below the cost's
    round-off the trial steps are coin flips; below ftol * cost a successful
    one would end the iteration anyway.
    """
    w = S * (Vt @ dz)
    return -float(g @ w) - 0.5 * float(w @ w)


def _step(S, Vt, g, keep, lam, x, scale, opt: SolverOptions, Js, r) -> np.ndarray:
    """The truncated, damped Gauss-Newton step in scaled coordinates."""
    f = np.where(keep, S / (S**2 + lam), 0.0)
    dz = -(Vt.T @ (f * g))
    if opt.lower is None and opt.upper is None:
        return dz
    return _bounded_step(Js, r, Vt[keep].T, lam, x, scale, opt, dz)


def _bounded_step(Js, r, Vk, lam, x, scale, opt: SolverOptions, dz_free) -> np.ndarray:
    """min |Js Vk w + r|^2 + lam |w|^2  s.t.  lower <= x + scale * Vk w <= upper  (OSQP)."""
    from qpsolvers import solve_ls

    lower = np.full(x.size, -np.inf) if opt.lower is None else opt.lower
    upper = np.full(x.size, np.inf) if opt.upper is None else opt.upper
    x_free = x + scale * dz_free
    if np.all(x_free >= lower) and np.all(x_free <= upper):
        return dz_free
    A = scale[:, None] * Vk
    rows = np.isfinite(upper)
    rows_l = np.isfinite(lower)
    G = np.vstack([A[rows], -A[rows_l]])
    h = np.concatenate([upper[rows] - x[rows], x[rows_l] - lower[rows_l]])
    R = Js @ Vk
    if lam > 0:
        R = np.vstack([R, np.sqrt(lam) * np.eye(Vk.shape[1])])
        s = np.concatenate([-r, np.zeros(Vk.shape[1])])
    else:
        s = -r
    w = solve_ls(
        R, s, G=G, h=np.maximum(h, 0.0), solver="osqp", eps_abs=1e-10, eps_rel=1e-10, max_iter=20000, polish=True
    )
    if w is None:
        log.warning("bounded step: OSQP found no solution; clipping the free step")
        return (np.clip(x_free, lower, upper) - x) / scale
    return Vk @ w
