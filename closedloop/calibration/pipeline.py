"""Calibrate: from a robot model, a joint log and loops to calibrated parameters and a verdict.

The pipeline (thesis 3.2, 4.2, with the noise treated as errors in variables):

1. `build_problem`: robot parameters of the loops' joints + loop parameters,
   over the logged configurations; `initial_values`: loop unknowns from the data.
2. `select_parameters`, `check_motion`: what to identify; joints that never
   move, loop mobility (Lemmas 4, 6), one scale factor if all are free (4.2.2).
3. `analyse_structure`: structural redundancies on data projected onto
   closure, and the length that sets the scale (3.3), named by what the robot
   does (`gauge`).
4. `solve_screened`: the outlier screen (`reject_outliers`, default: rows the
   noise cannot explain are found by a robust Cauchy refit and left out), the
   staged solve (`solve.solve_staged`: each configuration's closure weighted
   by W_i^-1 = (J_theta,i Sigma J_theta,i^T)^-1, the plain loop residual first
   where the weighting misleads; Levenberg-Marquardt with noise-aware SVD
   truncation, eq. 3.17, 4.2.6), restarts when the fit stalls far above any
   plausible noise.
5. `solve.recheck_at_solution`: the reduction and the gauge recomputed at
   the solution, reduced and re-solved where they differ; rejected rows the
   solution explains readmitted (`outliers.readmit`).
6. `name_gauge`: the held length that sets the size, with what it stands for.
7. `analyse_solution`: standard errors, directions the data do not determine,
   residuals before/after, a chi-square test, the share of the cost a
   Gauss-Newton step would still remove (0 at a minimum); `linearity.check_error_bars`:
   a long fit's error bars along the cost's profile, and where the cost falls beside the
   solution the fit solved again from the lower point (`_continued`; still falling, it is
   not converged); then `verdict.judge`.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from closedloop.analysis.gauge import short_gauge_warning
from closedloop.analysis.identifiability import Structure, analyse_structure, weak_directions
from closedloop.analysis.linearity import check_error_bars
from closedloop.analysis.scale import refuse_lengths, scale_findings
from closedloop.analysis.selection import (
    DEFAULT_IDENTIFY,
    MIN_RANGE,
    START_ROWS,
    check_motion,
    initial_values,
    select_parameters,
    structure_problem,
)
from closedloop.calibration.solve import (
    length_guard,
    recheck_at_solution,
    solve_from_starts,
    solve_readmitted,
    solve_staged,
    solve_with_restarts,
)
from closedloop.calibration.verdict import judge
from closedloop.errors import ConvergenceError, LogError, LoopError, NotIdentifiableError, ParameterError
from closedloop.estimate.lm import reducible_share, rms
from closedloop.estimate.model_error import (
    CELL_MIN,
    CELL_NOISE,
    EIV,
    ENCODER_NOISE,
    NOISE_MODEL,
    PLAIN,
    SANDWICH,
    configuration_cells,
    loo_prediction,
    neighbour_correlation,
    noise_test,
    sandwich_cov,
)
from closedloop.estimate.noise import noise_vector
from closedloop.estimate.outliers import readmit, reject_outliers, start_screen
from closedloop.estimate.residual import Fit
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.parameters import expand_fix
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.progress import ProgressReporter
from closedloop.records import (
    CalibrationOptions,
    CalibrationResult,
    FitRecord,
    IdentifiabilityRecord,
    LoopResiduals,
    NoiseRecord,
    OutlierRecord,
    ParameterRecord,
    ParamStatus,
    Rejected,
    ScaleRecord,
    residual_stats,
)

__all__ = [
    "CalibrationOptions",
    "CalibrationResult",
    "LoopResiduals",
    "ParameterRecord",
    "Rejected",
    "build_problem",
    "calibrate",
    "residual_stats",
    "DEFAULT_IDENTIFY",
    "MIN_RANGE",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- setup
def build_problem(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    priors: dict | None = None,
    row_numbers: np.ndarray | None = None,
) -> CalibrationProblem:
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
        named = ", ".join(f"'{lp.name}' ({', '.join(lp.frames)})" for lp in loops)
        raise LoopError(
            f"loop(s) {named}: no movable joint lies between the loop's frames and the base; "
            "put the loop on a link its joints move (frame=<link>)"
        )
    theta = log_.columns(joints)
    tau = log_.torques(joints)
    numbers = np.arange(1, len(log_) + 1) if row_numbers is None else np.asarray(row_numbers)
    blocks = []
    for lp in loops:
        if getattr(lp, "parameter_only", False):  # a known distance (closedloop.problem.distances): one row, no joint
            rows = np.arange(min(1, len(log_)))
        elif log_.loop is not None:
            rows = np.flatnonzero(log_.loop == lp.name)
            if rows.size == 0:
                raise LogError(f"{log_.source}: no row has loop '{lp.name}' in its 'loop' column")
        else:
            rows = np.arange(len(log_))
        at = getattr(lp, "measured_at", None)  # a known length: read at the readings it was measured at
        blocks.append(
            LoopBlock(
                lp,
                theta[rows] if at is None else at(joints),
                numbers[rows],
                tau[rows] if tau is not None and at is None else None,
                lp.measurements(log_.extra, rows),
            )
        )
    problem = CalibrationProblem(robot, joints, blocks, priors)
    # what each loop reads off the data once (`Loop.prepare`: the hinge's chart), at the nominal robot
    prepared = [
        b.loop.prepare(*problem.loop_poses(problem.nominal, bi), b.meas)
        if type(b.loop).prepare is not Loop.prepare
        else b.loop
        for bi, b in enumerate(blocks)
    ]
    if all(p is b.loop for p, b in zip(prepared, blocks)):
        return problem
    return CalibrationProblem(robot, joints, [replace(b, loop=p) for b, p in zip(blocks, prepared)], priors)


def analyse_solution(
    problem: CalibrationProblem, fit: Fit, opt: CalibrationOptions, status: list[ParamStatus], sandwich: bool = False
) -> dict:
    """Standard errors, weak directions and the chi-square test at the solution (eq. 4.17 truncation).

    With `sandwich` the covariance is the sandwich one clustered by cells of joint space
    (`model_error.sandwich_cov`, `configuration_cells`): the residual is not the assumed noise.  Edits
    `status` ('unidentifiable' for the parameters of weak directions).
    """
    est, fun = fit.est, fit.stage.fun
    scale = np.array([p.prior for p in problem.params])
    r, J = fun.linearized(fit.x[est])
    S, Vt, g = fun.factorised(fit.x[est], scale[est])  # no U; the solver's last factorisation where it is this J
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
    cov = (Vk / S[keep] ** 2) @ Vk.T * sigma_r**2 * np.outer(scale[est], scale[est])
    # clustered by cells of joint space: a pose's repeated readings are one cluster (`model_error`)
    noise_q = np.asarray(fit.sigma_q, dtype=float) * (sigma_r if weighted and not fit.known else 1.0)
    cells = configuration_cells(problem, np.maximum(CELL_NOISE * noise_q if weighted else 0.0, CELL_MIN))
    cov_s = sandwich_cov(problem, r, J, scale[est], Vk, S[keep], cells) if keep.any() else cov
    own = [c for c, b in zip(cells, problem.blocks) if not getattr(b.loop, "parameter_only", False)]
    n_cells = int(np.unique(np.concatenate(own)).size) if own else 0  # the sandwich's clusters: distinct poses
    d, ds = np.diag(cov), np.diag(cov_s)
    live = d > 0
    # mean variance ratio sandwich / noise model: ~1 where the residual is the assumed noise
    ratio = float(np.mean(ds[live] / d[live])) if live.any() else float("nan")
    if sandwich:
        cov = cov_s
    std = np.full(len(problem.params), np.nan)
    std[est] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for c in weak:
        for n, _ in c.terms:
            k = problem.index[n]
            status[k] = ParamStatus.UNIDENTIFIABLE
            std[k] = np.nan
    chi2 = float(r @ r) / (sigma_r**2 if not (fit.known and weighted) else 1.0)
    # At a minimum r is orthogonal to the columns of J: |U_k^T r|^2 / |r|^2, the share of the cost a
    # Gauss-Newton step would remove, is ~0 (at round-off closures anything: judged by `verdict._minimum`).
    # Near 1 the solver stopped where its linear model still sees the cost vanish.  With bounds an active
    # bound leaves a gradient: not computed.
    reducible = np.nan if opt.bounds else reducible_share(r, g, keep)
    return {
        "S": S,
        "rank": int(keep.sum()),
        "dof": dof,
        "sigma": sigma,
        "weak": weak,
        "cov": cov,
        "std": std,
        "chi2": chi2,
        "weighting": fun.weighting,
        "reducible": reducible,
        "sandwich_ratio": ratio,
        "sandwich_cells": n_cells,
    }


def calibrate(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    options: CalibrationOptions | None = None,
    progress: ProgressReporter | None = None,
) -> CalibrationResult:
    """Identify the selected parameters and judge the result; see the module docstring.

    One BLAS thread for the call, or `threads` (`estimate.threads.blas_threads`); a long log's rows on threads
    of their own (`parallel.chunks`).
    """
    from closedloop.estimate.threads import blas_threads
    from closedloop.io.marker import mark_running

    opt = options or CalibrationOptions()
    mark_running("calibrate")  # a supervising process may now interrupt the work (`io.marker`)
    with blas_threads(opt.threads):
        try:
            res = _calibrate(robot, log_, loops, opt, progress)
            # a known length that does not set the size never drives the estimate (closedloop.calibration.solve)
            return length_guard(res, lambda kept: _calibrate(robot, log_, kept, opt, progress), loops, opt.rules)
        except np.linalg.LinAlgError as exc:  # non-finite kinematics: values far outside any model
            raise ConvergenceError(
                f"{log_.source or 'the log'}: the solve broke down ({exc}): the data or the "
                "fixed values put the model where its kinematics are not finite"
            ) from None


def _calibrate(
    robot: RobotModel, log_: JointLog, loops: list[Loop], opt: CalibrationOptions, progress: ProgressReporter | None
) -> CalibrationResult:
    _check_options(opt)
    problem = build_problem(robot, log_, loops, opt.priors)
    opt = replace(opt, fix=expand_fix(opt.fix, problem.names))  # patterns (`--fix 'j*.offset'`) by name
    sample = problem.sampled(START_ROWS)  # what the loops' start and the data check read
    x0 = initial_values(sample, opt.initial)
    for bi, b in enumerate(sample.blocks):  # data no rough model of this loop explains: said before the fit
        why = b.loop.mismatch(sample.loop_frame_poses(x0, bi), b.meas)
        if why is not None:
            raise LoopError(f"{log_.source or 'the log'}: {why}")
    sample.forget_poses()  # the start's poses, read by the initialisation and the check above: not kept
    status = select_parameters(problem, opt.identify, opt.fix, x0)
    notes, dropped, motion_warnings = check_motion(problem, x0, status)
    free = [k for k, s in enumerate(status) if s == ParamStatus.SELECTED]
    if not free:
        raise NotIdentifiableError("no parameter is left to identify (all fixed or not selected)")
    refuse_lengths(problem, x0, free, opt.rules)
    sigma_q, known = noise_vector(problem, opt.noise)
    if progress:
        progress("analysing", 0)
    structure = analyse_structure(
        structure_problem(problem), x0, free
    )  # re-checked at the solution (recheck_at_solution)
    _check_rows(problem, structure, log_)
    if problem.keeps_jacobians:  # the solve's first J, taken first: the screen and `before` read it (the memo)
        problem.evaluate(x0, True, columns=structure.kept)
    before, start, structure0 = residual_stats(problem, problem.evaluate(x0, False)), problem, structure
    notes0 = list(notes)  # a re-solve with another estimator writes its own notes
    problem, fit, structure, rejected, suspects = solve_screened(
        problem, x0, free, structure, opt, sigma_q, known, len(log_), notes, progress, row_name=log_.where
    )
    choice: dict[str, Any] = {"estimator": EIV if fit.stage.fun.weighting == "noise" else PLAIN, "reason": "as asked"}
    choice |= {"error_bars": NOISE_MODEL, "evidence": {}}
    tested = noise_hypothesis(problem, fit, opt)
    if tested is not None and (tested["test"].holds or tested["test"].sigma_hat > opt.rules.failed_joint_noise):
        # beyond 0.01 rad no estimator mends a model that does not fit the data: kept, and the verdict says so
        choice |= {"reason": tested["test"].describe(), "evidence": tested["evidence"]}
    elif tested is not None:  # model error: the plain loop-closure fit (eq. 3.8), screened alike, sandwich error bars
        spent, notes[:] = fit.iterations, notes0
        problem, fit, structure, rejected, suspects = solve_screened(
            start, x0, free, structure0, replace(opt, weighting="none"), sigma_q, known, len(log_), notes, progress
        )
        fit.iterations += spent
        evidence = tested["evidence"] | {"left_out_rms_plain": _left_out(problem, fit)}
        if tested["test"].sigma_hat > opt.rules.plausible_joint_noise:
            fit.warnings.append(
                f"the errors-in-variables fit implies {tested['test'].sigma_hat:.3g} rad of joint noise, more than "
                "encoders give: the model misses an effect of that size (elasticity, gearing, backlash)"
            )
        choice = {"estimator": PLAIN, "reason": tested["test"].describe(), "error_bars": SANDWICH}
        choice["evidence"] = evidence
    notes.insert(0, f"estimator: {choice['estimator']} ({choice['reason']}); error bars from {choice['error_bars']}")
    if problem is not start:  # rows rejected: the start's closure on the rows kept
        before = residual_stats(problem, problem.evaluate(x0, False))
    fit.warnings.extend(motion_warnings)
    notes_fit, status_fit, warnings_fit = list(notes), list(status), list(fit.warnings)
    sigma_estimated = opt.noise is None
    for attempt in range(MINIMUM_RESTARTS + 1):  # until the profile check finds a minimum (`_continued`)
        notes, status, fit.warnings = list(notes_fit), list(status_fit), list(warnings_fit)
        after = residual_stats(problem, problem.evaluate(fit.x, False))  # the fit's own last evaluation (the memo)
        fit.x = x = fit.stage.fun.normalized(fit.x)  # loops in canonical form, the fit's Jacobian carried along
        for k in free:
            status[k] = ParamStatus.ESTIMATED if k in fit.est else ParamStatus.DROPPED
        gauge = name_gauge(problem, structure, x, status, opt, notes, fit.warnings)
        a = analyse_solution(problem, fit, opt, status, sandwich=choice["error_bars"] == SANDWICH)
        sol = fit.stage.solution
        if sol.status != "converged":
            notes.append(f"solver: {sol.message}")
        solution = FitRecord(
            names=problem.names,
            initial=x0,
            values=x,
            std=a["std"],
            status=status,
            estimated=fit.est,
            covariance=a["cov"],
            iterations=fit.iterations,
            solver_status=sol.status,
            solver_message=sol.message,
            residuals_before=before,
            residuals_after=after,
            reducible=a["reducible"],
        )
        # what sets the scale, each loop's noise model (closedloop.analysis.scale)
        found = scale_findings(
            problem, solution, a["weighting"], gauge, fit.sigma_q, structure.scale_free, opt.snr, opt.rules
        )
        # a long fit: do its error bars hold, is it a minimum? (closedloop.analysis.linearity)
        profiles, bar_warnings = check_error_bars(
            problem, solution, fit, a["sigma"], sigma_estimated, a["dof"], found["scale_std"]
        )
        fall = next((p for p in profiles if p.falls), None)
        if fall is None or sol.status != "converged":
            break
        if attempt == MINIMUM_RESTARTS:  # still falling: not called converged, and the verdict says why
            solution = replace(
                solution,
                solver_status="stalled",
                solver_message=f"no minimum found: after {attempt} restart(s) from lower points, {fall.describe()}",
            )
            break
        fit.warnings = list(warnings_fit)  # the solve's own, without this pass's analysis
        fit, note = _continued(problem, fit, fall, opt, progress)
        warnings_fit = list(fit.warnings)
        if choice["estimator"] == EIV and choice["evidence"]:  # the estimator's evidence, of the fit kept
            tested = noise_hypothesis(problem, fit, opt)
            if tested is not None:
                choice |= {"reason": tested["test"].describe(), "evidence": tested["evidence"]}
                notes_fit[0] = f"estimator: {choice['estimator']} ({choice['reason']}); error bars from " + str(
                    choice["error_bars"]
                )
        notes_fit.append(note)
    res = CalibrationResult(
        problem=problem,
        fit=solution,
        identifiability=IdentifiabilityRecord(
            dropped=dropped + list(structure.dropped), weak=a["weak"], singular_values=a["S"], rank=a["rank"]
        ),
        noise=NoiseRecord(
            sigma=a["sigma"],
            sigma_estimated=sigma_estimated,
            chi2=a["chi2"],
            dof=a["dof"],
            weighting=a["weighting"],
            estimator=choice["estimator"],
            estimator_reason=choice["reason"],
            error_bars=choice["error_bars"],
            model_error=choice["evidence"]
            | {"sandwich_variance_ratio": a["sandwich_ratio"], "sandwich_cells": a["sandwich_cells"]},
            noise_model=found["noise_model"],
            profiles=profiles,
        ),
        scale=ScaleRecord(
            gauge=gauge,
            gauge_note=structure.gauge_note,
            gauge_length=structure.gauge_length,
            scale_note=found["scale_note"],
            scale_std=found["scale_std"],
            length_response=found["length_response"],
            length_leak=found["length_leak"],
        ),
        outliers=OutlierRecord(rejected=rejected, suspects=suspects, rows_total=len(log_)),
        notes=notes + found["notes"],
        warnings=fit.warnings + found["warnings"] + bar_warnings,
    )
    return replace(res, verdict=judge(res, rules=opt.rules))


#: restarts from the lower point the profile check finds (`_continued`) before a fit is called no minimum
MINIMUM_RESTARTS = 2


def _continued(
    problem: CalibrationProblem, fit: Fit, fall, opt: CalibrationOptions, progress: ProgressReporter | None
) -> tuple[Fit, str]:
    """The fit solved again from the lower point its profile found (`fall`, a `linearity.Profile` that
    falls): a solver that stopped there was short of the minimum.  The same problem, rows, reduction and
    estimator (its weighting, its noise); the iterations, warnings and restart findings of `fit` carried.
    Returns the fit and a note for the result."""
    start = fit.x.copy()
    start[fit.est] = fall.lower
    how = opt if fit.stage.fun.weighting == opt.weighting else replace(opt, weighting=fit.stage.fun.weighting)
    again = solve_staged(problem, fit.x, start, list(fit.est), how, fit.sigma_q, fit.known, progress)
    again.iterations += fit.iterations
    again.warnings = list(dict.fromkeys(fit.warnings + again.warnings))
    again.hopeless = fit.hopeless
    note = (
        f"the solver stopped short of the minimum ({fall.describe()}): solved again from the profile's lower "
        f"point, {again.iterations - fit.iterations} more iterations"
    )
    return again, note


def noise_hypothesis(problem: CalibrationProblem, fit: Fit, opt: CalibrationOptions) -> dict | None:
    """Does joint noise explain the errors-in-variables fit's residual (`closedloop.estimate.model_error`)?

    The joint noise the weighted residual implies against the noise given, or a plausible encoder noise
    (`ENCODER_NOISE`), by chi-square; the nearest-configuration residual correlation and the left-out
    configurations' closure as evidence.  None where nothing is to be decided: ``weighting='none'``, a
    robust IRLS fit, ``choose_estimator=False``, or a fit the guard already moved to the plain residual.
    """
    fun = fit.stage.fun
    if not opt.choose_estimator or opt.weighting != "noise" or opt.robust in ("huber", "cauchy"):
        return None
    if fun.weighting != "noise":
        return None
    r, _ = fun.linearized(fit.x[fit.est])
    dof = max(r.size - fun.deficit - fun.missing - len(fit.est), 1)
    sigma_hat = rms(r, dof) * float(np.mean(fit.sigma_q))
    given = opt.noise is not None
    sigma_0 = float(np.mean(noise_vector(problem, opt.noise)[0])) if given else ENCODER_NOISE
    test = noise_test(sigma_hat, sigma_0, dof, neighbour_correlation(problem, r))
    return {
        "test": test,
        "evidence": {
            "joint_noise_implied": test.sigma_hat,
            "joint_noise_tested": test.sigma_0,
            "joint_noise_given": given,
            "chi2_per_dof": test.chi2_per_dof,
            "chi2_limit": test.limit,
            "neighbour_correlation": test.neighbour_rho,
            "noise_explains": test.holds,
            "left_out_rms_eiv": _left_out(problem, fit),
        },
    }


def _left_out(problem: CalibrationProblem, fit: Fit) -> float:
    """`loo_prediction` of a fit, on its own last Jacobian and that Jacobian's factorisation (shared with the
    solver's last iteration and `analyse_solution`)."""
    fun, xe = fit.stage.fun, fit.x[fit.est]
    r, J = fun.linearized(xe)
    S, Vt, _ = fun.factorised(xe, np.array([problem.params[k].prior for k in fit.est]))
    return loo_prediction(problem, fit.x, fit.est, r, J, factors=(S, Vt))


def _check_options(opt: CalibrationOptions) -> None:
    if opt.weighting not in ("noise", "none"):
        raise ParameterError(f"weighting must be 'noise' or 'none', not '{opt.weighting}'")
    if opt.robust not in (None, "auto", "huber", "cauchy"):
        raise ParameterError(f"robust must be 'auto', 'huber', 'cauchy' or None, not '{opt.robust}'")


def solve_screened(
    problem: CalibrationProblem,
    x0: np.ndarray,
    free: list[int],
    structure: Structure,
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    known: bool,
    n_rows: int,
    notes: list[str],
    progress: ProgressReporter | None,
    row_name=None,
) -> tuple[CalibrationProblem, Fit, Structure, list[Rejected], list]:
    """Outlier screen, staged solve, restarts and the re-checks at the solution (module docstring, 4-6).

    Returns the problem on the kept rows, its fit, the structure that holds
    at the solution, the rejected configurations and (``robust='huber'|
    'cauchy'``) the suspects.  Edits `notes`, naming rows with `row_name` (0-based row -> ``log.csv
    line 52``, `JointLog.where`).
    """
    rng = np.random.default_rng(opt.seed)
    rejected: list[Rejected] = []
    suspects: list = []
    screened = fit = None
    refit = False  # the robust refit from x0 has run on these rows (it is deterministic: once is enough)
    # rows no model error explains: far from a fit of the others (`gross_outliers`, `start_screen`)
    if opt.robust == "auto" and start_screen(problem, x0, structure.kept, sigma_q, opt):
        screened, refit = reject_outliers(problem, None, x0, structure.kept, opt, sigma_q, n_rows), True
    if screened is None:
        fit = solve_staged(problem, x0, x0, structure.kept, opt, sigma_q, known, progress)
        # screened before any restart: restarts on rows that are not closures are wasted
        if opt.robust == "auto" and not (refit and list(fit.est) == list(structure.kept)):
            screened = reject_outliers(problem, fit.x, x0, fit.est, opt, sigma_q, n_rows)
    problem_all = problem
    if screened is not None:
        problem, rejected, x_robust = screened
        structure = analyse_structure(structure_problem(problem), x0, free)
        weak = structure.nearly_redundant(problem.index)
        fit = solve_from_starts(problem, x0, [x0, x_robust], structure.kept, opt, sigma_q, known, progress, weak)
    fit = solve_with_restarts(
        problem, x0, structure.kept, opt, sigma_q, known, rng, progress, fit, structure.nearly_redundant(problem.index)
    )
    if opt.robust in ("huber", "cauchy"):
        from closedloop.estimate.outliers import irls_fit

        fit, suspects = irls_fit(problem, fit, opt, notes, row_name)
    fit, structure, recheck_notes = recheck_at_solution(problem, fit, structure, free, x0, opt, progress)
    if rejected and fit.hopeless:  # no fit closes the loops: nothing to confirm the rejections against
        notes.append(f"the {len(rejected)} rejected configuration(s) were not re-checked: no fit closes the loops")
    back = readmit(problem_all, fit.x, rejected, opt, sigma_q, fit.est) if rejected and not fit.hopeless else None
    if back is not None:  # rejections made short of the solution that it does not confirm
        notes.append(
            f"re-checked at the solution: {len(rejected) - len(back[1])} rejected configuration(s) "
            "fit within the noise there and were readmitted"
        )
        problem, rejected = back
        fit, structure, recheck_notes = solve_readmitted(problem, x0, fit, structure, free, opt, rng, progress)
    notes.extend(recheck_notes)
    return problem, fit, structure, rejected, suspects


def name_gauge(
    problem: CalibrationProblem,
    structure: Structure,
    x: np.ndarray,
    status: list[ParamStatus],
    opt: CalibrationOptions,
    notes: list[str],
    warnings: list[str],
) -> str | None:
    """The held length that sets the scale (thesis 3.3), with its notes; None if the data or the user set it.

    Edits `status` (the gauge is 'fixed'), `notes` and `warnings`.
    """
    if structure.gauge is None:
        if structure.scale_free and structure.gauge_note:
            warnings.append(structure.gauge_note)
        return None
    status[structure.gauge] = ParamStatus.FIXED
    gauge = problem.names[structure.gauge]
    notes.append(f"held {gauge} (correction {x[structure.gauge]:g}): {structure.gauge_note}")
    user_lengths = [problem.names[k] for k in opt_fixed(problem, opt) if problem.params[k].scales_with_length]
    if user_lengths:
        notes.append(
            f"the fixed length(s) {', '.join(user_lengths)} do not set the scale: they are absorbed by other parameters"
        )
    short = short_gauge_warning(gauge, structure.gauge_length, opt.rules.scale_suspect)
    if short:
        warnings.append(short)
    return gauge


def opt_fixed(problem: CalibrationProblem, opt: CalibrationOptions) -> set[int]:
    """Indices of the parameters the user fixed."""
    return {problem.index[n] for n in opt.fix if n in problem.index}


def _check_rows(problem: CalibrationProblem, structure: Structure, log_: JointLog) -> None:
    M = sum(b.theta.shape[0] * b.loop.dim for b in problem.blocks)
    if M <= len(structure.kept):  # the rows, not the model, limit the rank: nothing left to check
        raise LogError(
            f"{log_.source}: {len(log_)} rows give {M} equations, no more than the "
            f"{len(structure.kept)} parameters they could determine; log more configurations or "
            "identify fewer parameters"
        )
