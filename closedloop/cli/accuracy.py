"""`closedloop calibrate`'s predicted accuracy over the workspace: ``--workspace``, ``--accuracy``,
``--regions``, and the summary's lines (`closedloop.analysis.accuracy` computes; this module reads the
options, runs it and prints)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from closedloop.errors import InputError


def workspace_readings(args, robot, joints: list[str]) -> tuple[np.ndarray | None, str | None]:
    """The readings (n, joints) ``--workspace`` asks the accuracy to be predicted at, and where they come
    from: its log file (its rows, columns by joint name) or its box ``joint=lo:hi,...`` (random readings
    in it); (None, None) without it (random readings within the joint ranges, seed 0: the readings
    `closedloop check` compares the robots at)."""
    from closedloop.analysis.accuracy import N_WORKSPACE, random_readings

    spec = getattr(args, "workspace", None)
    if not spec:
        return None, None
    if Path(spec).is_file():
        from closedloop.io.logs import read_log

        lg = read_log(spec, robot.joint_names, degrees=bool(getattr(args, "degrees", False)))
        missing = [j for j in joints if j not in lg.joints]
        if missing:
            raise InputError(
                f"--workspace {spec}: no column for joint {missing[0]} (the calibrated joints: {', '.join(joints)})"
            )
        if len(lg) == 0:
            raise InputError(f"--workspace {spec}: no row")
        return lg.columns(joints), f"the {len(lg)} readings of {spec}"
    if "=" not in spec:
        raise InputError(f"--workspace {spec}: no such file (give a log file, or joint ranges joint=lo:hi,...)")
    from closedloop.cli.parse import parse_box

    box = parse_box(spec)
    return random_readings(robot, joints, box=box), f"{N_WORKSPACE} random readings within {spec}"


def predicted_accuracy(res, readings: np.ndarray | None = None, source: str | None = None):
    """The calibration's predicted accuracy over the workspace (`analysis.accuracy.predict_from_result`)
    at `readings` (`workspace_readings`; None: within the joint ranges); None where no loop has a frame
    to follow, or the kinematics are not finite at a reading (a note says so)."""
    from closedloop.analysis.accuracy import predict_from_result

    try:
        return predict_from_result(res, readings, source=source)
    except np.linalg.LinAlgError as exc:  # the calibration stands; the prediction is said to be missing
        res.notes.append(f"accuracy over the workspace not predicted: {exc}")
        return None


def next_poses(args, res, accuracy, report: dict) -> str | None:
    """``--suggest FILE``: the ``--suggest-n`` configurations of the first followed loop that most reduce the
    predicted workspace error (`closedloop.design.next_poses.suggest_poses`), as the CSV to write (a header
    of joint names, one row per configuration, radians: a log the robot can play), recorded in the report
    (``accuracy.next_poses``); None without --suggest or when none can be suggested (a note says why)."""
    path = getattr(args, "suggest", None)
    if not path:
        return None
    from closedloop.design.next_poses import suggest_poses

    k = int(getattr(args, "suggest_n", 10) or 10)
    followed = [
        i for i, b in enumerate(res.problem.blocks) if accuracy and b.loop.name in {f.loop for f in accuracy.frames}
    ]
    found = suggest_poses(res, accuracy, k, followed[0]) if followed else None
    if found is None or not found.readings.shape[0]:
        res.notes.append(f"--suggest {path}: no configuration to suggest (no followed loop closes at new readings)")
        return None
    report.setdefault("accuracy", {})["next_poses"] = {
        "file": str(path),
        "loop": found.loop,
        "configurations": int(found.readings.shape[0]),
        "candidates": found.candidates,
        "predicted_rms_before_m": found.rms_before_m,
        "predicted_rms_after_m": [float(v) for v in found.rms_after_m],
    }
    lines = [",".join(found.joints)] + [",".join(repr(float(v)) for v in row) for row in found.readings]
    return "\n".join(lines) + "\n"


def region_validation(robot, lg, loops, opts, args, res, prog) -> dict | None:
    """Held-out validation by region (`validation.regions.region_validate`, ``--regions K``), as the
    report's record; a region the refit cannot do without is a note, not an error."""
    from closedloop.errors import ClosedLoopError
    from closedloop.validation.regions import region_validate

    k = int(getattr(args, "regions", 0) or 0)
    if k < 2 or not res.converged:
        return None
    if len(lg) < 4 * k:  # regions of a few rows each say nothing of extrapolation: not run, said in the report
        return {"k": k, "skipped": f"{len(lg)} rows: too few for {k} regions (at least {4 * k})"}
    prog("validating", 0, 0.0)
    try:
        cv = region_validate(
            robot,
            lg,
            loops,
            res.problem.joints,
            opts,
            k=k,
            exclude=[rj.row - 1 for rj in res.rejected],
            progress=lambda done, n: prog("validating", done, n),
        )
    except ClosedLoopError as exc:
        prog.done()
        res.notes.append(f"region validation skipped: {str(exc).splitlines()[0]}")
        return {"k": k, "skipped": str(exc).splitlines()[0]}
    prog.done()
    return {
        "k": cv["k"],
        "rows": [len(r) for r in cv["regions"]],
        "test": cv["test"],
        "train": cv["train"],
        "folds_converged": [f["converged"] for f in cv["folds"]],
    }


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
        rms = f"{f['predicted_rms_m'] * 1e3:.3g} mm"
        nom = f.get("nominal_rms_m")
        rms += f", nominal model {nom * 1e3:.3g} mm" if nom is not None else ""
        lines.append(
            f"  loop {f['loop']}: {'tool point' if f['kind'] == 'point' else 'frame'} {f['frame']}: "
            f"{', '.join(parts)} at most (RMS {rms}; {f['predicted_unseen_rms_m'] * 1e3:.3g} mm RMS from what "
            "the data cannot see)"
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
        lines.append(f"  target {tgt['describe']}: {'met' if tgt['met'] else 'NOT met'} by the prediction")
    nxt = section.get("next_poses")
    if nxt:
        lines.append(
            f"  next: {nxt['configurations']} configurations of loop {nxt['loop']} in {nxt['file']}: predicted "
            f"RMS {nxt['predicted_rms_before_m'] * 1e3:.3g} mm -> {nxt['predicted_rms_after_m'][-1] * 1e3:.3g} mm "
            "once recorded and calibrated again"
        )
    return lines
