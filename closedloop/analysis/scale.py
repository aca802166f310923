"""What sets the robot's overall size, and how well: known lengths and distances, the held length, its error.

Closed loops close at any overall size (thesis 3.3): the size comes from a known length or distance
(`closedloop.problem.lengths`, `closedloop.problem.distances`) or from a length the model holds.  Here:
the sentence the summary gives (`scale_note`), the size's standard error (`scale_std`), whether a known
length sets the size (`size_response`, `length_findings`), how far a held length leaks into the rest
(`held_leak`), and `annotate`, which adds all of it to a result.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from closedloop.model.parameters import DEFAULT_PRIORS
from closedloop.problem.distances import DistanceLoop, distance_blocks
from closedloop.problem.lengths import LengthLoop, length_blocks, length_loops
from closedloop.records import FitRecord, ParamStatus, VerdictRules

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem


def _scale_labels(dists: list[DistanceLoop]) -> list[str]:
    """One label per free distance, one per block: 'the block front (3 points: a, b, c)'."""
    labels, blocks = [], {}
    for d in dists:
        if d.block is None:
            labels.append(d.label())
        elif d.block not in blocks:
            blocks[d.block] = [d]
            labels.append(d.block)
        else:
            blocks[d.block].append(d)
    for name, ds in blocks.items():
        pts = list(dict.fromkeys(r.rsplit(".", 1)[0] for d in ds for r in (d.a, d.b)))
        labels[labels.index(name)] = (
            f"the block {name} ({len(pts)} points: {', '.join(pts)}; "
            f"{len(ds)} distances up to {max(d.distance for d in ds) * 1e3:.4g} mm)"
        )
    return labels


def scale_note(problem: CalibrationProblem, gauge: str | None, scale_free: bool) -> str | None:
    """What sets the overall size: the known distances, else a held length ('not set by the data')."""
    dists = distance_blocks(problem)
    if dists:
        return "the scale is set by " + " and ".join(_scale_labels(dists))
    if gauge is not None:
        return (
            f"the scale is not set by the data: {gauge} is held at its value (give a known distance or length, "
            "e.g. --distance A.point B.point 0.050 or --length LINK_A LINK_B 0.316)"
        )
    if scale_free:
        return "the scale is not set by the data, and no held length sets it"
    return None


def scale_std(problem: CalibrationProblem, x: np.ndarray, est: list[int], cov: np.ndarray) -> float:
    """Standard error of the robot's overall size (relative), c^T Cov c with c the size change per parameter.

    c_k: the size change per unit of estimated parameter k (`gauge.size_per_parameter`).
    """
    from closedloop.analysis.gauge import size_per_parameter

    if not any(k < problem.n_robot for k in est) or cov.size == 0:
        return float("nan")
    c = size_per_parameter(problem, x, est)
    return float(np.sqrt(max(c @ cov @ c, 0.0)))


def scale_findings(
    problem: CalibrationProblem,
    fit: FitRecord,
    weighting: str,
    gauge: str | None,
    sigma_q: np.ndarray,
    scale_free: bool,
    snr: float = 1.0,
    rules: VerdictRules | None = None,
) -> dict:
    """What sets the scale (with the size's standard error) and each loop's noise model, for a solution.

    `fit`: the solution's record, `weighting` its fit's, `gauge` the held length (`ScaleRecord.gauge`).
    Returns `scale_note`, `scale_std` (relative), `length_response` and `length_leak` (known lengths
    between frames, `closedloop.problem.lengths`), `noise_model` (`variance.noise_summary`), and the
    `notes` and `warnings` it adds.  `rules`: the verdict's thresholds (`VerdictRules.sets_size_low`, ...).
    """
    from closedloop.estimate.variance import noise_notes, noise_summary

    notes: list[str] = []
    warnings: list[str] = []
    out: dict = {"length_response": None, "length_leak": None, "scale_std": float("nan"), "noise_model": []}
    note = scale_note(problem, gauge, scale_free)
    leak = None
    if length_blocks(problem) and fit.estimated:  # a known length between frames: does it set the size?
        sentence, found, out["length_response"], leak = length_findings(
            problem, fit, weighting, np.asarray(sigma_q, dtype=float), snr, rules or VerdictRules()
        )
        out["length_leak"] = leak
        warnings.extend(found)
        note = sentence if not distance_blocks(problem) else f"{note}; {sentence}"
    if (distance_blocks(problem) or length_blocks(problem)) and fit.estimated:
        try:
            std = scale_std(problem, fit.values, fit.estimated, fit.covariance)
            if leak is not None and np.isfinite(leak):  # what the held values add
                std = float(np.hypot(std, leak))
        except (np.linalg.LinAlgError, ValueError):
            std = float("nan")
        out["scale_std"] = std
        if note and np.isfinite(std):
            note += f" (the robot's size to +-{std:.2%}, one standard error)"
    out["scale_note"] = note
    if note:
        notes.append(note)
    if weighting == "noise":
        out["noise_model"] = noise_summary(problem, fit.values, np.asarray(sigma_q, dtype=float))
        notes.extend(noise_notes(out["noise_model"]))
    out["notes"], out["warnings"] = notes, warnings
    return out


LEAK_TOL = 1e-3  # relative size error from a 1 mm (1 mrad) error of what the loops cannot see


HELD_ERROR = 1e-3  # m or rad: the error `held_leak` is quoted for


STEP = 1e-3  # relative change of L in `size_response`


def size_response(
    problem: CalibrationProblem, x: np.ndarray, est: list[int], sigma_q: np.ndarray, weighting: str, snr: float
) -> float:
    """The robot's relative size change per relative change of the known lengths, at the solution x.

    The step is the least-squares answer of the fit's own system (whitened
    Jacobian J over `est`, prior-scaled, truncated below `snr` times the
    residual RMS as at the solution, eq. 4.17) to the residual change that
    scaling every known length by 1 + STEP makes; its size change is
    c^T dx with c the size change per parameter (`gauge.size_per_parameter`).
    """
    from closedloop.analysis.gauge import size_per_parameter
    from closedloop.estimate.residual import ResidualFunction
    from closedloop.problem.problem import CalibrationProblem as Problem

    lengths = length_loops(problem)
    if not lengths or not any(k < problem.n_robot for k in est):
        return 0.0
    blocks = [
        replace(b, loop=replace_length(lengths[bi], 1.0 + STEP)) if bi in lengths else b
        for bi, b in enumerate(problem.blocks)
    ]
    moved = Problem(problem.robot, problem.joints, blocks, problem.priors, problem.noise)
    r, J = ResidualFunction(problem, x, est, sigma_q, weighting)(x[est], True)
    r1, _ = ResidualFunction(moved, x, est, sigma_q, weighting)(x[est], False)
    scale = np.array([problem.params[k].prior for k in est])
    U, S, Vt = np.linalg.svd(J * scale, full_matrices=False)
    dof = max(r.size - len(est), 1)
    keep = S > max(1e-10 * (S[0] if S.size else 0.0), snr * float(np.sqrt(r @ r / dof)))
    dx = -(Vt[keep].T @ ((U[:, keep].T @ (r1 - r)) / S[keep])) * scale
    return float(size_per_parameter(problem, x, est) @ dx) / STEP


def replace_length(loop: LengthLoop, factor: float) -> LengthLoop:
    """A copy of `loop` with its length times `factor`."""
    out = LengthLoop(loop.frame_a, loop.frame_b, loop.length * factor, loop.sigma)
    out.name = loop.name
    return out


def length_findings(
    problem: CalibrationProblem, fit: FitRecord, weighting: str, sigma_q: np.ndarray, snr: float, rules: VerdictRules
) -> tuple[str, list[str], float, float]:
    """(the sentence on what sets the scale, the warnings that make the result suspect, the size response,
    the held-length leak) for a solution (`fit`, its fit's `weighting`) of a problem with known lengths
    (module docstring)."""
    labels = " and ".join(lp.label() for lp in length_loops(problem).values())
    response = size_response(problem, fit.values, fit.estimated, sigma_q, weighting, snr)
    free = [
        k
        for k, s in enumerate(fit.status)
        if s in (ParamStatus.ESTIMATED, ParamStatus.DROPPED, ParamStatus.UNIDENTIFIABLE)
    ]
    leak, held = held_leak(problem, fit.values, free)
    warnings = []
    if not rules.sets_size(response):
        warnings.append(
            f"{labels} sets the robot's size only in part (a change of it by 1 % scales the robot by "
            f"{response:.3g} %): the loops tie it to the rest of the robot too loosely; the "
            "scale is not set by the data"
        )
    if not leak <= LEAK_TOL:
        warnings.append(
            f"{labels} also changes with {held}, which the loops cannot see (held at its value): an "
            f"error of 1 mm or 1 mrad there changes the identified size by {leak:.2%}"
            if held
            else f"{labels}: whether it sets the size could not be checked at the solution"
        )
    if warnings:
        return warnings[0], warnings, response, leak
    return (
        f"the scale is set by {labels} (a change of it by 1 % scales the robot by {response:.3g} %)",
        [],
        response,
        leak,
    )


def held_leak(problem: CalibrationProblem, x: np.ndarray, free: list[int]) -> tuple[float, str | None]:
    """The relative size error a HELD_ERROR (1 mm, 1 mrad) error of what the loops cannot see makes through
    the known lengths, and the parameter that carries most of it (module docstring); (0, None) without."""
    from closedloop.analysis.gauge import kinematic_changes, random_configurations, scale_content
    from closedloop.analysis.identifiability import closure_jacobian
    from closedloop.problem.problem import CalibrationProblem as Problem

    lengths = length_loops(problem)
    if not lengths or not free:
        return 0.0, None
    loops = Problem(
        problem.robot,
        problem.joints,
        [b for bi, b in enumerate(problem.blocks) if bi not in lengths],
        problem.priors,
        problem.noise,
    )
    R = closure_jacobian(loops, x, free)
    if R is None:
        return float("nan"), None
    _, S, Vt = np.linalg.svd(R)
    null = np.concatenate([Vt[S.size :], Vt[: S.size][S <= 1e-8 * S[0]]]) if S.size else Vt
    if null.shape[0] == 0:
        return 0.0, None
    prior = np.array([problem.params[k].prior for k in free])
    V = np.zeros((len(problem.params), null.shape[0]))
    V[free] = null.T * prior[:, None]  # one prior-sized step along each null direction (an orthonormal basis)
    c, _ = scale_content(*kinematic_changes(loops, x, V, random_configurations(loops, 48)))
    evals = problem.evaluate(x, True, columns=free)
    worst, name = 0.0, None
    prior_m = float((problem.priors or {}).get("m", DEFAULT_PRIORS["m"]))  # the prior-sized step, in metres
    for bi, lp in lengths.items():
        g = evals[bi].jacobian()[0, 0]  # metres per unit of each free parameter
        gN = g @ V[free]
        perp = gN - (gN @ c) / max(c @ c, 1e-300) * c if c @ c > 0 else gN
        leak = HELD_ERROR / prior_m * float(np.linalg.norm(perp)) / lp.length
        if leak > worst:
            d = V[free] @ perp  # the held change that moves the length without the size
            worst, name = leak, problem.names[free[int(np.argmax(np.abs(d) / prior))]]
    return worst, name


def refuse_lengths(
    problem: CalibrationProblem, x: np.ndarray, free: list[int], rules: VerdictRules | None = None
) -> None:
    """Refuse, before the fit, a known length that no free parameter changes: the model fixes it already
    (both frames on one rigid body, or only held values between them), so it cannot set the size; and one
    more than `rules.scale_failed` (15 % by default) from the model's distance at x, which would scale the robot
    into a failed verdict (`VerdictRules.scale_failed`): a typo, or millimetres for metres."""
    from closedloop.errors import LoopError

    lengths = length_loops(problem)
    if not lengths:
        return
    evals = problem.evaluate(x, True, columns=free)
    for bi, lp in lengths.items():
        g = evals[bi].jacobian()[0, 0]  # metres per unit of each free parameter
        prior = np.array([problem.params[k].prior for k in free])
        if not np.any(np.abs(g * prior) > 1e-12 * lp.length):
            raise LoopError(
                f"--length {lp.frame_a} {lp.frame_b} {lp.length:g}: no calibrated parameter changes the distance "
                "between these frames (the model fixes it: one rigid body, or only held values between them), "
                "so it cannot set the robot's size"
            )
        model = float(evals[bi].r[0, 0]) + lp.length  # r = |p_B - p_A| - L
        if not abs(lp.length / max(model, 1e-12) - 1.0) <= (rules or VerdictRules()).scale_failed:
            raise LoopError(
                f"--length {lp.frame_a} {lp.frame_b} {lp.length:g}: the model puts these frames {model:.4g} m "
                f"apart at zero readings; a length {lp.length / max(model, 1e-12):.3g}x that is not a calibration "
                "(metres expected)"
            )
