"""Monte Carlo check of the estimator against the Cramer-Rao bound.

From a truth (parameter values and joint readings that close the loops
exactly) simulate M datasets by adding Gaussian noise to the readings,
calibrate each one with the noise-weighted (errors-in-variables) estimator and
with the plain unweighted one, and compare the empirical covariance of the
estimates with the Cramer-Rao bound at the truth,

    CRB = (sum_i J_i^T W_i^-1 J_i)^-1,   W_i = J_theta,i Sigma_q J_theta,i^T,

over the estimated parameters (J_i, J_theta,i evaluated at the true values and
the exact readings).  This is the bound of the implicit-loop (errors-in-
variables) model of Wampler, Hollerbach & Arai 1995 to first order in the
noise.  For the unweighted estimator the first-order (sandwich) covariance
(J^T J)^-1 J^T W J (J^T J)^-1 is reported too.

Comparison statistics, per estimator:

* ``trace_ratio``: tr(cov_emp) / tr(CRB), physical units (m, rad mixed, as
  the parameters are); ``trace_ratio_scaled`` in prior-scaled units;
* ``efficiency``: tr(CRB^-1 cov_emp) / L, coordinate-free (1 for an
  efficient estimator, the mean eigenvalue of CRB^-1/2 cov_emp CRB^-1/2);
* ``bias_over_se``: (mean - truth) / sqrt(diag CRB), the bias in units of
  the parameter's standard error; ``bias_t``: (mean - truth) /
  (std_emp / sqrt(M)), its t-statistic; ``bias_chi2`` = M b^T CRB^-1 b,
  ~ chi2(L) when unbiased and efficient.

Closure rotation vectors are unwrapped to the representative nearest the true
one before any comparison (r and r/|r| (|r| - 2 pi k) are the same rotation).
"""

from __future__ import annotations

import site
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from closedloop.analysis.observability import whitened_blocks
from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate
from closedloop.errors import ClosedLoopError
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.problem.unwrap import unwrap
from closedloop.progress import ProgressReporter


# --------------------------------------------------------------------------- scenario
@dataclass
class Scenario:
    """A truth: robot, loops, exact readings on the true closure manifold, true parameter values."""

    robot: RobotModel
    joints: list[str]
    loops: list[Loop]
    theta: np.ndarray  # (N, n_joints) exact readings (problem.joints order)
    truth: dict[str, float]  # every parameter of the problem, by name
    pool: np.ndarray | None = None  # optional extra exact readings (held-out / candidates)

    def log(self, theta: np.ndarray | None = None) -> JointLog:
        return JointLog(list(self.joints), np.array(self.theta if theta is None else theta, float))

    def truth_vector(self, problem: CalibrationProblem) -> np.ndarray:
        return np.array([self.truth[n] for n in problem.names])


def panda_urdf() -> str:
    return site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf"


def weld_scenario(
    n: int = 200,
    seed: int = 0,
    n_pool: int = 0,
    theta0=(0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8),
    stride: int = 3,
    pool: str = "walk",
) -> Scenario:
    """The 7-DOF Panda welded to a fixture at the hand: truth drawn in the identifiable set.

    `n` exact configurations along the self-motion (one every `stride` steps
    of 0.04 rad), and `n_pool` more in `pool`: with pool='walk' the walk
    continued (it bounces between the joint limits, so it revisits the same
    arc), with pool='manifold' `n_pool` configurations evenly spaced along the
    whole self-motion through the start pose, from joint limit to joint limit
    (``self_motion_manifold``): every configuration the robot can reach
    while holding the fixture on that branch.  `theta` is the same either way.
    """
    if pool not in ("walk", "manifold"):
        raise ValueError(f"pool must be 'walk' or 'manifold', not '{pool}'")
    from closedloop.loops import WeldLoop
    from closedloop.studies.identifiable import identifiable_names
    from closedloop.studies.synthetic import self_motion
    from closedloop.studies.truth import draw_truth

    rng = np.random.default_rng(seed)
    robot = RobotModel.from_file(panda_urdf())
    joints = robot.supporting_joints("panda_hand")
    loop = WeldLoop("fixture", "panda_hand")
    th_start = np.atleast_2d(np.asarray(theta0, float))
    names = identifiable_names(robot, [loop], th_start)
    tv = draw_truth(robot, names, rng)
    prob = CalibrationProblem(robot, joints, [LoopBlock(loop, th_start, np.arange(1))])
    truth = prob.nominal.copy()
    for k, v in tv.items():
        truth[prob.index[k]] = v
    th0 = (th_start - truth[prob.rp.offset_index()]) / truth[prob.rp.scale_index()]
    TA, TB = prob.loop_poses(truth, 0, th0)
    X = pin.SE3(TA[0])
    truth[prob.loop_slices[0]] = np.r_[X.translation, pin.log3(X.rotation)]
    if pool == "walk":
        th = self_motion(prob, truth, th0, n + n_pool, rng, stride=stride)
        extra = th[n:] if n_pool else None
    else:  # the walk's first n configurations are the same as above (sequential draws)
        th = self_motion(prob, truth, th0, n, rng, stride=stride)
        extra = self_motion_manifold(prob, truth, th0, n_pool) if n_pool else None
    return Scenario(
        robot,
        list(joints),
        [WeldLoop("fixture", "panda_hand")],
        th[:n],
        dict(zip(prob.names, map(float, truth))),
        extra,
    )


def self_motion_manifold(
    problem: CalibrationProblem,
    values: np.ndarray,
    theta0: np.ndarray,
    n: int,
    block: int = 0,
    margin: float = 0.05,
    step: float = 0.02,
) -> np.ndarray:
    """`n` readings evenly spaced (joint-space arc length) along the whole one-dimensional self-motion
    of loop `block` through `theta0`, at `values`.

    The curve {theta : loop closes} is traced both ways from theta0 (predictor: the null vector of
    the closure Jacobian d r / d theta, corrector: Gauss-Newton back onto the loop,
    ``synthetic.close``) in steps of `step` rad, until a joint comes within `margin` of its limit
    (failed steps are halved, down to step/64, so the ends sit at the limits) or the curve closes
    on itself.  The traced polyline is resampled at n equally spaced arc lengths and every sample
    is corrected onto the loop again (batched Gauss-Newton, minimum-norm steps).  Raises
    NotIdentifiableError when the self-motion is not one-dimensional.
    """
    from closedloop.errors import NotIdentifiableError
    from closedloop.studies.synthetic import close

    robot = problem.robot
    lo = np.array([robot.joint(j).lower for j in problem.joints]) + margin
    hi = np.array([robot.joint(j).upper for j in problem.joints]) - margin
    scale = values[problem.rp.scale_index()]
    off = values[problem.rp.offset_index()]
    thetas = [b.theta[:1] for b in problem.blocks]
    name = problem.blocks[block].loop.name

    def jq(th):
        thetas[block] = np.atleast_2d(th)
        return problem.evaluate(values, True, thetas, columns=[])[block].Jq

    def tangent(th, prev):
        _, S, Vt = np.linalg.svd(jq(th)[0])
        rank = int(np.sum(S > 1e-9 * S[0]))
        if Vt.shape[0] - rank != 1:
            raise NotIdentifiableError(f"the self-motion of loop {name} is {Vt.shape[0] - rank}-dimensional, not 1")
        t = Vt[-1]
        return -t if prev is not None and t @ prev < 0 else t

    def inside(th):
        a = th * scale + off
        return bool(np.all(a >= lo) and np.all(a <= hi))

    start, err = close(problem, values, np.atleast_2d(theta0), block)
    start = start[0]
    if err > 1e-9 or not inside(start):
        raise NotIdentifiableError(f"cannot close loop {name} within the joint limits from the start pose")
    t0 = tangent(start, None)
    halves, closed = [], False
    for sign in (1.0, -1.0):
        out: list[np.ndarray] = []
        th, t, h, walked = start, sign * t0, step, 0.0
        while h >= step / 64 and len(out) < 100000:
            cand, err = close(problem, values, (th + h * t)[None], block)
            cand = cand[0]
            if err > 1e-10 or not inside(cand) or np.linalg.norm(cand - th) > 2 * h:
                h /= 2  # a limit (or a fold) ahead: approach it in shorter steps
                continue
            walked += float(np.linalg.norm(cand - th))
            th, t, h = cand, tangent(cand, t), min(step, 2 * h)
            if walked > 4 * step and np.linalg.norm(th - start) < step:
                closed = True  # back at the start: a closed curve, traced once
                break
            out.append(th)
        halves.append(out)
        if closed:
            break
    if closed:
        poly = np.array([start] + halves[0] + [start])
    else:
        poly = np.array(halves[1][::-1] + [start] + halves[0])
    th = _resample_onto_loop(problem, values, thetas, block, poly, n, closed)
    if not all(inside(x) for x in th):
        raise NotIdentifiableError(f"resampling the self-motion of loop {name} left the loop or the limits")
    return th


def _resample_onto_loop(
    problem: CalibrationProblem,
    values: np.ndarray,
    thetas: list[np.ndarray],
    block: int,
    poly: np.ndarray,
    n: int,
    closed: bool,
) -> np.ndarray:
    """`n` readings at equal arc lengths along the polyline `poly`, each corrected onto loop `block`
    (batched Gauss-Newton, minimum-norm steps); NotIdentifiableError if one does not close."""
    from closedloop.errors import NotIdentifiableError

    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))]
    targets = np.linspace(0.0, s[-1], n, endpoint=not closed)
    th = np.array([np.interp(targets, s, poly[:, c]) for c in range(poly.shape[1])]).T
    for _ in range(20):
        thetas[block] = th
        ev = problem.evaluate(values, True, thetas, columns=[])[block]  # Jq alone
        assert ev.Jq is not None  # evaluated with Jacobians
        r, J = ev.r.reshape(len(th), -1), ev.Jq.reshape(len(th), -1, th.shape[1])
        if np.abs(r).max() < 1e-13:
            break
        th = th - np.einsum("nki,nk->ni", J, np.linalg.solve(J @ np.swapaxes(J, 1, 2), r[..., None])[..., 0])
    thetas[block] = th
    if np.abs(problem.evaluate(values, False, thetas)[block].r).max() > 1e-10:
        raise NotIdentifiableError(
            f"resampling the self-motion of loop {problem.blocks[block].loop.name} left the loop or the limits"
        )
    return th


# --------------------------------------------------------------------------- bound
def cramer_rao(
    problem: CalibrationProblem, truth: np.ndarray, params: list[int], noise, thetas: list[np.ndarray] | None = None
) -> np.ndarray:
    """(sum_i J_i^T W_i^-1 J_i)^-1 over `params` at `truth` (physical units)."""
    from closedloop.estimate.noise import noise_vector

    sigma_q, _ = noise_vector(problem, noise)
    blocks = whitened_blocks(problem, truth, params, sigma_q, "noise", thetas, scaled=False)
    C = np.vstack([J.reshape(-1, len(params)) for _, J in blocks])
    return np.linalg.inv(C.T @ C)


def sandwich_unweighted(
    problem: CalibrationProblem, truth: np.ndarray, params: list[int], noise, thetas: list[np.ndarray] | None = None
) -> np.ndarray:
    """First-order covariance of the unweighted estimator, (J^T J)^-1 J^T W J (J^T J)^-1
    (`estimate.model_error.plain_covariance`)."""
    from closedloop.estimate.model_error import plain_covariance
    from closedloop.estimate.noise import noise_vector

    sigma_q, _ = noise_vector(problem, noise)
    return plain_covariance(problem, truth, params, sigma_q, thetas)


# --------------------------------------------------------------------------- MC
@dataclass
class EstimatorStats:
    weighting: str
    estimates: np.ndarray  # (M, L) unwrapped, physical units
    mean: np.ndarray
    cov: np.ndarray
    bias: np.ndarray
    bias_over_se: np.ndarray  # bias / sqrt(diag CRB)
    bias_t: np.ndarray  # bias / (std_emp / sqrt(M))
    bias_chi2: float  # M b^T CRB^-1 b
    trace_ratio: float
    trace_ratio_scaled: float
    efficiency: float
    failures: int  # runs left out (error, or a different estimated set)
    truncated: int  # runs where the solver truncated a direction below the noise (kept)
    predicted_trace_ratio: float | None = None  # first-order prediction / CRB (1 for 'noise')


@dataclass
class MonteCarloResult:
    names: list[str]  # estimated parameters
    truth: np.ndarray  # (L,)
    crb: np.ndarray  # (L, L)
    n_runs: int
    n_configs: int
    noise: float
    stats: dict[str, EstimatorStats] = field(default_factory=dict)
    tolerance_trace: float = 0.0  # 1-sigma sampling spread of a trace ratio, sqrt(2 tr(CRB^2) / ((M-1) tr(CRB)^2))

    def summary(self) -> str:
        lines = [
            f"Monte Carlo: {self.n_runs} runs, {self.n_configs} configurations, noise {self.noise:g}, "
            f"{len(self.names)} estimated parameters; tr(CRB) = {np.trace(self.crb):.4g}",
            f"  sampling spread of a trace ratio (1 sigma): {self.tolerance_trace:.3f}",
        ]
        for w, s in self.stats.items():
            pred = f", first-order prediction {s.predicted_trace_ratio:.3f}" if s.predicted_trace_ratio else ""
            lines.append(
                f"  weighting={w:5s}: tr(cov)/tr(CRB) = {s.trace_ratio:.3f}{pred} "
                f"(prior-scaled {s.trace_ratio_scaled:.3f}); efficiency tr(CRB^-1 cov)/L = "
                f"{s.efficiency:.3f}; |bias|/se max {np.max(np.abs(s.bias_over_se)):.3f} "
                f"mean {np.mean(np.abs(s.bias_over_se)):.3f}; bias chi2 {s.bias_chi2:.1f} "
                f"(dof {len(self.names)}); max |t| {np.max(np.abs(s.bias_t)):.2f}; failures {s.failures}, truncated {s.truncated}"
            )
        return "\n".join(lines)


def _mc_draw(
    robot: RobotModel,
    joints: list[str],
    loops: list[Loop],
    base: CalibrationOptions,
    noise: float,
    weightings: tuple[str, ...],
    theta: np.ndarray,
) -> list[tuple]:
    """One Monte Carlo draw (a job): per weighting (estimated indices, truncated?, values), or Nones if it failed."""
    out: list[tuple] = []
    for w in weightings:
        opt = CalibrationOptions(**{**base.__dict__, "noise": noise, "weighting": w})
        try:
            res = calibrate(robot, JointLog(list(joints), np.array(theta, float)), loops, opt)
        except ClosedLoopError:
            out.append((None, None, None))
            continue
        out.append((list(res.fit.estimated), bool(res.identifiability.weak), res.fit.values))
    return out


def monte_carlo(
    scenario: Scenario,
    noise: float,
    n_runs: int,
    seed: int = 0,
    weightings: tuple[str, ...] = ("noise", "none"),
    options: CalibrationOptions | None = None,
    progress: ProgressReporter | None = None,
    executor=None,
) -> MonteCarloResult:
    """Calibrate `n_runs` noisy copies of the scenario's readings with each weighting.

    The noise is drawn here, in order, from `seed`; the calibrations run on
    `executor` (an engine or its name, ``closedloop.parallel.executor``; None: this
    process), so the result is the same on any engine.

    Every run must estimate the same parameters (the reduction is structural);
    a run that estimates a different set or fails counts as a failure and is
    left out.  `options` (noise and weighting are overridden) apply to all runs.
    """
    rng = np.random.default_rng(seed)
    base = options or CalibrationOptions()
    problem = build_problem(scenario.robot, scenario.log(), scenario.loops, base.priors)
    truth_full = scenario.truth_vector(problem)
    noisy = [scenario.theta + rng.normal(0.0, noise, scenario.theta.shape) for _ in range(n_runs)]
    est_set: list[int] | None = None
    raw: dict[str, list[np.ndarray]] = {w: [] for w in weightings}
    fails = dict.fromkeys(weightings, 0)
    truncated = dict.fromkeys(weightings, 0)
    from closedloop.parallel.executor import (
        imap,  # the draws run on any engine (closedloop.parallel.executor); results in draw order
    )

    shared = (scenario.robot, scenario.joints, scenario.loops, base, noise, weightings)
    runs: list = [None] * n_runs
    for count, outcome in enumerate(imap(_mc_draw, noisy, executor, shared=shared), start=1):
        if not outcome.ok:  # only a ClosedLoopError is a failed run; anything else stops the study, as before
            raise outcome.exception or ClosedLoopError(f"Monte Carlo draw {outcome.index}: {outcome.error}")
        runs[outcome.index] = outcome.value
        if progress:
            progress("monte carlo", count, n_runs)
    for per_w in runs:
        for w, (est, weak, values) in zip(weightings, per_w):
            if est is None:
                fails[w] += 1
                continue
            if est_set is None:
                est_set = est
            if est != est_set:
                fails[w] += 1
                continue
            if weak:
                truncated[w] += 1
            raw[w].append(unwrap(problem, values, truth_full)[est_set])
    if est_set is None:
        raise ClosedLoopError("every Monte Carlo run failed")
    crb = cramer_rao(problem, truth_full, est_set, noise)
    tru = truth_full[est_set]
    prior = np.array([problem.params[k].prior for k in est_set])
    crb_inv = np.linalg.inv(crb)
    se = np.sqrt(np.diag(crb))
    L = len(est_set)
    out = MonteCarloResult(
        [problem.names[k] for k in est_set],
        tru,
        crb,
        n_runs,
        scenario.theta.shape[0],
        noise,
        tolerance_trace=float(np.sqrt(2 * np.trace(crb @ crb) / (max(n_runs - 1, 1))) / np.trace(crb)),
    )
    for w in weightings:
        E = np.array(raw[w])
        if E.shape[0] < 2:
            continue
        M = E.shape[0]
        mean = E.mean(axis=0)
        cov = np.cov(E.T)
        bias = mean - tru
        pred = None
        if w == "none":
            sw = sandwich_unweighted(problem, truth_full, est_set, noise)
            pred = float(np.trace(sw) / np.trace(crb))
        elif w == "noise":
            pred = 1.0
        out.stats[w] = EstimatorStats(
            w,
            E,
            mean,
            cov,
            bias,
            bias / se,
            bias / (np.sqrt(np.diag(cov)) / np.sqrt(M)),
            float(M * bias @ crb_inv @ bias),
            float(np.trace(cov) / np.trace(crb)),
            float(np.trace(cov / np.outer(prior, prior)) / np.trace(crb / np.outer(prior, prior))),
            float(np.trace(crb_inv @ cov) / L),
            fails[w],
            truncated[w],
            pred,
        )
    return out
