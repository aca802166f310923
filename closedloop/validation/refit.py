"""A calibration refitted on part of its data, started at its solution (a warm refit).

Leave-one-fixture-out (`validation.fixtures`) refits the calibration once per fixture.  Removing one
fixture of many moves the solution by little, so each refit starts at the full calibration's solution
and shares what does not depend on the fixture left out:

* the rows the calibration rejected as outliers are left out of the refit's data (no outlier screen);
* the estimator (errors in variables) and the noise the calibration settled on: the joint noise (given,
  or estimated by it) and each loop's task-space noise (`estimate.variance`), held, not estimated again;
* the loops as calibrated (`CalibrationResult.loops`: their charts are those of its values).

What depends on the fixture left out is found again: the errors-in-variables fit (`residual.weighted_stage`,
eq. 3.17 weighted) of the parameters the calibration estimated, from its solution, on the remaining rows.
Where that fit truncates a direction (below the noise, eq. 4.17, or at the numerical floor: the remaining
loops do not determine it, or no longer set the size), the structural reduction is read again on the
remaining loops (`identifiability.analyse_structure`, at the solution); a parameter they cannot determine,
or the length that now holds the size, is held at its nominal start as in a calibration of its own.

No information of the fixture left out may reach the refit through its start: the directions the fit
still truncates are set back to the nominal start (`residual.below_noise_reset`) and the fit solved again from there, as a
calibration from the nominal model would leave them.

A refit that cannot be warm (bounds, a robust estimator, the plain estimator, a calibration that did not
converge) or whose warm fit does not converge within `WARM_ITER` iterations is a calibration of its own
(`calibrate`, with the same options on the same rows).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from closedloop.analysis.identifiability import analyse_structure
from closedloop.analysis.selection import initial_values, structure_problem
from closedloop.calibration.pipeline import build_problem, calibrate
from closedloop.errors import ClosedLoopError
from closedloop.estimate.lm import SolverOptions
from closedloop.estimate.noise import noise_vector
from closedloop.estimate.residual import below_noise_reset, weighted_stage
from closedloop.estimate.threads import blas_threads
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem
from closedloop.records import CalibrationOptions, CalibrationResult

#: iterations a warm refit may take; one that needs more is not near the calibration's solution, and
#: the refit is a calibration of its own
WARM_ITER = 30


@dataclass(frozen=True)
class Refit:
    """A refit's problem (its loops as refitted), its values (the problem's parameter order), whether it
    converged, its iterations, whether it started at the calibration's solution (`warm`), the parameters it
    estimated (indices into the problem's), its joint noise level (rad: the calibration's, held, or its
    own, given or estimated) and the rows of its log it rejected as outliers (0-based; none when warm: the
    calibration's screen is reused)."""

    problem: CalibrationProblem
    values: np.ndarray
    converged: bool
    iterations: int
    warm: bool
    estimated: tuple[int, ...] = ()
    sigma: float = 0.0
    rejected: tuple[int, ...] = ()


def as_refit(res: CalibrationResult) -> Refit:
    """A calibration of its own (`calibrate`) as a `Refit` (not warm)."""
    return Refit(
        problem=res.problem,
        values=res.fit.values,
        converged=res.converged,
        iterations=res.fit.iterations,
        warm=False,
        estimated=tuple(int(k) for k in res.fit.estimated),
        sigma=float(res.noise.sigma),
        rejected=tuple(rj.row - 1 for rj in res.outliers.rejected),  # `Rejected.row`: 1-based
    )


def refit(
    result: CalibrationResult | None,
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    opt: CalibrationOptions,
) -> Refit:
    """The calibration `result` refitted on `log_` (rows of the log it was fitted to, its rejected rows
    left out) with `loops` (a subset of its loops): warm where it can be (module docstring), else
    `calibrate` with `opt`.  Raises `ClosedLoopError` where the calibration of its own does."""
    warm = _warm(result, robot, log_, loops, opt) if result is not None else None
    if warm is not None:
        return warm
    return as_refit(calibrate(robot, log_, loops, opt))


def _warm(
    result: CalibrationResult, robot: RobotModel, log_: JointLog, loops: list[Loop], opt: CalibrationOptions
) -> Refit | None:
    """The warm refit, or None where it cannot be warm or did not converge near the solution."""
    if (
        not result.converged
        or opt.bounds
        or opt.robust in ("huber", "cauchy")
        or opt.weighting != "noise"
        or result.noise.weighting != "noise"
    ):
        return None
    calibrated = {lp.name: lp for lp in result.loops}
    if any(lp.name not in calibrated for lp in loops):  # a loop the calibration left out (`solve.length_guard`)
        return None
    try:
        problem = build_problem(robot, log_, [calibrated.get(lp.name, lp) for lp in loops], opt.priors)
    except ClosedLoopError:
        return None
    full = dict(zip(result.fit.names, result.fit.values.tolist()))
    if not set(problem.names) <= set(full):
        return None
    fitted = dict(zip([b.loop.name for b in result.problem.blocks], result.problem.noise))
    problem.noise = [fitted.get(b.loop.name, nz) for b, nz in zip(problem.blocks, problem.noise)]
    pattern, _ = noise_vector(problem, opt.noise)
    sigma_q = pattern * (result.noise.sigma / float(np.mean(pattern)))
    if not (np.all(np.isfinite(sigma_q)) and np.all(sigma_q > 0.0)):
        return None
    x_full = np.array([full[n] for n in problem.names])
    estimated = {result.fit.names[k] for k in result.fit.estimated}
    est = [k for k, n in enumerate(problem.names) if n in estimated]
    if not est or sum(b.theta.shape[0] * b.loop.dim for b in problem.blocks) <= len(est):
        return None  # too few rows for the parameters: the calibration of its own says so
    scale = np.array([p.prior for p in problem.params])
    sopt = SolverOptions(max_iter=WARM_ITER, noise=1.0, snr=opt.snr)
    with blas_threads(opt.threads):
        stage = weighted_stage(problem, x_full, x_full[est], est, scale, sigma_q, "noise", sopt, None)
        iterations = stage.solution.iterations
        if stage.solution.truncated:  # the rest does not determine every direction the calibration estimated
            x0 = initial_values(problem, opt.initial)  # where a calibration of its own starts
            try:
                structure = analyse_structure(structure_problem(problem), x_full, est)
            except ClosedLoopError:
                return None
            base = x_full.copy()
            held = [k for k in est if k not in structure.kept]  # unidentifiable now, or the length holding the size
            base[held] = x0[held]
            if held or list(structure.kept) != est:  # (else the same fit again: the same solution)
                est = list(structure.kept)
                if not est:
                    return None
                stage = weighted_stage(problem, base, base[est], est, scale, sigma_q, "noise", sopt, None)
                iterations += stage.solution.iterations
            truncated = stage.solution.truncated and stage.note is None  # directions below the noise: from x0
            args = (problem, base, base[est], base[est], x0[est], est, scale, sigma_q, opt.snr)
            start = below_noise_reset(*args) if truncated else None
            if start is not None:
                stage = weighted_stage(problem, base, start, est, scale, sigma_q, "noise", sopt, None)
                iterations += stage.solution.iterations
        if stage.note is not None or stage.solution.status != "converged" or not np.isfinite(stage.solution.cost):
            return None
        x = stage.fun.normalized(stage.fun.full(stage.solution.x))
    return Refit(
        problem=problem,
        values=x,
        converged=True,
        iterations=iterations,
        warm=True,
        estimated=tuple(est),
        sigma=float(result.noise.sigma),
    )
