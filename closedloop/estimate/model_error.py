"""Model error as a hypothesis: does joint noise explain the residual, and which estimator predicts best.

The errors-in-variables fit (thesis 3.2, eq. 3.17 weighting) treats the
whole closure residual as the image of joint-reading noise,
W_i = J_theta,i Sigma J_theta,i^T.  On a real robot most of the residual is
model error (elasticity, gearing, a commanded rather than measured joint),
and the weighting then only reshuffles the configurations' weights.  Three
pieces of evidence decide, read off the data:

* **chi-square**: the joint noise the weighted residual implies,
  sigma_hat = sigma_r mean(sigma_q), against a plausible encoder noise
  (`ENCODER_NOISE`, or the noise the user gave): the hypothesis fails when
  (sigma_hat / sigma_0)^2, the chi-square per degree of freedom at sigma_0,
  is above 1 + 3 sqrt(2 / dof);
* **structure**: the residual's correlation between each configuration and
  its nearest neighbour in joint space (`neighbour_correlation`): ~0 for
  independent noise, near 1 for a smooth misfit across the workspace;
* **held-out against training**: the leave-one-configuration-out prediction
  of each fit (`loo_prediction`, exact to first order: the hat matrix of the
  configuration's rows), the unweighted closure a configuration left out of
  the fit would show, reported for both estimators.

Where the noise hypothesis fails the calibration is the plain loop-closure
fit (eq. 3.8), with the same outlier screen (a robust loss).

Where the residual is not the assumed noise, the error bars are the sandwich
(Huber-White) covariance clustered by configuration (`sandwich_cov`):
Cov = c A^+ (sum_c J_c^T r_c r_c^T J_c) A^+, A = J^T J.  A cluster is a cell of
joint space (`configuration_cells`): readings of one configuration repeated (a
pose held while the log runs, a log tiled with noise) share their model error,
and counted as independent they would make the error bars too small by up to
the square root of the repeats; the noise model's variances against these are
the verdict's check that the error bars hold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from closedloop.estimate.qr import scaled_r_factor_of_blocks
from closedloop.parallel.chunks import chunk_threads, for_each_chunk
from closedloop.problem.problem import CalibrationProblem, even_sample

#: rad (m for prismatic joints): a joint reading worse than this is no encoder noise (0.01 deg)
ENCODER_NOISE = 2e-4
#: the estimators, and where the error bars come from (`NoiseRecord.estimator`, `.error_bars`)
EIV, PLAIN = "errors in variables", "plain least squares"
NOISE_MODEL, SANDWICH = "the noise model", "the sandwich covariance by configuration"


@dataclass(frozen=True)
class NoiseTest:
    """The test of the hypothesis 'joint noise explains the residual' (module docstring)."""

    sigma_hat: float  # joint noise the weighted residual implies (rad)
    sigma_0: float  # the noise it is tested against: given, or `ENCODER_NOISE`
    chi2_per_dof: float  # (sigma_hat / sigma_0)^2
    limit: float  # 1 + 3 sqrt(2 / dof)
    neighbour_rho: float  # `neighbour_correlation` of the weighted residual
    holds: bool

    def describe(self) -> str:
        """One line: the figures and the conclusion."""
        implied = (
            "no joint noise (the task's own noise explains it)"
            if self.sigma_hat <= 1e-12
            else f"{self.sigma_hat:.3g} rad of joint noise"
        )
        verdict = "explains" if self.holds else "does not explain"
        against = "within" if self.holds else "more than"
        return (
            f"joint noise {verdict} the residual: it implies {implied}, {against} the {self.sigma_0:.3g} rad "
            f"tested against (chi-square/dof {self.chi2_per_dof:.3g}, limit {self.limit:.3g}); "
            f"nearest-configuration residual correlation {self.neighbour_rho:.2f}"
        )


def noise_test(sigma_hat: float, sigma_0: float, dof: int, rho: float) -> NoiseTest:
    """`NoiseTest` of an implied joint noise `sigma_hat` against `sigma_0` with `dof` degrees of freedom."""
    chi = (sigma_hat / sigma_0) ** 2 if sigma_0 > 0 else np.inf
    limit = 1.0 + 3.0 * np.sqrt(2.0 / max(dof, 1))
    return NoiseTest(float(sigma_hat), float(sigma_0), float(chi), float(limit), float(rho), bool(chi <= limit))


def _config_rows(problem: CalibrationProblem) -> list[tuple[int, int, int]]:
    """(first row, configurations, rows per configuration) of each block in the stacked residual."""
    out, at = [], 0
    for b in problem.blocks:
        n, m = b.theta.shape[0], b.loop.dim
        out.append((at, n, m))
        at += n * m
    return out


#: configurations above which `nearest_other` searches a k-d tree (below: blocks of exact distances, no
#: SciPy import; at 4,096 rows the tree is 8 times faster)
KD_TREE_ROWS = 2048
#: configurations above which `neighbour_correlation` pools a sample of this many
NEIGHBOUR_SAMPLE = 4096
_DISTANCE_BLOCK = 512  # rows of one block of exact distances (a block is this many x N)


def nearest_other(points: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """Index of the nearest other row of `points` (Euclidean) to each row of `rows` (default: every row);
    a duplicate row's nearest is its copy.

    Above `KD_TREE_ROWS` points by a k-d tree (O(N log N) to build, O(log N) a query, O(N) memory; in
    joint space a query costs 10-200 us); below, by exact distances a block of rows at a time (O(N^2) time,
    `_DISTANCE_BLOCK` x N memory), which spares short logs the import of ``scipy.spatial``.
    """
    n = points.shape[0]
    rows = np.arange(n) if rows is None else np.asarray(rows)
    if n > KD_TREE_ROWS:
        from scipy.spatial import cKDTree  # loaded on first use: short logs never pay for it

        idx = cKDTree(points).query(points[rows], k=2)[1]
        return np.where(idx[:, 0] == rows, idx[:, 1], idx[:, 0])
    out = np.empty(rows.size, dtype=np.intp)
    sq = np.sum(points**2, axis=1)
    for lo in range(0, rows.size, _DISTANCE_BLOCK):
        at = rows[lo : lo + _DISTANCE_BLOCK]
        d2 = sq[at, None] + sq[None, :] - 2.0 * points[at] @ points.T
        d2[np.arange(at.size), at] = np.inf
        out[lo : lo + at.size] = np.argmin(d2, axis=1)
    return out


def neighbour_correlation(problem: CalibrationProblem, r: np.ndarray) -> float:
    """Pooled correlation of each configuration's residual with its nearest neighbour's (joint space).

    rho = sum_i r_i . r_nn(i) / sum_i |r_i|^2 over the blocks (a block's residual rows per configuration,
    the readings' Euclidean distance).  Independent noise gives ~0 (standard error ~1/sqrt(N)); a misfit
    that varies smoothly over the workspace, near 1.  A block of more than `NEIGHBOUR_SAMPLE` configurations
    contributes `NEIGHBOUR_SAMPLE` of them, evenly spaced, each with its nearest among all (a ratio
    estimator: standard error ~1/sqrt(NEIGHBOUR_SAMPLE) = 0.016 for independent noise), so the cost grows
    as N log N.  On readings that repeat configurations with noise of the size of the distance between
    them (a tiled log), the nearest copy is the one whose noise is most alike: rho is then positive
    without any misfit.
    """
    num = den = 0.0
    for (at, n, m), b in zip(_config_rows(problem), problem.blocks):
        if n < 3:
            continue
        R = r[at : at + n * m].reshape(n, m)
        i = np.arange(n) if n <= NEIGHBOUR_SAMPLE else np.linspace(0, n - 1, NEIGHBOUR_SAMPLE).astype(np.intp)
        nn = nearest_other(b.theta, i)
        num += float(np.sum(R[i] * R[nn]))
        den += float(np.sum(R[i] * R[i]))
    return num / den if den > 0 else 0.0


#: configurations per block above which `loo_prediction` is estimated on an evenly spaced sample of this many
LOO_SAMPLE = 8192


def _pinv_normal(
    J: np.ndarray, scale: np.ndarray, rcond: float = 1e-10, factors: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """(J^T J)^+ in the prior-scaled coordinates (J D), truncated at `rcond` of the largest singular value.

    From the triangle R of J D = Q R (formed a chunk of rows at a time): J D and R share their singular
    values and right singular vectors, and R is p x p where J has a row per residual.  `factors`: (S, Vt) of
    J D where the caller has them (`residual.ResidualFunction.factorised`): no pass over the rows."""
    if factors is None:
        R = scaled_r_factor_of_blocks([J], scale)
        _, S, Vt = np.linalg.svd(R, full_matrices=False)
    else:
        S, Vt = factors
    keep = S > rcond * (S[0] if S.size else 0.0)
    V = Vt[keep].T
    return (V / S[keep] ** 2) @ V.T


def left_out(
    problem: CalibrationProblem,
    r: np.ndarray,
    J: np.ndarray,
    Ainv: np.ndarray,
    scale: np.ndarray,
    picks: list[np.ndarray] | None = None,
):
    """Per block: (whitened left-out residuals (N, m), parameter changes (N, p) in scaled units) of each
    configuration c: r~_c = (I - H_c)^-1 r_c, H_c = J_c A^+ J_c^T, and dx_c = A^+ J_c^T r~_c.  With `picks`
    (indices per block), of those configurations only."""
    Js = J * scale if picks is None else J
    out = []
    for bi, (at, n, m) in enumerate(_config_rows(problem)):
        Jc = Js[at : at + n * m].reshape(n, m, -1)
        rc = r[at : at + n * m].reshape(n, m)
        if picks is not None:
            Jc, rc = Jc[picks[bi]] * scale, rc[picks[bi]]
        B = Jc @ Ainv  # (n, m, p)
        H = np.einsum("nip,njp->nij", B, Jc)
        I_H = np.eye(m)[None] - H
        try:
            rt = np.linalg.solve(I_H, rc[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a configuration that alone determines a direction: no prediction
            rt = np.einsum("nij,nj->ni", np.linalg.pinv(I_H), rc)
        out.append((rt, np.einsum("nip,ni->np", B, rt)))
    return out


def loo_prediction(
    problem: CalibrationProblem,
    x: np.ndarray,
    est: list[int],
    r: np.ndarray,
    J: np.ndarray,
    factors: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """RMS of the unweighted closure each configuration would show if left out of the fit (first order).

    `r`, `J`: the fit's own (whitened, for the weighted fit) residual and Jacobian over `est` at `x`.  The
    left-out fit moves the parameters by dx_c (`left_out`); the configuration's raw closure there is
    e_c + E_c dx_c, with e_c, E_c its unweighted residual and Jacobian.  A block of more than `LOO_SAMPLE`
    configurations is represented by `LOO_SAMPLE` of them, evenly spaced (`even_sample`; the RMS of a
    sample of 8,192 x m closures, ~1 % standard error), so that the cost stays that of the fit's last step.
    `factors`: (S, Vt) of J D, D the priors of `est`, where the caller has them (`_pinv_normal`).
    """
    scale = np.array([problem.params[k].prior for k in est])
    Ainv = _pinv_normal(J, scale, factors=factors)
    picks = [even_sample(n, LOO_SAMPLE) for _, n, _ in _config_rows(problem)]
    sampled = any(p.size < n for p, (_, n, _) in zip(picks, _config_rows(problem)))
    kept = problem.kept(x, est) if sampled else None  # the fit's own on a long log: its sample's rows
    if kept is not None:
        evals = [ev.take(p) for ev, p in zip(kept, picks)]
    else:
        evals = (problem.sampled(LOO_SAMPLE) if sampled else problem).evaluate(x, True, columns=est)
    total, count = 0.0, 0
    for ev, (_, dx) in zip(evals, left_out(problem, r, J, Ainv, scale, picks if sampled else None)):
        if ev.r.shape[0] == 0 or ev.rows is None:
            continue
        pred = ev.r + np.einsum("nip,np->ni", ev.J * scale, dx)
        if ev.valid is not None:
            pred = np.where(ev.valid, pred, 0.0)
        total += float(np.sum(pred**2))
        count += ev.r.size
    return float(np.sqrt(total / count)) if count else 0.0


_SUM_CHUNK = 16384  # configurations whose products `plain_linearization` forms at a time


def plain_linearization(
    problem: CalibrationProblem,
    x: np.ndarray,
    est: list[int],
    sigma_q: np.ndarray,
    thetas: list[np.ndarray] | None = None,
    evaluated: tuple[list[int], list] | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The plain loop-closure estimator (eq. 3.8) linearized at `x`: its Gauss-Newton step from `x`,
    dx = -A^+ sum_i J_i^T r_i, the decrease of the squared closure it predicts (sum_i J_i^T r_i)^T A^+ (...),
    and its first-order covariance under the errors-in-variables noise model
    (eq. 3.17), Cov = A^+ (sum_i J_i^T W_i J_i) A^+, with A = sum_i J_i^T J_i, J_i and r_i the closure
    Jacobian over the `est` columns and residual of configuration i, W_i = J_theta,i diag(sigma_q^2)
    J_theta,i^T + C_i (C_i a loop's measurement covariance).  A^+ in the parameters' prior units, directions
    below 1e-12 of the largest dropped; configurations several blocks share are taken as independent.
    Step and covariance in the parameters' own units, order `est`.

    `evaluated`: (columns, the problem's evaluations at `x` with the Jacobian over those columns, a superset
    of `est`), an evaluation the caller shares with other uses; None: evaluated here.  The sums are matrix
    products over all rows at once: sum_i J_i^T W_i J_i = M^T M + sum_i J_i^T C_i J_i, M the rows
    J_theta,i^T diag(sigma_q) J_i stacked."""
    scale = np.array([problem.params[k].prior for k in est], dtype=float)
    L = len(est)
    JtJ = np.zeros((L, L))
    meat = np.zeros((L, L))
    Jtr = np.zeros(L)
    if evaluated is None:
        evals, pick = problem.evaluate(x, True, thetas, columns=est), None
    else:
        at = {k: i for i, k in enumerate(evaluated[0])}
        evals, pick = evaluated[1], [at[k] for k in est]
    for ev, nz in zip(evals, problem.noise):
        if ev.J is None or ev.Jq is None or not ev.J.size:
            continue
        starts = list(range(0, ev.J.shape[0], _SUM_CHUNK))
        sums: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray]] = {}

        def chunk(a: int, _slot: None, ev=ev, nz=nz, sums=sums) -> None:  # the temporaries a chunk at a time
            e = slice(a, a + _SUM_CHUNK)
            J, Jq, r = ev.J[e] if pick is None else ev.J[e][:, :, pick], ev.Jq[e], ev.r[e]
            if ev.valid is not None:  # rows with no observation hold NaN (`BlockEval.valid`): they add nothing
                J, Jq, r = np.nan_to_num(J), np.nan_to_num(Jq), np.nan_to_num(r)
            Jq = Jq * sigma_q[None, None, :]
            rows = J.reshape(-1, L)  # unscaled: the sums are scaled once, below (no scaled copy of J)
            M = (np.swapaxes(Jq, 1, 2) @ J).reshape(-1, L)  # J_theta,i^T diag(sigma_q) J_i per configuration
            C = None if nz.measurement_cov is None else rows.T @ (nz.measurement_cov @ J).reshape(-1, L)
            sums[a] = (rows.T @ rows, M.T @ M, C, rows.T @ r.reshape(-1))

        for_each_chunk(chunk, starts, [None] * chunk_threads(len(starts)))
        for a in starts:  # summed in the order of the rows, whichever thread formed them
            jtj, mtm, c, jtr = sums[a]
            JtJ += jtj
            meat += mtm
            if c is not None:
                meat += c
            Jtr += jtr
    outer = np.outer(scale, scale)  # the sums of the prior-scaled J D: D (J^T J) D, D (M^T M) D, D J^T r
    JtJ, meat, Jtr = JtJ * outer, meat * outer, Jtr * scale
    Ainv = np.linalg.pinv(JtJ, rcond=1e-12, hermitian=True)
    return -(Ainv @ Jtr) * scale, Ainv @ meat @ Ainv * np.outer(scale, scale), float(Jtr @ Ainv @ Jtr)


def plain_covariance(
    problem: CalibrationProblem,
    x: np.ndarray,
    est: list[int],
    sigma_q: np.ndarray,
    thetas: list[np.ndarray] | None = None,
) -> np.ndarray:
    """First-order covariance of the plain loop-closure estimator under the errors-in-variables noise model
    (`plain_linearization`)."""
    return plain_linearization(problem, x, est, sigma_q, thetas)[1]


#: a cell of `configuration_cells` is this many joint-noise standard deviations wide, and at least `CELL_MIN`
#: (rad, or m for a prismatic joint): repeated readings of one pose spread over a few standard deviations
CELL_NOISE = 100.0
CELL_MIN = 1e-3


def configuration_cells(problem: CalibrationProblem, width: np.ndarray) -> list[np.ndarray]:
    """Per block, a cluster label per configuration: the cell of joint space its readings fall in, cells
    `width` wide per joint (the problem's joints).  Labels are shared across blocks (the same readings, the
    same cell).  Readings of one pose held or repeated fall in one cell, distinct poses in cells of their
    own; a log that moves slowly puts its neighbouring rows together, whose model error is shared too.

    A grid's borders fall anywhere: the readings of one pose that straddle one (on some of a dozen joints,
    most poses do) fall in two or more cells whose centres lie within a small fraction of a cell of each
    other.  A cell whose readings span less than `JOIN` of a cell in every joint (a piece of a pose, not a
    stretch of a moving log) joins the fullest cell whose centre (the mean of its readings) lies within `JOIN`
    of its own in every joint (`_joined`), so that a pose's readings are one cluster wherever the grid cuts
    them; the cells a moving log passes through stay as they are."""
    w = np.maximum(np.broadcast_to(np.asarray(width, dtype=float), (len(problem.joints),)), 1e-12)
    weights = np.random.default_rng(0).integers(1, 2**61, size=w.size, dtype=np.int64)  # a hash of the cell
    labels = [np.full(b.theta.shape[0], -1 - bi, dtype=np.int64) for bi, b in enumerate(problem.blocks)]
    own = [bi for bi, b in enumerate(problem.blocks) if b.theta.size and not getattr(b.loop, "parameter_only", False)]
    if not own:  # (a known length: one cluster)
        return labels
    Z = np.concatenate([problem.blocks[bi].theta / w for bi in own])
    joined = _joined(Z, np.floor(Z).astype(np.int64) @ weights)
    at = np.cumsum([0] + [problem.blocks[bi].theta.shape[0] for bi in own])
    for k, bi in enumerate(own):
        labels[bi] = joined[at[k] : at[k + 1]]
    return labels


#: a cell whose readings span less than this share of a cell joins a fuller one whose centre lies within it of
#: its own, in every joint (`configuration_cells`): the pieces of one pose's readings span a few noise
#: deviations, a hundredth of a cell, and lie as far apart; a moving log's cells, about a cell
JOIN = 0.25


def _joined(Z: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """`labels` (a cell per row of readings `Z` in cell units) with each cell whose readings span less than
    `JOIN` joined to the fullest cell whose centre lies within `JOIN` of its own in every joint (the first in
    label order on a tie; itself if none is fuller): one step, no chain of joins across cells.  Centres by a
    k-d tree above `KD_TREE_ROWS` cells (the 8 nearest), by exact distances below."""
    cells, inv = np.unique(labels, return_inverse=True)
    C = cells.size
    if C < 2:
        return labels
    counts = np.bincount(inv, minlength=C)
    order = np.argsort(inv, kind="stable")
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    span = np.maximum.reduceat(Z[order], starts, axis=0) - np.minimum.reduceat(Z[order], starts, axis=0)
    small = span.max(axis=1) < JOIN
    sums = np.stack([np.bincount(inv, weights=Z[:, j], minlength=C) for j in range(Z.shape[1])], axis=1)
    centres = sums / counts[:, None]
    key = counts.astype(np.int64) * (C + 1) + (C - np.arange(C))  # fuller first, then the first in label order
    if C > KD_TREE_ROWS:
        from scipy.spatial import cKDTree  # loaded on first use: short logs never pay for it

        d, nb = cKDTree(centres).query(centres, k=min(8, C), distance_upper_bound=JOIN, p=np.inf)
        nb = np.where(np.isfinite(d), nb, np.arange(C)[:, None])
        parent = nb[np.arange(C), np.argmax(key[nb], axis=1)]
    else:
        parent = np.empty(C, dtype=np.intp)
        for lo in range(0, C, _DISTANCE_BLOCK):
            near = np.max(np.abs(centres[lo : lo + _DISTANCE_BLOCK, None, :] - centres[None, :, :]), axis=2) < JOIN
            parent[lo : lo + _DISTANCE_BLOCK] = np.argmax(np.where(near, key[None, :], -1), axis=1)
    parent = np.where(small, parent, np.arange(C))
    return cells[parent][inv]


def sandwich_cov(
    problem: CalibrationProblem,
    r: np.ndarray,
    J: np.ndarray,
    scale: np.ndarray,
    V: np.ndarray,
    S: np.ndarray,
    clusters: list[np.ndarray],
) -> np.ndarray:
    """The sandwich (Huber-White) covariance clustered by configuration, with the usual small-sample factor.

    Cov = c A^+ (sum_g J_g^T r_g r_g^T J_g) A^+, the sum over the clusters g (all rows of the configurations of
    one cluster: per block, a label per configuration in `clusters`, `configuration_cells`), c = G/(G-1) (N-1)/(N-p) (CR1: G clusters, N rows, p parameters).
    `V`, `S`: the kept right singular vectors and values of the scaled J (the directions the fit determines);
    A^+ = V S^-2 V^T.  A block without configurations (a known distance) is one cluster.  Returns the
    covariance in the parameters' own units.
    """
    Ainv = (V / S**2) @ V.T
    parts = []
    for at, n, m in _config_rows(problem):
        R, Jb = r[at : at + n * m].reshape(n, m), J[at : at + n * m].reshape(n, m, -1)
        g = np.einsum("nm,nmp->np", R, Jb)  # J_g^T r_g per configuration, one pass over J (no copy of it)
        parts.append(g * scale)
    g = np.concatenate(parts) if parts else np.zeros((0, S.size))
    labels = [np.asarray(c) for c in clusters]
    _, inv = np.unique(np.concatenate(labels), return_inverse=True) if labels else (None, np.zeros(0, int))
    G = int(inv.max()) + 1 if inv.size else 0
    inv = inv.ravel()
    sums = np.zeros((G, g.shape[1]))  # each cluster's sum of J_g^T r_g, a column at a time (3x `np.add.at`)
    for k in range(g.shape[1]):
        sums[:, k] = np.bincount(inv, weights=g[:, k], minlength=G)
    meat = sums.T @ sums
    N, p = r.size, S.size
    c = G / max(G - 1, 1) * (N - 1) / max(N - p, 1)
    return c * Ainv @ meat @ Ainv * np.outer(scale, scale)
