"""The joint-noise level when an external measurement's noise is known (variance components).

Each configuration's closure residual has the covariance (errors in variables,
Wampler, Hollerbach & Arai 1995; thesis eq. 3.17 weighted)

    W_i(s) = s A_i + C_i,      A_i = J_theta,i D^2 J_theta,i^T,

with D the per-joint noise pattern (relative levels), s the unknown joint
variance scale (joint sigma_j = sqrt(s) D_j) and C_i the covariance of an
external measurement (a tracker, ``sigma_t``/``sigma_r`` of a measured loop;
0 for a closed loop).  With C_i = 0 everywhere s only scales the weights and
is estimated from the final residual as usual; with a known C_i the *ratio*
of joint noise to measurement noise decides the weighting, so s must be
estimated: reading the tracker noise as joint noise (or ignoring it) costs
accuracy, most visibly when the joints are almost noise free.

Estimate: the zero of the Gaussian likelihood's score in s,

    sum_i r_i^T W_i^-1 A_i W_i^-1 r_i  =  c sum_i tr(W_i^-1 A_i),

with c = (M - p) / M for the M residual rows and p estimated parameters (the
fitted residual is smaller than the noise by that fraction; a REML-like
correction).  In the coordinates that whiten C_i (C_i = L L^T, L^-1 A_i L^-T =
U diag(mu) U^T, z = U^T L^-1 r_i) both sides are sums of scalars,

    sum mu z^2 / (s mu + 1)^2  =  c sum mu / (s mu + 1),

and for a block without measurement (A_i = U diag(mu) U^T, z = U^T r_i) they
are sum z^2 / (mu s^2) and c rank(A_i) / s.  If even s = 0 leaves the left
side below the right (the residual is all measurement noise), s = 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from closedloop.errors import ParameterError
from closedloop.parallel.chunks import chunk_threads, for_each_chunk

if TYPE_CHECKING:
    from closedloop.problem.problem import BlockEval, BlockNoise, CalibrationProblem

BlockRoot = tuple[np.ndarray, int]  # a block's W^-1/2 (N, m, m) and its rank deficit
GroupRoot = tuple[np.ndarray, int, tuple[int, ...], np.ndarray]  # a group's W^-1/2, deficit, blocks, indices
Roots = list[BlockRoot | GroupRoot | None]  # `whiten`'s roots: per block (None: unweighted), then per group

__all__ = ["joint_variance_scale", "noise_vector", "whiten", "whiten_block", "cholesky_inverse", "pinv_sqrt"]


def _eig_terms(A: np.ndarray, r: np.ndarray, C: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(mu, z^2) per configuration and direction; mu = 0 where joint noise cannot act."""
    if C is not None:
        Li = np.linalg.inv(np.linalg.cholesky(C))
        A = Li @ A @ Li.T
        r = r @ Li.T
    mu, U = np.linalg.eigh(A)
    z = np.einsum("nji,nj->ni", U, r)
    tiny = mu <= 1e-12 * np.maximum(mu[:, -1:], 1e-300)
    return np.where(tiny, 0.0, mu), np.where(tiny, 0.0, z * z)


def joint_variance_scale(
    residuals: list[np.ndarray], jq: list[np.ndarray], covs: list[np.ndarray | None], pattern: np.ndarray, n_params: int
) -> float:
    """The joint variance scale s (joint sigma = sqrt(s) * pattern) from fitted residuals.

    Args:
        residuals: per loop block, the unweighted closure residuals (N, m).
        jq: per block, d r / d readings (N, m, n_joints).
        covs: per block, the measurement covariance (m, m), or None (a closed loop).
        pattern: relative noise level of each joint (n_joints,).
        n_params: number of estimated parameters (for the degrees of freedom).
    """
    mus, z2s, bare_quad, bare_rank = [], [], 0.0, 0
    for r, J, C in zip(residuals, jq, covs):
        Jd = J * pattern[None, None, :]
        mu, z2 = _eig_terms(Jd @ np.swapaxes(Jd, 1, 2), r, C)
        if C is None:
            live = mu > 0
            bare_quad += float(np.sum(z2[live] / mu[live]))
            bare_rank += int(live.sum())
        else:
            mus.append(mu.ravel())
            z2s.append(z2.ravel())
    mu = np.concatenate(mus) if mus else np.zeros(0)
    z2 = np.concatenate(z2s) if z2s else np.zeros(0)
    rows = sum(r.size for r in residuals)
    c = max(rows - n_params, 1) / max(rows, 1)
    if not mu.size:  # no measured loop: the usual closed form
        return bare_quad / max(c * bare_rank, 1e-300)

    def score(s: float) -> float:
        d = s * mu + 1.0
        out = float(np.sum(mu * z2 / d**2) - c * np.sum(mu / d))
        if bare_rank:
            out += bare_quad / s**2 - c * bare_rank / s
        return out

    if not bare_rank and score(0.0) <= 0.0:
        return 0.0
    hi = 1.0 / max(float(mu.max()), 1e-300)  # where joint noise equals the measurement noise
    for _ in range(200):
        if score(hi) < 0.0:
            break
        hi *= 4.0
    lo = hi / 4.0
    for _ in range(200):
        if score(lo) > 0.0:
            break
        lo /= 4.0
        if lo < 1e-300:
            return 0.0
    from scipy.optimize import brentq  # ~0.15 s to import: only for this estimate

    return float(brentq(score, lo, hi, xtol=1e-14 * hi, rtol=1e-10))


# --------------------------------------------------------------------------- whitening
def noise_vector(problem: CalibrationProblem, noise) -> tuple[np.ndarray, bool]:
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


def cholesky_inverse(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """L^-1 for a stack of symmetric positive semi-definite A = L L^T (n, m, m), and kappa (n,).

    kappa = tr(A) tr(A^-1) = tr(A) |L^-1|_F^2 bounds the condition number:
    lambda_max <= tr A and 1/lambda_min <= tr A^-1, so every eigenvalue of A
    exceeds lambda_max / kappa.  Where A is not positive definite (or nearly
    so) kappa is inf and L^-1 meaningless.  Cholesky and forward substitution
    entry by entry over the whole stack, laid out (m, m, n) so that each step is a
    product of rows of n contiguous numbers (a LAPACK call per small matrix costs
    more than the arithmetic; the stack's own (n, m, m) order, four times as long).
    """
    m = A.shape[-1]
    S = np.ascontiguousarray(np.moveaxis(A, 0, 2))  # (m, m, n)
    L = np.zeros_like(S)
    X = np.zeros_like(S)
    with np.errstate(divide="ignore", invalid="ignore"):
        for j in range(m):
            d = S[j, j] - np.einsum("kn,kn->n", L[j, :j], L[j, :j]) if j else S[j, j]
            L[j, j] = np.sqrt(d)
            for i in range(j + 1, m):
                s = S[i, j] - np.einsum("kn,kn->n", L[i, :j], L[j, :j]) if j else S[i, j]
                L[i, j] = s / L[j, j]
        for i in range(m):  # L X = I, X lower triangular
            X[i, i] = 1.0 / L[i, i]
            for j in range(i):
                X[i, j] = -np.einsum("kn,kn->n", L[i, j:i], X[j:i, j]) * X[i, i]
        kappa = np.trace(S) * np.einsum("ijn,ijn->n", X, X)
    return np.moveaxis(X, 2, 0), np.where(np.isfinite(kappa), kappa, np.inf)


def pinv_sqrt(W: np.ndarray) -> tuple[np.ndarray, int]:
    """Symmetric pseudo-inverse square roots V diag(lambda^-1/2) V^T of a stack of covariances.

    Eigenvalues below 1e-9 of the largest are dropped; returns the roots and the number dropped.
    """
    lam, V = np.linalg.eigh(W)
    keep = lam > 1e-9 * np.maximum(lam[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
    return (V * inv[:, None, :]) @ np.swapaxes(V, 1, 2), int(np.sum(~keep))


def whiten(
    evals: list[BlockEval],
    sigma_q: np.ndarray,
    weighting: str,
    jacobian: bool = True,
    loops: Sequence[BlockNoise] | None = None,
    Winv: Roots | None = None,
    symmetric: bool = True,
    overwrite: bool = False,
) -> tuple[np.ndarray, np.ndarray | None, Roots]:
    """Stack residuals (and Jacobians) whitened by W_i^-1/2, W_i = Jq Sigma Jq^T (+ measurement covariance).

    `Winv` reuses the W_i^-1/2 of an earlier evaluation (trial steps, which
    have no Jq); the W_i^-1/2 used are returned so that the caller can.
    A residual direction that no joint noise can produce (W_i singular, e.g. a
    passive joint eliminated by projection) gets zero weight: W^-1/2 is the
    pseudo-inverse square root (eigenvalues below 1e-9 of the largest dropped),
    never an amplification by a tiny regulariser.
    With `symmetric` False any square root F of the pseudo-inverse (F^T F = W^+)
    may stand for W^-1/2: the inverse Cholesky factor L^-1 where W_i is well
    conditioned (kappa of `cholesky_inverse` below 1e9, so that nothing would
    be dropped), the symmetric root elsewhere.  Each configuration's whitened
    rows are then turned by an orthogonal matrix, which changes neither
    |r|^2, nor J^T J, nor J^T r: the least-squares problem is the same, at a
    fraction of the cost of the eigendecompositions.
    Configurations whose readings several blocks use (the same log row,
    `BlockEval.rows`: two cameras seeing one marker) are
    whitened together: their stacked residual has the covariance
    J_theta Sigma J_theta^T of the stacked J_theta (+ each block's measurement
    covariance on the diagonal), so the joint noise they share counts once
    (`_config_groups`; the symmetric root).
    With `overwrite` the blocks' J are whitened in place (the caller's
    evaluations are its own, used once): a large log then costs no second
    copy of J.
    Returns (r, J or None, list of (W^-1/2, rank deficit) per block, or None
    entries, then one (W^-1/2, deficit, blocks, indices) per group of blocks).
    """
    groups = _config_groups(evals) if weighting == "noise" else []
    overwrite = overwrite and not groups  # a group is whitened from its blocks' own J, after them
    shared = [np.zeros(ev.r.shape[0], dtype=bool) for ev in evals]
    for pattern, idx in groups:
        for k, bi in enumerate(pattern):
            shared[bi][idx[:, k]] = True
    rs: list[np.ndarray] = []
    Js: list[np.ndarray] = []
    used: Roots = []
    for bi, ev in enumerate(evals):
        entry = Winv[bi] if Winv is not None else None
        Wh, deficit = (entry[0], entry[1]) if entry is not None else (None, 0)
        if weighting == "noise" and Wh is None and ev.Jq is not None:
            C = loops[bi].measurement_cov if loops is not None else None
            Wh, deficit = _roots(ev.Jq, sigma_q, C, shared[bi], symmetric)
        rs.append(np.einsum("nij,nj->ni", Wh, ev.r) if Wh is not None else ev.r)
        if jacobian:
            Jb = _given(ev.J, f"block {bi}'s Jacobian")
            Js.append(_times(Wh, Jb, overwrite) if Wh is not None else Jb)
        used.append((Wh, deficit) if Wh is not None else None)
    for gi, (pattern, idx) in enumerate(groups):
        cached = Winv[len(evals) + gi] if Winv is not None and len(Winv) > len(evals) + gi else None
        if cached is None and any(evals[bi].Jq is None for bi in pattern):
            continue  # no Jacobian to weight with: left as the blocks had them (unweighted rows)
        Wh, deficit = cached[:2] if cached is not None else _group_root(evals, pattern, idx, sigma_q, loops)
        _whiten_group(evals, pattern, idx, Wh, rs, Js if jacobian else None)
        used.append((Wh, deficit, pattern, idx))
    r = np.concatenate([x.ravel() for x in rs]) if rs else np.zeros(0)
    J: np.ndarray | None = None
    if jacobian and Js:  # one block: its rows as they are (a copy of J costs as much as the whitening)
        J = Js[0].reshape(-1, Js[0].shape[-1]) if len(Js) == 1 else np.vstack([x.reshape(-1, x.shape[-1]) for x in Js])
    return r, J, used


def whiten_block(
    ev: BlockEval, sigma_q: np.ndarray, weighting: str, noise: BlockNoise
) -> tuple[np.ndarray, np.ndarray]:
    """One block whitened on its own (`whiten` of ``[ev]``): its residual (N, m) and Jacobian (N, m, C)."""
    N, m = ev.r.shape
    r, J, _ = whiten([ev], sigma_q, weighting, True, [noise])
    return r.reshape(N, m), _given(J, "the block's Jacobian").reshape(N, m, -1)


_CHUNK = 8192  # configurations whitened at a time (`_roots`, `_times`): their temporaries stay in cache


def _roots(
    Jq: np.ndarray, sigma_q: np.ndarray, C: np.ndarray | None, shared: np.ndarray, symmetric: bool
) -> tuple[np.ndarray, int]:
    """W_i^-1/2 of W_i = Jq_i Sigma Jq_i^T + C (eq. 3.17) for a block's configurations, and the rank deficit.

    A chunk of configurations at a time.  With `symmetric` the pseudo-inverse square root (`pinv_sqrt`),
    else the inverse Cholesky factor where W_i is well conditioned and the symmetric root elsewhere
    (`whiten`).  Configurations `shared` with other blocks get a zero placeholder (whitened as a group).
    """
    N, m = Jq.shape[:2]
    Wh = np.empty((N, m, m))
    starts = list(range(0, N, _CHUNK))
    deficits = [0] * len(starts)

    def chunk(a: int, _slot: None) -> None:
        Js = Jq[a : a + _CHUNK] * sigma_q
        W = Js @ np.swapaxes(Js, 1, 2)
        if C is not None:
            W += C
        sh = shared[a : a + _CHUNK]
        if sh.any():
            W[sh] = np.eye(m)
        d = 0
        if symmetric:
            Wh[a : a + _CHUNK], d = pinv_sqrt(W)
        else:
            Wh[a : a + _CHUNK], kappa = cholesky_inverse(W)
            ill = np.flatnonzero(kappa >= 1e9)
            if ill.size:
                Wh[a + ill], d = pinv_sqrt(W[ill])
        deficits[a // _CHUNK] = d
        if sh.any():
            Wh[a : a + _CHUNK][sh] = 0.0

    for_each_chunk(chunk, starts, [None] * chunk_threads(len(starts)))
    return Wh, sum(deficits)


def _given(a: np.ndarray | None, what: str) -> np.ndarray:
    """`a`, an array the caller's evaluation must hold (asked for); a ValueError naming `what` if it does not."""
    if a is None:
        raise ValueError(f"{what} was not evaluated; whitening needs it")
    return a


def _times(Wh: np.ndarray, J: np.ndarray, overwrite: bool) -> np.ndarray:
    """Wh @ J for stacks (N, m, m) and (N, m, C), a chunk of configurations at a time (on threads,
    `parallel.chunks`); with `overwrite`, into J where it is writable (a kept evaluation is shared read-only:
    `problem.blocks.read_only`)."""
    if J.shape[0] <= _CHUNK:
        return Wh @ J if not (overwrite and J.flags.writeable) else np.matmul(Wh, J, out=J)
    dest = J if overwrite and J.flags.writeable else np.empty(J.shape)
    starts = list(range(0, J.shape[0], _CHUNK))

    def chunk(a: int, _slot: None) -> None:
        dest[a : a + _CHUNK] = Wh[a : a + _CHUNK] @ J[a : a + _CHUNK]

    for_each_chunk(chunk, starts, [None] * chunk_threads(len(starts)))
    return dest


def _whiten_group(
    evals: list[BlockEval],
    pattern: tuple[int, ...],
    idx: np.ndarray,
    Wh: np.ndarray,
    rs: list[np.ndarray],
    Js: list[np.ndarray] | None,
) -> None:
    """Rows of one group of configurations whitened together, written back into each block's rows."""
    R = np.concatenate([evals[bi].r[idx[:, k]] for k, bi in enumerate(pattern)], axis=1)
    Z = np.einsum("nij,nj->ni", Wh, R)
    JJ = (
        Wh
        @ np.concatenate(
            [_given(evals[bi].J, f"block {bi}'s Jacobian")[idx[:, k]] for k, bi in enumerate(pattern)], axis=1
        )
        if Js is not None
        else None
    )
    off = 0
    for k, bi in enumerate(pattern):
        m = evals[bi].r.shape[1]
        rs[bi][idx[:, k]] = Z[:, off : off + m]
        if Js is not None and JJ is not None:
            Js[bi][idx[:, k]] = JJ[:, off : off + m]
        off += m


_GROUPS: dict[tuple, list] = {}  # `_config_groups` by the blocks' rows: a fit asks for the same ones every iteration


def _config_groups(evals: list[BlockEval]) -> list[tuple[tuple[int, ...], np.ndarray]]:
    """Log rows read by several blocks: per pattern of blocks, the (K, len(pattern)) configuration indices."""
    if sum(ev.rows is not None for ev in evals) < 2:
        return []
    key = tuple(
        None if ev.rows is None else (np.asarray(ev.rows).dtype.str, np.asarray(ev.rows).tobytes()) for ev in evals
    )
    if key in _GROUPS:
        return _GROUPS[key]
    where: dict[int, list[tuple[int, int]]] = {}
    for bi, ev in enumerate(evals):
        if ev.rows is None:
            continue
        for i, row in enumerate(np.asarray(ev.rows).tolist()):
            where.setdefault(int(row), []).append((bi, i))
    patterns: dict[tuple[int, ...], list[list[int]]] = {}
    for members in where.values():
        if len(members) > 1:
            patterns.setdefault(tuple(b for b, _ in members), []).append([i for _, i in members])
    out = [(pat, np.array(ix, dtype=int)) for pat, ix in patterns.items()]
    if len(_GROUPS) >= 16:
        _GROUPS.clear()
    _GROUPS[key] = out
    return out


def _group_root(
    evals: list[BlockEval],
    pattern: tuple[int, ...],
    idx: np.ndarray,
    sigma_q: np.ndarray,
    loops: Sequence[BlockNoise] | None,
) -> tuple[np.ndarray, int]:
    """W^-1/2 of the stacked residuals of one configuration in several blocks (their joint noise shared)."""
    Jq = (
        np.concatenate([_given(evals[bi].Jq, f"block {bi}'s Jq")[idx[:, k]] for k, bi in enumerate(pattern)], axis=1)
        * sigma_q[None, None, :]
    )
    W = Jq @ np.swapaxes(Jq, 1, 2)
    off = 0
    for bi in pattern:
        m = evals[bi].r.shape[1]
        C = loops[bi].measurement_cov if loops is not None else None
        if C is not None:
            W[:, off : off + m, off : off + m] += C
        off += m
    return pinv_sqrt(W)
