"""Whether the fit's error bars hold: the cost's profile along its weakest directions (Bates & Watts 1988, ch. 6).

The standard errors of a calibration are those of the Gauss-Newton covariance
at the solution, C = sigma^2 (J^T J)^-1 over the estimated parameters (the
truncated eq. 4.17).  They describe the cost only as far as it is quadratic.
On a weakly determined problem it is not: a 7-DOF arm on one self-motion
(80 configurations, 5e-5 rad) fits in a long curved valley, takes hundreds of
iterations, and its error bars were 3-7 times too small with the verdict `ok`
(README, "Not (yet) done").

The check: along a direction u of the parameters, pin the combination u^T x
at its value +- K standard errors (s_u = sqrt(u^T C u)) and re-minimise the
rest (the profile).  Where the linearisation holds, the cost (in units of
the noise variance) rises by K^2 / 2 on both sides.  A rise below
`HOLDS` of that on either side means the error bar understates the
uncertainty along u by more than 1/sqrt(HOLDS), or that the solution is not
the minimum there: a warning, which makes the verdict `suspect`.

Directions: the covariance's weakest axis in prior-scaled units (the
largest standard error relative to the priors), and the robot's size when a
known length or distance sets it (`gauge.size_per_parameter`).  Checked on
fits that took more than `PROFILE_AFTER` iterations (a curved valley's
symptom; the well-posed fits of the examples take 3-7): each profile point
is a solve of its own.  Not on exact data (an estimated joint noise below
`EXACT`): its error bars are round-off.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from closedloop.estimate.lm import SolverOptions, levenberg_marquardt
from closedloop.estimate.residual import ResidualFunction
from closedloop.records import FitRecord

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem

log = logging.getLogger(__name__)

PROFILE_AFTER = 20  # iterations above which a fit's error bars are checked along its profile
K = 2.0  # standard errors out on each side
HOLDS = 0.5  # the rise must reach this fraction of K^2 / 2 on both sides
PIN = 1e3  # weight of the pinning row, in noise units per standard error
EXACT = 1e-9  # an estimated joint noise below this (rad) is exact data: its error bars are round-off
#: a profile point whose cost is below the solution's by more than this (noise variances; the residual's own
#: variance per degree of freedom where that is larger than the noise given) shows the solution is no minimum:
#: the fit continues from there (`calibration.pipeline`).  0.5 is a chi-square difference of 1: a smaller fall
#: leaves the solution within one standard error of the minimum along the direction, which the error bars
#: already allow for (the rise falling short of K^2 / 2 is `holds`'s finding).  Measured against a noise given
#: far below the residual's (a model that does not fit: chi-square per degree of freedom in the thousands), a
#: fall of tens of noise variances is a few millionths of the cost, the solver's own tolerance, not a minimum
#: missed
FALLS = 0.5


@dataclass
class Profile:
    """The profile of the cost along one direction: its standard error and the rises at -K and +K of them."""

    name: str
    std: float  # s_u = sqrt(u^T C u), in the direction's own units
    rise: tuple[float, float]  # cost increase (noise variances) at u^T x -+ K s_u, the rest re-minimised
    #: the estimated values at the profile's lower point where its cost falls below the solution's by more
    #: than `FALLS` (the solution is then no minimum); None at a minimum
    lower: np.ndarray | None = None

    @property
    def falls(self) -> bool:
        """Whether the cost falls along the profile by more than `FALLS`: the solution is no minimum."""
        return self.lower is not None

    @property
    def expected(self) -> float:
        """The rise on each side where the linearisation holds: K^2 / 2."""
        return K * K / 2.0

    @property
    def holds(self) -> bool:
        return min(self.rise) >= HOLDS * self.expected

    def describe(self) -> str:
        return (
            f"along {self.name}, the cost rises by {self.rise[0]:.2g} and {self.rise[1]:.2g} at -{K:g} and "
            f"+{K:g} standard errors ({self.expected:g} if the error bars held"
            + ("; it falls: the solution is no minimum)" if self.falls else ")")
        )


class _Pinned:
    """`fun` on x = x0 + B z (B: the directions the fit estimates), with one more row PIN (u^T x - target) / s_u:
    the combination held at `target`, the rest free within what the fit itself moves."""

    def __init__(
        self,
        fun: ResidualFunction,
        x0: np.ndarray,
        B: np.ndarray,
        u: np.ndarray,
        target: float,
        s_u: float,
        noise: float,
    ):
        self.fun, self.x0, self.B, self.u, self.target = fun, x0, B, u, target
        self.w = PIN * noise / s_u

    def x(self, z: np.ndarray) -> np.ndarray:
        return self.x0 + self.B @ z

    def __call__(self, z: np.ndarray, jac: bool | None):
        x = self.x(z)
        r, J = self.fun(x, jac)
        r = np.append(r, self.w * (float(self.u @ x) - self.target))
        if jac:
            J = np.vstack([J @ self.B, self.w * (self.u @ self.B)[None, :]])
        return r, J


def profile(
    make: Callable[[], ResidualFunction],
    x: np.ndarray,
    cov: np.ndarray,
    u: np.ndarray,
    noise: float,
    prior: np.ndarray,
    name: str,
    unit: float = 1.0,
) -> Profile:
    """The profile of 1/2 |r|^2 / noise^2 along u from the solution x (estimated values), covariance `cov`;
    its lower point kept where the cost falls by more than `FALLS` x `unit` (`Profile.lower`).

    `make` gives a fresh residual function: each cost is taken with the weights W_i at its own point.  The
    rest is re-minimised within the range of `cov`: the directions the fit estimates (those it truncates
    below the noise it holds at their start, and so does the profile; their share of the uncertainty is
    not the error bars' to show).
    """
    s_u = float(np.sqrt(max(u @ cov @ u, 0.0)))
    base = _cost(make(), x, noise)
    scaled = cov / np.outer(prior, prior)
    lam, V = np.linalg.eigh(scaled)
    B = V[:, lam > 1e-12 * lam[-1]] * prior[:, None]  # the estimated directions, in parameter units
    rises, points = [], []
    for k in (-K, K):
        target = float(u @ x) + k * s_u
        start = x + k * (cov @ u) / s_u  # the linear model's profile point, in the range of cov
        pinned = _Pinned(make(), start, B, u, target, s_u, noise)
        sol = levenberg_marquardt(
            pinned, np.zeros(B.shape[1]), np.ones(B.shape[1]), SolverOptions(noise=noise, max_iter=50)
        )
        rises.append(_cost(make(), pinned.x(sol.x), noise) - base)
        points.append(pinned.x(sol.x))
    low = int(np.argmin(rises))
    lower = (
        points[low]
        if rises[low] < -FALLS * unit and _falls_as_solved(make, x, points[low], noise, base, unit)
        else None
    )
    return Profile(name, s_u, (rises[0], rises[1]), lower)


def _falls_as_solved(
    make: Callable[[], ResidualFunction], x: np.ndarray, lower: np.ndarray, noise: float, base: float, unit: float
) -> bool:
    """Whether the cost at `lower` is below the solution's by more than `FALLS` x `unit` with the weights W_i
    held at the solution `x`: the criterion the solver minimises (each step's weights taken where it stands).
    The errors-in-variables cost with W_i at each point can also fall where the weights grow (the joints'
    effect on the closure inflated along a direction the loops cannot see), a lower cost that is no better
    closure: no minimum missed."""
    fun = make()
    fun(x, None)  # W_i at the solution, kept for the next probe
    r, _ = fun(lower, None)
    return base - 0.5 * float(r @ r) / noise**2 > FALLS * unit


def _cost(fun: ResidualFunction, xe: np.ndarray, noise: float) -> float:
    r, _ = fun(xe, False)  # a fresh function: W_i at xe
    return 0.5 * float(r @ r) / noise**2


def check_profiles(
    make: Callable[[], ResidualFunction],
    problem,
    values: np.ndarray,
    est: list[int],
    cov: np.ndarray,
    noise: float,
    size: np.ndarray | None,
    unit: float = 1.0,
) -> list[Profile]:
    """Profiles along the weakest axis of `cov` (prior-scaled) and along `size` (d size / d parameter, if given).

    `make` gives a fresh copy of the fit's residual function (its weighting and row weights);
    `noise` is its residual's noise level (1 with a known joint noise, else the fit's RMS); `unit` the
    residual's own variance per degree of freedom in noise variances where above 1 (a fall is measured
    in it: `FALLS`).
    """
    if not est or not np.all(np.isfinite(cov)):
        return []
    prior = np.array([problem.params[k].prior for k in est])
    scaled = cov / np.outer(prior, prior)
    lam, V = np.linalg.eigh(scaled)
    directions = {"the weakest direction of the parameters": V[:, -1] / prior}
    if size is not None and np.any(size != 0):
        directions["the robot's size"] = size
    out = []
    for name, u in directions.items():
        p = profile(make, values[est], cov, u, noise, prior, name, unit)
        log.info("profile %s", p.describe())
        out.append(p)
    return out


def check_error_bars(
    problem: CalibrationProblem,
    record: FitRecord,
    fit,
    sigma: float,
    sigma_estimated: bool,
    dof: int,
    scale_std: float,
) -> tuple[list[Profile], list[str]]:
    """The profiles of a calibration's solution (`record`) that took more than `PROFILE_AFTER` iterations, and
    a warning (for `CalibrationResult.warnings`: the verdict is `suspect`) for each direction whose error bar
    does not hold; `sigma`, `sigma_estimated`, `dof`: the noise at the solution (`NoiseRecord`), `scale_std`
    the size's relative standard error (`ScaleRecord`: profiled along the size where finite).

    On the fit's own residual function (`fit.stage.fun`: its weighting, its row weights, such as a known
    length's in an unweighted fit), at the reported values.
    """
    if record.iterations <= PROFILE_AFTER or not record.estimated or record.covariance.size == 0:
        return [], []
    if sigma_estimated and not sigma > EXACT:  # exact data: error bars of round-off, nothing to check
        return [], []
    from closedloop.analysis.gauge import size_per_parameter

    est = list(record.estimated)
    make = lambda: replace(fit.stage.fun, x0=record.values.copy())  # noqa: E731  (fresh: no cached weights)
    r, _ = make()(record.values[est], False)
    known = fit.known and fit.stage.fun.weighting == "noise"
    noise = 1.0 if known else float(np.sqrt(r @ r / max(dof, 1)))
    unit = max(1.0, float(r @ r) / max(dof, 1) / noise**2)  # the residual's own variance, in noise variances
    size = size_per_parameter(problem, record.values, est) if scale_std is not None and np.isfinite(scale_std) else None
    profiles = check_profiles(make, problem, record.values, est, record.covariance, noise, size, unit)
    warnings = [
        f"the error bars do not hold: {p.describe()}; the fit lies in a curved valley its "
        "linearisation does not see, and the standard errors understate the uncertainty"
        for p in profiles
        if not p.holds
    ]
    return profiles, warnings
