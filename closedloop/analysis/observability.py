"""Observability indices of a calibration experiment.

All indices are functions of the singular values s_1 >= ... >= s_L of the
calibration Jacobian of the L *estimated* parameters, taken in the form the
estimator actually uses:

* whitened: each configuration's m closure rows are multiplied by W_i^-1/2,
  W_i = J_theta,i Sigma_q J_theta,i^T, the covariance of the closure error
  propagated from the joint-reading noise (the implicit-loop, errors-in-
  variables weighting of Wampler, Hollerbach & Arai 1995; ``estimate.noise.whiten``);
* column-scaled: column k is multiplied by the parameter's prior error
  magnitude ``params[k].prior`` (the scaling of thesis 4.2.6), so a singular
  value of 1 means "the data determine this direction as well as the prior".

The indices are taken on the Jacobian itself, NOT on J^T J (whose singular
values are the squares).  With M the number of configurations:

O1 = (s_1 s_2 ... s_L)^(1/L) / sqrt(M)
    Borm & Menq, "Determination of optimal measurement configurations for robot
    calibration based on observability measure", Int. J. Robotics Research
    10(1):51-63, 1991.  The geometric mean of the singular values per
    configuration: the volume of the confidence ellipsoid (D-optimality).
O2 = s_L / s_1
    Driels & Pathre, "Significance of observation strategy on the design of
    robot calibration experiments", J. Robotic Systems 7(2):197-223, 1990.
    The inverse condition number: how round the ellipsoid is.
O3 = s_L
    Nahvi, Hollerbach & Hayward, "Calibration of a parallel robot using
    multiple kinematic closed loops", IEEE ICRA 1994, pp. 407-412.  The
    minimum singular value: the worst-determined direction (E-optimality).
O4 = s_L^2 / s_1
    Nahvi & Hollerbach, "The noise amplification index for optimal pose
    selection in robot calibration", IEEE ICRA 1996, pp. 647-654.  The noise
    amplification index, O2 * O3.
O5 = 1 / (1/s_1 + ... + 1/s_L)
    Sun & Hollerbach, "Observability index selection for robot calibration",
    IEEE ICRA 2008, pp. 831-836 (in the Nahvi-Hollerbach line of indices).
    Dominated by the small singular values; related to A-optimality
    (the trace of the covariance is sum 1/s_i^2).

Larger is better for every index.  Because the Jacobian is whitened and
scaled, the covariance of the scaled estimates is (C^T C)^-1 = V S^-2 V^T, so
O3^-2 is the largest variance (in prior units) and sum s_i^-2 its trace.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from closedloop.estimate.noise import noise_vector, whiten_block
from closedloop.problem.problem import CalibrationProblem
from closedloop.records import CalibrationResult

INDEX_NAMES = ("O1", "O2", "O3", "O4", "O5")


# --------------------------------------------------------------------------- helpers
def resolve(
    result_or_problem: CalibrationResult | CalibrationProblem,
    values: np.ndarray | None = None,
    params: list[int] | list[str] | None = None,
    noise=None,
) -> tuple[CalibrationProblem, np.ndarray, list[int], np.ndarray]:
    """(problem, values, parameter indices, per-joint noise) from a result or a problem.

    For a result the defaults are its values, its estimated parameters and
    its noise level (`result.noise.sigma` on every joint).  For a bare problem the
    defaults are the nominal values, every parameter, and unit noise.
    """
    if isinstance(result_or_problem, CalibrationResult):
        res = result_or_problem
        problem = res.problem
        vals = res.fit.values if values is None else np.asarray(values, float)
        idx = list(res.fit.estimated) if params is None else _indices(problem, params)
        if noise is None:
            noise = float(res.noise.sigma) if np.isfinite(res.noise.sigma) and res.noise.sigma > 0 else 1.0
    else:
        problem = result_or_problem
        vals = problem.nominal if values is None else np.asarray(values, float)
        idx = list(range(len(problem.params))) if params is None else _indices(problem, params)
        if noise is None:
            noise = 1.0
    sigma_q, _ = noise_vector(problem, noise)
    return problem, vals, idx, sigma_q


def _indices(problem: CalibrationProblem, params) -> list[int]:
    return [problem.index[p] if isinstance(p, str) else int(p) for p in params]


def whitened_blocks(
    problem: CalibrationProblem,
    values: np.ndarray,
    params: list[int],
    sigma_q: np.ndarray,
    weighting: str = "noise",
    thetas: list[np.ndarray] | None = None,
    scaled: bool = True,
    blocks: list[int] | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-configuration whitened residuals and Jacobians, one (r (N,m), J (N,m,L)) per loop block.

    Same whitening as `estimate.noise.whiten` (so stacking these gives exactly the
    estimator's system), kept per configuration; J's columns are `params`,
    multiplied by their prior magnitudes when `scaled`.
    """
    evals = problem.evaluate(values, True, thetas)
    scale = np.array([problem.params[k].prior for k in params]) if scaled else np.ones(len(params))
    out = []
    for bi, ev in enumerate(evals):
        if blocks is not None and bi not in blocks:
            continue
        r, J = whiten_block(ev, sigma_q, weighting, problem.noise[bi])
        out.append((r, J[:, :, params] * scale))
    return out


def indices_from_singular_values(s: np.ndarray, n_configs: int) -> dict[str, float]:
    """O1..O5 from the singular values of the (whitened, scaled) Jacobian; see the module docstring."""
    s = np.sort(np.asarray(s, float))[::-1]
    L = s.size
    if L == 0:
        return dict.fromkeys(INDEX_NAMES, 0.0)
    smax, smin = float(s[0]), float(s[-1])
    if smin <= 0.0:
        o1 = 0.0
        o5 = 0.0
    else:
        o1 = float(np.exp(np.mean(np.log(s)))) / np.sqrt(max(n_configs, 1))
        o5 = float(1.0 / np.sum(1.0 / s))
    return {
        "O1": o1,
        "O2": smin / smax if smax > 0 else 0.0,
        "O3": smin,
        "O4": smin**2 / smax if smax > 0 else 0.0,
        "O5": o5,
    }


# --------------------------------------------------------------------------- API
def observability(
    result_or_problem: CalibrationResult | CalibrationProblem,
    values: np.ndarray | None = None,
    params: list[int] | list[str] | None = None,
    noise=None,
    weighting: str = "noise",
    thetas: list[np.ndarray] | None = None,
) -> dict[str, Any]:
    """Observability indices O1-O5 of an experiment.

    result_or_problem: a `CalibrationResult` (defaults: its values, its
      estimated parameters, its noise level) or a `CalibrationProblem`
      (defaults: nominal values, all parameters, unit noise; pass `params`).
    thetas: readings per loop block to evaluate instead of the problem's own
      (e.g. a candidate experiment).
    Returns {'O1'..'O5', 'singular_values', 'n_configs', 'n_rows', 'params'
    (names), 'trace_cov_scaled' (sum s^-2: trace of the covariance in prior
    units), 'cond'}.
    """
    problem, vals, idx, sigma_q = resolve(result_or_problem, values, params, noise)
    blocks = whitened_blocks(problem, vals, idx, sigma_q, weighting, thetas)
    C = np.vstack([J.reshape(-1, len(idx)) for _, J in blocks])
    s = np.linalg.svd(C, compute_uv=False)
    n_cfg = sum(J.shape[0] for _, J in blocks)
    out: dict[str, Any] = indices_from_singular_values(s, n_cfg)
    out.update(
        singular_values=s,
        n_configs=n_cfg,
        n_rows=C.shape[0],
        params=[problem.names[k] for k in idx],
        trace_cov_scaled=float(np.sum(1.0 / s**2)) if s.size and s[-1] > 0 else float("inf"),
        cond=float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf"),
    )
    return out
