"""The JSON calibration report (schema in the README)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from closedloop.calibration.pipeline import CalibrationResult
from closedloop.io.files import atomic_write_text
from closedloop.records import ParamStatus
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
    return {
        "status": verdict.status,
        "reasons": list(verdict.reasons),
        "evidence": {
            k: (float(v) if isinstance(v, (int, float, np.floating)) else v) for k, v in verdict.evidence.items()
        },
    }


def build_report(res: CalibrationResult, model_path=None, log_path=None) -> dict:
    """A plain-dict report of a calibration."""
    prob = res.problem
    params = []
    for k, p in enumerate(prob.params):
        params.append(
            {
                "name": p.name,
                "kind": p.kind,
                "unit": p.unit,
                "initial": float(res.initial[k]),
                "calibrated": float(res.values[k]),
                "std_error": _f(res.std[k]),
                "status": res.status[k],
                "identifiable": res.status[k] == ParamStatus.ESTIMATED,
            }
        )
    p_value = _chi2_sf(res.chi2, res.dof) if not res.sigma_estimated else None
    return {
        "closedloop_version": __version__,
        "model": str(model_path) if model_path else None,
        "log": str(log_path) if log_path else None,
        "loops": [b.loop.describe() | {"configurations": int(b.theta.shape[0])} for b in prob.blocks],
        "joints": prob.joints,
        "solver": {"status": res.solver_status, "message": res.solver_message, "iterations": res.iterations},
        "noise": {
            "joint_sigma": res.sigma,
            "estimated": res.sigma_estimated,
            "chi2": res.chi2,
            "dof": res.dof,
            "chi2_per_dof": res.chi2 / max(res.dof, 1),
            "p_value": p_value,
            "consistent": None if p_value is None else bool(p_value > 1e-3),
        },
        "residuals": {
            "before": [asdict(r) for r in res.residuals_before],
            "after": [asdict(r) for r in res.residuals_after],
        },
        "identifiability": {
            "estimated": len(res.estimated),
            "rank": res.rank,
            "singular_values": [float(s) for s in res.singular_values],
            "dropped": [
                {
                    "name": d.name,
                    "reason": d.reason,
                    "description": d.describe(),
                    "absorbed_into": [{"name": n, "coefficient": c} for n, c in d.absorbed_into],
                }
                for d in res.dropped
            ],
            "not_identifiable": [
                {
                    "singular_value": c.singular_value,
                    "description": c.describe(),
                    "parameters": [{"name": n, "weight": w} for n, w in c.terms],
                }
                for c in res.weak
            ],
            "notes": res.notes,
        },
        "verdict": verdict_record(res.verdict),
        "gauge": {
            "length_scale_set_by": res.gauge,
            "stands_for_length_m": res.gauge_length or None,
            "note": res.gauge_note,
            "scale": getattr(res, "scale_note", None),
            "scale_std_relative": _f(getattr(res, "scale_std", None)),
            # known lengths between frames (closedloop.problem.lengths): size change per change of them, and
            # the size error a 1 mm / 1 mrad error of what the loops cannot see makes through them
            "length_response": _f(getattr(res, "length_response", None)),
            "length_held_leak": _f(getattr(res, "length_leak", None)),
        },
        # a long fit's error bars checked along the cost's profile (closedloop.analysis.linearity); [] when not checked
        "error_bars": [
            {"direction": p.name, "std": p.std, "rise": list(p.rise), "expected_rise": p.expected, "holds": p.holds}
            for p in getattr(res, "profiles", [])
        ],
        "noise_model": list(getattr(res, "noise_model", [])),  # per loop: task-space vs joint noise
        "shared_parameters": _shared(prob),
        "rejected": [asdict(r) for r in res.rejected],
        "weighting": res.weighting,
        # which estimator the data support and why, where the standard errors come from (estimate.model_error)
        "estimator": {
            "name": getattr(res, "estimator", None),
            "reason": getattr(res, "estimator_reason", None),
            "error_bars": getattr(res, "error_bars", None),
            "evidence": dict(getattr(res, "model_error", {}) or {}),
        },
        "robust": {
            "suspects": [
                {
                    "row": sp.row,
                    "loop": sp.loop,
                    "standardized": sp.standardized,
                    "p_value": sp.p_value,
                    "weight": sp.weight,
                }
                for sp in res.suspects
            ]
        },
        "scale_factors": {p.name: float(res.values[k]) for k, p in enumerate(prob.params) if p.kind == "scale"},
        "compliance": {
            p.name: float(res.values[k])
            for k, p in enumerate(prob.params)
            if p.kind == "compliance" and res.status[k] == ParamStatus.ESTIMATED
        },
        "parameters": params,
    }


def _shared(prob) -> dict[str, list[str]]:
    """Parameters read by several loops (closedloop.problem.shared) -> the loops that read them."""
    out: dict[str, list[str]] = {}
    for b, cols in zip(prob.blocks, prob.loop_columns):
        for k in cols:
            out.setdefault(prob.names[k], []).append(b.loop.name)
    return {n: lps for n, lps in out.items() if len(lps) > 1}


def write_report(report: dict, path: str | Path) -> None:
    atomic_write_text(Path(path), json.dumps(report, indent=2) + "\n")
