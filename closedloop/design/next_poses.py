"""The next configurations to record: those that most reduce the predicted error over the workspace.

The pose selection of `closedloop.design.poses` turned to the workspace target.  A calibration's
prediction (`closedloop.analysis.accuracy.WorkspaceAccuracy`) carries the covariance Sigma of every
parameter it considered (estimated and unseen), those that move a followed frame and the loops' own
unknowns that move none (a plane's normal and distance, a socket's position), cross terms included
(`full_covariance`), and the gauge-free workspace matrix A (the frames' position errors per parameter
over the workspace readings; zero in a loop unknown's column): the predicted mean squared position
error is (tr(A Sigma A^T) + |A b|^2) / n, b the systematic error a model error adds (zero where none is
found), which no new configuration removes.

**Candidates.**  Configurations the loop can be recorded at, at its current place (the same socket,
fixture, hinge): random readings within the joint limits, each moved onto the loop by Gauss-Newton on
the calibrated model's closure, theta <- theta - Jq^+ r(theta) (Jq the closure's derivative with respect
to the readings, `LoopBlock` evaluation at new readings), kept where the closure falls below 1e-9 and the
readings stay `LIMIT_MARGIN` inside the limits (a configuration at a joint's stop is one the robot may
not reach, or reaches pressed against the stop rather than resting on the loop).

**The promise.**  Recorded and calibrated again, the new rows enter the fit beside the old: to first
order its information is the old one plus theirs (thesis eq. 4.17's weighted normal equations over the
log and the new rows), in information form

    Sigma_new^-1 = Sigma^-1 + sum_i B_i^T B_i,

B_i the closure Jacobian of candidate i over every parameter of Sigma, whitened by the joint noise,
B_i = L_i^-1 J_i with L_i L_i^T = S_i = sigma^2 Jq_i Jq_i^T (eq. 4.17's weighting, errors in
variables); after a plain loop-closure fit (eq. 3.8, `NoiseRecord.joint_noise` None) as that fit weighs
its rows, S_i = sigma^2 I, sigma its closure residual's scale (whitened by the joint noise instead, the
closure scale read as radians, the promise on a UR5 socket was 1.5 times below what the plain
recalibration reported).  The recalibration estimates the loop's place again from the new rows: J_i has its columns
(a new point on a plane tells of the plane as of the arm), and what they resolve of it resolves, through
the cross terms of Sigma, the arm's parameters correlated with it.  Left out (the place taken as
known), the update would be the marginal covariance of the arm's parameters updated as if the place were
free of error, neither the posterior nor a bound (on a UR3's tool on a plane it promised 1.5 times
less error than the recalibration reported).  The promised RMS is
sqrt((tr(A Sigma_new A^T) + |A b|^2) / n), Sigma_new with its part along what the log and the new rows
see least replaced as the recalibration's prediction finds it (`Unseen`, `analysis.accuracy`): the nominal
tolerance there, and the solution's move along those directions.  Updated as a prior instead, that part
shrank where the recalibration leaves it unestimated: on a Z1 arm's tool on a plane (40 configurations,
six seeds) the promise was 1.7-4.7 times lower than the recalibration's prediction, with it 0.39-1.86
times (the spread is the move, which each calibration draws anew along what it barely sees).

**Selection** (I-optimal, greedy): adding candidate i lowers the covariance to
Sigma - Sigma B_i^T (I + B_i Sigma B_i^T)^-1 B_i Sigma (Sherman-Morrison-Woodbury: the information form
above one candidate at a time, without inverting Sigma, which is singular along what no data see) and
the objective by tr(A Sigma B_i^T (I + B_i Sigma B_i^T)^-1 B_i Sigma A^T); the candidate with the
largest fall is taken, Sigma updated, and so on.  The candidates lie at the loop's current place (the
calibrated one): the new rows are recorded where the data already put it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from closedloop.analysis.accuracy import joint_ranges, least_seen, tolerance_factor
from closedloop.estimate.noise import pinv_sqrt
from closedloop.problem.problem import CalibrationProblem, LoopBlock

N_CANDIDATES = 400  # random starts moved onto the loop
CLOSED = 1e-9  # a candidate's closure (m, rad) below which it is on the loop
#: how far inside its limits a suggested reading stays: 0.1 (rad, or m for a prismatic joint), at most 10 %
#: of the joint's range, the margin the simulator's planner keeps (`SimSettings.limit_margin`); a robot
#: playing a reading on a closed loop settles a few hundredths of a radian from it, and a sample within
#: 0.02 rad of a limit is one the simulator drops (HyQ's leg on a plane, 0.05 rad: 2 of 20 dropped)
LIMIT_MARGIN = 0.1


@dataclass(frozen=True)
class NextPoses:
    """The suggested configurations and the predicted error over the workspace before and after them."""

    loop: str
    joints: tuple[str, ...]
    readings: np.ndarray = field(repr=False)  # (k, joints) in the order chosen
    rms_before_m: float  # predicted RMS position error over the workspace, every followed frame
    rms_after_m: np.ndarray = field(repr=False)  # (k,) after the first 1, 2, ... k suggestions
    candidates: int  # configurations on the loop the choice was made among
    #: the share of the last of `rms_after_m` from what the log and the suggestions still cannot see (`Unseen`)
    unseen_rms_m: float = 0.0

    def record(self, path) -> dict:
        """What the report says of the suggestions written to `path` (``accuracy.next_poses``)."""
        return {
            "file": str(path),
            "loop": self.loop,
            "configurations": int(self.readings.shape[0]),
            "candidates": self.candidates,
            "predicted_rms_before_m": self.rms_before_m,
            "predicted_rms_after_m": [float(v) for v in self.rms_after_m],
            "predicted_unseen_rms_m": self.unseen_rms_m,
        }

    def csv(self) -> str:
        """The suggestions as a CSV log the robot can play (`closedloop.io.logs.log_csv`: a header of joint
        names, one row per configuration, radians)."""
        from closedloop.io.logs import log_csv

        return log_csv({j: self.readings[:, k] for k, j in enumerate(self.joints)})


def suggest_next(res, workspace, k: int = 10) -> NextPoses | None:
    """`suggest_poses` on the first loop whose frame the prediction `workspace` follows; None where none is
    followed, or no configuration of it can be suggested."""
    followed = [
        i for i, b in enumerate(res.problem.blocks) if workspace and b.loop.name in {f.loop for f in workspace.frames}
    ]
    found = suggest_poses(res, workspace, k, followed[0]) if followed else None
    return found if found is not None and found.readings.shape[0] else None


def _sub_problem(problem: CalibrationProblem, block_index: int, values: np.ndarray, readings: np.ndarray):
    """The problem of one loop at new `readings` (N, joints) and the parameter vector mapped to it by name.
    Where the log carried joint torques, the new configurations' are the model's gravity torques (a static
    robot carrying itself: what `closedloop calibrate` assumes of a log without torques)."""
    b = problem.blocks[block_index]
    tau = None if b.tau is None else problem.robot.gravity_torques(readings, list(problem.joints))
    block = LoopBlock(b.loop, readings, np.arange(1, readings.shape[0] + 1), tau)
    sub = CalibrationProblem(problem.robot, problem.joints, [block], problem.priors)
    x = np.array([values[problem.index[n]] for n in sub.names], dtype=float)
    return sub, x


def loop_candidates(
    problem: CalibrationProblem, values: np.ndarray, block_index: int, n: int = N_CANDIDATES, seed: int = 0
) -> np.ndarray:
    """Readings (k, joints) on the loop of block `block_index` at its current place (module docstring)."""
    lo, hi = joint_ranges(problem.robot, problem.joints)
    rng = np.random.default_rng(seed)
    X = rng.uniform(lo, hi, (n, len(problem.joints)))
    r = np.full((n, 1), np.inf)
    for _ in range(40):
        sub, x = _sub_problem(problem, block_index, values, X)
        ev = sub.evaluate(x, True, columns=[])[0]
        r = ev.r
        if ev.Jq is None:
            return np.zeros((0, len(problem.joints)))
        step = np.einsum("nij,nj->ni", np.linalg.pinv(ev.Jq, rcond=1e-8), r)
        X = X - step
        if np.all(np.linalg.norm(step, axis=1) < 1e-12):
            break
    sub, x = _sub_problem(problem, block_index, values, X)
    r = sub.evaluate(x, False)[0].r
    ok = np.all(np.isfinite(r), axis=1) & (np.linalg.norm(r, axis=1) < CLOSED)
    ok &= inside_limits(X, lo, hi)
    return X[ok]


def inside_limits(X: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(k,) whether each row of readings `X` (k, joints) lies `LIMIT_MARGIN` inside the range lo..hi of every
    joint (at most 10 % of the range inside: a short prismatic travel keeps 80 % of it)."""
    margin = np.minimum(LIMIT_MARGIN, 0.1 * (np.asarray(hi) - np.asarray(lo)))
    return np.all((X >= lo + margin) & (X <= hi - margin), axis=1)


@dataclass(frozen=True)
class Unseen:
    """What a calibration leaves unseen, to be found again after new rows (`recalibrated`).

    The prediction's covariance carries the nominal tolerance along the `n` directions the data see least
    (`analysis.accuracy.unseen_factor`: the right singular vectors of the prior-scaled closure Jacobian C).
    Recalibrated with new rows, the fit again leaves the directions the data then see least unestimated, at
    their nominal tolerance: new rows change which ones (a weak direction they see turns into an estimated
    one, and the next least-seen takes its place), they do not shrink a tolerance that stays unestimated."""

    n: int  # directions left unseen (the dropped parameters and the undetermined combinations)
    R: np.ndarray  # the log's prior-scaled closure Jacobian reduced to its triangle (names order)
    p: np.ndarray  # the parameters' prior scales
    t: np.ndarray  # their nominal tolerances (`PriorTolerance`)
    moved: np.ndarray  # the solution's move from the nominal model (0 for a loop's place)

    @classmethod
    def of(cls, res, workspace, names: list[str]) -> "Unseen":
        """The unseen part of the calibration `res` whose prediction is `workspace`, over `names`."""
        from closedloop.analysis.accuracy import UNSEEN_SAMPLE, data_triangle
        from closedloop.records import ParamStatus

        problem = res.problem
        cols = [problem.index[n] for n in names]
        p = np.array([problem.params[k].prior for k in cols], dtype=float)
        t = np.array([workspace.prior.of(problem.params[k].kind, problem.params[k].unit) for k in cols], float)
        n = len(res.identifiability.weak) + sum(res.fit.status[k] == ParamStatus.DROPPED for k in cols)
        values, initial = np.asarray(res.fit.values, float), np.asarray(res.fit.initial, float)
        moved = np.array([values[k] - initial[k] if k < problem.n_robot else 0.0 for k in cols])
        if n <= 0:
            return cls(0, np.zeros((0, len(cols))), p, t, moved)
        long_ = any(b.theta.shape[0] > UNSEEN_SAMPLE for b in problem.blocks)
        return cls(n, data_triangle(problem.sampled(UNSEEN_SAMPLE) if long_ else problem, values, cols), p, t, moved)

    def recalibrated(self, sigma: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`sigma` (the information-form update of the prediction's covariance by the new rows, names order)
        with its part along what the log and the new closure `rows` (not whitened) see least replaced by the
        nominal tolerance there and the solution's move along it (`analysis.accuracy.unseen_factor`'s
        Sigma_unseen + d_u d_u^T, on the new directions): the covariance the recalibration predicts, and
        that unseen part of it."""
        if self.n <= 0:
            return sigma, np.zeros_like(sigma)
        Vu = least_seen(np.vstack([self.R, rows * self.p]), self.n)
        out = np.eye(len(self.p)) - (self.p[:, None] * Vu) @ (Vu.T / self.p)  # what the fit estimates: the seen part
        L_u = tolerance_factor(Vu, self.p, self.t, self.moved)
        unseen = L_u @ L_u.T
        return out @ sigma @ out.T + unseen, unseen


def suggest_poses(
    res, workspace, k: int = 10, block_index: int = 0, n_candidates: int = N_CANDIDATES, seed: int = 0
) -> NextPoses | None:
    """The `k` configurations of loop `block_index` that most reduce the predicted workspace error of
    `workspace` (`WorkspaceAccuracy` of the calibration `res`), greedily (module docstring); None where
    the prediction has no design matrix, the loop measures something at each row (a tracker, a camera:
    its future measurements are not known) or no candidate closes the loop."""
    problem = res.problem
    b = problem.blocks[block_index]
    if workspace is None or workspace.design is None or workspace.full_covariance is None or b.meas is not None:
        return None
    values = np.asarray(res.fit.values, dtype=float)
    C = loop_candidates(problem, values, block_index, n_candidates, seed)
    if not C.shape[0]:
        return None
    sub, x = _sub_problem(problem, block_index, values, C)
    names = list(workspace.parameters) + list(workspace.loop_parameters)
    cols = [sub.index[n] for n in names if n in sub.index]
    keep = [i for i, n in enumerate(names) if n in sub.index]
    ev = sub.evaluate(x, True, columns=cols)[0]
    sigma = max(float(res.noise.sigma), 1e-9)
    B = np.zeros((C.shape[0], ev.r.shape[1], len(names)))
    Jq = ev.Jq if ev.Jq is not None else np.zeros((C.shape[0], ev.r.shape[1], 0))
    if res.noise.joint_noise is None:  # a plain fit (eq. 3.8): every closure row weighs 1 / sigma^2
        Wi = np.broadcast_to(np.eye(ev.r.shape[1]) / sigma, (C.shape[0], ev.r.shape[1], ev.r.shape[1]))
    else:  # whitening B_i = W_i^-1/2 J_i, W_i = sigma^2 Jq Jq^T (eq. 3.17); a direction no joint noise moves
        # (a door's angle, projected out: W_i singular) weighs nothing, as in the fit (`noise.whiten`)
        Wi = pinv_sqrt(sigma**2 * Jq @ np.swapaxes(Jq, 1, 2))[0]
    B[:, :, keep] = Wi @ ev.jacobian()
    # the loop's place moves no frame: its columns of A are zero, its covariance and cross terms are kept
    A = np.hstack([workspace.design, np.zeros((workspace.design.shape[0], len(workspace.loop_parameters)))])
    Sig = np.array(workspace.full_covariance, dtype=float)
    n = workspace.readings.shape[0]
    # the model error's systematic part: no new data removes it (`analysis.accuracy`, Model error)
    floor = float(np.sum((workspace.design @ workspace.bias) ** 2)) if workspace.bias is not None else 0.0
    before = float(np.sqrt((np.trace(A @ Sig @ A.T) + floor) / (n * len(workspace.frames))))
    unseen = Unseen.of(res, workspace, names)
    J_new = np.zeros((C.shape[0], ev.r.shape[1], len(names)))  # the candidates' closure rows, not whitened
    J_new[:, :, keep] = ev.jacobian()
    chosen: list[int] = []
    after = []
    for _ in range(min(k, C.shape[0])):
        M = B @ Sig  # (K, m, P)
        Si = np.eye(B.shape[1]) + M @ np.swapaxes(B, 1, 2)
        T = np.einsum("rp,kmp->krm", A, M)  # A Sigma B_i^T
        gain = np.einsum("krm,krm->k", T, np.linalg.solve(Si, np.swapaxes(T, 1, 2)).swapaxes(1, 2))
        gain[chosen] = -np.inf
        i = int(np.argmax(gain))
        chosen.append(i)
        Sig = Sig - M[i].T @ np.linalg.solve(Si[i], M[i])
        promised, left = unseen.recalibrated(Sig, J_new[chosen].reshape(-1, len(names)))
        after.append(float(np.sqrt((max(np.trace(A @ promised @ A.T), 0.0) + floor) / (n * len(workspace.frames)))))
    left_rms = float(np.sqrt(max(np.trace(A @ left @ A.T), 0.0) / (n * len(workspace.frames)))) if chosen else 0.0
    return NextPoses(
        loop=b.loop.name,
        joints=tuple(problem.joints),
        readings=C[chosen],
        rms_before_m=before,
        rms_after_m=np.array(after),
        candidates=int(C.shape[0]),
        unseen_rms_m=left_rms,
    )
