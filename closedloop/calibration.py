"""Calibrate: from a robot model, a joint log and loops to calibrated parameters and a verdict.

The pipeline (thesis 3.2, 4.2, with the noise treated as errors in variables):

1. `build_problem`: robot parameters of the loops' joints + loop parameters,
   over the logged configurations; `initial_values`: loop unknowns from the data.
2. `select_parameters`, `check_motion`: what to identify; joints that never
   move, loop mobility (Lemmas 4, 6), one scale factor if all are free (4.2.2).
3. `analyse_structure`: structural redundancies on data projected onto
   closure, and the length that sets the scale (3.3), named by what the robot
   does (`gauge`).
4. `solve_staged`: the plain loop residual first, then each configuration's
   closure weighted by W_i^-1 = (J_theta,i Sigma J_theta,i^T)^-1, by
   Levenberg-Marquardt with noise-aware SVD truncation (eq. 3.17, 4.2.6);
   restarts when the fit stalls far above any plausible noise.
5. `reject_outliers` (default): configurations the noise cannot explain are
   found by a robust (Cauchy) refit and left out; steps 3-4 run on the rest.
6. `recheck_at_solution`: the reduction and the gauge recomputed at the
   solution; reduced and re-solved where they differ.
7. `analyse_solution`: standard errors, directions the data do not determine,
   residuals before/after, a chi-square test; then `verdict.judge`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from .data import JointLog
from .errors import ConvergenceError, LogError, LoopError, NotIdentifiableError, ParameterError
from .fit import ResidualFunction, StageResult, plain_stage, random_start, unweighted_closure, weighted_stage
from .identifiability import Structure, analyse_structure, closure_jacobian, structure_holds, weak_directions
from .loops.base import Loop
from .noise import joint_variance_scale, noise_vector
from .outliers import gross_outliers, reject_outliers
from .problem import CalibrationProblem, LoopBlock
from .records import (CalibrationOptions, CalibrationResult, LoopResiduals, ParameterRecord, Rejected,
                      residual_stats)
from .robot import RobotModel
from .selection import DEFAULT_IDENTIFY, MIN_RANGE, check_motion, initial_values, select_parameters
from .solver import SolverOptions, rms, scaled_svd
from .verdict import judge

__all__ = ["CalibrationOptions", "CalibrationResult", "LoopResiduals", "ParameterRecord", "Rejected",
           "build_problem", "calibrate", "residual_stats", "DEFAULT_IDENTIFY", "MIN_RANGE"]

log = logging.getLogger(__name__)
Progress = Callable[[str, int, float], None]


# --------------------------------------------------------------------------- setup
def build_problem(robot: RobotModel, log_: JointLog, loops: list[Loop], priors: dict | None = None,
                  row_numbers: np.ndarray | None = None) -> CalibrationProblem:
    """The problem for `loops` over `log_`; checks frames, joints and row assignment.

    `row_numbers` (1-based, one per log row) name the rows in messages when
    `log_` is a subset of the user's file.
    """
    if not loops:
        raise LoopError("no loop given: say how the chain is closed (e.g. --loop weld:frame=tool)")
    names = [lp.name for lp in loops]
    if len(set(names)) != len(names):
        raise LoopError(f"duplicate loop names: {names}")
    joints: list[str] = []
    for lp in loops:
        for f in lp.frames:
            try:
                robot.frame_id(f)
            except Exception as exc:
                raise LoopError(f"loop '{lp.name}': {exc}") from None
            for j in robot.supporting_joints(f):
                if j not in joints:
                    joints.append(j)
    order = {n: i for i, n in enumerate(robot.joint_names)}
    joints.sort(key=lambda n: order[n])
    if not joints:
        raise LoopError("no movable joint lies between the loops' frames and the base")
    theta = log_.columns(joints)
    tau = log_.torques(joints)
    numbers = np.arange(1, len(log_) + 1) if row_numbers is None else np.asarray(row_numbers)
    blocks = []
    for lp in loops:
        if log_.loop is not None:
            rows = np.flatnonzero(log_.loop == lp.name)
            if rows.size == 0:
                raise LogError(f"{log_.source}: no row has loop '{lp.name}' in its 'loop' column")
        else:
            rows = np.arange(len(log_))
        lp.bind({k: v[rows] for k, v in log_.extra.items()})
        blocks.append(LoopBlock(lp, theta[rows], numbers[rows], tau[rows] if tau is not None else None))
    return CalibrationProblem(robot, joints, blocks, priors)


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


def _solver_options(opt: CalibrationOptions, problem: CalibrationProblem, est: list[int], known: bool
                    ) -> SolverOptions:
    lower = upper = None
    if opt.bounds:
        lower, upper = np.full(len(est), -np.inf), np.full(len(est), np.inf)
        for n, (lo, hi) in opt.bounds.items():
            if n not in problem.index:
                raise ParameterError(f"bound for unknown parameter '{n}'")
            k = problem.index[n]
            if k in est:
                lower[est.index(k)], upper[est.index(k)] = lo, hi
    return SolverOptions(max_iter=opt.max_iter, noise=(1.0 if known and opt.weighting == "noise" else None),
                         snr=opt.snr, lower=lower, upper=upper)


def solve_staged(problem: CalibrationProblem, x0: np.ndarray, start: np.ndarray, est: list[int],
                 opt: CalibrationOptions, sigma_q: np.ndarray, known: bool,
                 progress: Progress | None = None, plain_start: bool = False) -> Fit:
    """The weighted fit from `start`; staged through the plain residual where the weighting misleads.

    The errors-in-variables fit is tried first (it is the estimator; on a
    single self-motion, where many robots close the same curve, the plain
    residual's long steps can reach a degenerate one).  When it stalls far
    above any plausible noise, leaves directions undetermined (a spurious
    minimum reports many), or its weighting turns singular on the way
    (more residual directions discarded than at the start), the plain
    loop-closure fit is solved from `start` and the weighted fit restarted
    from it (`fit.weighted_stage` keeps the plain solution if the weighting
    would hide a residual there).  `plain_start` goes through the plain stage
    directly.
    """
    scale = np.array([p.prior for p in problem.params])
    sopt = _solver_options(opt, problem, est, known)
    prog = (lambda it, c: progress("solving", it, c)) if progress else None
    warnings: list[str] = []
    base = x0.copy()
    base[est] = start[est]
    xs, iters = start[est], 0
    b = None
    if not plain_start or opt.weighting != "noise":
        b = weighted_stage(problem, base, xs, est, scale, sigma_q, opt.weighting, sopt, prog)
        iters = b.solution.iterations
    if b is None or (opt.weighting == "noise" and (b.note or b.solution.truncated
                                                    or _misled(problem, b))):
        a = plain_stage(problem, base, xs, est, scale, sopt, prog)
        b2 = weighted_stage(problem, base, a.solution.x, est, scale, sigma_q, opt.weighting, sopt, prog)
        iters += a.solution.iterations + b2.solution.iterations
        b = b2 if b is None else _better(problem, [b, b2], start, est, scale)
    if b.note:
        warnings.append(b.note)
    xs = b.solution.x
    joint_beside_measurement = (not known and opt.weighting == "noise" and b.fun.weighting == "noise"
                                and any(bl.loop.measurement_cov is not None for bl in problem.blocks))
    if joint_beside_measurement:
        # The ratio of joint to measurement noise sets the weights: estimate the joint level
        # (closedloop.noise) at the fit, re-solve with it, until it settles.
        pattern, s_prev = sigma_q.copy(), None
        covs = [bl.loop.measurement_cov for bl in problem.blocks]
        start_e = start[est]
        for _ in range(4):
            evs = problem.evaluate(b.fun.full(b.solution.x), True, columns=[])
            s = joint_variance_scale([e.r for e in evs], [e.Jq for e in evs], covs, pattern, len(est))
            if s_prev is not None and abs(s - s_prev) <= 0.05 * max(s, s_prev):
                break
            sigma_q, known, s_prev = np.sqrt(s) * pattern, True, s
            b = weighted_stage(problem, base, start_e, est, scale, sigma_q, "noise", replace(sopt, noise=1.0), prog)
            iters += b.solution.iterations
    return Fit(b.fun.full(b.solution.x), b, est, sigma_q, known, iters, warnings)


def _misled(problem: CalibrationProblem, stage: StageResult) -> bool:
    """The weighted fit stalled far above the noise, or its weighting discards more than at the start."""
    if stage.solution.status != "converged" or _closure_level(problem, stage) > 1.0:
        return True
    return stage.fun.deficit > stage.deficit_start


PLAUSIBLE_JOINT_NOISE = 2e-3  # rad: no encoder reads worse; a closure it cannot explain is a stalled fit


def _closure_level(problem: CalibrationProblem, stage: StageResult) -> float:
    """The typical configuration's closure in units of what 2 mrad of joint noise (plus the loops' own
    measurement noise, a camera's pixels) explains: the median, so that a few outliers do not count."""
    if not np.isfinite(stage.solution.cost):
        return np.inf
    fun = ResidualFunction(problem, stage.fun.full(stage.solution.x), [],
                           np.full(len(problem.joints), PLAUSIBLE_JOINT_NOISE), "noise")
    per_config = np.concatenate([np.linalg.norm(b, axis=1) / np.sqrt(b.shape[1])
                                 for b in fun.blocks(np.zeros(0)) if b.size])
    return float(np.median(per_config)) if per_config.size else 0.0


def _stalled(problem: CalibrationProblem, fit: Fit) -> bool:
    """The fit stopped far above any plausible noise (`_closure_level` above 1)."""
    return _closure_level(problem, fit.stage) > 1.0


def _better(problem: CalibrationProblem, stages: list[StageResult], start: np.ndarray, est: list[int],
            scale: np.ndarray) -> StageResult:
    """Of the fits that close as well as the best, the nearest the start (in prior units): a degenerate
    robot (a forearm of zero length) may close a single self-motion as well as the real one."""
    levels = [_closure_level(problem, st) for st in stages]
    # as good as the best: within 10x of its closure, or both below 1/1000 of a plausible noise
    good = [st for st, lv in zip(stages, levels) if lv <= max(10.0 * min(levels), 1e-3)]
    return min(good, key=lambda st: float(np.linalg.norm((st.solution.x - start[est]) / scale[est])))


def solve_with_restarts(problem: CalibrationProblem, x0: np.ndarray, est: list[int], opt: CalibrationOptions,
                        sigma_q: np.ndarray, known: bool, rng: np.random.Generator,
                        progress: Progress | None = None, first: Fit | None = None) -> Fit:
    """`solve_staged` from x0 (or `first`); if it stalls far above the noise, from other starts.

    Starts: the loop parameters and offsets first with the geometry held, then
    all; then x0 moved at random by 1x and 3x the parameters' priors.  Among
    the fits that close within a plausible noise, the nearest to the start
    (in prior units) is kept: on a single self-motion degenerate robots (a
    forearm of zero length) close the loop as well as the real one.  If none
    does, the one with the lowest unweighted closure.
    """
    fit = first if first is not None else solve_staged(problem, x0, x0, est, opt, sigma_q, known, progress)
    if opt.restarts <= 0 or not _stalled(problem, fit):
        return fit
    scale = np.array([p.prior for p in problem.params])
    fits = [fit]
    starts = []
    sub = [k for k in est if problem.params[k].kind in ("loop", "offset")]
    if sub and len(sub) < len(est):
        starts.append(solve_staged(problem, x0, x0, sub, opt, sigma_q, known, plain_start=True).x)
    for size in (1.0, 3.0, 1.0, 3.0)[:max(opt.restarts - len(starts), 0)]:
        starts.append(random_start(x0, est, scale, rng, size))
    for k, st in enumerate(starts[:opt.restarts]):
        log.info("restart %d: the fit stalled far above the noise", k + 1)
        fits.append(solve_staged(problem, x0, st, est, opt, sigma_q, known, progress))
        if not _stalled(problem, fits[-1]):
            break
    good = [f for f in fits if not _stalled(problem, f)]
    if good:
        best = min(good, key=lambda f: float(np.linalg.norm((f.x - x0)[est] / scale[est])))
    else:
        best = min(fits, key=lambda f: unweighted_closure(problem, f.x))
    best.warnings.append("the fit stalled far above the noise from the given start; "
                         f"{'a restart reached' if good else 'no restart reached'} a closure within a plausible noise")
    return best


def recheck_at_solution(problem: CalibrationProblem, fit: Fit, structure: Structure, free: list[int],
                        x0: np.ndarray, opt: CalibrationOptions, progress: Progress | None
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
        notes.append(f"re-checked at the solution: {why}"
                     + (f" ({', '.join(problem.names[k] for k in gone)} now redundant)" if gone else "")
                     + (f" ({', '.join(problem.names[k] for k in new)} now identifiable)" if new else "")
                     + "; re-solved with the solution's reduction")
        structure = st
        fit = solve_staged(problem, fit.x, fit.x, st.kept, opt, fit.sigma_q, fit.known, progress)
    return fit, structure, notes


def analyse_solution(problem: CalibrationProblem, fit: Fit, opt: CalibrationOptions, status: list[str]
                     ) -> dict:
    """Standard errors, weak directions and the chi-square test at the solution (eq. 4.17 truncation).

    Edits `status` ('unidentifiable' for the parameters of weak directions).
    """
    est, fun = fit.est, fit.stage.fun
    scale = np.array([p.prior for p in problem.params])
    r, J = fun(fit.x[est], True)
    S, Vt, _ = scaled_svd(J, r, scale[est])  # no U, no threaded LAPACK on the tall Jacobian
    rank_num = int(np.sum(S > 1e-10 * S[0])) if S.size else 0
    dof = max(r.size - fun.deficit - fun.missing - rank_num, 1)  # eliminated or unobserved rows carry none
    weighted = fun.weighting == "noise"
    if fit.known and weighted:
        sigma_r, sigma = 1.0, float(np.mean(fit.sigma_q))
    else:
        sigma_r = rms(r, dof)
        sigma = sigma_r * (float(np.mean(fit.sigma_q)) if weighted else 1.0)
    threshold = max(1e-10 * (S[0] if S.size else 0.0), opt.snr * sigma_r)
    weak = weak_directions(S, Vt, threshold, [problem.names[k] for k in est])
    keep = S > threshold
    Vk = Vt[keep].T
    cov = (Vk / S[keep] ** 2) @ Vk.T * sigma_r ** 2 * np.outer(scale[est], scale[est])
    std = np.full(len(problem.params), np.nan)
    std[est] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for c in weak:
        for n, _ in c.terms:
            k = problem.index[n]
            status[k] = "unidentifiable"
            std[k] = np.nan
    chi2 = float(r @ r) / (sigma_r ** 2 if not (fit.known and weighted) else 1.0)
    return {"S": S, "rank": int(keep.sum()), "dof": dof, "sigma": sigma, "weak": weak, "cov": cov, "std": std,
            "chi2": chi2, "weighting": fun.weighting}


def calibrate(robot: RobotModel, log_: JointLog, loops: list[Loop], options: CalibrationOptions | None = None,
              progress: Progress | None = None) -> CalibrationResult:
    """Identify the selected parameters and judge the result; see the module docstring.

    BLAS threads are limited for the call by problem size (`threads.blas_threads`).
    """
    from .threads import blas_threads

    opt = options or CalibrationOptions()
    with blas_threads(opt.threads, 6 * len(log_), 6 * len(robot.joint_names) + 6):
        try:
            return _calibrate(robot, log_, loops, opt, progress)
        except np.linalg.LinAlgError as exc:  # non-finite kinematics: values far outside any model
            raise ConvergenceError(f"{log_.source or 'the log'}: the solve broke down ({exc}): the data or the "
                                   "fixed values put the model where its kinematics are not finite") from None


def _calibrate(robot: RobotModel, log_: JointLog, loops: list[Loop], opt: CalibrationOptions,
               progress: Progress | None) -> CalibrationResult:
    if opt.weighting not in ("noise", "none"):
        raise ParameterError(f"weighting must be 'noise' or 'none', not '{opt.weighting}'")
    if opt.robust not in (None, "auto", "huber", "cauchy"):
        raise ParameterError(f"robust must be 'auto', 'huber', 'cauchy' or None, not '{opt.robust}'")
    problem = build_problem(robot, log_, loops, opt.priors)
    x0 = initial_values(problem, opt.initial)
    status = select_parameters(problem, opt.identify, opt.fix, x0)
    notes, dropped, motion_warnings = check_motion(problem, x0, status)
    free = [k for k, s in enumerate(status) if s == "selected"]
    if not free:
        raise NotIdentifiableError("no parameter is left to identify (all fixed or not selected)")
    sigma_q, known = noise_vector(problem, opt.noise)
    rng = np.random.default_rng(opt.seed)
    if progress:
        progress("analysing", 0, 0.0)
    structure = analyse_structure(problem, x0, free)  # re-checked at the solution (recheck_at_solution)
    _check_rows(problem, structure, log_)
    rejected: list[Rejected] = []
    suspects: list = []
    screened = fit = None
    if opt.robust == "auto" and gross_outliers(problem, x0, sigma_q, opt):  # rows no model error explains
        screened = reject_outliers(problem, None, x0, structure.kept, opt, sigma_q, log_, loops,
                                   build_problem)
    if screened is None:
        fit = solve_staged(problem, x0, x0, structure.kept, opt, sigma_q, known, progress)
        if opt.robust == "auto":  # screened before any restart: restarts on rows that are not closures are wasted
            screened = reject_outliers(problem, fit.x, x0, fit.est, opt, sigma_q, log_, loops, build_problem)
    if screened is not None:
        problem, rejected, x_robust = screened
        structure = analyse_structure(problem, x0, free)
        fit = solve_staged(problem, x0, x_robust, structure.kept, opt, sigma_q, known, progress)
    fit = solve_with_restarts(problem, x0, structure.kept, opt, sigma_q, known, rng, progress, fit)
    if opt.robust in ("huber", "cauchy"):
        from .outliers import irls_fit

        fit, suspects = irls_fit(problem, fit, opt, notes)
    fit, structure, recheck_notes = recheck_at_solution(problem, fit, structure, free, x0, opt, progress)
    notes.extend(recheck_notes)
    x = fit.x.copy()
    for b, sl in zip(problem.blocks, problem.loop_slices):
        x[sl] = b.loop.normalize(x[sl])
    fit.x = x
    fit.warnings.extend(motion_warnings)
    for k in free:
        status[k] = "estimated" if k in fit.est else "dropped"
    gauge = None
    if structure.gauge is not None:
        status[structure.gauge] = "fixed"
        gauge = problem.names[structure.gauge]
        notes.append(f"fixed {gauge} = {x[structure.gauge]:g}: {structure.gauge_note}")
        user_lengths = [problem.names[k] for k in opt_fixed(problem, opt) if problem.params[k].scales_with_length]
        if user_lengths:
            notes.append(f"the fixed length(s) {', '.join(user_lengths)} do not set the scale: they are absorbed "
                         "by other parameters")
        if structure.gauge_warning:
            fit.warnings.append(structure.gauge_warning)
    elif structure.scale_free and structure.gauge_note:
        fit.warnings.append(structure.gauge_note)
    dropped = dropped + [d for d in structure.dropped]
    a = analyse_solution(problem, fit, opt, status)
    evals0 = problem.evaluate(x0, False)
    evals1 = problem.evaluate(x, False)
    sol = fit.stage.solution
    if sol.status != "converged":
        notes.append(f"solver: {sol.message}")
    res = CalibrationResult(problem, problem.names, x0, x, a["std"], status, dropped, a["weak"], a["S"], a["rank"],
                            residual_stats(problem, evals0), residual_stats(problem, evals1), fit.iterations,
                            sol.status, sol.message, a["sigma"], opt.noise is None, a["chi2"],
                            a["dof"], notes, a["cov"], fit.est, suspects, a["weighting"], gauge,
                            structure.gauge_note, structure.gauge_length, rejected, len(log_), fit.warnings)
    res.verdict = judge(res)
    return res


def opt_fixed(problem: CalibrationProblem, opt: CalibrationOptions) -> set[int]:
    """Indices of the parameters the user fixed."""
    return {problem.index[n] for n in opt.fix if n in problem.index}


def _check_rows(problem: CalibrationProblem, structure: Structure, log_: JointLog) -> None:
    M = sum(b.theta.shape[0] * b.loop.dim for b in problem.blocks)
    if M <= len(structure.kept):  # the rows, not the model, limit the rank: nothing left to check
        raise LogError(f"{log_.source}: {len(log_)} rows give {M} equations, no more than the "
                       f"{len(structure.kept)} parameters they could determine; log more configurations or "
                       "identify fewer parameters")
