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
look "suspect").  `calibrate` screens the plain fit; if anything is flagged it
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
    of freedom of a loop): importing scipy.special costs ~0.25 s and scipy.stats 0.4-1 s."""

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
    """`suspects` of a calibration at its solution (noise default: result.sigma on every joint)."""
    p = result.problem
    res = config_residuals(p, result.values, result.sigma if noise is None else noise)
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
    """Iteratively reweighted Gauss-Newton over `result.estimated`, from `result.values`.

    A reference for the integration in `calibrate`: each iteration computes
    the whitened per-configuration residuals, the MAD scale (unless `scale`
    is given), the weights, and one weighted Gauss-Newton step (SVD with the
    numerical-rank floor only).  Stops when the scaled step is below `tol`.
    """
    p = result.problem
    est = list(result.estimated)
    prior = np.array([p.params[k].prior for k in est])
    sigma_q = _sigma_q(p, result.sigma if noise is None else noise)
    x = result.values.copy()
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
