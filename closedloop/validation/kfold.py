"""Held-out and k-fold validation of a calibration.

A calibration is judged on configurations it did not see: refit on the
training rows with the same options, then evaluate the closure residual of
the held-out rows at the fitted parameters (unweighted, per loop: RMS of the
translation error norm in metres and of the rotation error norm in radians,
as in ``records.residual_stats``).  With the noise known and the
'noise' weighting, the held-out whitened RMS (per residual row) should be
close to 1: much larger means the model does not generalise (over-fit,
unmodelled error, or an outlier in the held-out fold).

The held-out figure is a prediction: the held-out rows are evaluated at the
fold's own values, every parameter (the robot's, a shared ball, a tracker's
base, each loop's place) as the training rows fitted it; nothing is refitted
on them.

Rows are split at random, per loop (each loop's rows are spread over the
folds), reproducibly from `seed`.

Rows that are not data are not judged: the closure statistics of a fold
leave out the rows its refit rejected as outliers (training) and the rows
the full calibration rejected (`exclude`: training and held-out).  A few
corrupted readings would otherwise set both figures alike (a 0.1 rad
reading error is a closure of centimetres against microns), and the
held-out/training ratio, the test of generalisation, would see nothing.  With
`train_without_excluded` the refits reuse the full calibration's outlier
screen instead of screening again: its rejected rows are left out of their
data, and the rest, screened by it already, is not screened again (a robust
refit costs many times a clean fit, once per fold).
Held-out rows are never screened against the fold's own fit: a model that
does not generalise would screen away the evidence.

On a long log (a loop of more than `VALIDATION_ROWS` configurations) a fold's
training rows, and the held-out rows it is judged on, are an even sample of at
most `VALIDATION_ROWS` per loop (`validation_rows`; 'n_train' and 'n_test' of
each fold count them).  Thousands of configurations fix the parameters far
below what the held-out closure measures, and give its RMS to a few per cent,
so the figures keep their meaning while the validation's cost stops growing
with the log.  Given the full calibration (`cross_validate`'s `result`, with
its outlier screen reused), such a refit then starts at its solution
(`validation.refit`: a warm refit, a few iterations, noise held): with
thousands of rows in and out, the training sample's minimum lies within its
standard errors of the full solution, and the fit reaches it from there.  A
refit that cannot be warm is a calibration of its own, as on a short log,
whose refits are always calibrations of their own.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np

from closedloop.calibration.pipeline import (
    CalibrationOptions,
    CalibrationResult,
    build_problem,
    calibrate,
    residual_stats,
)
from closedloop.errors import ParameterError
from closedloop.estimate.noise import noise_vector, whiten
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.parallel.chunks import chunk_threads
from closedloop.parallel.engine import ThreadEngine
from closedloop.problem.blocks import BlockEval
from closedloop.problem.problem import CalibrationProblem, even_sample
from closedloop.problem.unwrap import unwrap
from closedloop.progress import ProgressReporter
from closedloop.validation.refit import Refit, as_refit, refit


def subset(log_: JointLog, rows: np.ndarray) -> JointLog:
    """The rows `rows` (0-based) of a log, extra columns and loop labels included."""
    rows = np.asarray(rows, dtype=int)
    return JointLog(
        list(log_.joints),
        log_.angles[rows],
        log_.source,
        None if log_.loop is None else log_.loop[rows],
        {k: v[rows] for k, v in log_.extra.items()},
        log_.files,
        None if log_.lines is None else log_.lines[rows],
    )


def folds(log_: JointLog, k: int, seed: int = 0) -> list[np.ndarray]:
    """k disjoint sets of row indices covering the log, each loop's rows spread evenly."""
    if k < 2:
        raise ParameterError("k-fold validation needs k >= 2")
    rng = np.random.default_rng(seed)
    groups = (
        [np.arange(len(log_))]
        if log_.loop is None
        else [np.flatnonzero(log_.loop == name) for name in dict.fromkeys(log_.loop.tolist())]
    )
    for g in groups:
        if g.size < k:
            which = "" if log_.loop is None else f" of loop '{log_.loop[g[0]]}'" if g.size else ""
            raise ParameterError(
                f"{k}-fold validation needs at least {k} rows{which}; {log_.source or 'the log'} has {g.size}"
            )
    out: list[list[int]] = [[] for _ in range(k)]
    for g in groups:
        perm = rng.permutation(g)
        for f, chunk in enumerate(np.array_split(perm, k)):
            out[f].extend(chunk.tolist())
    return [np.sort(np.array(f, dtype=int)) for f in out]


#: configurations per loop a held-out refit is trained on, and judged on, at most (`validation_rows`)
VALIDATION_ROWS = 4096


def validation_rows(log_: JointLog, rows: np.ndarray, cap: int | None = None) -> np.ndarray:
    """The rows (0-based, sorted) of `rows` a refit trains on or is judged on: all of them, or an even sample
    (`even_sample`, first to last along the log) of at most `cap` (default `VALIDATION_ROWS`) per loop where a
    loop has more."""
    cap = VALIDATION_ROWS if cap is None else cap
    rows = np.asarray(rows, dtype=int)
    if log_.loop is None:
        return rows[even_sample(rows.size, cap)]
    names = log_.loop[rows]
    keep = [g[even_sample(g.size, cap)] for g in (np.flatnonzero(names == n) for n in dict.fromkeys(names.tolist()))]
    return rows[np.sort(np.concatenate(keep))] if keep else rows


def closure_residuals(
    result: CalibrationResult | Refit,
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    noise=None,
    skip=None,
    problem: CalibrationProblem | None = None,
) -> dict[str, Any]:
    """Closure residuals of `log_` at the calibrated values of `result` (a calibration, or a refit:
    `validation.refit.Refit`), without its rows `skip` (0-based).  `problem`: that of `log_` with the
    fit's loops and noise where the caller has it (a warm refit's own, which keeps its evaluation at the
    refit's values); None: built here.

    Returns {'loops': [LoopResiduals as dict], 'whitened_rms': per-row RMS of
    the noise-whitened residual (None when no noise level is known),
    'skipped': the number of rows left out}.
    """
    fitted = result if isinstance(result, Refit) else as_refit(result)
    if problem is None:
        calibrated = {b.loop.name: b.loop for b in fitted.problem.blocks}  # their charts are those of the values
        problem = build_problem(robot, log_, [calibrated.get(lp.name, lp) for lp in loops], None)
        noises = dict(zip([b.loop.name for b in fitted.problem.blocks], fitted.problem.noise))
        problem.noise = [noises.get(b.loop.name, nz) for b, nz in zip(problem.blocks, problem.noise)]  # the fit's
    if problem.names != fitted.problem.names:
        raise ValueError("the validation rows give a different parameter set than the calibration")
    values = fitted.values
    evals = problem.evaluate(values, noise is not None, columns=[])  # the whitening needs Jq alone
    skipped = np.zeros(0, dtype=int) if skip is None else np.unique(np.asarray(skip, dtype=int))
    if skipped.size:
        evals = [_without_rows(ev, skipped + 1) for ev in evals]
    stats = residual_stats(problem, evals)
    wr = None
    if noise is not None:
        sigma_q, _ = noise_vector(problem, noise)
        # |W_i^-1/2 r_i|^2 is the same for any root of W_i^-1: the Cholesky one (`whiten`'s symmetric=False)
        r, _, _ = whiten(evals, sigma_q, "noise", False, problem.noise, symmetric=False)
        wr = float(np.sqrt(np.mean(r**2))) if r.size else None
    return {"loops": [asdict(s) for s in stats], "whitened_rms": wr, "skipped": int(skipped.size)}


def _without_rows(ev: BlockEval, numbers: np.ndarray) -> BlockEval:
    """A block's evaluation without the configurations of log rows `numbers` (1-based, `BlockEval.rows`)."""
    if ev.rows is None:  # a known distance: no configuration
        return ev
    return ev.take(~np.isin(ev.rows, numbers))


def holdout(
    robot: RobotModel,
    train: JointLog,
    test: JointLog,
    loops: list[Loop],
    options: CalibrationOptions | None = None,
    skip_train=None,
    skip_test=None,
    start: CalibrationResult | None = None,
) -> dict[str, Any]:
    """Fit on `train`, report the closure residuals on `train` (fit) and on `test` (prediction).

    Not judged: the training rows the fit rejected as outliers and `skip_train`, and the held-out rows
    `skip_test` (0-based rows of each log; the rows the full calibration rejected, `cross_validate`).
    `start`: the full calibration, whose rejected rows `train` leaves out; the fit is then its warm refit
    (`validation.refit.refit`: 'result' a `Refit`), else a calibration of its own ('result' a
    `CalibrationResult`).
    """
    opt = options or CalibrationOptions()
    if start is not None:
        fitted = refit(start, robot, train, loops, opt)
        res: CalibrationResult | Refit = fitted
    else:
        res = calibrate(robot, train, loops, opt)
        fitted = as_refit(res)
    noise = opt.noise if opt.noise is not None else (fitted.sigma if opt.weighting == "noise" else None)
    if noise is not None and not isinstance(noise, dict) and noise <= 0.0:
        # joint noise estimated at zero beside a measurement's (closedloop.estimate.noise): W_i is that covariance alone
        noise = float(np.finfo(float).tiny)
    skip = np.union1d(fitted.rejected, [] if skip_train is None else skip_train)
    pred = closure_residuals(fitted, robot, test, loops, noise, skip_test)
    own = fitted.problem if fitted.warm else None  # a warm refit's problem is that of `train`, all of its rows
    fit = closure_residuals(fitted, robot, train, loops, noise, skip, own)
    return {"result": res, "train": fit, "test": pred, "n_train": len(train), "n_test": len(test)}


def _mean_loops(per_fold: list[list[dict]]) -> list[dict]:
    """Per loop, the RMS over folds (weighted by rows) of rms_m / rms_rad and the max of max_*."""
    out = []
    for li in range(len(per_fold[0])):
        rows = [f[li] for f in per_fold]
        n = np.array([r["n"] for r in rows], float)
        d = {"loop": rows[0]["loop"], "n": int(n.sum())}
        for key in ("rms_m", "rms_rad", "rms_px"):
            vals = [r.get(key) for r in rows]
            d[key] = None if any(v is None for v in vals) else float(np.sqrt(np.sum(n * np.array(vals) ** 2) / n.sum()))
        for key in ("max_m", "max_rad", "max_px"):
            given = [v for v in (r.get(key) for r in rows) if v is not None]
            d[key] = float(max(given)) if len(given) == len(rows) else None
        out.append(d)
    return out


def _holdout_job(
    robot: RobotModel, loops: list[Loop], opt: CalibrationOptions, start: CalibrationResult | None, split: tuple
) -> dict[str, Any]:
    """One fold's refit (a job for closedloop.parallel.executor): `split` = (training log, held-out log, rows of
    each not judged, whether the training rows are a sample: then warm from `start`)."""
    return holdout(robot, split[0], split[1], loops, opt, split[2], split[3], start if split[4] else None)


def cross_validate(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    options: CalibrationOptions | None = None,
    k: int = 5,
    seed: int = 0,
    executor=None,
    progress: ProgressReporter | None = None,
    exclude=None,
    parts: list[np.ndarray] | None = None,
    train_without_excluded: bool = False,
    result: CalibrationResult | None = None,
) -> dict[str, Any]:
    """k-fold cross-validation with the same options on every fold.

    `parts`: the held-out sets (0-based rows, disjoint) where they are not the random `folds` (the
    regions of joint space of `closedloop.validation.regions`).

    Each fold trains on, and is judged on, at most `VALIDATION_ROWS` configurations per loop
    (`validation_rows`); 'n_train' and 'n_test' count those.  `result`: the calibration of `log_` with
    `options` whose rejections are `exclude`; with `train_without_excluded`, a fold whose training rows
    are a sample starts at its solution (a warm refit, module docstring; 'warm' says which did).

    `exclude`: rows of `log_` (0-based) whose closure no fold judges, the full calibration's rejected
    outliers (``[rj.row - 1 for rj in result.outliers.rejected]``); they stay in the refits' data, whose outlier
    screen meets them as the full calibration's did, or with `train_without_excluded` are left out of it,
    and the refits reuse that screen's decision (``robust='auto'`` refits screen nothing again: their rows
    are the full calibration's kept rows less the held-out fold, and its robust refit costs many times a
    clean fit).  `exclude` must then be the rejections of a calibration with `options` on `log_`.

    Returns
      'folds': per fold {'fold', 'n_train', 'n_test', 'train': residuals,
               'test': residuals, 'converged', 'warm', 'values' (name -> value)},
      'excluded': the rows of `exclude`, and per fold 'skipped' (rows not judged:
               under 'train' and 'test', `closure_residuals`),
      'test' / 'train': per loop, residuals pooled over folds (RMS weighted by
               rows; max over folds),
      'test_whitened_rms' / 'train_whitened_rms': mean over folds (None
               without a noise level),
      'parameter_spread': name -> std over folds of the estimated parameters
               (the estimated set is the same in every fold when the
               reduction is structural; names estimated in some folds only
               are listed under 'inconsistent').
    The refits run on `executor` (an engine or its name, closedloop.parallel.executor;
    None: this process, in fold order, or where every refit is warm on threads of it, `ThreadEngine`, each
    on a problem of its own); the result is the same on any engine.
    `progress` is told ``("validating", folds finished, k)`` as each refit finishes (on a long log each
    takes a second or more).
    """
    opt = options or CalibrationOptions()
    parts = folds(log_, k, seed) if parts is None else parts
    per_fold = []
    ref = None
    from closedloop.parallel.executor import (
        run,  # the refits run on any engine (closedloop.parallel.executor); results in fold order
    )

    bad = np.zeros(0, dtype=int) if exclude is None else np.unique(np.asarray(exclude, dtype=int))
    splits = []
    is_bad = np.zeros(len(log_), dtype=bool)  # masks, not set operations: a long log's folds in O(N)
    is_bad[bad] = True
    for rows in parts:
        kept = np.ones(len(log_), dtype=bool)
        kept[rows] = False
        if train_without_excluded:
            kept &= ~is_bad
        rest = np.flatnonzero(kept)
        train = validation_rows(log_, rest)
        rows = validation_rows(log_, rows)
        splits.append(
            (
                subset(log_, train),
                subset(log_, rows),
                np.flatnonzero(is_bad[train]),
                np.flatnonzero(is_bad[rows]),
                train.size < rest.size,  # a sample of a long log's training rows: warm from `result`
            )
        )
    # the full calibration's screen decision reused (docstring): its rejected rows are out of every refit's data
    refit_opt = replace(opt, robust=None) if train_without_excluded and opt.robust == "auto" else opt
    start = result if train_without_excluded else None  # a warm refit reuses the calibration's screen
    shared = (robot, loops, refit_opt, start)
    if executor is None and start is not None and len(splits) > 1 and all(sp[4] for sp in splits):
        executor = ThreadEngine(chunk_threads(len(splits)))  # warm refits, each on a problem of its own
    refits = run(_holdout_job, splits, executor, shared=shared, progress=progress, task="validating")
    for f, ho in enumerate(refits):
        fit = ho["result"] if isinstance(ho["result"], Refit) else as_refit(ho["result"])
        ref = fit.values if ref is None else ref
        vals = unwrap(fit.problem, fit.values, ref)  # closure rotation vectors on one branch
        per_fold.append(
            {
                "fold": f,
                "n_train": ho["n_train"],
                "n_test": ho["n_test"],
                "train": ho["train"],
                "test": ho["test"],
                "converged": fit.converged,
                "warm": fit.warm,
                "values": {fit.problem.names[i]: float(vals[i]) for i in fit.estimated},
            }
        )
    names = sorted(set.union(*(set(p["values"]) for p in per_fold)))
    common = [n for n in names if all(n in p["values"] for p in per_fold)]
    spread = {n: float(np.std([p["values"][n] for p in per_fold], ddof=1)) for n in common}

    def _mean(key, part):
        vals = [p[part][key] for p in per_fold]
        return None if any(v is None for v in vals) else float(np.mean(vals))

    return {
        "k": k,
        "seed": seed,
        "folds": per_fold,
        "excluded": bad.tolist(),
        "test": _mean_loops([p["test"]["loops"] for p in per_fold]),
        "train": _mean_loops([p["train"]["loops"] for p in per_fold]),
        "test_whitened_rms": _mean("whitened_rms", "test"),
        "train_whitened_rms": _mean("whitened_rms", "train"),
        "parameter_spread": spread,
        "inconsistent": [n for n in names if n not in common],
    }
