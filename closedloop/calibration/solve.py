"""How a reduced calibration problem is solved: which stages from which starts, and the checks at the solution.

The residual functions and one solve of each (a stage) are `closedloop.estimate.residual`'s; this module
decides the order.  `solve_staged` runs the errors-in-variables fit (`residual.weighted_stage`) and,
where the weighting misleads (a stall far above any plausible noise, a
weighting that turns singular on the way), the plain loop-closure fit
(`residual.plain_stage`, eq. 3.8) first; `solve_with_restarts` tries other starts
when the fit stalls; `recheck_at_solution` recomputes the structural reduction
and the gauge at the solution and re-solves where they differ (no
decision is kept that does not hold at the solution); `length_guard` solves again
without a known length that does not set the size.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from closedloop.analysis.identifiability import (
    Structure,
    analyse_structure,
    closure_jacobian,
    collapsed,
    structure_holds,
)
from closedloop.calibration.verdict import SIZE_NOT_MEASURED, Verdict
from closedloop.errors import ParameterError
from closedloop.estimate.lm import SolverOptions, scaled_svd
from closedloop.estimate.residual import (
    Fit,
    ResidualFunction,
    StageResult,
    below_noise_reset,
    plain_stage,
    random_start,
    unweighted_closure,
    weighted_stage,
)
from closedloop.estimate.variance import measurement_row_weights, task_blocks, variance_components
from closedloop.problem.lengths import LengthLoop
from closedloop.problem.problem import CalibrationProblem
from closedloop.progress import ProgressReporter
from closedloop.records import FAILED, SUSPECT, CalibrationOptions, CalibrationResult, VerdictRules

log = logging.getLogger(__name__)


def _solver_options(opt: CalibrationOptions, problem: CalibrationProblem, est: list[int], known: bool) -> SolverOptions:
    lower = upper = None
    if opt.bounds:
        lower, upper = np.full(len(est), -np.inf), np.full(len(est), np.inf)
        for n, (lo, hi) in opt.bounds.items():
            if n not in problem.index:
                raise ParameterError(f"bound for unknown parameter '{n}'")
            k = problem.index[n]
            if k in est:
                lower[est.index(k)], upper[est.index(k)] = lo, hi
    return SolverOptions(
        max_iter=opt.max_iter,
        noise=(1.0 if known and opt.weighting == "noise" else None),
        snr=opt.snr,
        lower=lower,
        upper=upper,
    )


def solve_staged(
    problem: CalibrationProblem,
    x0: np.ndarray,
    start: np.ndarray,
    est: list[int],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    known: bool,
    progress: ProgressReporter | None = None,
    plain_start: bool = False,
) -> Fit:
    """The weighted fit from `start`; staged through the plain residual where the weighting misleads.

    The errors-in-variables fit is tried first (it is the estimator; on a
    single self-motion, where many robots close the same curve, the plain
    residual's long steps can reach a degenerate one).  When it stalls far
    above any plausible noise, leaves directions undetermined (a spurious
    minimum reports many), or its weighting turns singular on the way
    (more residual directions discarded than at the start), the plain
    loop-closure fit is solved from `start` and the weighted fit restarted
    from it (`residual.weighted_stage` keeps the plain solution if the weighting
    would hide a residual there).  `plain_start` goes through the plain stage
    directly, from a solution (the re-checks at the solution): the plain fit truncates at the numerical floor
    only, and may move a long way along a direction the weighted fit truncates there (a combination the
    data barely see: two joint origins along one line) for a cost within the noise; the weighted fit would
    hold that move, so it starts from the plain solution with those directions set back to `start`'s
    (`residual.below_noise_reset`).
    """
    scale = np.array([p.prior for p in problem.params])
    sopt = _solver_options(opt, problem, est, known)
    prog = (lambda it, c: progress("solving", it, None, f"cost {c:.3e}")) if progress else None
    plausible = opt.rules.plausible_joint_noise
    warnings: list[str] = []
    base = x0.copy()
    base[est] = start[est]
    xs, iters = start[est], 0
    b = None
    if opt.weighting == "noise" and task_blocks(problem):
        # the loops' task-space noise (closedloop.estimate.variance) is first read off the plain fit's residual: a
        # weighted fit with the joint noise alone (given far too small) can run off before it is estimated
        a = plain_stage(problem, base, xs, est, scale, sopt, prog)
        iters += a.solution.iterations
        evs = problem.evaluate(a.fun.full(a.solution.x), True, columns=[])
        variance_components(problem, evs, sigma_q.copy(), len(est), task_blocks(problem), known)
    if not plain_start or opt.weighting != "noise":
        b = weighted_stage(problem, base, xs, est, scale, sigma_q, opt.weighting, sopt, prog)
        iters += b.solution.iterations
    if b is None or (opt.weighting == "noise" and (b.note or b.solution.truncated or _misled(problem, b, plausible))):
        a = plain_stage(problem, base, xs, est, scale, sopt, prog)
        xa = a.solution.x
        if b is None and opt.weighting == "noise":  # from a solution: no move along what it holds (docstring)
            reset = below_noise_reset(problem, base, xs, xa, xs, est, scale, sigma_q, opt.snr)
            xa = xa if reset is None else reset
        b2 = weighted_stage(problem, base, xa, est, scale, sigma_q, opt.weighting, sopt, prog)
        iters += a.solution.iterations + b2.solution.iterations
        b = b2 if b is None else _better(problem, [b, b2], start, est, scale, plausible)
    if opt.weighting == "none":  # known measurements at their sigma against the closures' own level
        b, n = _unweighted_with_measurements(problem, base, est, scale, sigma_q, sopt, prog, b)
        iters += n
    if opt.weighting == "noise" and b.fun.weighting == "noise":
        b, more = _polished(problem, base, b, est, scale, sigma_q, sopt, prog, plausible)
        iters += more
    if b.note:
        warnings.append(b.note)
    xs = b.solution.x
    tasks = task_blocks(problem) if opt.weighting == "noise" and b.fun.weighting == "noise" else []
    joint_beside_measurement = (
        not known
        and opt.weighting == "noise"
        and b.fun.weighting == "noise"
        and any(nz.measurement_cov is not None for nz in problem.noise)
    ) or bool(tasks)
    if joint_beside_measurement:
        # The ratio of joint to measurement noise sets the weights: estimate the joint level and the
        # loops' task-space noise (closedloop.estimate.variance) at the fit, re-solve with them, until they settle.
        pattern, s_prev, joint_given = sigma_q.copy(), None, known
        start_e = start[est]
        for _ in range(4):
            evs = problem.evaluate(b.fun.full(b.solution.x), True, columns=[])
            s, moved = variance_components(problem, evs, pattern, len(est), tasks, joint_given)
            if s_prev is not None and abs(s - s_prev) <= 0.05 * max(s, s_prev) and not moved:
                break
            sigma_q, known, s_prev = np.sqrt(s) * pattern, True, s
            b = weighted_stage(problem, base, start_e, est, scale, sigma_q, "noise", replace(sopt, noise=1.0), prog)
            iters += b.solution.iterations
    return Fit(b.fun.full(b.solution.x), b, est, sigma_q, known, iters, warnings)


EXACT_LEVEL = 1e-3  # a closure level (`_closure_level`) below this is no noise: exact data, or a stall


def _polished(
    problem: CalibrationProblem,
    base: np.ndarray,
    b: StageResult,
    est: list[int],
    scale: np.ndarray,
    sigma_q: np.ndarray,
    sopt: SolverOptions,
    prog,
    plausible: float,
) -> tuple[StageResult, int]:
    """The weighted fit `b`, or, where it stalled a hair above zero, the plain fit from it and the weighted from that.

    A weighted fit that stops with nothing truncated at a closure a thousandth
    of any plausible noise (`EXACT_LEVEL`) whose residual is smooth along the
    log (`_smooth`) has stalled in a valley: its step neglects the weighting's
    own derivative, W_i^-1 = (J_theta,i Sigma J_theta,i^T)^-1 moving with the
    parameters, which there is as large as the closure's.  The plain
    residual (eq. 3.8) has no such term; from the weighted point its
    Gauss-Newton steps finish the descent (the door's start 27: closure 2.7e-9
    to 2e-16 in two iterations).  The better closing of the two is kept.
    Returns the stage and the iterations spent.
    """
    if (
        b.solution.truncated
        or b.note
        or _closure_level(problem, b, plausible) >= EXACT_LEVEL
        or not _smooth(problem, b, plausible)
    ):
        return b, 0
    a = plain_stage(problem, base, b.solution.x, est, scale, sopt, prog)
    b2 = weighted_stage(problem, base, a.solution.x, est, scale, sigma_q, "noise", sopt, prog)
    spent = a.solution.iterations + b2.solution.iterations
    if unweighted_closure(problem, b2.fun.full(b2.solution.x)) < unweighted_closure(problem, b.fun.full(b.solution.x)):
        log.info("the weighted fit stalled a hair above zero; the plain fit from it closed further")
        return b2, spent
    return b, spent


def _misled(problem: CalibrationProblem, stage: StageResult, plausible: float) -> bool:
    """The weighted fit stalled far above the noise, or its weighting discards more than at the start."""
    if stage.solution.status != "converged" or _closure_level(problem, stage, plausible) > 1.0:
        return True
    return stage.fun.deficit > stage.deficit_start


def _closure_level(problem: CalibrationProblem, stage: StageResult, plausible: float) -> float:
    """The typical configuration's closure in units of what `plausible` joint noise (rad: the verdict's
    `VerdictRules.plausible_joint_noise`, 2 mrad by default: no encoder reads worse; a closure it cannot explain
    is a stalled fit), plus the loops' own measurement noise (a camera's pixels), explains: the median, so that a
    few outliers do not count.  Infinite for a degenerate robot whose loops do not move with its joints
    (`collapsed`): it closes nothing."""
    if stage.closure_level is not None:
        return stage.closure_level
    if not np.isfinite(stage.solution.cost):
        return np.inf
    if collapsed(problem, stage.fun.full(stage.solution.x)):
        stage.closure_level = np.inf
        return stage.closure_level
    fun = ResidualFunction(
        problem, stage.fun.full(stage.solution.x), [], np.full(len(problem.joints), plausible), "noise"
    )
    per_config = np.concatenate(
        [np.linalg.norm(b, axis=1) / np.sqrt(b.shape[1]) for b in fun.blocks(np.zeros(0), symmetric=False) if b.size]
    )
    stage.closure_level = float(np.median(per_config)) if per_config.size else 0.0
    return stage.closure_level


def _stalled(problem: CalibrationProblem, fit: Fit, plausible: float) -> bool:
    """The fit stopped far above any plausible noise (`_closure_level` above 1), or at a residual that is
    no noise while directions below it were left undetermined (`_systematic`, truncated)."""
    return _closure_level(problem, fit.stage, plausible) > 1.0 or (
        fit.stage.solution.truncated > 0 and _systematic(problem, fit, plausible)
    )


def _systematic(problem: CalibrationProblem, fit: Fit, plausible: float) -> bool:
    """A residual that is no noise: smooth along the log.

    The lag-1 autocorrelation of each block's whitened residual along its rows,
    pooled, rho = sum r_i . r_i+1 / sum |r_i|^2, is ~N(0, 1/N) for noise and
    near 1 for a smooth misfit when the log follows a motion (a door's swing):
    on exact data a local minimum a hair above zero, which leaves the weak
    directions truncated 'below the noise'.  Round-off (closure level below
    1e-9) does not count.  A log in random order shows no misfit this way.
    """
    return _smooth(problem, fit.stage, plausible)


def _smooth(problem: CalibrationProblem, stage: StageResult, plausible: float) -> bool:
    """`_systematic` for a stage: its whitened residual's pooled lag-1 autocorrelation is far above noise's."""
    if _closure_level(problem, stage, plausible) < 1e-9:
        return False
    num = den = 0.0
    n = 0
    for r in stage.fun.blocks(stage.solution.x):
        num += float(np.sum(r[1:] * r[:-1]))
        den += float(np.sum(r * r))
        n += r.shape[0]
    return den > 0.0 and n >= 8 and num / den > max(0.5, 4.0 / np.sqrt(n))


def _better(
    problem: CalibrationProblem,
    stages: list[StageResult],
    start: np.ndarray,
    est: list[int],
    scale: np.ndarray,
    plausible: float,
) -> StageResult:
    """Of the fits that close as well as the best, the nearest the start (in prior units): a degenerate
    robot (a forearm of zero length) may close a single self-motion as well as the real one.  A fit whose
    solver stopped short of a minimum (its iteration cap, a crawl) counts only where none reached one."""
    levels = [_closure_level(problem, st, plausible) for st in stages]
    # as good as the best: within 10x of its closure, or both below 1/1000 of a plausible noise
    good = [st for st, lv in zip(stages, levels) if lv <= max(10.0 * min(levels), 1e-3)]
    # a solve that stopped short of its minimum is no rival to one that reached its own
    good = [st for st in good if st.solution.status == "converged"] or good
    return min(good, key=lambda st: float(np.linalg.norm((st.solution.x - start[est]) / scale[est])))


def solve_with_restarts(
    problem: CalibrationProblem,
    x0: np.ndarray,
    est: list[int],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    known: bool,
    rng: np.random.Generator,
    progress: ProgressReporter | None = None,
    first: Fit | None = None,
    weak: list[int] | None = None,
) -> Fit:
    """`solve_staged` from x0 (or `first`); if it stalls far above the noise, from other starts.

    Starts: the loop parameters and offsets first with the geometry held, then
    all; then x0 moved at random by 1x and 3x the parameters' priors.  Among
    the fits that close within a plausible noise, the nearest to the start
    (in prior units) is kept: on a single self-motion degenerate robots (a
    forearm of zero length) close the loop as well as the real one.  If none
    does, the one with the lowest unweighted closure.  When no restart leaves
    the minimum, it is left along its valley (`_along_valley`), with the
    `weak` parameters (`Structure.nearly_redundant`) freed: a reduction read
    off the start may hold back a parameter the solution needs.  A fit that
    stopped within a plausible noise at a residual that is no noise
    (`_systematic`: a spurious minimum a hair above zero, the floor of a long
    valley of a single self-motion, the door) has its valley searched first:
    restarts reach the same floor at the cost of a full fit each, where the
    search along it takes plain fits.
    """
    fit = first if first is not None else solve_staged(problem, x0, x0, est, opt, sigma_q, known, progress)
    plausible = opt.rules.plausible_joint_noise
    if opt.restarts <= 0 or not _stalled(problem, fit, plausible):
        return fit
    scale = np.array([p.prior for p in problem.params])
    fits = [fit]
    starts = []
    log.info(
        "the fit from the given start stalled at closure level %.3g", _closure_level(problem, fit.stage, plausible)
    )
    valley = _floor(problem, fit, plausible)  # searched along first
    found = valley and _along_valley(problem, x0, fit, est, opt, sigma_q, known, progress, fits, weak or [])
    if not found:
        sub = [k for k in est if problem.params[k].kind in ("loop", "offset")]
        if sub and len(sub) < len(est):
            starts.append(solve_staged(problem, x0, x0, sub, opt, sigma_q, known, plain_start=True).x)
        for size in (1.0, 3.0, 1.0, 3.0)[: max(opt.restarts - len(starts), 0)]:
            starts.append(random_start(x0, est, scale, rng, size))
    hopeless = False
    for k, st in enumerate(starts[: opt.restarts]):
        log.info("restart %d: the fit stalled far above the noise or where its residual is not noise", k + 1)
        fits.append(solve_staged(problem, x0, st, est, opt, sigma_q, known, progress))
        log.info("restart %d: closure level %.3g", k + 1, _closure_level(problem, fits[-1].stage, plausible))
        if not _stalled(problem, fits[-1], plausible):
            break
        hopeless = _hopeless(problem, fits, opt.rules)
        if hopeless:
            break
    good = [f for f in fits if _good(problem, f, plausible)]
    if not good and not hopeless and not valley:  # no restart left the valley: along it, the nearly redundant freed
        good = _along_valley(problem, x0, fit, est, opt, sigma_q, known, progress, fits, weak or [])
    far = _closure_level(problem, fit.stage, plausible) > 1.0
    if good:
        best = min(good, key=lambda f: float(np.linalg.norm((f.x - x0)[est] / scale[est])))
    elif far:
        best = min(fits, key=lambda f: unweighted_closure(problem, f.x))
    else:  # a systematic residual that no restart removes: a model misfit, not a minimum to leave
        log.info("no restart removed the systematic residual: keeping the fit from the given start")
        return fit
    why = "far above the noise" if far else "at a residual that is no noise (a local minimum)"
    best.warnings.append(
        f"the fit stalled {why} from the given start; "
        f"{'a restart reached' if good else 'no restart reached'} a closure within a plausible noise"
    )
    if hopeless:
        best.hopeless = True
        level = min(_closure_level(problem, f.stage, plausible) for f in fits)
        best.warnings.append(
            f"restarts stopped after {len(fits) - 1}: every start stalls alike, at a closure {level:.3g} times what "
            f"{plausible * 1e3:g} mrad of joint noise explains: the loops as given cannot close on "
            "this data (check each loop's type and frames against the rig)"
        )
    return best


HOPELESS = 5.0  # times the joint noise the verdict fails (`VerdictRules.failed_joint_noise`): a hopeless closure


def _hopeless(problem: CalibrationProblem, fits: list[Fit], rules: VerdictRules) -> bool:
    """Another start will not close the loops: every fit so far (the given start's and at least one restart)
    stalled above what `HOPELESS` times the joint noise the verdict fails explains (closure level 25 with the
    default rules: 50 mrad), none at under half the given start's closure level.  A rough start stalls
    in a basin a restart leaves (its closure drops by orders); a loop that does not describe the data (a weld
    on a ball joint) stalls at the same gross level from every start."""
    plausible = rules.plausible_joint_noise
    levels = [_closure_level(problem, f.stage, plausible) for f in fits]
    hopeless = HOPELESS * rules.failed_joint_noise / plausible
    return len(levels) >= 2 and min(levels) > max(hopeless, 0.5 * levels[0])


VALLEY_DIRECTIONS = 4  # weakest directions probed from a stalled fit (`valley_starts`), both ways


def valley_starts(
    problem: CalibrationProblem, fit: Fit, x0: np.ndarray, scale: np.ndarray, k: int = VALLEY_DIRECTIONS
) -> list[np.ndarray]:
    """Starts along the valley a stalled fit lies in: x_f -+ d D v_i for its k weakest directions v_i.

    On the data of a single self-motion (the door) the closure has long, nearly
    flat valleys: a fit can stop at a spurious minimum 1e-7 m above zero, a
    robot far from the true one, while the solution lies further along the
    same valley.  Its directions are the weakest right singular vectors of the
    prior-scaled plain closure Jacobian J D = U S V^T at the fit x_f (the
    smallest s_i above the numerical floor 1e-10 s_1); d = |D^-1 (x_f - x_0)|
    is the distance the fit travelled from the start in prior units: the start's
    own error, so the scale on which its basin can be missed.  The hinge's
    chart is centred on x_f first (`ResidualFunction.retract`) and the starts
    are returned in the problem's charts.  Weakest first, -d before +d.
    """
    est = fit.est
    d = float(np.linalg.norm((fit.x - x0)[est] / scale[est]))
    if not np.isfinite(d) or d == 0.0:
        return []
    fun = ResidualFunction(problem, fit.x, est, np.ones(len(problem.joints)), "none")
    xe = fun.retract(fit.x[est].copy())
    r, J = fun.linearized(xe)
    S, Vt, _ = scaled_svd(J, r, scale[est])
    live = np.flatnonzero(S > 1e-10 * S[0]) if S.size else np.zeros(0, int)
    return [fun.full(xe + sign * d * Vt[i] * scale[est]) for i in live[::-1][:k] for sign in (-1.0, 1.0)]


def _along_valley(
    problem: CalibrationProblem,
    x0: np.ndarray,
    fit: Fit,
    est: list[int],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    known: bool,
    progress: ProgressReporter | None,
    fits: list[Fit],
    weak: list[int],
) -> list[Fit]:
    """The fits from `valley_starts` that close within a plausible noise with a residual that is noise.

    With `weak` parameters (held back as redundant, but not to round-off),
    the start is first solved again with them freed (the solver's floor
    truncation takes any exact null direction among them), and the valley
    searched from that fit.  Each start is first taken by the plain fit
    alone (cheap, and the one that follows the valley); only one that closes
    10x better than the given stalled fit is solved in full (`solve_staged`), and
    the search stops at the first good fit (`_good`).  Appends what it
    solves to `fits`.
    """
    scale = np.array([p.prior for p in problem.params])
    plausible = opt.rules.plausible_joint_noise
    level = unweighted_closure(problem, fit.x)
    if weak:
        est = sorted(set(est) | set(weak))
        fits.append(solve_staged(problem, x0, x0, est, opt, sigma_q, known, progress))
        if _good(problem, fits[-1], plausible):
            return [f for f in fits if _good(problem, f, plausible)]
        fit = fits[-1]
    sopt = _solver_options(opt, problem, est, known)
    for k, st in enumerate(valley_starts(problem, fit, x0, scale)):
        a = plain_stage(problem, st, st[est], est, scale, sopt, None)
        xa = a.fun.full(a.solution.x)
        if not unweighted_closure(problem, xa) < 0.1 * level:
            continue
        log.info(
            "valley start %d: the plain fit closes %.3g, the stalled one %.3g",
            k + 1,
            unweighted_closure(problem, xa),
            level,
        )
        fits.append(solve_staged(problem, x0, xa, est, opt, sigma_q, known, progress))
        if _good(problem, fits[-1], plausible):
            break
    return [f for f in fits if _good(problem, f, plausible)]


def _floor(problem: CalibrationProblem, fit: Fit, plausible: float) -> bool:
    """The fit stopped within a plausible noise (closure level at most 1) at a residual that is no noise:
    smooth along the log (`_systematic`), or below `EXACT_LEVEL` and above round-off (1e-9) with directions
    truncated below it (exact data: no encoder reads a thousand times better than plausible).  A spurious
    minimum a hair above zero, the floor of a long valley (a single self-motion: the door) that other
    starts reach as well and `valley_starts` leaves along it."""
    level = _closure_level(problem, fit.stage, plausible)
    if level > 1.0:
        return False
    exact = fit.stage.solution.truncated > 0 and 1e-9 <= level < EXACT_LEVEL
    return exact or _systematic(problem, fit, plausible)


def _good(problem: CalibrationProblem, fit: Fit, plausible: float) -> bool:
    """The fit closes within a plausible noise (`_closure_level`) and its residual is noise (not `_systematic`)."""
    return _closure_level(problem, fit.stage, plausible) <= 1.0 and not _systematic(problem, fit, plausible)


def recheck_at_solution(
    problem: CalibrationProblem,
    fit: Fit,
    structure: Structure,
    free: list[int],
    x0: np.ndarray,
    opt: CalibrationOptions,
    progress: ProgressReporter | None,
) -> tuple[Fit, Structure, list[str]]:
    """The reduction and gauge recomputed at the solution; re-solved from it where they differ."""
    notes = []
    for _ in range(2):
        R = closure_jacobian(problem, fit.x, free)
        why, warning = structure_holds(problem, fit.x, structure, free, R)
        if warning:
            fit.warnings.append(warning)
        if why is None:
            break
        st = analyse_structure(problem, fit.x, free, prefer=structure.gauge, R=R)
        st.rechecked = True
        gone = sorted(set(structure.kept) - set(st.kept))
        new = sorted(set(st.kept) - set(structure.kept))
        notes.append(
            f"re-checked at the solution: {why}"
            + (f" ({', '.join(problem.names[k] for k in gone)} now redundant)" if gone else "")
            + (f" ({', '.join(problem.names[k] for k in new)} now identifiable)" if new else "")
            + "; re-solved with the solution's reduction"
        )
        structure = st
        before = fit.iterations
        # through the plain residual first: the weighted fit's linear model can stall on the newly free
        # directions (its weighting's own derivative, neglected, is as large as their signal)
        fit = solve_staged(problem, fit.x, fit.x, st.kept, opt, fit.sigma_q, fit.known, progress, plain_start=True)
        fit.iterations += before
    return fit, structure, notes


def solve_readmitted(
    problem: CalibrationProblem,
    x0: np.ndarray,
    checked: Fit,
    structure: Structure,
    free: list[int],
    opt: CalibrationOptions,
    rng: np.random.Generator,
    progress: ProgressReporter | None = None,
) -> tuple[Fit, Structure, list[str]]:
    """The fit on `problem` (the rows kept once some rejected ones came back, `outliers.readmit`), warm-started
    at `checked`, the solution the readmission was decided at, with its reduction (`structure`, re-checked
    there); the reduction re-checked at the new solution (`recheck_at_solution`).

    The rows brought back are ones that solution explains within the noise, so it is a few iterations from
    the fit on the rows kept now.  Solved from the start instead, a fit can stop where the start's reduction
    leaves it (a contact point started on a joint axis and found off it: a local minimum micrometres above
    zero on exact data), and every restart `checked` went through runs again.  Restarts (`solve_with_restarts`)
    only where `checked` closed within a plausible noise and the warm-started fit does not: where `checked`
    did not, its restarts already found nothing better on nearly the same rows.
    """
    plausible = opt.rules.plausible_joint_noise
    fit = solve_staged(
        problem, x0, checked.x, structure.kept, opt, checked.sigma_q, checked.known, progress, plain_start=True
    )
    if _good(problem, checked, plausible) and not _good(problem, fit, plausible):
        fit = solve_with_restarts(
            problem,
            x0,
            structure.kept,
            opt,
            checked.sigma_q,
            checked.known,
            rng,
            progress,
            fit,
            structure.nearly_redundant(problem.index),
        )
    fit, structure, notes = recheck_at_solution(problem, fit, structure, free, x0, opt, progress)
    fit.iterations += checked.iterations
    return fit, structure, notes


def solve_from_starts(
    problem: CalibrationProblem,
    x0: np.ndarray,
    starts: list[np.ndarray],
    est: list[int],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    known: bool,
    progress: ProgressReporter | None = None,
    weak: list[int] | None = None,
) -> Fit:
    """`solve_staged` from each start; of the fits that close as well as the best, the nearest to x0 (`_better`).

    After outliers are rejected the robust refit's point is one start and x0 the
    other: a robust fit dragged by the rejected rows may lead the inliers' fit
    to another minimum than the plain start would.  A fit that stops on a
    valley's floor (`_floor`) is first left along the valley (`_along_valley`,
    `weak` freed, as `solve_with_restarts` would next); where that closes within
    the noise the later starts are not solved: they reach the same floor, at a
    full fit each (the door's exact data, a few rows rejected by a screen at a
    stalled fit).
    """
    scale = np.array([p.prior for p in problem.params])
    plausible = opt.rules.plausible_joint_noise
    fits = []
    for st in starts:
        fits.append(solve_staged(problem, x0, st, est, opt, sigma_q, known, progress))
        if _floor(problem, fits[-1], plausible):
            good = _along_valley(problem, x0, fits[-1], est, opt, sigma_q, known, progress, [], weak or [])
            if good:
                log.info("a fit stopped on a valley's floor; along the valley a fit closes within the noise")
                return min(good, key=lambda f: float(np.linalg.norm((f.x - x0)[est] / scale[est])))
    stage = _better(problem, [f.stage for f in fits], x0, est, scale, plausible)
    return next(f for f in fits if f.stage is stage)


def _unweighted_with_measurements(
    problem: CalibrationProblem,
    base: np.ndarray,
    est: list[int],
    scale: np.ndarray,
    sigma_q: np.ndarray,
    sopt,
    prog,
    b: StageResult,
) -> tuple[StageResult, int]:
    """The unweighted fit re-solved with known measurements weighted against the closures' level
    (`variance.measurement_row_weights`) until that level settles (5 %); unchanged without measurements."""
    iters, level = 0, None
    for _ in range(4):
        w = measurement_row_weights(problem, b.fun.full(b.solution.x))
        if w is None:
            break
        now = float(w.max())
        if level is not None and abs(now - level) <= 0.05 * level:
            break
        level = now
        b = weighted_stage(problem, base, b.solution.x, est, scale, sigma_q, "none", sopt, prog, w)
        iters += b.solution.iterations
    return b, iters


def length_guard(
    result: CalibrationResult, solve: Callable[[list], CalibrationResult], loops: list, rules: VerdictRules
) -> CalibrationResult:
    """A known length between frames (`problem.lengths`) that does not set the size never drives the estimate.

    The fit with the length is kept when the length sets the size (its size response, `analysis.scale`,
    within `rules.sets_size_low`..`sets_size_high`) and the verdict is not failed.  Otherwise the loops are
    solved without it (`solve(loops)`):
    a length that does not set the size moves the estimate along what the loops cannot see (a frame's slide
    along a joint axis), and one that fails a fit the loops alone pass contradicts them.  That fit is
    returned, `suspect` with the reason, unless the loops alone fail too (then the length was not the cause
    and the fit with it is returned as it is).
    """
    given = [lp for lp in loops if isinstance(lp, LengthLoop)]
    response = result.scale.length_response
    if not given or response is None:
        return result
    if result.verdict is None:
        raise ValueError("length_guard: the fit must be judged first (`judge`)")
    sets = rules.sets_size(response)
    if sets and result.verdict.status != FAILED:
        return result
    alone = solve([lp for lp in loops if not isinstance(lp, LengthLoop)])
    if alone.verdict is None:
        raise ValueError("length_guard: `solve` must return a judged fit (`judge`)")
    if alone.verdict.status == FAILED:
        return result
    labels = " and ".join(lp.label() for lp in given)
    if not sets:
        why = (
            f"{labels} cannot set the robot's size (a change of it by 1 % scales the fitted robot by "
            f"{response:.3g} %: it moves with what the loops cannot see); it was left out of the fit"
        )
    else:
        failed = "; ".join(r for r in result.verdict.reasons if r.startswith(FAILED))
        why = f"{labels} contradicts the loops (the fit with it failed: {failed}); it was left out of the fit"
    v = alone.verdict
    verdict = Verdict(v.status, [r for r in v.reasons if not r.startswith(SIZE_NOT_MEASURED)], dict(v.evidence))
    verdict.add(SUSPECT, why)
    verdict.reasons.extend(r for r in v.reasons if r.startswith(SIZE_NOT_MEASURED))
    verdict.evidence["length_left_out"] = True
    return replace(
        alone,
        verdict=verdict,
        warnings=alone.warnings + [why],
        notes=alone.notes + [why],
        # the size response and leak of the length left out: why it was left out
        scale=replace(alone.scale, length_response=response, length_leak=result.scale.length_leak),
    )
