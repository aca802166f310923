"""Configurations the noise cannot explain: found by a robust refit, left out of the final fit.

A log may hold rows that are not closures of the loop at all (a reading taken
while the tool slipped, a row of another robot, a corrupted cell).  Least
squares on them is dragged anywhere.  `reject_outliers` screens the first
fit: per configuration the standardized closure error d_i (`robust`), with
d_i^2 against chi2_m at level 1 - alpha / N (Bonferroni).  If any is beyond,
the fit is redone from the start with Cauchy weights 1 / (1 + (d/c)^2)
(iteratively reweighted, the scale re-estimated by the MAD at each pass), which
gross errors cannot drag; the configurations beyond the threshold at that
robust fit are rejected and the problem rebuilt on the rest.  Rejection needs
a clear majority of inliers: with half the rows or more flagged nothing is
rejected and the verdict reports the misfit.

The metric is the noise model's own (`screen`): beside a tracker's stated noise
the unknown joint level is the median configuration's (`screen_sigma`), and a
fit's closures are studentized by each row's share of that fit (`_studentized`),
so that clean rows cross the threshold about as often as its level says (alpha per calibration).

`irls_fit` is the older option (``robust='huber'|'cauchy'``): the weights are
kept in the final fit and the suspects reported, nothing is removed.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from closedloop.estimate import residual
from closedloop.estimate.lm import SolverOptions, levenberg_marquardt
from closedloop.estimate.residual import ResidualFunction, weighted_stage
from closedloop.estimate.robust import (
    cauchy_weights,
    component_standardized,
    flagged,
    mad_scale,
    median_joint_scale,
    standardized,
    studentize,
)
from closedloop.estimate.robust import suspects as find_suspects
from closedloop.estimate.robust import weights as robust_weights
from closedloop.problem.problem import CalibrationProblem
from closedloop.records import Rejected

if TYPE_CHECKING:
    from closedloop.estimate.residual import Fit
    from closedloop.records import CalibrationOptions

log = logging.getLogger(__name__)
# below these a closure error is never an outlier (a micrometre, a microradian, a thousandth of a pixel):
# a fit at round-off or at a simulator's residual compliance is not screened
SCALE_FLOOR = {"m": 1e-6, "rad": 1e-6, "px": 1e-3}


def _floors(problem: CalibrationProblem) -> list[np.ndarray]:
    out = []
    for b in problem.blocks:
        fl = np.full(b.loop.dim, SCALE_FLOOR["m"])
        fl[list(b.loop.rotation_rows)] = SCALE_FLOOR["rad"]
        fl[list(b.loop.pixel_rows)] = SCALE_FLOOR["px"]
        out.append(fl)
    return out


def screen(
    problem: CalibrationProblem,
    x: np.ndarray,
    sigma_q: np.ndarray,
    known: bool = False,
    est: list[int] | None = None,
    weights: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Standardized closure error per configuration (per block), at `x`.

    `est`: the parameters a fit at `x` estimated, with `weights` the weight it gave each configuration
    (None: 1 each, over the problem's configurations in block order): each closure is then studentized
    by its own spread under that fit (`_studentized`), so that neither the rows the fit leans on nor the
    rows it left out are read as outliers for the share of the noise the fit took or did not take.
    None (a start, no fit): the closures as they are.

    With the noise weighting, in robust standard deviations (the MAD of the
    whitened closures' components, pooled); with a `known` joint noise, never
    in units smaller than that noise: data better than the stated noise have
    no outliers (a simulator's compliance at 1e-7 rad is not a gross error).
    The closures are whitened by the inverse Cholesky factor of W_i (`noise.whiten`,
    `symmetric` False): under the noise model the components of F r_i are
    independent N(0, 1) for any F with F^T F = W_i^-1, so their MAD estimates
    the same scale as the symmetric root's, without an eigendecomposition per
    configuration (the norms |F r_i| are the same for any root).

    The metric does not depend on the fit's own weighting (`_screen_weighting`).  Loops with task-space
    noise (`variance.task_blocks`: contact play) are screened on the unweighted closure: the joint-noise
    weighting would read their isotropic noise as outliers."""
    sig = screen_sigma(problem, x, sigma_q, known)
    if est is not None and est and _screen_weighting(problem) == "noise" and _rows(problem) <= STUDENTIZE_ROWS:
        return _standardized(problem, _studentized(problem, x, est, sig, weights, known), known)
    return _standardized(problem, _closures(problem, x, sig), known)


#: residual rows up to which the screen studentizes a fit's closures (`_studentized`); beyond, each row's
#: share of the fit (p / M on average) is too small to matter and J would be large
STUDENTIZE_ROWS = 20000


def _rows(problem: CalibrationProblem) -> int:
    return sum(b.theta.shape[0] * b.loop.dim for b in problem.blocks)


def _studentized(
    problem: CalibrationProblem,
    x: np.ndarray,
    est: list[int],
    sigma_q: np.ndarray,
    weights: np.ndarray | None,
    known: bool,
) -> list[np.ndarray]:
    """The whitened closures at a fit with the parameters `est` and configuration `weights`, studentized
    (`robust.studentize`): each divided by its own spread under that fit.

    On a plane loop (one row per configuration, 23 parameters, 100 configurations) the rows that alone
    fix a direction close far better than the noise, and the rows a refit down-weighted or left out far
    worse: read against the noise alone, 10 of 100 clean configurations were rejected.
    """
    f = ResidualFunction(problem, x, list(est), sigma_q, "noise")
    r, J = f(x[est], True)
    dims = [b.loop.dim for b in problem.blocks]
    counts = [b.theta.shape[0] for b in problem.blocks]
    sizes = np.cumsum([n * m for n, m in zip(counts, dims)])[:-1]
    J = np.asarray(J)
    rb = [p.reshape(n, m) for p, n, m in zip(np.split(r, sizes), counts, dims)]
    Jb = [p.reshape(n, m, -1) for p, n, m in zip(np.split(J, sizes), counts, dims)]
    w = np.ones(sum(counts)) if weights is None else np.asarray(weights, float)
    # the fit's truncation (`lm`): directions below snr x the noise level, in the columns scaled by the priors
    level = 1.0 if known else max(mad_scale(rb), SCALE_FLOOR["rad"])
    prior = np.array([problem.params[k].prior for k in est], dtype=float)
    return studentize(rb, Jb, np.split(w, np.cumsum(counts)[:-1]), prior, TRUNCATION_SNR * level)


#: the solver's default truncation (`CalibrationOptions.snr`): the screen's fits are the default ones
TRUNCATION_SNR = 1.0


def screen_sigma(problem: CalibrationProblem, x: np.ndarray, sigma_q: np.ndarray, known: bool) -> np.ndarray:
    """The joint noise the screen whitens with at `x`: `sigma_q`, rescaled where it is not known and a loop
    measures with a known covariance (a tracker's sigma_t).

    With a measurement covariance C_i beside the joint noise, W_i = J_theta,i Sigma J_theta,i^T + C_i
    (eq. 3.17) has a shape that depends on the ratio of the two: an unknown joint noise taken at its
    pattern (1 rad) reads the tracker's isotropic noise as joint noise, and whitening by J_theta,i^-1
    amplifies it wherever the arm's Jacobian is small (120 clean configurations of the ur5 tracker scenario:
    13 rejected at chi2 standardized closures up to 18).  The joint level is estimated here at the median
    configuration (`robust.median_joint_scale`), which gross errors cannot drag, so the screen's metric
    is the noise model's own.  Known distances (`parameter_only` blocks) do not enter the estimate.
    """
    if known or _screen_weighting(problem) != "noise":
        return sigma_q
    blocks = [
        bi
        for bi, b in enumerate(problem.blocks)
        if not getattr(b.loop, "parameter_only", False) and b.theta.shape[0] > 0
    ]
    if not any(problem.noise[bi].measurement_cov is not None for bi in blocks):
        return sigma_q
    evals = problem.evaluate(x, True, columns=[])
    res, jq = [], []
    for bi in blocks:
        ev = evals[bi]
        ok = np.all(ev.valid, axis=1) if ev.valid is not None else slice(None)  # rows with every observation
        res.append(ev.r[ok])
        jq.append(np.asarray(ev.Jq)[ok])
    s = median_joint_scale(res, jq, [problem.noise[bi].measurement_cov for bi in blocks], sigma_q)
    # a floor: the screen's whitening stays defined where the joints carry no noise at all
    return np.sqrt(max(s, 1e-24)) * sigma_q


def _closures(problem: CalibrationProblem, x: np.ndarray, sigma_q: np.ndarray) -> list[np.ndarray]:
    """The closures at `x` per configuration (per block) in the screen's metric (`screen`), whitened with
    the joint noise `sigma_q` (`screen_sigma`'s)."""
    if _screen_weighting(problem) == "noise":
        return ResidualFunction(problem, x, [], sigma_q, "noise").blocks(np.zeros(0), symmetric=False)
    return ResidualFunction(problem, x, [], sigma_q, "none").blocks(np.zeros(0))


def _level(blocks: list[np.ndarray], known: bool) -> float:
    """The noise level of whitened closures `blocks` (`_closures`) in the screen's metric: their robust scale,
    never below a known noise's 1 nor, unknown, below the floor of exact data (`SCALE_FLOOR`)."""
    return max(mad_scale(blocks), 1.0 if known else SCALE_FLOOR["rad"])


def _standardized(problem: CalibrationProblem, blocks: list[np.ndarray], known: bool) -> list[np.ndarray]:
    """`screen`'s d_i of the closures `blocks` (`_closures`)."""
    if _screen_weighting(problem) == "noise":
        out = standardized(blocks, _level(blocks, known))
    else:
        out = component_standardized(blocks, _floors(problem))
    # a known distance (closedloop.problem.distances) is no configuration: never an outlier
    return [np.zeros_like(d) if getattr(b.loop, "parameter_only", False) else d for d, b in zip(out, problem.blocks)]


def _spread(problem: CalibrationProblem, blocks: list[np.ndarray]) -> float:
    """The median configuration's closure (`_closures`; metres and radians in units of SCALE_FLOOR where
    unweighted): what the robust refit's passes are ranked by (least median of squares)."""
    norms = [
        np.linalg.norm(b if _screen_weighting(problem) == "noise" else b / fl, axis=1)
        for b, fl, bl in zip(blocks, _floors(problem), problem.blocks)
        if b.size and not getattr(bl.loop, "parameter_only", False)
    ]
    return float(np.median(np.concatenate(norms))) if norms else 0.0


ROBUST_ROWS = 2048  # configurations per block the robust refit is solved on (`robust_refit`)
#: the robust refit's passes stop at a relative cost decrease of 1e-6 (the final fit's 1e-10): each pass only
#: sets the next pass's weights, and the screen's threshold is no sharper than its closures' scale
REFIT_FTOL, REFIT_XTOL = 1e-6, 1e-6


def robust_refit(
    problem: CalibrationProblem,
    x0: np.ndarray,
    est: list[int],
    sigma_q: np.ndarray,
    max_iter: int = 30,
    passes: int = 8,
    known: bool = False,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """IRLS with the Cauchy loss from x0 (the screening residual, `screen`); returns x and the d_i there.

    Each pass's weights come from the closures where the pass before ended; the passes may wander (a
    reweighted fit of a nonlinear model is no contraction: the xArm weld, 14 of 100 rows with joint4 off
    by 0.1 rad, had the 14 among 18 flagged after one pass, then 67, 21, 44 ... 79, and nothing was
    rejected).  Of the points the passes reach, x0 included, the one whose median configuration closes
    best (`_spread`: least median of squares, which 49 % of outliers cannot drag) is returned.

    On a long log the refit is solved on ROBUST_ROWS configurations of each block, evenly spaced along it
    (`CalibrationProblem.sampled`: outliers as frequent as in the whole), and every row is screened at its
    solution.  The refit's x only has to be where gross errors did not drag it (the final fit on the rows
    kept is the estimator), and on 2,048 configurations its closures' scale is as well estimated.
    """
    key = (x0.tobytes(), tuple(est), sigma_q.tobytes(), max_iter, passes, known)
    if not (_LAST_REFIT and _LAST_REFIT[0] is problem and _LAST_REFIT[1] == key):
        _LAST_REFIT[:] = [problem, key, _robust_refit(problem, x0, est, sigma_q, max_iter, passes, known)]
    x, ds = _LAST_REFIT[2]
    return x.copy(), [d.copy() for d in ds]


#: the last `robust_refit` (the problem itself, its arguments, its result): the refit depends on neither the
#: fit's weighting nor its estimator, and a calibration that re-solves with another asks for the same one
_LAST_REFIT: list = []


def _robust_refit(
    problem: CalibrationProblem,
    x0: np.ndarray,
    est: list[int],
    sigma_q: np.ndarray,
    max_iter: int,
    passes: int,
    known: bool,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """`robust_refit` itself."""
    scale = np.array([p.prior for p in problem.params])
    sample = problem.sampled(ROBUST_ROWS)
    dims = [b.loop.dim for b in sample.blocks]
    sopt = SolverOptions(max_iter=max_iter, ftol=REFIT_FTOL, xtol=REFIT_XTOL)
    weighting = _screen_weighting(sample)
    x, w_prev = x0.copy(), None
    best: tuple[float, np.ndarray, list[np.ndarray]] = (np.inf, x0, [])
    for _ in range(passes):
        sig = screen_sigma(sample, x, sigma_q, known)  # the pass's fit is weighted as it is screened
        blocks = _closures(sample, x, sig)
        best = min(best, (_spread(sample, blocks), x, blocks), key=lambda b: b[0])
        w = np.concatenate(cauchy_weights(_standardized(sample, blocks, False), dims))
        row_w = np.repeat(np.sqrt(w), [b.loop.dim for b in sample.blocks for _ in range(b.theta.shape[0])])
        # The pass's whitening held with its weights: one weighted least-squares problem per pass.  Its
        # truncation is at the closures' robust scale, the noise level the screen reads them at: the pass
        # never crawls along directions that noise hides (each pass only sets the next one's weights).
        fun = ResidualFunction(sample, x, est, sig, weighting, row_w, frozen=True)
        level = _level(blocks, known) if weighting == "noise" else None
        x = fun.full(levenberg_marquardt(fun, x[est], scale[est], replace(sopt, noise=level)).x)
        if w_prev is not None and np.max(np.abs(w - w_prev)) < 1e-3:
            break
        w_prev = w
    blocks = _closures(sample, x, screen_sigma(sample, x, sigma_q, known))
    spread = _spread(sample, blocks)
    if spread > best[0]:
        log.info(
            "the robust refit's passes wandered off (median closure %.3g, %.3g before): the best pass kept",
            spread,
            best[0],
        )
        x, blocks = best[1], best[2]
    if sample is not problem:  # a long log: each row's share of the fit is negligible
        return x, screen(problem, x, sigma_q, known)
    # screened as the refit weighs them (`screen`): a row it down-weighted is not also counted against it
    w = np.concatenate(cauchy_weights(_standardized(problem, blocks, False), dims))
    return x, screen(problem, x, sigma_q, known, est, w)


def _screen_weighting(problem: CalibrationProblem) -> str:
    """The screen's metric: the joint-noise whitening (eq. 3.17) whatever the fit's own weighting, unless
    loops carry contact play (`variance.task_blocks`), whose isotropic noise it would read as outliers.

    An unweighted fit screened on its raw closures flags clean configurations where the Jacobian
    amplifies the joint noise: on the Monte Carlo weld (200 configurations, 1e-4 rad), every unweighted
    calibration went through the robust refit and 7 of 20 rejected one or two clean rows."""
    from closedloop.estimate.variance import task_blocks

    return "none" if task_blocks(problem) else "noise"


def gross_outliers(
    problem: CalibrationProblem, x0: np.ndarray, est: list[int], sigma_q: np.ndarray, opt: CalibrationOptions
) -> bool:
    """Configurations whose closure at the start is far beyond what the model fitted to the others explains.

    At the nominal model the closures carry its error, smooth over the workspace: every joint origin
    millimetres off spreads the closures well past a median's, and their tails cross the threshold
    (`screen`) on a clean log.  That is what calibration fixes, not outliers.  So the configurations
    flagged at `x0` are left out of one short fit of the parameters `est` from `x0` on the others
    (`_fit_without`, in the screen's own metric), and the start screen fires only if some configuration
    is still beyond the threshold there (the flagged ones studentized as left out, `screen`): a reading
    no model explains (a corrupted cell, a slipped tool) stays far from any fit of the rest.  Where the
    rest has fewer closure rows than twice the parameters, it cannot say what the model is: it fires.

    A start screen that does not fire leaves the outliers to the screen after the first fit
    (`reject_outliers` with that fit), which runs the same robust refit when any are beyond.
    """
    dims = [b.loop.dim for b in problem.blocks]
    known = opt.noise is not None
    flags = flagged(screen(problem, x0, sigma_q, known), dims, opt.outlier_alpha)
    n_flagged = sum(f.size for f in flags)
    if not n_flagged:
        return False
    rest = sum((b.theta.shape[0] - f.size) * b.loop.dim for b, f in zip(problem.blocks, flags))
    if not est or rest < 2 * len(est):  # too few configurations left to fit the model on
        return True
    x1 = _fit_without(problem.sampled(ROBUST_ROWS), x0, est, sigma_q, known, _log_rows(problem, flags))
    used = _used(problem, _log_rows(problem, flags))
    return any(f.size for f in flagged(screen(problem, x1, sigma_q, known, est, used), dims, opt.outlier_alpha))


def start_screen(
    problem: CalibrationProblem, x0: np.ndarray, est: list[int], sigma_q: np.ndarray, opt: CalibrationOptions
) -> bool:
    """`gross_outliers` at the start; on a long log (a block of `residual.PRESOLVE_ABOVE` configurations or
    more) only where its presolve sample (`residual.presolved`: `PRESOLVE_ROWS` evenly spaced ones per block)
    has one, or where some configuration closes far beyond every one of the sample (`beyond_sample`).

    The start screen whitens every closure, a pass with the joints' Jacobian over the whole log (the
    largest part of a pass).  Gross errors are what it is for: the nominal model's error spreads the
    start's closures, so nothing subtler stands out there (those rows are left to the screen at the fit,
    `reject_outliers`, as on a short log).  A gross error stands out in the raw closure too, which the
    start's statistics read anyway (a pass without Jacobians); the sample, which the presolve is solved
    on, is screened itself, whitened.  A log where either finds one is screened whole, as a short one."""
    if all(b.theta.shape[0] < residual.PRESOLVE_ABOVE for b in problem.blocks):
        return gross_outliers(problem, x0, est, sigma_q, opt)
    sample = problem.sampled(residual.PRESOLVE_ROWS)
    sample.evaluate(x0, True, columns=est)  # kept by the sample: its presolve's first evaluation, the screen's Jq
    if gross_outliers(sample, x0, est, sigma_q, opt) or beyond_sample(problem, sample, x0):
        log.info("the start's closures hold a gross error: every configuration screened")
        return gross_outliers(problem, x0, est, sigma_q, opt)
    return False


#: `beyond_sample`: a configuration closing this many times worse than the worst of an even sample of its log
#: (per loop and residual component, raw) is a gross error.  Clean rows beyond the sample's worst are drawn from
#: the same smooth model error and noise: of 100,000 normal draws the largest is 1.13 times that of 8,192
FAR_FACTOR = 4.0


def beyond_sample(problem: CalibrationProblem, sample: CalibrationProblem, x: np.ndarray) -> bool:
    """Whether some configuration of `problem` closes at `x` more than `FAR_FACTOR` times worse than every
    configuration of `sample` (an even sample of it), in some residual component of some loop (raw closures,
    the sample's worst floored at `SCALE_FLOOR`), or not at all (a non-finite closure)."""
    for e, es, fl in zip(problem.evaluate(x, False), sample.evaluate(x, False), _floors(problem)):
        if not e.r.size:
            continue
        if np.isinf(e.r).any():  # NaN: a row with no observation (`BlockEval.valid`)
            return True
        worst = np.maximum(np.nanmax(np.abs(es.r), axis=0, initial=0.0), fl)
        if np.any(np.abs(np.nan_to_num(e.r, nan=0.0)) > FAR_FACTOR * worst):
            return True
    return False


#: the start screen's fit of the rows not flagged (`gross_outliers`): a few iterations from the nominal model,
#: which is millimetres from the solution; it only has to remove the model error's smooth share
SCREEN_FIT_ITER = 10


def _log_rows(problem: CalibrationProblem, flags: list[np.ndarray]) -> list[np.ndarray]:
    """Per block, the log rows (`LoopBlock.rows`) of its configurations `flags` (indices)."""
    return [np.asarray(b.rows)[f] for b, f in zip(problem.blocks, flags)]


def _used(problem: CalibrationProblem, out: list[np.ndarray]) -> np.ndarray:
    """1 per configuration of `problem` (block order), 0 for those whose log rows are in `out` (per block)."""
    return np.concatenate([np.where(np.isin(b.rows, o), 0.0, 1.0) for b, o in zip(problem.blocks, out)])


def _fit_without(
    problem: CalibrationProblem, x0: np.ndarray, est: list[int], sigma_q: np.ndarray, known: bool, out: list
) -> np.ndarray:
    """The parameters `est` fitted from `x0` to the configurations of `problem` whose log rows are not in `out`
    (per block; those weigh 0), in the screen's metric (`screen_sigma`, `_screen_weighting`); a short solve
    (`SCREEN_FIT_ITER`).  On a long log `problem` is an even sample of it (`ROBUST_ROWS`, as the robust refit)."""
    scale = np.array([p.prior for p in problem.params])
    sopt = SolverOptions(max_iter=SCREEN_FIT_ITER, ftol=REFIT_FTOL, xtol=REFIT_XTOL)
    used = _used(problem, out)
    row_w = np.repeat(used, [b.loop.dim for b in problem.blocks for _ in range(b.theta.shape[0])])
    sig = screen_sigma(problem, x0, sigma_q, known)
    st = weighted_stage(problem, x0, x0[est], est, scale, sig, _screen_weighting(problem), sopt, None, row_w)
    return st.fun.full(st.solution.x)


def reject_outliers(
    problem: CalibrationProblem,
    x_fit: np.ndarray | None,
    x0: np.ndarray,
    est: list[int],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    n_rows: int,
) -> tuple[CalibrationProblem, list[Rejected], np.ndarray] | None:
    """The problem without its outliers, the rejected configurations and the robust fit; None if clean.

    `x_fit`: a fit on every row to screen first (None: straight to the robust refit); `n_rows`: the
    log's rows (no more than half of them are rejected).  The problem on the rest is `problem`'s
    blocks without the rejected rows (`CalibrationProblem.without_rows`).
    """
    dims = [b.loop.dim for b in problem.blocks]
    if x_fit is not None and not any(
        f.size for f in flagged(screen(problem, x_fit, sigma_q, opt.noise is not None, est), dims, opt.outlier_alpha)
    ):
        return None
    x_r, ds = robust_refit(problem, x0, est, sigma_q, min(opt.max_iter, 30), known=opt.noise is not None)
    flags = flagged(ds, dims, opt.outlier_alpha)
    bad_rows = sorted({int(problem.blocks[bi].rows[i]) for bi, f in enumerate(flags) for i in f})
    if not bad_rows:
        return None
    if len(bad_rows) >= 0.5 * n_rows:
        log.info("%d of %d configurations look like outliers: too many to reject", len(bad_rows), n_rows)
        return None
    evals = problem.evaluate(x_r, False)
    rejected = []
    for bi, f in enumerate(flags):
        b = problem.blocks[bi]
        for i in f:
            r = evals[bi].r[i]
            t = float(np.linalg.norm(r[list(b.loop.translation_rows)])) if b.loop.translation_rows else None
            w = float(np.linalg.norm(r[list(b.loop.rotation_rows)])) if b.loop.rotation_rows else None
            rejected.append(Rejected(int(b.rows[i]), b.loop.name, float(ds[bi][i]), t, w))
    log.info("rejected %d outlier configurations", len(bad_rows))
    return problem.without_rows(bad_rows), sorted(rejected, key=lambda r: -r.standardized), x_r


def irls_fit(problem: CalibrationProblem, fit: Fit, opt: CalibrationOptions, notes: list[str], row_name=None):
    """Reweighted fits with the chosen loss (``robust='huber'|'cauchy'``); suspects noted (by `row_name`:
    0-based row -> ``log.csv line 52``), none removed."""
    loss = opt.robust
    if loss is None:
        raise ValueError("irls_fit: no robust loss chosen (CalibrationOptions.robust)")
    scale = np.array([p.prior for p in problem.params])
    known_scale = 1.0 if fit.known and opt.weighting == "noise" else None
    sopt = SolverOptions(
        max_iter=opt.max_iter, noise=(1.0 if fit.known and opt.weighting == "noise" else None), snr=opt.snr
    )
    est, xe, w_prev, st = fit.est, fit.x[fit.est], None, fit.stage
    for _ in range(10):
        blocks = replace(st.fun, row_weights=None).blocks(xe)
        w = np.concatenate(robust_weights(blocks, loss, scale=known_scale))
        row_w = np.repeat(np.sqrt(w), [b.loop.dim for b in problem.blocks for _ in range(b.theta.shape[0])])
        st = weighted_stage(problem, fit.x, xe, est, scale, fit.sigma_q, opt.weighting, sopt, None, row_w)
        xe = st.solution.x
        if w_prev is not None and np.max(np.abs(w - w_prev)) < 1e-3:
            break
        w_prev = w
    blocks = replace(st.fun, row_weights=None).blocks(xe)
    sus = find_suspects(
        blocks,
        rows=[b.rows for b in problem.blocks],
        loops=[b.loop.name for b in problem.blocks],
        loss=loss,
        scale=known_scale,
    )
    name = (lambda row: row_name(row - 1)) if row_name is not None else (lambda row: f"log row {row}")
    for sp in sus[:10]:
        notes.append(
            f"suspect configuration: {name(sp.row)} (loop {sp.loop}): closure error "
            f"{sp.standardized:.3g} standard deviations, weight {sp.weight:.2g}"
        )
    if len(sus) > 10:
        notes.append(f"... and {len(sus) - 10} more suspect configurations")
    fit.stage, fit.x = st, st.fun.full(xe)
    return fit, sus


def readmit(
    problem_all: CalibrationProblem,
    x: np.ndarray,
    rejected: list[Rejected],
    opt: CalibrationOptions,
    sigma_q: np.ndarray,
    est: list[int] | None = None,
) -> tuple[CalibrationProblem, list[Rejected]] | None:
    """The rejection re-checked at the solution: rejected configurations the final fit explains come back.

    A robust refit from a far start may stop short of the solution and
    flag good configurations there.  At the final `x` every configuration
    of the whole log is screened again (`screen`, the same Bonferroni
    threshold); those of `rejected` that are no longer beyond it are
    readmitted.  `problem_all`: the problem on the whole log.  `est`: the
    parameters the final fit estimated; the closures are then studentized
    as that fit saw them (`screen`: the rows it used, the rejected ones as
    left out).  Returns the problem without the configurations still
    rejected and their records, or None when every rejection holds.
    """
    dims = [b.loop.dim for b in problem_all.blocks]
    out = {r.row for r in rejected}
    used = np.concatenate([[0.0 if int(row) in out else 1.0 for row in b.rows] for b in problem_all.blocks])
    ds = screen(problem_all, x, sigma_q, opt.noise is not None, est, used)
    flags = flagged(ds, dims, opt.outlier_alpha)
    still = {int(problem_all.blocks[bi].rows[i]) for bi, f in enumerate(flags) for i in f}
    kept_out = [r for r in rejected if r.row in still]
    if len(kept_out) == len(rejected):
        return None
    log.info("readmitted %d configurations the solution explains", len(rejected) - len(kept_out))
    return problem_all.without_rows([r.row for r in kept_out]), kept_out
