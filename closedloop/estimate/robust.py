"""Robust losses and outlier flags per configuration.

The unit is a configuration: its m whitened closure rows share one weight.
With r_i (m,) the whitened residual of configuration i (``whiten``: W_i^-1/2
r_i, ~ N(0, s^2 I_m) under the noise model with s = 1 when the noise level
is right), the standardized residual is

    d_i = |r_i| / s,        s: a robust scale (MAD, below),

and d_i^2 ~ chi2(m) for a clean configuration.  IRLS weights (Holland &
Welsch 1977; Huber 1981):

    Huber:   w(d) = 1            if d <= c,   c / d   otherwise
    Cauchy:  w(d) = 1 / (1 + (d/c)^2)

applied as sqrt(w_i) to all m rows of configuration i.  Default tuning
constants are for m-dimensional residuals: Huber c = sqrt(chi2_m^-1(0.95))
(clean configurations are essentially never down-weighted), Cauchy
c = sqrt(chi2_m^-1(0.5)) (the median clean configuration gets weight 1/2).

Scale: s = 1.4826 * median_k |e_k - median(e)| over every scalar whitened
residual e_k of every configuration (Hampel's MAD, consistent for the
Gaussian; each whitened component has variance s^2).  With less than half
the configurations bad, s is not dragged by them.

Suspects: configurations with d_i beyond the chi(m) quantile at level
1 - alpha / N_total (Bonferroni over all configurations), each reported with
its row in the log and its standardized residual.

Outlier screening before any identifiability decision (`screen`): the
same standardized residuals, with a per-component robust scale where the
residual is not whitened (metres and radians mixed), and a floor under the
scale (exact data have a MAD at round-off, where every configuration would
look "suspect").  At a fit the residuals are studentized first
(`studentize`: each configuration's by its covariance under the fit, I - H_ii
for a row it used, I + H_ii for a row it left out), and beside a known
measurement covariance the unknown joint level is the median configuration's
(`median_joint_scale`), so that d_i^2 ~ chi2(m) holds for every clean row.  `calibrate` screens the plain fit; if anything is flagged it
refits robustly (IRLS with the Cauchy loss, which gross outliers cannot drag)
and rejects the flagged configurations before the final, unweighted-by-loss
fit on the inliers.

For integration in ``calibrate``: `config_residuals` gives the whitened
per-configuration residuals at given values; `irls` is a reference
iteratively reweighted Gauss-Newton over a fixed set of parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import OptionError
from closedloop.estimate.noise import noise_vector, whiten, whiten_block
from closedloop.problem.problem import CalibrationProblem

if TYPE_CHECKING:
    from closedloop.records import CalibrationResult

MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4)


def _log_gamma_tail(a: float, x: float, upper: bool) -> float:
    """log Q(a, x) (upper) or log P(a, x) = log(1 - Q): the regularized incomplete gamma functions.

    x < a + 1: the series P = x^a e^-x / Gamma(a) sum_n x^n / (a (a+1) ... (a+n)) (A&S 6.5.29);
    otherwise Lentz's continued fraction for Q = x^a e^-x / Gamma(a) / (x + 1 - a - 1(1-a)/(x + 3 - a - ...))
    (A&S 6.5.31); the tail not computed directly is log1p(-other), both to round-off.
    """
    if x <= 0.0:
        return 0.0 if upper else -math.inf
    if not math.isfinite(x):  # inf: all the mass below; nan: unknown
        return x if math.isnan(x) else (-math.inf if upper else 0.0)
    front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        n = 0
        while abs(term) > total * 1e-17 and n < 100000:
            n += 1
            term *= x / (a + n)
            total += term
        log_p = front + math.log(total)
        return (math.log1p(-math.exp(log_p)) if log_p < 0.0 else -math.inf) if upper else min(log_p, 0.0)
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for n in range(1, 100000):
        an = -n * (n - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            break
    log_q = front + math.log(h)
    return min(log_q, 0.0) if upper else (math.log1p(-math.exp(log_q)) if log_q < 0.0 else -math.inf)


def _chi2_quantile(p: float, df: float, upper: bool) -> float:
    """x with P(chi2_df > x) = p (upper) or P(chi2_df <= x) = p: safeguarded Newton on the log tail
    (d log Q / dx = -pdf / Q, d log P / dx = pdf / P), bisection where a step leaves the bracket."""
    if not 0.0 < p < 1.0:
        return (math.inf if p <= 0.0 else 0.0) if upper else (0.0 if p <= 0.0 else math.inf)
    target, k, sign = math.log(p), 0.5 * df, 1.0 if upper else -1.0
    lo, hi = 0.0, max(df, 1.0)
    while sign * (_log_gamma_tail(k, 0.5 * hi, upper) - target) > 0:  # the tail at hi still beyond p
        lo, hi = hi, 2.0 * hi
    x = 0.5 * (lo + hi)
    for _ in range(200):
        g = _log_gamma_tail(k, 0.5 * x, upper)
        f = sign * (g - target)  # > 0: x below the quantile
        lo, hi = (x, hi) if f > 0 else (lo, x)
        log_pdf = (k - 1.0) * math.log(x) - 0.5 * x - k * math.log(2.0) - math.lgamma(k)
        slope = math.exp(min(log_pdf - g, 700.0))  # |d log tail / dx|
        nxt = x + f / slope if slope > 0.0 else hi
        if not lo < nxt < hi:
            nxt = 0.5 * (lo + hi)
        if abs(nxt - x) <= 1e-15 * x:
            return nxt
        x = nxt
    return x


class _Chi2:
    """scipy.stats.chi2's sf, isf and ppf in plain Python (within ~1e-12 relative for the degrees
    of freedom of a loop): the package's one chi-square, used by the outlier screen, the robust losses
    and the report's p-value; nothing in the package imports `scipy.stats` or `scipy.special`
    (tests/test_one_way.py).  Their import costs more than a small calibration: measured (CPU s, least
    of 5, shared 2-core AMD EPYC at load 15) 0.35 s for `scipy.special`, 1.52 s for `scipy.stats` over
    numpy's 0.21 s, where `closedloop calibrate` of 200 configurations fits in ~0.5 s."""

    @staticmethod
    def sf(x, df):
        return math.exp(_log_gamma_tail(0.5 * float(df), 0.5 * float(x), True))

    @staticmethod
    def isf(p, df):
        return _chi2_quantile(float(p), float(df), True)

    @staticmethod
    def ppf(p, df):
        return _chi2_quantile(float(p), float(df), False)


class stats:  # noqa: N801  (read as scipy.stats at the call sites)
    chi2 = _Chi2


def default_c(loss: str, m: int) -> float:
    if loss == "huber":
        return float(np.sqrt(stats.chi2.ppf(0.95, m)))
    if loss == "cauchy":
        return float(np.sqrt(stats.chi2.ppf(0.5, m)))
    raise OptionError(f"loss must be 'huber' or 'cauchy', not '{loss}'")


def mad_scale(residual_blocks: list[np.ndarray]) -> float:
    """Robust std of the scalar whitened residuals: 1.4826 * MAD over all components."""
    e = np.concatenate([np.asarray(r, float).ravel() for r in residual_blocks]) if residual_blocks else np.zeros(0)
    if e.size == 0:
        return 1.0
    s = MAD_TO_SIGMA * float(np.median(np.abs(e - np.median(e))))
    return s if s > 0 else float(np.sqrt(np.mean(e**2))) or 1.0


def standardized(residual_blocks: list[np.ndarray], scale: float | None = None) -> list[np.ndarray]:
    """d_i = |r_i| / s per configuration, per block ((N,) each)."""
    s = mad_scale(residual_blocks) if scale is None else float(scale)
    return [np.linalg.norm(np.asarray(r, float), axis=1) / s for r in residual_blocks]


def component_standardized(residual_blocks: list[np.ndarray], floors: list[np.ndarray]) -> list[np.ndarray]:
    """d_i = |r_i / s| with a robust scale s_k per residual component of each block.

    For residuals that are not whitened (a weld's metres and radians):
    s_k = max(1.4826 MAD_k, floor_k) over the block's configurations.
    """
    out = []
    for r, fl in zip(residual_blocks, floors):
        r = np.asarray(r, float)
        if r.shape[0] == 0:
            out.append(np.zeros(0))
            continue
        mad = MAD_TO_SIGMA * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
        out.append(np.linalg.norm(r / np.maximum(mad, fl), axis=1))
    return out


def cauchy_weights(ds: list[np.ndarray], dims: list[int]) -> list[np.ndarray]:
    """Cauchy IRLS weights 1 / (1 + (d / c)^2) with c = sqrt(chi2_m^-1(0.5)) per block."""
    return [1.0 / (1.0 + (d / default_c("cauchy", m)) ** 2) for d, m in zip(ds, dims)]


def flagged(ds: list[np.ndarray], dims: list[int], alpha: float = 0.01) -> list[np.ndarray]:
    """Per block, the configurations with d_i^2 > chi2_m^-1(1 - alpha / N_total) (Bonferroni)."""
    n_total = max(sum(d.size for d in ds), 1)
    return [np.flatnonzero(d > np.sqrt(stats.chi2.isf(alpha / n_total, m))) for d, m in zip(ds, dims)]


def median_joint_scale(
    residuals: list[np.ndarray],
    jq: list[np.ndarray],
    covs: list[np.ndarray | None],
    pattern: np.ndarray,
    alpha: float = 0.01,
    max_rows: int = 1024,
) -> float:
    """The joint variance scale s at which the median configuration closes as the noise model expects.

    Each configuration's closure has the covariance W_i(s) = s A_i + C_i, A_i = J_theta,i D^2 J_theta,i^T
    (eq. 3.17 weighted; D = diag(`pattern`)) and C_i a loop's known measurement covariance (a tracker's
    sigma_t; None: a closed loop).  Its squared norm d_i^2(s) = r_i^T W_i(s)^+ r_i is chi2 with m_i = rank W_i
    degrees of freedom under the model and falls as s grows; s solves

        median_i d_i^2(s) / chi2_{m_i}^-1(1/2) = 1,

    the median configuration at the median of its chi-square, then again on the configurations within
    chi2_{m_i}^-1(1 - alpha / N) there (Bonferroni, as `flagged`), until that set settles: gross errors
    first shift the median (20 % of them double s), then leave.  The median is what up to half the
    configurations cannot drag: the ratio of joint to measurement noise an outlier screen can whiten with
    (`noise.joint_variance_scale`, the likelihood's, is pulled by every row).
    Returns 0 where the measurement covariance alone explains more than the median (nothing for the joints),
    and 1 where no block has a measurement covariance (s then only scales, which the screen's MAD absorbs).
    At most `max_rows` configurations, evenly spaced over the blocks, are used.
    """
    n_all = sum(r.shape[0] for r in residuals)
    if n_all == 0 or all(C is None for C in covs):
        return 1.0
    step = max(1, int(np.ceil(n_all / max_rows)))
    parts = []
    for r, J, C in zip(residuals, jq, covs):
        if r.shape[0] == 0:
            continue
        Jd = J[::step] * pattern[None, None, :]
        parts.append((r[::step], Jd @ np.swapaxes(Jd, 1, 2), C))
    top = max(r.shape[1] for r, _, _ in parts)
    med = np.array([np.nan] + [stats.chi2.ppf(0.5, m) for m in range(1, top + 1)])
    cut = np.array([np.nan] + [stats.chi2.isf(alpha / n_all, m) for m in range(1, top + 1)])

    def d2(s: float) -> tuple[np.ndarray, np.ndarray]:
        """d_i^2(s) and rank W_i over the configurations used."""
        out, ranks = [], []
        for r, A, C in parts:
            lam, V = np.linalg.eigh(s * A if C is None else s * A + C)
            keep = lam > 1e-9 * np.maximum(lam[:, -1:], 1e-300)
            z = np.einsum("nji,nj->ni", V, r)
            out.append(np.sum(np.where(keep, z * z / np.where(keep, lam, 1.0), 0.0), axis=1))
            ranks.append(keep.sum(axis=1))
        return np.concatenate(out), np.concatenate(ranks)

    def solve(inlier: np.ndarray) -> float:
        def excess(s: float) -> float:
            v, m = d2(s)
            use = inlier & (m > 0)
            return float(np.median(v[use] / med[m[use]])) if use.any() else 0.0

        if all(C is not None for _, _, C in parts) and excess(0.0) <= 1.0:
            return 0.0
        # where the joint term equals the measurement term, for the median configuration
        ratio = [np.trace(C) / np.maximum(np.trace(A, axis1=1, axis2=2), 1e-300) for _, A, C in parts if C is not None]
        hi = max(float(np.median(np.concatenate(ratio))), 1e-300)
        lo = hi
        for _ in range(200):
            if excess(hi) <= 1.0:
                break
            lo, hi = hi, hi * 10.0
        for _ in range(200):
            if excess(lo) > 1.0 or lo < 1e-300:
                break
            lo, hi = lo / 10.0, lo
        for _ in range(40):  # geometric bisection to 0.1 %
            if hi <= lo * 1.001:
                break
            mid = float(np.sqrt(lo * hi))
            lo, hi = (mid, hi) if excess(mid) > 1.0 else (lo, mid)
        return float(np.sqrt(lo * hi))

    inlier = np.ones(sum(r.shape[0] for r, _, _ in parts), dtype=bool)
    s = solve(inlier)
    for _ in range(5):
        v, m = d2(s)
        now = (m == 0) | (v <= np.where(m > 0, cut[m], np.inf))
        if np.array_equal(now, inlier) or now.sum() <= 0.5 * now.size:
            break
        inlier = now
        s = solve(inlier)
    return s


def studentize(
    residual_blocks: list[np.ndarray],
    jacobian_blocks: list[np.ndarray],
    weights: list[np.ndarray],
    scale: np.ndarray | None = None,
    floor: float = 0.0,
) -> list[np.ndarray]:
    """Whitened residuals of a weighted least-squares fit, each configuration's divided by its own spread.

    residual_blocks: per block, (N, m) whitened residuals at the fit; jacobian_blocks: (N, m, p) their
    whitened Jacobian in the fitted parameters; weights: (N,) the weight the fit gave each configuration
    (1: an ordinary row, 0: left out).  The fit leaves e = (I - J K J^T W) eps with K = (J^T W J)^+,
    so configuration i's residual has the covariance

        S_i = I - 2 w_i H_ii + J_i K (J^T W^2 J) K J_i^T,        H_ii = J_i K J_i^T,

    I - H_ii for a row of the fit (its m degrees of freedom less tr H_ii, the share the fit used) and
    I + H_ii for a row left out (the fit's own error added).  K is the fit's own (`lm`, eq. 4.2.6): on
    the columns scaled by `scale` (the parameters' priors; None: unit columns), the directions of
    W^1/2 J with singular values at or below `floor` (snr x the noise level) are truncated, held by the
    fit and so moved by no noise; without that, a direction only the left-out rows determine would
    give them any spread.  Returns S_i^-1/2 e_i (symmetric root; components along an eigenvalue of S_i
    below 1e-6, directions a row's fit passes through, set to 0): N(0, 1) components under the noise
    model whatever each row's share of the fit.
    """
    dims = [r.shape[1] for r in residual_blocks]
    p = jacobian_blocks[0].shape[2] if jacobian_blocks else 0
    J = np.vstack([j.reshape(-1, p) for j in jacobian_blocks]) if p else np.zeros((0, 0))
    if not p or not J.size:
        return [np.asarray(r, float).copy() for r in residual_blocks]
    w_rows = np.concatenate([np.repeat(w, m) for w, m in zip(weights, dims)])
    if scale is None:
        norm = np.linalg.norm(J, axis=0)
        scale = 1.0 / np.where(norm > 0, norm, 1.0)
    J = J * scale
    _, S, Vt = np.linalg.svd(np.sqrt(w_rows)[:, None] * J, full_matrices=False)
    keep = S > max(floor, 1e-10 * (S[0] if S.size else 0.0))
    K = (Vt[keep].T / S[keep] ** 2) @ Vt[keep]
    JK = J @ K
    JKG = JK @ (J.T @ ((w_rows**2)[:, None] * J))
    out, off = [], 0
    for r, w, m in zip(residual_blocks, weights, dims):
        n = r.shape[0]
        sl = slice(off, off + n * m)
        Jb, JKb, JKGb = (a[sl].reshape(n, m, p) for a in (J, JK, JKG))
        Sc = np.eye(m) - 2.0 * np.asarray(w, float)[:, None, None] * np.einsum("nap,nbp->nab", JKb, Jb)
        Sc += np.einsum("nap,nbp->nab", JKGb, JKb)
        lam, V = np.linalg.eigh(0.5 * (Sc + np.swapaxes(Sc, 1, 2)))
        live = lam > 1e-6
        z = np.einsum("nji,nj->ni", V, np.asarray(r, float))
        z = np.where(live, z / np.sqrt(np.where(live, lam, 1.0)), 0.0)
        out.append(np.einsum("nij,nj->ni", V, z))
        off += n * m
    return out


def weights(
    residual_blocks: list[np.ndarray], loss: str = "huber", c: float | None = None, scale: float | None = None
) -> list[np.ndarray]:
    """IRLS weights, one per configuration ((N,) per block), from whitened residual blocks (N, m).

    scale: the residual scale s (None: the MAD estimate; give 1.0 to trust a
    known noise level).  c: tuning constant in units of s (None: the default
    for the block's m, see the module docstring).
    """
    if loss not in ("huber", "cauchy"):
        raise OptionError(f"loss must be 'huber' or 'cauchy', not '{loss}'")
    ds = standardized(residual_blocks, scale)
    out = []
    for r, d in zip(residual_blocks, ds):
        m = np.asarray(r).shape[1] if np.asarray(r).ndim == 2 else 1
        cc = default_c(loss, m) if c is None else float(c)
        if loss == "huber":
            w = np.where(d <= cc, 1.0, cc / np.maximum(d, 1e-300))
        else:
            w = 1.0 / (1.0 + (d / cc) ** 2)
        out.append(w)
    return out


@dataclass
class Suspect:
    """A configuration whose closure error the noise model does not explain."""

    block: int  # loop block
    index: int  # configuration within the block
    row: int | None  # data row in the log (1-based), when known
    loop: str | None
    standardized: float  # d = |W^-1/2 r| / s
    p_value: float  # P(chi2_m > d^2) for a clean configuration (not Bonferroni-corrected)
    weight: float  # its IRLS weight under `loss`


def suspects(
    residual_blocks: list[np.ndarray],
    rows: list[np.ndarray] | None = None,
    loops: list[str] | None = None,
    alpha: float = 0.01,
    scale: float | None = None,
    loss: str = "huber",
    c: float | None = None,
) -> list[Suspect]:
    """Configurations with d_i^2 > chi2_m^-1(1 - alpha / N_total), most suspect first.

    rows: per block, the log row numbers of its configurations (e.g.
    ``problem.blocks[i].rows``); loops: per block, the loop name.
    """
    ds = standardized(residual_blocks, scale)
    ws = weights(residual_blocks, loss, c, scale)
    n_total = sum(d.size for d in ds)
    out = []
    for b, (r, d, w) in enumerate(zip(residual_blocks, ds, ws)):
        m = np.asarray(r).shape[1]
        thr = np.sqrt(stats.chi2.isf(alpha / max(n_total, 1), m))
        for i in np.flatnonzero(d > thr):
            out.append(
                Suspect(
                    b,
                    int(i),
                    int(rows[b][i]) if rows is not None else None,
                    loops[b] if loops is not None else None,
                    float(d[i]),
                    float(stats.chi2.sf(d[i] ** 2, m)),
                    float(w[i]),
                )
            )
    return sorted(out, key=lambda s: -s.standardized)


# --------------------------------------------------------------------------- on a problem
def _sigma_q(problem: CalibrationProblem, noise) -> np.ndarray:
    if isinstance(noise, np.ndarray) and noise.shape == (len(problem.joints),):
        return noise
    return noise_vector(problem, noise)[0]


def config_residuals(
    problem: CalibrationProblem, values: np.ndarray, noise=None, weighting: str = "noise"
) -> list[np.ndarray]:
    """Whitened closure residuals per configuration, (N, m) per block, at `values`.

    noise: one level, a dict per joint (as in CalibrationOptions) or a per-joint vector.
    """
    sigma_q = _sigma_q(problem, noise)
    evals = problem.evaluate(values, weighting == "noise")
    out = []
    for bi, ev in enumerate(evals):
        r, _, _ = whiten([ev], sigma_q, weighting, False, [problem.noise[bi]])
        out.append(r.reshape(ev.r.shape))
    return out


def result_suspects(
    result: CalibrationResult,
    noise=None,
    alpha: float = 0.01,
    loss: str = "huber",
    c: float | None = None,
    scale: float | None = None,
) -> list[Suspect]:
    """`suspects` of a calibration at its solution (noise default: result.noise.sigma on every joint)."""
    p = result.problem
    res = config_residuals(p, result.fit.values, result.noise.sigma if noise is None else noise)
    return suspects(res, [b.rows for b in p.blocks], [b.loop.name for b in p.blocks], alpha, scale, loss, c)


@dataclass
class IRLSResult:
    values: np.ndarray
    weights: list[np.ndarray]
    scale: float
    iterations: int
    suspects: list[Suspect]


def irls(
    result: CalibrationResult,
    loss: str = "huber",
    c: float | None = None,
    noise=None,
    max_iter: int = 30,
    tol: float = 1e-8,
    scale: float | None = None,
    alpha: float = 0.01,
) -> IRLSResult:
    """Iteratively reweighted Gauss-Newton over `result.fit.estimated`, from `result.fit.values`.

    A reference for the integration in `calibrate`: each iteration computes
    the whitened per-configuration residuals, the MAD scale (unless `scale`
    is given), the weights, and one weighted Gauss-Newton step (SVD with the
    numerical-rank floor only).  Stops when the scaled step is below `tol`.
    """
    p = result.problem
    est = list(result.fit.estimated)
    prior = np.array([p.params[k].prior for k in est])
    sigma_q = _sigma_q(p, result.noise.sigma if noise is None else noise)
    x = result.fit.values.copy()
    w: list[np.ndarray] = []
    s = 1.0
    it = 0
    for it in range(1, max_iter + 1):
        evals = p.evaluate(x, True)
        rs, Js = [], []
        for bi, ev in enumerate(evals):
            r, J = whiten_block(ev, sigma_q, "noise", p.noise[bi])
            rs.append(r)
            Js.append(J[:, :, est])
        s = mad_scale(rs) if scale is None else float(scale)
        w = weights(rs, loss, c, s)
        rw = np.concatenate([(np.sqrt(wi)[:, None] * r).ravel() for wi, r in zip(w, rs)])
        Jw = np.vstack([(np.sqrt(wi)[:, None, None] * J).reshape(-1, len(est)) for wi, J in zip(w, Js)]) * prior
        U, S, Vt = np.linalg.svd(Jw, full_matrices=False)
        keep = S > 1e-10 * S[0]
        dz = -(Vt[keep].T @ ((U[:, keep].T @ rw) / S[keep]))
        x[est] += prior * dz
        if np.linalg.norm(dz) < tol:
            break
    final = config_residuals(p, x, sigma_q)
    # Flag against the clean scale: the MAD of the final residuals.
    sus = suspects(final, [b.rows for b in p.blocks], [b.loop.name for b in p.blocks], alpha, scale, loss, c)
    return IRLSResult(x, w, s, it, sus)
