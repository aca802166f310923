"""Calibrate: from a robot model, a joint log and loops to calibrated parameters.

Pipeline (thesis 3.2, 4.2, with the noise treated as errors in variables):

1. Build the problem (robot parameters of the loops' joints + loop parameters)
   and initialise unknown closures from the data.
2. Select parameters (patterns, ``fix``), check the data (joints that never
   move, loop mobility, enough equations).
3. Remove structural redundancies on the data projected onto closure; fix a
   length if the loops cannot see the overall size (3.3) and one scale factor
   if all are free (4.2.2).
4. Weight each configuration's closure error by the inverse of its covariance
   propagated from the joint-reading noise, W_i = J_theta,i Sigma J_theta,i^T
   (the implicit-loop method of Wampler, Hollerbach & Arai 1995), and solve
   by Levenberg-Marquardt with noise-aware SVD truncation (eq. 3.17, 4.2.6).
5. Report: values, standard errors from the whitened Jacobian, directions the
   data do not determine, residuals before/after, a chi-square test.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from .data import JointLog
from .errors import LogError, LoopError, NotIdentifiableError, ParameterError
from .identifiability import (Combination, Dropped, greedy_reduction, length_gauge, loop_mobility,
                              weak_directions)
from .loops.base import Loop
from .noise import joint_variance_scale
from .parameters import match
from .problem import BlockEval, CalibrationProblem, LoopBlock
from .robot import RobotModel
from .solver import SolverOptions, levenberg_marquardt, rms

log = logging.getLogger(__name__)

DEFAULT_IDENTIFY = {"urdf": ["placement", "offset", "loop"], "mjcf": ["placement", "offset", "loop"],
                    "dh": ["theta_off", "s", "a", "alpha", "loop"]}
MIN_RANGE = 1e-6  # a joint whose readings span less than this never moves


@dataclass
class CalibrationOptions:
    """What to identify and how.

    identify: parameter patterns (``placement``, ``offset``, ``scale``,
      ``loop``, or globs such as ``panda_joint[2-7].*``); None for the defaults
      (URDF: placement, offset, loop; D-H: theta_off, s, a, alpha, loop).
    fix: name -> value (None keeps the current value) of parameters held fixed.
    noise: joint-reading standard deviation (rad, or m for prismatic joints),
      one number or per joint; None estimates one level from the residual.
    weighting: 'noise' (errors in variables, default) or 'none' (the thesis's
      plain loop-closure least squares).
    """

    identify: list[str] | None = None
    fix: dict[str, float | None] = field(default_factory=dict)
    noise: float | dict[str, float] | None = None
    weighting: str = "noise"
    snr: float = 1.0
    max_iter: int = 100
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    priors: dict | None = None
    initial: dict[str, float] = field(default_factory=dict)
    robust: str | None = None  # 'huber' | 'cauchy': IRLS with suspect configurations reported


@dataclass
class LoopResiduals:
    loop: str
    n: int
    rms_m: float | None
    max_m: float | None
    rms_rad: float | None
    max_rad: float | None
    rms_px: float | None = None  # image-point error (camera loops)
    max_px: float | None = None


@dataclass
class CalibrationResult:
    """Everything a report needs; `values` are absolute parameter values."""

    problem: CalibrationProblem
    names: list[str]
    initial: np.ndarray
    values: np.ndarray
    std: np.ndarray  # NaN where not estimated or not identifiable
    status: list[str]  # 'estimated' | 'fixed' | 'dropped' | 'unidentifiable' | 'not selected'
    dropped: list[Dropped]
    weak: list[Combination]
    singular_values: np.ndarray
    rank: int
    residuals_before: list[LoopResiduals]
    residuals_after: list[LoopResiduals]
    iterations: int
    solver_status: str
    solver_message: str
    sigma: float  # joint noise level (given, or estimated)
    sigma_estimated: bool
    chi2: float
    dof: int
    notes: list[str]
    covariance: np.ndarray  # over estimated parameters (order: `estimated`)
    estimated: list[int]
    suspects: list = field(default_factory=list)  # robust.Suspect, most suspect first

    @property
    def converged(self) -> bool:
        return self.solver_status == "converged"

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.values)))


# --------------------------------------------------------------------------- setup
def build_problem(robot: RobotModel, log_: JointLog, loops: list[Loop], priors: dict | None = None
                  ) -> CalibrationProblem:
    """The problem for `loops` over `log_`; checks frames, joints and row assignment."""
    if not loops:
        raise LoopError("no loop given: say how the chain is closed (e.g. --loop weld:frame=tool)")
    names = [lp.name for lp in loops]
    if len(set(names)) != len(names):
        raise LoopError(f"duplicate loop names: {names}")
    joints: list[str] = []
    for lp in loops:
        for f in (lp.frame_a, lp.frame_b):
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
    blocks = []
    for lp in loops:
        if log_.loop is not None:
            rows = np.flatnonzero(log_.loop == lp.name)
            if rows.size == 0:
                raise LogError(f"{log_.source}: no row has loop '{lp.name}' in its 'loop' column")
        else:
            rows = np.arange(len(log_))
        lp.bind({k: v[rows] for k, v in log_.extra.items()})
        blocks.append(LoopBlock(lp, theta[rows], rows + 1, tau[rows] if tau is not None else None))
    return CalibrationProblem(robot, joints, blocks, priors)


def _noise_vector(problem: CalibrationProblem, noise) -> tuple[np.ndarray, bool]:
    """Per-joint noise std and whether it is known."""
    n = len(problem.joints)
    if noise is None:
        return np.ones(n), False
    if isinstance(noise, dict):
        unknown = set(noise) - set(problem.joints)
        if unknown:
            raise ParameterError(f"noise given for unknown joint(s) {sorted(unknown)}")
        default = noise.get("*", None)
        missing = [j for j in problem.joints if j not in noise and default is None]
        if missing:
            raise ParameterError(f"noise: no level for joint(s) {missing} (give '*' as a default)")
        vec = np.array([noise.get(j, default) for j in problem.joints], dtype=float)
    else:
        vec = np.full(n, float(noise))
    if np.any(~np.isfinite(vec)) or np.any(vec <= 0):
        raise ParameterError("noise levels must be positive and finite")
    return vec, True


def _cholesky_inverse(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L^-1 for a stack of symmetric positive semi-definite A = L L^T (n, m, m), and kappa (n,).

    kappa = tr(A) tr(A^-1) = tr(A) |L^-1|_F^2 bounds the condition number:
    lambda_max <= tr A and 1/lambda_min <= tr A^-1, so every eigenvalue of A
    exceeds lambda_max / kappa.  Where A is not positive definite (or nearly
    so) kappa is inf and L^-1 meaningless.  Cholesky and forward substitution
    column by column over the whole stack (a LAPACK call per small matrix
    costs more than the arithmetic).
    """
    m = A.shape[-1]
    L = np.zeros_like(A)
    X = np.zeros_like(A)
    with np.errstate(divide="ignore", invalid="ignore"):
        for j in range(m):
            v = A[:, j:, j] - np.einsum("nik,nk->ni", L[:, j:, :j], L[:, j, :j])
            L[:, j, j] = np.sqrt(v[:, 0])
            L[:, j + 1:, j] = v[:, 1:] / L[:, j, j, None]
        for i in range(m):  # L X = I, X lower triangular
            X[:, i, i] = 1.0 / L[:, i, i]
            X[:, i, :i] = -np.einsum("nk,nkj->nj", L[:, i, :i], X[:, :i, :i]) * X[:, i, i, None]
        kappa = np.trace(A, axis1=1, axis2=2) * np.einsum("nij,nij->n", X, X)
    return X, np.where(np.isfinite(kappa), kappa, np.inf)


def _pinv_sqrt(W: np.ndarray) -> tuple[np.ndarray, int]:
    """Symmetric pseudo-inverse square roots V diag(lambda^-1/2) V^T of a stack of covariances.

    Eigenvalues below 1e-9 of the largest are dropped; returns the roots and the number dropped.
    """
    lam, V = np.linalg.eigh(W)
    keep = lam > 1e-9 * np.maximum(lam[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
    return (V * inv[:, None, :]) @ np.swapaxes(V, 1, 2), int(np.sum(~keep))


def whiten(evals: list[BlockEval], sigma_q: np.ndarray, weighting: str, jacobian: bool = True,
           loops: list[Loop] | None = None, Winv: list[np.ndarray | None] | None = None, symmetric: bool = True):
    """Stack residuals (and Jacobians) whitened by W_i^-1/2, W_i = Jq Sigma Jq^T (+ measurement covariance).

    `Winv` reuses the W_i^-1/2 of an earlier evaluation (trial steps, which
    have no Jq); the W_i^-1/2 used are returned so that the caller can.
    A residual direction that no joint noise can produce (W_i singular, e.g. a
    passive joint eliminated by projection) gets zero weight: W^-1/2 is the
    pseudo-inverse square root (eigenvalues below 1e-9 of the largest dropped),
    never an amplification by a tiny regulariser.
    With `symmetric` False any square root F of the pseudo-inverse (F^T F = W^+)
    may stand for W^-1/2: the inverse Cholesky factor L^-1 where W_i is well
    conditioned (kappa of `_cholesky_inverse` below 1e9, so that nothing would
    be dropped), the symmetric root elsewhere.  Each configuration's whitened
    rows are then turned by an orthogonal matrix, which changes neither
    |r|^2, nor J^T J, nor J^T r: the least-squares problem is the same, at a
    fraction of the cost of the eigendecompositions.
    Returns (r, J or None, list of (W^-1/2, rank deficit) per block, or None entries).
    """
    rs, Js, used = [], [], []
    for bi, ev in enumerate(evals):
        r, J = ev.r, ev.J
        Wh = Winv[bi] if Winv is not None else None
        deficit = 0
        if isinstance(Wh, tuple):
            Wh, deficit = Wh
        if weighting == "noise" and Wh is None and ev.Jq is not None:
            Jq = ev.Jq * sigma_q[None, None, :]
            W = Jq @ np.swapaxes(Jq, 1, 2)
            if loops is not None and loops[bi].measurement_cov is not None:
                W = W + loops[bi].measurement_cov
            if symmetric:
                Wh, deficit = _pinv_sqrt(W)
            else:
                Wh, kappa = _cholesky_inverse(W)
                ill = np.flatnonzero(kappa >= 1e9)
                if ill.size:
                    Wh[ill], deficit = _pinv_sqrt(W[ill])
        if Wh is not None:
            r = np.einsum("nij,nj->ni", Wh, r)
            if jacobian:
                J = Wh @ J
        used.append((Wh, deficit) if Wh is not None else None)
        rs.append(r.ravel())
        if jacobian:
            Js.append(J.reshape(-1, J.shape[-1]))
    r = np.concatenate(rs) if rs else np.zeros(0)
    J = np.vstack(Js) if jacobian and Js else None
    return r, J, used


def residual_stats(problem: CalibrationProblem, evals: list[BlockEval]) -> list[LoopResiduals]:
    out = []
    for b, ev in zip(problem.blocks, evals):
        lp = b.loop
        t = ev.r[:, list(lp.translation_rows)] if lp.translation_rows else None
        w = ev.r[:, list(lp.rotation_rows)] if lp.rotation_rows else None
        tn = np.linalg.norm(t, axis=1) if t is not None else None
        wn = np.linalg.norm(w, axis=1) if w is not None else None
        # image points: the (u, v) pairs' Euclidean errors, pooled over configurations and cameras
        pn = (np.linalg.norm(ev.r[:, list(lp.pixel_rows)].reshape(-1, 2), axis=1)
              if lp.pixel_rows and ev.r.size else None)
        out.append(LoopResiduals(lp.name, ev.r.shape[0],
                                 float(np.sqrt(np.mean(tn ** 2))) if tn is not None else None,
                                 float(tn.max()) if tn is not None else None,
                                 float(np.sqrt(np.mean(wn ** 2))) if wn is not None else None,
                                 float(wn.max()) if wn is not None else None,
                                 float(np.sqrt(np.mean(pn ** 2))) if pn is not None else None,
                                 float(pn.max()) if pn is not None else None))
    return out


def project_to_closure(problem: CalibrationProblem, values: np.ndarray, iters: int = 8) -> list[np.ndarray]:
    """Joint readings moved onto the closure manifold of the model at `values`.

    Gauss-Newton on the readings, theta <- theta - pinv(J_theta) r, per
    configuration.  Used only to make structural redundancies exact.  Where
    J_theta J_theta^T is well conditioned (kappa of `_cholesky_inverse` below
    1e6) the minimum-norm step is J_theta^T (J_theta J_theta^T)^-1 r through
    its Cholesky factor; elsewhere the SVD pseudo-inverse (rcond 1e-10).
    """
    thetas = [b.theta.copy() for b in problem.blocks]
    for _ in range(iters):
        evals = problem.evaluate(values, True, thetas, columns=[])
        worst = 0.0
        for k, ev in enumerate(evals):
            Linv, kappa = _cholesky_inverse(ev.Jq @ np.swapaxes(ev.Jq, 1, 2))
            y = np.einsum("nji,nj->ni", Linv, np.einsum("nij,nj->ni", Linv, ev.r))  # (Jq Jq^T)^-1 r
            step = np.einsum("nji,nj->ni", ev.Jq, y)
            ill = np.flatnonzero(kappa >= 1e6)
            if ill.size:
                step[ill] = np.einsum("nij,nj->ni", np.linalg.pinv(ev.Jq[ill], rcond=1e-10), ev.r[ill])
            thetas[k] = thetas[k] - step
            worst = max(worst, float(np.abs(ev.r).max()) if ev.r.size else 0.0)
        if worst < 1e-13:
            break
    return thetas


# --------------------------------------------------------------------------- main
def calibrate(robot: RobotModel, log_: JointLog, loops: list[Loop], options: CalibrationOptions | None = None,
              progress: Callable[[str, int, float], None] | None = None) -> CalibrationResult:
    """Identify the selected parameters; see the module docstring for the method."""
    opt = options or CalibrationOptions()
    if opt.weighting not in ("noise", "none"):
        raise ParameterError(f"weighting must be 'noise' or 'none', not '{opt.weighting}'")
    problem = build_problem(robot, log_, loops, opt.priors)
    names = problem.names
    P = len(names)
    notes: list[str] = []
    x0 = problem.nominal

    # Unknown closures start from the nominal model's pose at the first configuration.
    for bi, (b, sl) in enumerate(zip(problem.blocks, problem.loop_slices)):
        if sl.stop > sl.start:
            TA, TB = problem.loop_poses(x0, bi)
            init = b.loop.initialize(TA, TB)
            if init is not None:
                x0[sl] = init
    for n, v in opt.initial.items():
        if n not in problem.index:
            raise ParameterError(f"initial value for unknown parameter '{n}'")
        x0[problem.index[n]] = v

    # ---- selection
    patterns = opt.identify if opt.identify is not None else DEFAULT_IDENTIFY[robot.kind]
    loop_names = [p.name for p in problem.params if p.kind == "loop"]
    pats = [q for q in patterns if q != "loop"]
    selected = set(match(names, pats)) | (set(loop_names) if "loop" in patterns else set())
    for q in pats:
        if not match(names, [q]):
            raise ParameterError(f"--identify {q}: matches no parameter of this problem")
    status = ["not selected"] * P
    for n in selected:
        status[problem.index[n]] = "selected"
    wants_tau = [n for n in selected if problem.params[problem.index[n]].kind == "compliance"]
    if wants_tau and any(b.tau is None for b in problem.blocks):
        raise LogError(f"{log_.source}: identifying joint compliance ({wants_tau[0]}, ...) needs the actuator "
                       f"torques as columns 'tau:<joint>' for every loop joint")
    for n, v in opt.fix.items():
        if n not in problem.index:
            raise ParameterError(f"--fix {n}: no parameter of this problem has that name")
        k = problem.index[n]
        if v is not None:
            x0[k] = v
        status[k] = "fixed"
    dropped: list[Dropped] = []
    scale = np.array([p.prior for p in problem.params])

    # ---- data checks: motion and mobility
    theta_all = np.vstack([b.theta for b in problem.blocks])
    ranges = theta_all.max(axis=0) - theta_all.min(axis=0)
    for j, name in enumerate(problem.joints):
        if ranges[j] < MIN_RANGE:
            notes.append(f"joint {name} never moves in the data (range {ranges[j]:.2e}); its scale and "
                         "the geometry it would reveal cannot be identified (Singularity 5)")
            k = problem.rp.index[problem.rp._sensor_name(name, "scale")]
            if status[k] == "selected":
                status[k] = "dropped"
                dropped.append(Dropped(names[k], "its joint never moves, so scale and offset are one"))
    if np.all(ranges < MIN_RANGE):
        raise NotIdentifiableError("no joint moves in the log: every configuration is the same pose, "
                                   "so nothing can be identified")
    evals0 = problem.evaluate(x0, True)
    for b, ev in zip(problem.blocks, evals0):
        if not b.loop.scale_free:  # a measured (open) loop: mobility is not a question
            continue
        mob, moves = loop_mobility(ev.Jq)
        if mob == 0:
            notes.append(f"loop {b.loop.name} is immobile (Lemma 4: J_theta has full column rank): "
                         "the closed chain cannot move, so its configurations carry no new information")
        for j, name in enumerate(problem.joints):
            if not moves[j] and ranges[j] >= MIN_RANGE and np.any(np.abs(ev.Jq[:, :, j]) > 0):
                notes.append(f"joint {name} is structurally immobile in loop {b.loop.name} "
                             "(Lemma 6: no self-motion of the closed chain moves it)")

    # ---- Singularity 1: consecutive parallel axes in plain D-H rows
    if robot.kind == "dh":
        rows = robot.dh.rows
        for r1, r2 in zip(rows, rows[1:]):
            if r1.convention == "dh" and abs(np.sin(r1.alpha)) < 1e-6 and r1.name in problem.joints:
                notes.append(f"D-H rows {r1.name} and {r2.name}: consecutive parallel axes (alpha_{r1.name} = "
                             f"{r1.alpha:.3g} rad); the common normal is not unique, so {r1.name}.s and "
                             f"{r2.name}.s are not separately identifiable (thesis 3.3, Singularity 1; see "
                             "what absorbs them). Write these rows with convention: hayati (eq. 4.2)")

    # ---- scale factors: k = 0 fits any data if all are free (4.2.2)
    sc = [problem.rp.index[problem.rp._sensor_name(j, "scale")] for j in problem.joints]
    if sc and all(status[k] == "selected" for k in sc):
        k = sc[-1]
        status[k] = "fixed"
        notes.append(f"fixed {names[k]} = {x0[k]:g}: with every scale factor free, k = 0 fits any data "
                     "(thesis 4.2.2)")

    sigma_q, known = _noise_vector(problem, opt.noise)
    noise_given = known
    # unknown joint noise beside a loop's known measurement noise: their ratio must be estimated
    joint_noise_beside_measurement = (not known and opt.weighting == "noise" and not opt.robust
                                      and any(b.loop.measurement_cov is not None for b in problem.blocks))
    free = [k for k in range(P) if status[k] == "selected"]
    M = sum(b.theta.shape[0] * b.loop.dim for b in problem.blocks)
    if not free:
        raise NotIdentifiableError("no parameter is left to identify (all fixed or not selected)")

    # ---- structural reduction on closure-projected data
    if progress:
        progress("analysing", 0, 0.0)
    # Analysed at the starting point: a special start (an unknown tool point at a frame origin that
    # lies on the last joint axis) makes the tilt of that axis look redundant, which is exactly right
    # when the real tool point is there, and needs a rough off-axis initial guess when it is not.
    thetas_c = project_to_closure(problem, x0)
    evc = problem.evaluate(x0, True, thetas_c)
    Jc = np.vstack([ev.J.reshape(-1, P) for ev in evc])
    Cs = Jc[:, free] * scale[free]
    length_mask = np.array([problem.params[k].scales_with_length != 0.0 and problem.params[k].kind != "loop"
                            for k in free])
    user_fixed_length = any(status[k] == "fixed" and problem.params[k].scales_with_length != 0.0 for k in range(P))
    scale_free = all(b.loop.scale_free for b in problem.blocks)
    if scale_free and not user_fixed_length and length_mask.any():
        sdir = np.array([problem.params[k].scales_with_length for k in free]) / scale[free]
        if length_gauge(Cs, sdir, length_mask):
            cand = [i for i in range(len(free)) if length_mask[i]]
            best = max(cand, key=lambda i: abs(sdir[i]))
            k = free[best]
            status[k] = "fixed"
            notes.append(f"fixed {names[k]} = {x0[k]:g} to set the length scale: the loops close at any "
                         "overall size (thesis 3.3)")
            free = [f for f in free if f != k]
            Cs = Jc[:, free] * scale[free]
    order = sorted(range(len(free)), key=lambda i: (problem.params[free[i]].priority,
                                                   -problem.params[free[i]].order
                                                   if problem.params[free[i]].kind in ("placement", "dh")
                                                   else problem.params[free[i]].order, free[i]))
    kept_local, drop = greedy_reduction(Cs, [names[k] for k in free], order)
    for d in drop:
        status[problem.index[d.name]] = "dropped"
    dropped.extend(drop)
    est = sorted(free[i] for i in kept_local)
    for k in est:
        status[k] = "estimated"
    if M <= len(est):  # the rows, not the model, limit the rank: nothing left to estimate noise or check
        raise LogError(f"{log_.source}: {len(log_)} rows give {M} equations, no more than the {len(est)} "
                       "parameters they could determine; log more configurations or identify fewer parameters")
    if drop:
        log.info("dropped %d redundant parameters", len(drop))

    # ---- solve
    loops_ = [b.loop for b in problem.blocks]
    rows_per_block = [b.theta.shape[0] * b.loop.dim for b in problem.blocks]

    def make_fun(weighting: str, row_w: np.ndarray | None = None, symmetric: bool = False):
        """Residual function over the estimated parameters; W_i from the last Jacobian call.

        Only the estimated columns of the Jacobian are formed.  The solver's
        functions whiten with the cheap square root of W_i^-1 (`whiten`,
        symmetric=False: the same least-squares problem); the robust weights
        need the components of the symmetric W_i^-1/2 r (`symmetric`).
        Evaluations are reused, never changed: the first trial point after a
        Jacobian call is evaluated with its Jacobian (Levenberg-Marquardt
        usually accepts it and asks for that next; its cost is still taken
        with the old W_i), and the last Jacobian evaluation is returned again
        for the same parameters (the final analysis asks for the solution's).
        """
        cache: dict = {"W": None, "x": None, "trial": None}

        def fun(xe: np.ndarray, jac: bool):
            if jac and cache["x"] is not None and np.array_equal(xe, cache["x"]):
                return cache["rJ"]
            x = x0.copy()
            x[est] = xe
            trial = cache["trial"]
            first_trial = not jac and cache["W"] is not None and trial is None
            if jac and trial is not None and np.array_equal(xe, trial[0]):
                evals = trial[1]
            else:
                full = jac or first_trial
                evals = problem.evaluate(x, full or cache["W"] is None, columns=est if full else [])
            r, J, used = whiten(evals, sigma_q, weighting, jac, loops_, None if jac else cache["W"], symmetric)
            if jac or cache["W"] is None:
                cache["W"] = used
                cache["deficit"] = sum(u[1] for u in used if u is not None)
            if row_w is not None:
                r = r * row_w
                if jac:
                    J = J * row_w[:, None]
            if jac:
                cache["x"], cache["rJ"], cache["trial"] = xe.copy(), (r, J), None
            elif first_trial:
                cache["trial"] = (xe.copy(), evals)
            return r, J
        fun.cache = cache  # type: ignore[attr-defined]
        return fun

    def block_residuals(xe: np.ndarray) -> list[np.ndarray]:
        r, _ = make_fun(opt.weighting, symmetric=True)(xe, False)
        parts = np.split(r, np.cumsum(rows_per_block)[:-1])
        return [p.reshape(b.theta.shape[0], b.loop.dim) for p, b in zip(parts, problem.blocks)]

    lower = upper = None
    if opt.bounds:
        lower = np.full(len(est), -np.inf)
        upper = np.full(len(est), np.inf)
        for n, (lo, hi) in opt.bounds.items():
            if n not in problem.index:
                raise ParameterError(f"bound for unknown parameter '{n}'")
            k = problem.index[n]
            if k in est:
                lower[est.index(k)], upper[est.index(k)] = lo, hi
    sopt = SolverOptions(max_iter=opt.max_iter, noise=(1.0 if known and opt.weighting == "noise" else None),
                         snr=opt.snr, lower=lower, upper=upper)
    prog = (lambda it, c: progress("solving", it, c)) if progress else None
    suspects: list = []
    row_w = None
    if opt.robust:
        # Gross outliers wreck the noise-weighted fit (their W_i are meaningless), so start from the
        # plain loop-closure fit, then iterate reweighted fits with the chosen weighting (IRLS).
        from .robust import suspects as find_suspects
        from .robust import weights as robust_weights

        if opt.robust not in ("huber", "cauchy"):
            raise ParameterError(f"robust loss must be 'huber' or 'cauchy', not '{opt.robust}'")
        xe = levenberg_marquardt(make_fun("none"), x0[est], scale[est], replace(sopt, noise=None), prog).x
        w_prev = None
        for _ in range(10):
            blocks_r = block_residuals(xe)
            ws = robust_weights(blocks_r, opt.robust, scale=1.0 if known and opt.weighting == "noise" else None)
            w = np.concatenate(ws)
            row_w = np.repeat(np.sqrt(w), [b.loop.dim for b in problem.blocks for _ in range(b.theta.shape[0])])
            fun = make_fun(opt.weighting, row_w)
            res = levenberg_marquardt(fun, xe, scale[est], sopt, prog)
            xe = res.x
            if w_prev is not None and np.max(np.abs(w - w_prev)) < 1e-3:
                break
            w_prev = w
        blocks_r = block_residuals(xe)
        suspects = find_suspects(blocks_r, rows=[b.rows for b in problem.blocks], loops=[b.loop.name for b in problem.blocks],
                                 loss=opt.robust, scale=1.0 if known and opt.weighting == "noise" else None)
        for sp in suspects[:10]:
            notes.append(f"suspect configuration: log row {sp.row} (loop {sp.loop}): closure error "
                         f"{sp.standardized:.3g} standard deviations, weight {sp.weight:.2g}")
        if len(suspects) > 10:
            notes.append(f"... and {len(suspects) - 10} more suspect configurations")
    else:
        fun = make_fun(opt.weighting)
        res = levenberg_marquardt(fun, x0[est], scale[est], sopt, prog)
        if joint_noise_beside_measurement:
            # The ratio of joint to measurement noise sets the weights: estimate the joint level
            # (closedloop.noise) at the fit, re-solve from x0 with it, until it settles.
            pattern, s_prev = sigma_q.copy(), None
            covs = [lp.measurement_cov for lp in loops_]
            for _ in range(4):
                x = x0.copy()
                x[est] = res.x
                evs = problem.evaluate(x, True, columns=[])
                s = joint_variance_scale([e.r for e in evs], [e.Jq for e in evs], covs, pattern, len(est))
                if s_prev is not None and abs(s - s_prev) <= 0.05 * max(s, s_prev):
                    break
                sigma_q, known, s_prev = np.sqrt(s) * pattern, True, s
                fun = make_fun(opt.weighting)
                res = levenberg_marquardt(fun, x0[est], scale[est], replace(sopt, noise=1.0), prog)
            notes.append(f"joint noise estimated at {float(np.mean(sigma_q)):.3g} beside the given measurement "
                         "noise (variance components); give --noise to fix it")
    x = x0.copy()
    x[est] = res.x
    for b, sl in zip(problem.blocks, problem.loop_slices):
        x[sl] = b.loop.normalize(x[sl])

    # ---- final analysis at the solution (normalised loop parameters)
    r, J = fun(x[est], True)
    Js = J * scale[est]
    U, S, Vt = np.linalg.svd(Js, full_matrices=False)
    rank_num = int(np.sum(S > 1e-10 * S[0])) if S.size else 0
    dof = max(r.size - fun.cache.get("deficit", 0) - rank_num, 1)  # eliminated passive directions carry none
    if known and opt.weighting == "noise":
        sigma_r, sigma = 1.0, float(np.mean(sigma_q))
    else:
        sigma_r = rms(r, dof)
        sigma = sigma_r * (float(np.mean(sigma_q)) if opt.weighting == "noise" else 1.0)
    threshold = max(1e-10 * (S[0] if S.size else 0.0), opt.snr * sigma_r)
    weak = weak_directions(S, Vt, threshold, [names[k] for k in est])
    keep = S > threshold
    Vk = Vt[keep].T
    cov_s = (Vk / S[keep] ** 2) @ Vk.T * sigma_r ** 2
    cov = cov_s * np.outer(scale[est], scale[est])
    std = np.full(P, np.nan)
    std[est] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for c in weak:
        for n, _ in c.terms:
            k = problem.index[n]
            status[k] = "unidentifiable"
            std[k] = np.nan
    chi2 = float(r @ r) / (sigma_r ** 2 if not known else 1.0)
    evals1 = problem.evaluate(x, False)
    if res.status != "converged":
        notes.append(f"solver: {res.message}")
    return CalibrationResult(problem, names, x0, x, std, status, dropped, weak, S,
                             int(keep.sum()), residual_stats(problem, evals0), residual_stats(problem, evals1),
                             res.iterations, res.status, res.message, sigma, not noise_given, chi2, dof, notes,
                             cov, est, suspects)
