"""The summary's lines of a run's predicted accuracy (the report's ``accuracy`` section,
`closedloop.output.report.accuracy_record`; computed by `closedloop.run.accuracy`)."""

from __future__ import annotations

from closedloop.output.report import next_poses_words


def accuracy_lines(section: dict | None) -> list[str]:
    """The summary's lines of the report's ``accuracy`` section (`output.report.accuracy_record`)."""
    if not section or not section.get("workspace"):
        return []
    ws = section["workspace"]
    lines = [f"predicted accuracy over the workspace ({ws['source']}; error bars from {ws['error_bars']}):"]
    for f in ws["frames"]:
        parts = [f"{f['predicted_max_m'] * 1e3:.3g} mm"]
        if f.get("predicted_max_rad") is not None:
            parts.append(f"{f['predicted_max_rad'] * 1e3:.3g} mrad")
        b95 = [f"{f['predicted_max95_m'] * 1e3:.3g} mm"] if f.get("predicted_max95_m") is not None else []
        if b95 and f.get("predicted_max95_rad") is not None:
            b95.append(f"{f['predicted_max95_rad'] * 1e3:.3g} mrad")
        rms = f"{f['predicted_rms_m'] * 1e3:.3g} mm"
        nom = f.get("nominal_rms_m")
        rms += f", nominal model {nom * 1e3:.3g} mm" if nom is not None else ""
        model = f.get("predicted_model_error_rms_m")
        shares = f"{f['predicted_unseen_rms_m'] * 1e3:.3g} mm RMS from what the data cannot see"
        if model:  # the estimators disagree beyond the noise: a residual the kinematics cannot explain
            shares += f", {model * 1e3:.3g} mm from model error"
        lines.append(
            f"  loop {f['loop']}: {'tool point' if f['kind'] == 'point' else 'frame'} {f['frame']}: "
            f"{', '.join(parts)} at most expected"
            + (f" (95 % bound {', '.join(b95)}; RMS {rms}; {shares})" if b95 else f" (RMS {rms}; {shares})")
        )
    reg = section.get("regions")
    if reg and "test" in reg:
        for t in reg["test"]:
            if t.get("rms_m") is None and t.get("rms_rad") is None:
                continue
            parts = [f"{t['rms_m'] * 1e3:.4g} mm" if t.get("rms_m") is not None else ""]
            parts.append(f"{t['rms_rad'] * 1e3:.4g} mrad" if t.get("rms_rad") is not None else "")
            lines.append(
                f"  {reg['k']} regions held out in turn, loop {t['loop']}: held-out closure RMS "
                + ", ".join(p for p in parts if p)
            )
    tgt = section.get("target")
    if tgt:
        said = "NOT met by the prediction"
        if tgt["met"]:
            said = (
                "met by the prediction"
                if tgt.get("met_95", True)
                else "met by the expected largest error, NOT by its 95 % bound"
            )
        lines.append(f"  target {tgt['describe']}: {said}")
    nxt = section.get("next_poses")
    if nxt:
        lines.append(f"  next: {next_poses_words(nxt)}")
    return lines
