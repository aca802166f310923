"""The records a calibration takes and gives: options, residual summaries, results."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING

import numpy as np

from closedloop.problem.problem import BlockEval, CalibrationProblem

if TYPE_CHECKING:
    from closedloop.calibration.verdict import VerdictRules

#: the verdict's three values, in rank order (`closedloop.calibration.verdict`)
OK, SUSPECT, FAILED = "ok", "suspect", "failed"
_RANK = {OK: 0, SUSPECT: 1, FAILED: 2}


@dataclass
class CalibrationOptions:
    """What to identify and how.

    Attributes:
        identify: parameter patterns (``placement``, ``offset``, ``scale``, ``loop``, or globs such as
            ``panda_joint[2-7].*``); None for the defaults (URDF: placement, offset, loop; D-H: theta_off,
            s, a, alpha, loop).
        fix: name -> value (None keeps the current value) of parameters held fixed.
        noise: joint-reading standard deviation (rad, or m for prismatic joints), one number or per joint;
            None estimates one level from the residual.
        weighting: 'noise' (errors in variables, default) or 'none' (the thesis's plain loop-closure least
            squares).
        robust: 'auto' (default: configurations the noise cannot explain are found by a robust fit and
            rejected before the final fit), 'huber' or 'cauchy' (IRLS kept in the final fit, suspects
            reported), or None (no outlier handling).
        restarts: further starts tried when the fit stalls far above any plausible noise.
        seed: the random draws of the restarts.
        choose_estimator: with weighting 'noise', test whether joint noise explains the residual and, where it
            does not, keep the plain fit if it predicts left-out configurations better; the error bars then
            come from the sandwich covariance (`closedloop.estimate.model_error`).  False: the weighting as
            given, error bars from the noise model.
        rules: the verdict's thresholds (`closedloop.calibration.verdict.VerdictRules`); None for the defaults.
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
    robust: str | None = "auto"
    restarts: int = 4
    seed: int = 0
    outlier_alpha: float = 0.01
    choose_estimator: bool = True
    threads: int | None = None  # BLAS threads for the call (closedloop.estimate.threads); None: by problem size
    rules: VerdictRules | None = None


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
class Rejected:
    """A configuration left out of the final fit: its closure error is not noise."""

    row: int  # data row in the log (1-based)
    loop: str
    standardized: float  # |r| in robust standard deviations, at the robust fit
    closure_m: float | None  # |translation error| at the final parameters
    closure_rad: float | None


class ParamStatus(str, Enum):
    """What a calibration did with a parameter (a `str`: compares equal to, and prints as, its value)."""

    SELECTED = "selected"  # chosen for estimation, before the structural reduction
    NOT_SELECTED = "not selected"  # not among the parameters to identify (held at its initial value)
    ESTIMATED = "estimated"
    FIXED = "fixed"  # held at a value: by the user, or as the gauge that sets the overall size
    DROPPED = "dropped"  # removed before solving: redundant with the kept ones (`Dropped`)
    UNIDENTIFIABLE = "unidentifiable"  # the data do not determine it (`Combination`)

    __str__ = str.__str__

    def __format__(self, format_spec: str) -> str:
        return str.__format__(self, format_spec)


@dataclass(frozen=True)
class ParameterRecord:
    """One parameter of a calibration, as a record."""

    name: str
    kind: str
    unit: str
    initial: float
    value: float
    std: float  # NaN where not estimated or not identifiable
    status: ParamStatus


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a report needs; `values` are absolute parameter values.

    Built once, by keyword, when the fit is done; what is added after (the scale's findings, the error-bar
    profiles, the verdict) makes a new record with ``dataclasses.replace``.
    """

    problem: CalibrationProblem
    names: list[str]
    initial: np.ndarray
    values: np.ndarray
    std: np.ndarray  # NaN where not estimated or not identifiable
    status: list[ParamStatus]
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
    weighting: str = "noise"  # the weighting of the final fit
    gauge: str | None = None  # the length held to set the overall size
    gauge_note: str | None = None
    gauge_length: float = 0.0  # the length the gauge stands for: holding it longer by d scales by 1 + d / L
    rejected: list[Rejected] = field(default_factory=list)
    rows_total: int = 0
    warnings: list[str] = field(default_factory=list)  # findings that make the result suspect
    profiles: list = field(default_factory=list)  # linearity.Profile: the error bars checked along the cost's profile
    verdict: Verdict | None = None
    scale_note: str | None = None  # what sets the overall size (closedloop.analysis.scale.annotate)
    scale_std: float = float("nan")  # relative standard error of the size, when a known distance sets it
    length_response: float | None = (
        None  # size change per change of the known frame lengths (closedloop.problem.lengths)
    )
    length_leak: float | None = None  # size error per prior-sized error of what the loops cannot see, through them
    noise_model: list = field(default_factory=list)  # per loop: task vs joint noise (noise.noise_summary)
    reducible: float = 0.0  # share of the final cost one Gauss-Newton step would remove: ~0 at a minimum (NaN: bounds)
    estimator: str = "errors in variables"  # the estimator of the final fit (closedloop.estimate.model_error)
    estimator_reason: str = ""  # why: the noise hypothesis' test and the left-out closures compared
    error_bars: str = "the noise model"  # where the standard errors come from: the noise model or the sandwich
    model_error: dict = field(default_factory=dict)  # the test's figures (implied joint noise, chi-square, ...)

    @property
    def converged(self) -> bool:
        return self.solver_status == "converged"

    def value(self, name: str) -> float:
        return float(self.values[self.names.index(name)])

    @property
    def loops(self) -> list:
        """The loops as calibrated (`Loop.prepare`d): the values of their parameters are coordinates in
        these objects' charts (the hinge's H0 fitted to the data), not in the caller's loop objects'."""
        return [b.loop for b in self.problem.blocks]

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.values)))

    @property
    def parameters(self) -> list[ParameterRecord]:
        """Every parameter as a named record, in the problem's order."""
        return [
            ParameterRecord(
                name=p.name,
                kind=p.kind,
                unit=p.unit,
                initial=float(self.initial[k]),
                value=float(self.values[k]),
                std=float(self.std[k]),
                status=ParamStatus(self.status[k]),
            )
            for k, p in enumerate(self.problem.params)
        ]


def residual_stats(problem: CalibrationProblem, evals: list[BlockEval]) -> list[LoopResiduals]:
    """Per loop: RMS and max of the translation, rotation and image-point error norms."""
    out = []
    for b, ev in zip(problem.blocks, evals):
        lp = b.loop
        t = ev.r[:, list(lp.translation_rows)] if lp.translation_rows else None
        w = ev.r[:, list(lp.rotation_rows)] if lp.rotation_rows else None
        tn = np.linalg.norm(t, axis=1) if t is not None else None
        wn = np.linalg.norm(w, axis=1) if w is not None else None
        # image points: the (u, v) pairs' Euclidean errors, pooled over configurations and cameras
        pn = (
            np.linalg.norm(ev.r[:, list(lp.pixel_rows)].reshape(-1, 2), axis=1) if lp.pixel_rows and ev.r.size else None
        )
        ok = getattr(ev, "valid", None)  # rows with an observation (LoopEval.valid): missing ones do not count
        if ok is not None:
            tn = None if tn is None else tn[ok[:, list(lp.translation_rows)].all(axis=1)]
            wn = None if wn is None else wn[ok[:, list(lp.rotation_rows)].all(axis=1)]
            pn = None if pn is None else pn[ok[:, list(lp.pixel_rows)].reshape(-1, 2).all(axis=1)]

        def rms(v):
            return float(np.sqrt(np.mean(v**2))) if v is not None and v.size else None

        def mx(v):
            return float(v.max()) if v is not None and v.size else None

        out.append(LoopResiduals(lp.name, ev.r.shape[0], rms(tn), mx(tn), rms(wn), mx(wn), rms(pn), mx(pn)))
    return out


@dataclass
class Dropped:
    """A parameter removed before solving, and why."""

    name: str
    reason: str
    absorbed_into: list[tuple[str, float]] = field(default_factory=list)
    residual: float = 0.0  # its column's relative residual on the kept ones' span (round-off: exactly redundant)

    def describe(self) -> str:
        if not self.absorbed_into:
            return f"{self.name}: {self.reason}"
        parts = " ".join(f"{c:+.3g}*{n}" for n, c in self.absorbed_into)
        return f"{self.name}: {self.reason}; its effect equals {parts}"


@dataclass
class Combination:
    """A direction of parameter space that the data do not determine."""

    singular_value: float
    terms: list[tuple[str, float]]  # (name, coefficient) of the unit null direction (scaled units)

    def describe(self) -> str:
        names = [n for n, _ in self.terms]
        if len(self.terms) == 1:
            return f"{names[0]} is not identifiable with this data"
        if len(self.terms) == 2:
            (n1, c1), (n2, c2) = self.terms
            sign = "-" if c1 * c2 > 0 else "+"
            return (
                f"{n1} and {n2} are identifiable only together, as {n1} {sign} {n2} "
                f"(in prior-scaled units); the direction {c1:+.2f}*{n1} {c2:+.2f}*{n2} is not"
            )
        dirn = " ".join(f"{c:+.2f}*{n}" for n, c in self.terms)
        return f"{', '.join(names)} are not separately identifiable: the combination {dirn} is not determined"


@dataclass
class Verdict:
    """ok | suspect | failed, with the reasons (empty when ok) and the numbers they rest on."""

    status: str = OK
    reasons: list[str] = field(default_factory=list)
    evidence: dict = field(default_factory=dict)

    def add(self, status: str, reason: str) -> None:
        if _RANK[status] > _RANK[self.status]:
            self.status = status
        self.reasons.append(f"{status}: {reason}")

    @property
    def ok(self) -> bool:
        return self.status == OK

    def describe(self) -> str:
        return self.status if not self.reasons else f"{self.status} ({'; '.join(self.reasons)})"
