"""The records a calibration takes and gives: options, residual summaries, results."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import TYPE_CHECKING, Any

import numpy as np

from closedloop.problem.problem import BlockEval, CalibrationProblem

if TYPE_CHECKING:
    from closedloop.calibration.verdict import Verdict

#: the verdict's three values, in rank order (`closedloop.calibration.verdict.Verdict`)
OK, SUSPECT, FAILED = "ok", "suspect", "failed"


def _rule(default: float, unit: str, meaning: str):
    """A threshold of `VerdictRules`: its default, unit and meaning (read by the docs' generated table)."""
    return field(default=default, metadata={"unit": unit, "meaning": meaning})


#: an observed error is foretold by a prediction when it is at most this many times the predicted one
#: (`closedloop.validation.check.unforetold`; the verdict's size finding, `calibration.verdict.judge_size`)
FORETOLD = 3.0


@dataclass(frozen=True)
class VerdictRules:
    """Every threshold the verdict (`closedloop.calibration.verdict.judge`) and the solve's stall test apply.

    One instance is carried by `CalibrationOptions.rules` into the pipeline, the staged solve and `judge`;
    each field's unit and meaning is in its metadata (``dataclasses.fields(VerdictRules)``), from which the
    docs' table of rules is generated.  Closures are RMS norms per configuration: metres (``m``), radians
    (``rad``), image pixels (``px``).
    """

    plausible_joint_noise: float = _rule(
        2e-3,
        "rad",
        "estimated joint noise above this is suspect (no encoder reads worse); the staged solve calls a fit that "
        "this joint noise cannot explain stalled",
    )
    failed_joint_noise: float = _rule(
        1e-2, "rad", "estimated joint noise above this is failed: the model does not fit the data"
    )
    chi2_suspect: float = _rule(2.0, "1", "chi2/dof above this, with a given noise, is suspect (p < 1e-3)")
    chi2_failed: float = _rule(100.0, "1", "chi2/dof above this, with a given noise, is failed")
    scale_suspect: float = _rule(0.03, "1", "a change of the robot's overall size beyond this share is suspect")
    scale_failed: float = _rule(0.15, "1", "a change of the robot's overall size beyond this share is failed")
    sets_size_low: float = _rule(
        0.9, "1", "a known length sets the size when its size response (size change per change of it) is at least this"
    )
    sets_size_high: float = _rule(1.1, "1", "... and at most this (`closedloop.analysis.scale.size_response`)")
    outliers_suspect: float = _rule(
        0.05, "1", "a share of configurations rejected as gross errors above this is suspect"
    )
    outliers_failed: float = _rule(0.20, "1", "a share of configurations rejected as gross errors above this is failed")
    gross_outlier: float = _rule(
        5.0,
        "1",
        "a rejected configuration counts as a gross error when its closure at the solution exceeds this many times "
        "the RMS closure of its loop's kept configurations",
    )
    heldout_suspect: float = _rule(
        3.0, "1", "a validation fold's held-out closure over this many times its training closure is suspect"
    )
    heldout_failed: float = _rule(
        30.0, "1", "a validation fold's held-out closure over this many times its training closure is failed"
    )
    heldout_floor: float = _rule(
        3.0, "1", "held-out closures under this many times the noise floor (`floor_m`, ...) are not judged"
    )
    reducible_suspect: float = _rule(
        0.1, "1", "the share of the final cost one Gauss-Newton step would still remove above this is suspect"
    )
    reducible_failed: float = _rule(0.5, "1", "... above this is failed (the solver stopped short of a minimum)")
    closure_worse: float = _rule(
        1.1, "1", "a loop's closure after calibration over this many times the one before is failed"
    )
    floor_m: float = _rule(1e-7, "m", "closures below this are round-off or noise-free data: not compared")
    floor_rad: float = _rule(1e-7, "rad", "closures below this are round-off or noise-free data: not compared")
    floor_px: float = _rule(1e-4, "px", "closures below this are round-off or noise-free data: not compared")
    roundoff_m: float = _rule(
        1e-12,
        "m",
        "closures below this are round-off itself (seen 5e-16..9e-14 m on exact data): the minimum check is off",
    )
    roundoff_rad: float = _rule(1e-12, "rad", "the same in rotation")
    roundoff_px: float = _rule(1e-9, "px", "the same in image points")
    round_off_noise: float = _rule(
        1e-9, "rad", "a fit implying less joint noise closes exact data: its error bars are not checked"
    )
    error_bar_ratio: float = _rule(
        2.25,
        "1",
        "sandwich / noise-model variance beyond this (or below its inverse; 1.5x in standard error): the error bars "
        "are suspect",
    )
    sandwich_configurations: float = _rule(
        3.0, "1", "configurations per estimated parameter a sandwich covariance needs; fewer is suspect"
    )
    offset_suspect: float = _rule(0.5, "rad", "a joint offset corrected by more than this is suspect")
    rotation_suspect: float = _rule(0.3, "rad", "a joint origin turned by more than this is suspect")
    origin_suspect: float = _rule(
        0.5, "1", "a joint origin moved by more than this share of its length (and `origin_suspect_min`) is suspect"
    )
    origin_suspect_min: float = _rule(0.05, "m", "... and by more than this distance")
    corrections_failed: float = _rule(
        3.0, "1", "corrections this many times the suspect sizes above are failed (a flipped axis, a wrong log)"
    )

    def floor(self, key: str) -> float:
        """The noise floor of a `LoopResiduals` field (``rms_m``, ``rms_rad``, ``rms_px``)."""
        return float(getattr(self, "floor_" + key.rsplit("_", 1)[1]))

    def roundoff(self, key: str) -> float:
        """The round-off level of a `LoopResiduals` field (``rms_m``, ``rms_rad``, ``rms_px``)."""
        return float(getattr(self, "roundoff_" + key.rsplit("_", 1)[1]))

    def sets_size(self, response: float) -> bool:
        """Does a known length whose size response is `response` set the robot's size?"""
        return self.sets_size_low <= response <= self.sets_size_high


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
        rules: the verdict's thresholds (`VerdictRules`), applied by the pipeline, its staged solve and `judge`.
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
    threads: int | None = None  # BLAS threads, and the rows' cap (closedloop.estimate.threads); None: 1 BLAS thread
    rules: VerdictRules = field(default_factory=VerdictRules)  # the verdict's thresholds


@dataclass
class LoopResiduals:
    """One loop's closure over its configurations: RMS and largest error of the position rows (m), the
    rotation rows (rad) and the image points (px, camera loops); None where the loop has no such rows.

    Attributes:
        loop: the loop's name.
        n: its configurations.
        rms_m: RMS of the per-configuration position error (m).
        max_m: the largest position error (m).
        rms_rad: RMS of the per-configuration rotation error (rad).
        max_rad: the largest rotation error (rad).
        rms_px: RMS of the image points' errors (px).
        max_px: the largest image-point error (px).
    """

    loop: str
    n: int
    rms_m: float | None
    max_m: float | None
    rms_rad: float | None
    max_rad: float | None
    rms_px: float | None = None
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
class FitRecord:
    """The solution: every parameter's value, status and standard error, the solver's run and the closures.

    `values` are absolute parameter values, in the problem's order (`names`); `covariance` is over the
    estimated parameters (order: `estimated`).
    """

    names: list[str]
    initial: np.ndarray
    values: np.ndarray
    std: np.ndarray  # NaN where not estimated or not identifiable
    status: list[ParamStatus]
    estimated: list[int]
    covariance: np.ndarray
    iterations: int
    solver_status: str
    solver_message: str
    residuals_before: list[LoopResiduals]
    residuals_after: list[LoopResiduals]
    reducible: float = 0.0  # share of the final cost one Gauss-Newton step would remove: ~0 at a minimum (NaN: bounds)

    @property
    def converged(self) -> bool:
        return self.solver_status == "converged"


@dataclass(frozen=True)
class IdentifiabilityRecord:
    """What the data determine: the parameters dropped before solving, the directions left undetermined."""

    dropped: list[Dropped]
    weak: list[Combination]
    singular_values: np.ndarray
    rank: int


@dataclass(frozen=True)
class NoiseRecord:
    """The noise, the estimator and where the error bars come from (`closedloop.estimate.model_error`)."""

    sigma: float  # joint noise level (given, or estimated)
    sigma_estimated: bool
    chi2: float
    dof: int
    weighting: str = "noise"  # the weighting of the final fit
    estimator: str = "errors in variables"  # the estimator of the final fit
    estimator_reason: str = ""  # why: the noise hypothesis' test and the left-out closures compared
    error_bars: str = "the noise model"  # where the standard errors come from: the noise model or the sandwich
    model_error: dict = field(default_factory=dict)  # the test's figures (implied joint noise, chi-square, ...)
    noise_model: list = field(default_factory=list)  # per loop: task vs joint noise (variance.noise_summary)
    profiles: list = field(default_factory=list)  # linearity.Profile: the error bars checked along the cost's profile

    @property
    def joint_noise(self) -> float | None:
        """The joint noise (rad) the final fit weighed its rows with (eq. 3.17), given or estimated; None
        for a plain loop-closure fit (eq. 3.8), whose `sigma` is the closure residual's scale per degree
        of freedom (the loops' metres and radians), not a joint noise."""
        return None if self.weighting == "none" else self.sigma

    def describe(self) -> str:
        """The noise in words, as the summary and the HTML report print it."""
        if self.joint_noise is None:
            return (
                f"no joint noise weighs the rows (plain least squares): closure residual {self.sigma:.3g} "
                "per degree of freedom (m, rad)"
            )
        how = "estimated" if self.sigma_estimated else "given"
        return f"joint noise {self.sigma:.3g} rad ({how})"


@dataclass(frozen=True)
class ScaleRecord:
    """What sets the robot's overall size (thesis 3.3; `closedloop.analysis.scale`)."""

    gauge: str | None = None  # the length held to set the overall size
    gauge_note: str | None = None
    gauge_length: float = 0.0  # the length the gauge stands for: holding it longer by d scales by 1 + d / L
    scale_note: str | None = None  # what sets the overall size, in words
    scale_std: float = float("nan")  # relative standard error of the size, when a known distance sets it
    length_response: float | None = None  # size change per change of the known frame lengths (problem.lengths)
    length_leak: float | None = None  # size error per prior-sized error of what the loops cannot see, through them


@dataclass(frozen=True)
class OutlierRecord:
    """The configurations left out of the final fit, or down-weighted in it, and how many there were."""

    rejected: list[Rejected] = field(default_factory=list)
    suspects: list = field(default_factory=list)  # robust.Suspect, most suspect first (robust='huber'|'cauchy')
    rows_total: int = 0


@dataclass(frozen=True)
class AccuracyRecord:
    """What the calibrated robot is predicted to do (reported under ``report["accuracy"]``).

    `workspace`: the prediction of the tool's accuracy over the workspace
    (`closedloop.analysis.accuracy.WorkspaceAccuracy`), reported as ``report["accuracy"]["workspace"]``;
    None where not predicted.  `regions`: the held-out validation by region (`closedloop.validation.regions`);
    `target`: the accuracy target asked for and whether the prediction meets it
    (`closedloop.calibration.verdict.judge_accuracy`).
    """

    workspace: Any = None
    regions: dict | None = None
    target: dict | None = None


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a report needs, composed of one record per concern, each built by keyword once.

    `fit` (the solution), `identifiability`, `noise` (noise, estimator, error bars), `scale` (what sets the
    size), `outliers`; the `notes` and `warnings` (findings that make the result suspect) in words; the
    `verdict` and the `accuracy` prediction, attached after (``dataclasses.replace``).
    """

    problem: CalibrationProblem
    fit: FitRecord
    identifiability: IdentifiabilityRecord
    noise: NoiseRecord
    scale: ScaleRecord = field(default_factory=ScaleRecord)
    outliers: OutlierRecord = field(default_factory=OutlierRecord)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # findings that make the result suspect
    verdict: Verdict | None = None
    accuracy: AccuracyRecord | None = None

    @property
    def converged(self) -> bool:
        return self.fit.converged

    def value(self, name: str) -> float:
        return float(self.fit.values[self.fit.names.index(name)])

    @property
    def loops(self) -> list:
        """The loops as calibrated (`Loop.prepare`d): the values of their parameters are coordinates in
        these objects' charts (the hinge's H0 fitted to the data), not in the caller's loop objects'."""
        return [b.loop for b in self.problem.blocks]

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.fit.names, map(float, self.fit.values)))

    @property
    def parameters(self) -> list[ParameterRecord]:
        """Every parameter as a named record, in the problem's order."""
        f = self.fit
        return [
            ParameterRecord(
                name=p.name,
                kind=p.kind,
                unit=p.unit,
                initial=float(f.initial[k]),
                value=float(f.values[k]),
                std=float(f.std[k]),
                status=ParamStatus(f.status[k]),
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
