"""The JSON calibration report (schema in the README)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from closedloop.calibration.pipeline import CalibrationResult
from closedloop.io.files import atomic_write_text
from closedloop.records import AccuracyRecord, ParamStatus
from closedloop.version import __version__


def _chi2_sf(x: float, dof: int) -> float:
    """P(chi2_dof > x), the chi-square test's p-value (scipy.stats.chi2.sf(x, dof) in plain Python,
    `robust.stats`: importing scipy.special costs ~0.25 s, scipy.stats ~0.4 s)."""
    from closedloop.estimate.robust import stats

    return stats.chi2.sf(x, dof)


def _f(v) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def verdict_record(verdict) -> dict | None:
    """The verdict as a plain dict (status, reasons, the numbers behind them)."""
    if verdict is None:
        return None
    ev = dict(verdict.evidence)
    size_measured, held = ev.pop("size_measured", None), ev.pop("size_held_by", None)
    return {
        "status": verdict.status,
        "reasons": list(verdict.reasons),
        # False: the loops do not see the robot's size; it is the model file's, held by `size_held_by`
        # (None: the model's lengths together)
        "size_measured": None if size_measured is None else bool(size_measured),
        "size_held_by": held,
        "evidence": {k: (float(v) if isinstance(v, (int, float, np.floating)) else v) for k, v in ev.items()},
    }


def sensor_corrections(res: CalibrationResult, model_out: str | None = None, kind: str = "urdf") -> dict | None:
    """What the model file cannot carry, as the fit used it: joint scale factors and compliances, and
    the loops' parameters.

    ``joints``: every scale factor and compliance at a value other than its nominal one (1 and 0),
    whatever its status: a value the fit used but reported as not identifiable still shapes the fit's
    predictions, and the written model must predict what the fit predicts.  A D-H table carries its
    scale factors (``k``) itself: only compliances are listed for it.  ``loop_parameters``: every loop
    parameter at the fit's value (tool points, fixtures, sensors, cameras; the ones with a place in
    the model are also frames of it, `closedloop.output.urdf.model_frames`), which ``closedloop
    evaluate`` holds where they were estimated once for all data.  None when there is nothing.
    """
    joints: dict[str, dict[str, float]] = {}
    for k, p in enumerate(res.problem.params):
        if p.kind not in ("scale", "compliance") or (p.kind == "scale" and kind == "dh"):
            continue
        v = float(res.fit.values[k])
        if v != p.nominal or res.fit.status[k] == ParamStatus.ESTIMATED:
            joints.setdefault(p.owner, {})["scale" if p.kind == "scale" else "compliance"] = v
    loops = {p.name: float(res.fit.values[k]) for k, p in enumerate(res.problem.params) if k >= res.problem.n_robot}
    if not joints and not loops:
        return None
    return {
        "model": model_out,
        "joints": joints,
        "loop_parameters": loops,
        "note": "joint value for the calibrated model = scale * reading - compliance * tau "
        "(offsets are folded into the model); scale 1 and compliance 0 where a joint is not listed",
    }


def sensors_path(model_out: str | Path) -> Path:
    """The sensor file beside a written model: ``<model without suffix>.sensors.yaml``."""
    return Path(str(Path(model_out).with_suffix("")) + ".sensors.yaml")


def write_sensors(res: CalibrationResult, model_out: str | Path, kind: str = "urdf") -> Path | None:
    """`sensors_text` written beside the model (`sensors_path`); the path, or None when there is none."""
    text = sensors_text(res, model_out, kind)
    if text is None:
        return None
    path = sensors_path(model_out)
    atomic_write_text(path, text)
    return path


def sensors_text(res: CalibrationResult, model_out: str | Path, kind: str = "urdf") -> str | None:
    """The sensor file beside a model written at `model_out` (`sensor_corrections` as YAML), or None when
    there is none."""
    import yaml

    corr = sensor_corrections(res, str(model_out), kind)
    if corr is None:
        return None
    return "# closedloop: joint sensor corrections the model file cannot carry\n" + yaml.safe_dump(
        corr, sort_keys=False
    )


def read_sensors(path: str | Path) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
    """A sensor file's joints, {joint: {'scale': k, 'compliance': c}} (missing entries: 1 and 0), and
    its loop parameters {name: value}."""
    from closedloop.errors import InputError
    from closedloop.io.schemas import load_yaml

    doc = load_yaml(Path(path), "sensor corrections", InputError)
    joints = (doc or {}).get("joints", {}) if isinstance(doc, dict) else None
    if not isinstance(joints, dict):
        raise InputError(f"{path}: a sensor file needs a 'joints' mapping (joint: {{scale, compliance}})")
    out = {}
    for j, d in joints.items():
        if not isinstance(d, dict) or not set(d) <= {"scale", "compliance"}:
            raise InputError(f"{path}: joint '{j}': give 'scale' and/or 'compliance' numbers")
        try:
            out[str(j)] = {"scale": float(d.get("scale", 1.0)), "compliance": float(d.get("compliance", 0.0))}
        except (TypeError, ValueError):
            raise InputError(f"{path}: joint '{j}': 'scale' and 'compliance' must be numbers") from None
    loops = doc.get("loop_parameters") or {}
    if not isinstance(loops, dict) or not all(isinstance(v, (int, float)) for v in loops.values()):
        raise InputError(f"{path}: 'loop_parameters' must map parameter names to numbers")
    return out, {str(n): float(v) for n, v in loops.items()}


def sensor_values(joints: dict[str, dict[str, float]], robot=None) -> dict[str, float]:
    """A sensor file's joints as parameter values (``<joint>.scale``, ``<joint>.compliance``; a D-H
    model's scale is its ``k``, in the table)."""
    out = {}
    for j, d in joints.items():
        if robot is None or robot.kind != "dh":
            out[f"{j}.scale"] = d["scale"]
        out[f"{j}.compliance"] = d["compliance"]
    return out


def moved_not_identifiable(res: CalibrationResult) -> list[dict]:
    """Parameters reported as not identifiable whose calibrated value differs from their initial one.

    A direction the data do not determine is a combination of parameters; each of them also takes part
    in directions the data do determine, and the fit moves it along those.  Its value is the fit's (the
    written model holds it, so that it predicts what the fit predicts); only the combination named in
    ``not_identifiable`` is undetermined.  Each entry names the parameter, the change and the
    combinations it is in.
    """
    out = []
    for k, p in enumerate(res.problem.params):
        if res.fit.status[k] != ParamStatus.UNIDENTIFIABLE:
            continue
        change = float(res.fit.values[k] - res.fit.initial[k])
        if change == 0.0:
            continue
        combos = [c.describe() for c in res.identifiability.weak if any(n == p.name for n, _ in c.terms)]
        out.append(
            {
                "name": p.name,
                "unit": p.unit,
                "initial": float(res.fit.initial[k]),
                "calibrated": float(res.fit.values[k]),
                "change": change,
                "change_in_priors": change / p.prior if p.prior else None,
                "why": "moved by the fit along the determined directions it takes part in; only the "
                "combination(s) below are undetermined, and the written model keeps the fit's value",
                "combinations": combos,
            }
        )
    return out


def build_report(
    res: CalibrationResult,
    model_path=None,
    log_path=None,
    row_name: Callable[[int], str] | None = None,
    *,
    inputs: dict | None = None,
    timing: dict | None = None,
    validation: dict | None = None,
    fixture_validation: dict | None = None,
    outputs: dict | None = None,
    next_poses: dict | None = None,
) -> dict:
    """The JSON report of a calibration, whole: the one place its dict is built, from the result's records.

    `row_name` (`JointLog.where`: 0-based row -> ``log.csv line 52``) names the rejected and suspect rows by
    file and line (``where``).  What a run adds around the fit goes in by keyword, each its own section:
    `inputs` (the command's inputs), `timing` (seconds and CPU seconds, into ``solver``), `validation`
    (k-fold, `closedloop.validation.kfold.cross_validate`), `fixture_validation`
    (`closedloop.validation.fixtures`), `outputs` (what was written).  The result's `accuracy` record
    (`AccuracyRecord`) is reported under ``accuracy``, with `next_poses` (the configurations ``--suggest``
    wrote, `closedloop.design.next_poses`) as its ``next_poses``.
    """
    where = (lambda row: row_name(row - 1)) if row_name is not None else (lambda row: None)
    prob = res.problem
    params = []
    for k, p in enumerate(prob.params):
        params.append(
            {
                "name": p.name,
                "kind": p.kind,
                "unit": p.unit,
                "initial": float(res.fit.initial[k]),
                "calibrated": float(res.fit.values[k]),
                "std_error": _f(res.fit.std[k]),
                "status": res.fit.status[k],
                "identifiable": res.fit.status[k] == ParamStatus.ESTIMATED,
                "change": float(res.fit.values[k] - res.fit.initial[k]),
            }
        )
    # a given noise is tested by the chi-square; an estimated one, or a plain fit's residual scale, makes
    # chi2 / dof 1 by construction
    tested = not res.noise.sigma_estimated and res.noise.joint_noise is not None
    p_value = _chi2_sf(res.noise.chi2, res.noise.dof) if tested else None
    report: dict[str, Any] = {
        "closedloop_version": __version__,
        "model": str(model_path) if model_path else None,
        "log": str(log_path) if log_path else None,
        "loops": [b.loop.describe() | {"configurations": int(b.theta.shape[0])} for b in prob.blocks],
        "joints": prob.joints,
        "solver": {
            "status": res.fit.solver_status,
            "message": res.fit.solver_message,
            "iterations": res.fit.iterations,
        },
        "noise": {
            "joint_sigma": res.noise.joint_noise,
            "closure_sigma": res.noise.sigma if res.noise.joint_noise is None else None,
            "estimated": res.noise.sigma_estimated,
            "chi2": res.noise.chi2,
            "dof": res.noise.dof,
            "chi2_per_dof": res.noise.chi2 / max(res.noise.dof, 1),
            "p_value": p_value,
            "consistent": None if p_value is None else bool(p_value > 1e-3),
        },
        "residuals": {
            "before": [asdict(r) for r in res.fit.residuals_before],
            "after": [asdict(r) for r in res.fit.residuals_after],
        },
        "identifiability": {
            "estimated": len(res.fit.estimated),
            "rank": res.identifiability.rank,
            "singular_values": [float(s) for s in res.identifiability.singular_values],
            "dropped": [
                {
                    "name": d.name,
                    "reason": d.reason,
                    "description": d.describe(),
                    "absorbed_into": [{"name": n, "coefficient": c} for n, c in d.absorbed_into],
                }
                for d in res.identifiability.dropped
            ],
            "not_identifiable": [
                {
                    "singular_value": c.singular_value,
                    "description": c.describe(),
                    "parameters": [{"name": n, "weight": w} for n, w in c.terms],
                }
                for c in res.identifiability.weak
            ],
            "notes": res.notes,
            "moved_not_identifiable": moved_not_identifiable(res),
        },
        "verdict": verdict_record(res.verdict),
        "gauge": {
            "length_scale_set_by": res.scale.gauge,
            "stands_for_length_m": res.scale.gauge_length or None,
            "note": res.scale.gauge_note,
            "scale": res.scale.scale_note,
            "scale_std_relative": _f(res.scale.scale_std),
            # known lengths between frames (closedloop.problem.lengths): size change per change of them, and
            # the size error a 1 mm / 1 mrad error of what the loops cannot see makes through them
            "length_response": _f(res.scale.length_response),
            "length_held_leak": _f(res.scale.length_leak),
        },
        # a long fit's error bars checked along the cost's profile (closedloop.analysis.linearity); [] when not checked
        "error_bars": [
            {
                "direction": p.name,
                "std": p.std,
                "rise": list(p.rise),
                "expected_rise": p.expected,
                "holds": p.holds,
                "falls": p.falls,
            }
            for p in res.noise.profiles
        ],
        "noise_model": list(res.noise.noise_model),  # per loop: task-space vs joint noise
        "shared_parameters": _shared(prob),
        "rejected": [asdict(r) | {"where": where(r.row)} for r in res.outliers.rejected],
        "weighting": res.noise.weighting,
        # which estimator the data support and why, where the standard errors come from (estimate.model_error)
        "estimator": {
            "name": res.noise.estimator,
            "reason": res.noise.estimator_reason,
            "error_bars": res.noise.error_bars,
            "evidence": dict(res.noise.model_error),
        },
        "robust": {
            "suspects": [
                {
                    "row": sp.row,
                    "where": where(sp.row),
                    "loop": sp.loop,
                    "standardized": sp.standardized,
                    "p_value": sp.p_value,
                    "weight": sp.weight,
                }
                for sp in res.outliers.suspects
            ]
        },
        "scale_factors": {p.name: float(res.fit.values[k]) for k, p in enumerate(prob.params) if p.kind == "scale"},
        # every compliance the fit used (estimated, or moved while not identifiable): what the written model predicts with
        "compliance": {
            p.name: float(res.fit.values[k])
            for k, p in enumerate(prob.params)
            if p.kind == "compliance" and (res.fit.status[k] == ParamStatus.ESTIMATED or res.fit.values[k] != p.nominal)
        },
        "parameters": params,
    }
    if timing:
        report["solver"] |= timing
    if res.accuracy is not None:
        report["accuracy"] = accuracy_record(res.accuracy)
    if next_poses is not None:
        report.setdefault("accuracy", {})["next_poses"] = next_poses
    for key, section in (
        ("inputs", inputs),
        ("validation", validation),
        ("fixture_validation", fixture_validation),
        ("outputs", outputs),
    ):
        if section is not None:
            report[key] = section
    return report


def accuracy_record(accuracy: AccuracyRecord) -> dict:
    """The report's ``accuracy`` section of the result's `AccuracyRecord` (`accuracy_section`)."""
    return accuracy_section(accuracy.workspace, accuracy.regions, accuracy.target)


def _shared(prob) -> dict[str, list[str]]:
    """Parameters read by several loops (closedloop.problem.shared) -> the loops that read them."""
    out: dict[str, list[str]] = {}
    for b, cols in zip(prob.blocks, prob.loop_columns):
        for k in cols:
            out.setdefault(prob.names[k], []).append(b.loop.name)
    return {n: lps for n, lps in out.items() if len(lps) > 1}


#: the share of the promised RMS error, from what the data cannot see, at which the words of the suggestions
#: say so: at 0.7 it is half the promised mean squared error or more
UNSEEN_DOMINATES = 0.7


def next_poses_words(nxt: dict) -> str:
    """The report's ``accuracy.next_poses`` (`closedloop.design.next_poses`) in words, as the summary and the
    HTML page print it: the configurations, the file and the predicted RMS error before and after them; where
    what the data cannot see is most of the error after them, that the suggestions leave it: only a loop
    that sees more (another place of the loop, another loop type) would."""
    before, after = nxt["predicted_rms_before_m"], nxt["predicted_rms_after_m"][-1]
    words = (
        f"{nxt['configurations']} configurations of loop {nxt['loop']} in {nxt['file']}: predicted RMS "
        f"{before * 1e3:.3g} mm -> {after * 1e3:.3g} mm once recorded and calibrated again"
    )
    unseen = nxt.get("predicted_unseen_rms_m") or 0.0
    if unseen >= UNSEEN_DOMINATES * after:
        words += (
            f" ({unseen * 1e3:.3g} mm RMS of it from what this loop's data cannot see, which these "
            "configurations leave: a loop that sees more would, at another place or of another type)"
        )
    return words


def write_report(report: dict, path: str | Path) -> None:
    """Write `report_text` to `path` whole."""
    atomic_write_text(Path(path), report_text(report))


def report_text(report: dict) -> str:
    """The report (`build_report`) as the JSON text written."""
    return json.dumps(report, indent=2) + "\n"


def accuracy_section(workspace, regions: dict | None = None, target: dict | None = None) -> dict:
    """The report's ``accuracy`` section: the predicted accuracy over the workspace
    (`closedloop.analysis.accuracy.WorkspaceAccuracy`, per followed frame: RMS, 95th percentile and
    expected largest error in m and rad, the share from what the data cannot see, the worst
    configuration), the held-out validation by region (`closedloop.validation.regions`) and the
    accuracy target (``--accuracy``) with whether the prediction meets it."""
    ws = None
    if workspace is not None:
        ws = {
            "configurations": int(workspace.readings.shape[0]),
            "source": workspace.source,
            # the readings are `closedloop check`'s (random within the joint ranges, seed 0): it compares with them
            "check_readings": bool(workspace.default_readings),
            "error_bars": workspace.error_bars,
            "size_removed": bool(workspace.size_removed),
            "prior": asdict(workspace.prior),
            "max_m": _f(workspace.max_m),
            "max_rad": _f(workspace.max_rad),
            "better_than_nominal": bool(workspace.better_than_nominal),
            "frames": [
                {
                    "loop": f.loop,
                    "frame": f.frame,
                    "kind": f.kind,
                    "predicted_rms_m": _f(f.rms_m),
                    "predicted_p95_m": _f(f.p95_m),
                    "predicted_max_m": _f(f.max_m),
                    "predicted_rms_rad": _f(f.rms_rad),
                    "predicted_p95_rad": _f(f.p95_rad),
                    "predicted_max_rad": _f(f.max_rad),
                    "predicted_max95_m": _f(f.max95_m),
                    "predicted_max95_rad": _f(f.max95_rad),
                    # the chance that one calibrated robot's largest error lies within 0.5-2x predicted_max_m
                    "predicted_max_within_2x": _f(f.max_within_2x),
                    "predicted_unseen_rms_m": _f(f.unseen_rms_m),
                    "predicted_unseen_rms_rad": _f(f.unseen_rms_rad),
                    # the share from the model error the estimators' disagreement shows (0: none found)
                    "predicted_model_error_rms_m": _f(f.model_rms_m),
                    "predicted_model_error_rms_rad": _f(f.model_rms_rad),
                    # the nominal model's expected error (its tolerance, same readings and gauge)
                    "nominal_rms_m": _f(f.nominal_rms_m),
                    "nominal_rms_rad": _f(f.nominal_rms_rad),
                    "worst_configuration": dict(f.worst),
                }
                for f in workspace.frames
            ],
        }
        me = workspace.model_error
        if me is not None:  # the plain fit against the calibration, over the workspace (analysis.accuracy)
            ws["model_error"] = {
                "ratio": _f(me.ratio),
                "dof": _f(me.dof),
                "limit": _f(me.limit),
                "share": _f(me.share),
                "found": bool(me.found),
            }
        if workspace.size_std is not None:  # the size the data do not measure: its predicted relative error
            ws["size"] = {
                "predicted_std": _f(workspace.size_std),
                "predicted": _f(workspace.size_predicted),
                "predicted95": _f(1.96 * workspace.size_std),
                "held_std": _f(workspace.size_held_std),
            }
        if workspace.covariance is not None:  # what `closedloop evaluate` propagates to its own configurations
            ws["covariance"] = {"parameters": list(workspace.parameters), "matrix": workspace.error_covariance.tolist()}
    return {"workspace": ws, "regions": regions, "target": target}
