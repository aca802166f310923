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

import numpy as np
from scipy.optimize import brentq

__all__ = ["joint_variance_scale"]


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


def joint_variance_scale(residuals: list[np.ndarray], jq: list[np.ndarray], covs: list[np.ndarray | None],
                         pattern: np.ndarray, n_params: int) -> float:
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
        out = float(np.sum(mu * z2 / d ** 2) - c * np.sum(mu / d))
        if bare_rank:
            out += bare_quad / s ** 2 - c * bare_rank / s
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
    return float(brentq(score, lo, hi, xtol=1e-14 * hi, rtol=1e-10))
