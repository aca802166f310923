"""Command-line pieces for rigs: ``closedloop evaluate`` and calibrate's rig options.

    closedloop evaluate nominal.urdf calibrated.urdf other.urdf log.csv --loop point:frame=ball,name=a ...
    closedloop evaluate nominal.urdf calibrated.urdf --joints j1,...,j7 \\
        --loop point:frame=ball,name=p3a,tip=@ball,log=place3_a.csv --loop ...,log=place3_b.csv

Each model's closure on the data with the robot untouched (`closedloop.validation.evaluate`): what a
calibration estimated once for all data (a shared ball ``tip=@ball``, tool points, a tracker's base,
cameras) is taken from the calibration, read from the sensor file beside a calibrated model
(``<model>.sensors.yaml``, which also carries its joint scale factors and compliances) or from
``--calibration REPORT``; only what is new at each place (a socket's position, a fixture's pose) is
fitted, unweighted.  ``--refit`` fits every loop unknown.  A loop frame that only the calibrated model
has (its written tool point ``ball_tip``) is lent to the other models.  Printed as a table (mean /
RMS closure per loop, mm) and written with ``--report`` as JSON.

Calibrate's rig options (`add_rig_options`, `rig_inputs`): ``--distance A B D
[SIGMA]`` (a known distance between loop points, `closedloop.problem.distances`), ``--length FRAME_A
FRAME_B L [SIGMA]`` (between two robot frames, `closedloop.problem.lengths`), ``--block NAME
A.point=X,Y,Z ...`` (a rigid block of known shape), ``--joints j1,j2,...``
(the column order of header-less logs), a loop's own log file
(``--loop ...,log=FILE``; then no positional log), and leave-one-fixture-out
validation (``--lofo auto|off``, `closedloop.validation.fixtures`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from closedloop.errors import InputError


def add_rig_options(c) -> None:
    """calibrate's options for rigs (module docstring)."""
    c.add_argument(
        "--distance",
        action="append",
        nargs="+",
        default=[],
        metavar="ARG",
        help="a known distance between two loop points: A.point B.point METRES [SIGMA] "
        "(e.g. front_a.point front_b.point 0.050); it sets the scale",
    )
    c.add_argument(
        "--length",
        action="append",
        nargs="+",
        default=[],
        metavar="ARG",
        help="a known length between two frames of the robot a fixed distance apart: FRAME_A FRAME_B "
        "METRES [SIGMA] (e.g. a link measured with calipers); the report says how far it sets "
        "the scale",
    )
    c.add_argument(
        "--block",
        action="append",
        nargs="+",
        default=[],
        metavar="ARG",
        help="points of one rigid block at known positions in its own frame: NAME A.point=X,Y,Z "
        "B.point=X,Y,Z ... [sigma=S] (metres); its pairwise distances set the scale",
    )
    c.add_argument(
        "--joints", metavar="J1,J2,...", help="the column order of header-less CSV logs (the first row is then data)"
    )
    c.add_argument(
        "--readings",
        choices=["measured", "commanded"],
        default="measured",
        help="what the log's joint values are: measured by encoders (default) or the controller's commanded "
        "setpoints; commanded readings make the residual model and servo error, not reading noise: the fit "
        "is plain least squares unless --weighting is given, and the report records it",
    )
    # --weighting's default is decided with --readings (`resolve_weighting`): None here means "not given"
    c.set_defaults(weighting=None, weighting_default=c.get_default("weighting"))
    c.add_argument(
        "--lofo",
        choices=["auto", "off"],
        default="auto",
        help="leave-one-fixture-out validation when the loops form several fixtures (default: auto)",
    )


def _order(args) -> list[str] | None:
    text = getattr(args, "joints", None)
    return [j.strip() for j in text.split(",") if j.strip()] if text else None


def read_inputs(log_path: str | None, robot, loops: list, degrees: bool = False, order: list[str] | None = None):
    """The joint log: the positional file (CSV or bag), or each loop's own ``log=`` file (one per fixture);
    refused where most readings of a joint lie far beyond its limits (`data.check_angle_units`)."""
    from closedloop.io.logs import check_angle_units

    lg = _read_inputs(log_path, robot, loops, degrees, order)
    check_angle_units(lg, robot, degrees)
    return with_gravity_torques(lg, robot)


def with_gravity_torques(lg, robot):
    """The log with ``tau:<joint>`` columns from the model's inertials (`RobotModel.gravity_torques`) when it
    carries none and the model has masses; otherwise as it is.  The compliance model (theta' = k theta +
    theta_off - c tau) then needs no torque logging on a robot that carries only itself; logged torques
    always win.  `torque_source` says which: 'log', 'gravity' or None."""
    present = [j for j in robot.joint_names if f"tau:{j}" in lg.extra]
    if present or not robot.has_inertias:
        lg.torque_source = "log" if present else None
        return lg
    known = [j for j in robot.joint_names if j in lg.joints]
    tau = robot.gravity_torques(lg.columns(known), known)
    lg.extra.update({f"tau:{j}": tau[:, k] for k, j in enumerate(known)})
    lg.torque_source = "gravity"
    return lg


def resolve_weighting(args) -> str | None:
    """`--weighting` as given, else plain least squares ('none') for commanded readings (the errors-in-variables
    weighting models reading noise, which a setpoint does not have), else the parser's default; sets
    ``args.weighting`` and returns the note the summary prints (None when there is nothing to say)."""
    given = getattr(args, "weighting", None)
    commanded = getattr(args, "readings", "measured") == "commanded"
    if given is None:
        args.weighting = "none" if commanded else (getattr(args, "weighting_default", None) or "noise")
        if commanded:
            return (
                "readings are commanded setpoints (--readings commanded): the residual is model and servo "
                "error, not reading noise; fitted by plain least squares (--weighting none)"
            )
    elif commanded and given == "noise":
        return (
            "readings are commanded setpoints, yet --weighting noise treats the residual as reading noise: "
            "its noise estimate stands for model and servo error"
        )
    return None


def input_record(args, lg, res=None) -> dict:
    """What the report says about the inputs: whether the readings are measured or commanded, the weighting
    that follows, and where the joint torques the compliance model used come from ('log', 'gravity': the
    model's inertials at the readings; null when no compliance was used)."""
    used = res is None or any(
        p.kind == "compliance" and (res.status[k] == "estimated" or res.values[k] != 0.0)
        for k, p in enumerate(res.problem.params)
    )
    return {
        "readings": getattr(args, "readings", "measured"),
        "weighting": getattr(args, "weighting", None),
        "torques": getattr(lg, "torque_source", None) if used else None,
    }


def _read_inputs(log_path: str | None, robot, loops: list, degrees: bool, order: list[str] | None):
    from closedloop.io.logs import read_log, read_loop_logs

    linear = [j for j, info in robot.joints.items() if info.kind == "prismatic"]
    real = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    own = [lp for lp in real if getattr(lp, "log_path", None)]
    if own:
        if len(own) != len(real):
            missing = [lp.name for lp in real if not getattr(lp, "log_path", None)]
            raise InputError(
                f"loop(s) {', '.join(missing)} have no log=FILE while others have: give every loop "
                "its file, or one log with a 'loop' column"
            )
        if log_path:
            raise InputError(f"{log_path}: the loops name their own log files (log=...); give no log besides")
        return read_loop_logs([(lp.name, lp.log_path) for lp in own], robot.joint_names, degrees, linear, order)
    if not log_path:
        raise InputError("no log given: name the CSV log (or each loop's file with --loop ...,log=FILE)")
    if order:
        return read_log(log_path, robot.joint_names, degrees, linear, order)
    from closedloop.cli.tools import read_log_or_bag

    return read_log_or_bag(log_path, robot, degrees)


def rig_inputs(args, robot, loops: list):
    """(log, loops + known distances and lengths) for calibrate."""
    from closedloop.problem.distances import parse_blocks, parse_distances
    from closedloop.problem.lengths import parse_lengths

    lg = read_inputs(args.log, robot, loops, args.degrees, _order(args))
    loops = (
        list(loops)
        + parse_distances(getattr(args, "distance", []) or [], loops)
        + parse_blocks(getattr(args, "block", []) or [], loops)
        + parse_lengths(getattr(args, "length", []) or [], robot)
    )
    if not args.log:
        args.log = str(lg.source)
    return lg, loops


def fixture_validation(robot, lg, loops: list, opts, report: dict, args, prog=None) -> dict | None:
    """Leave-one-fixture-out validation (default when the loops form several fixtures); into the report."""
    from closedloop.validation.fixtures import fixture_groups, leave_one_fixture_out

    if getattr(args, "lofo", "auto") == "off" or lg.loop is None or len(fixture_groups(loops)) < 2:
        return None
    if prog:
        prog("validating fixtures", 0, 0.0)
    out = leave_one_fixture_out(robot, lg, loops, opts)
    if prog:
        prog.done()
    if out is not None:
        report["fixture_validation"] = out
    return out


def fixture_lines(out: dict | None) -> list[str]:
    """The summary's lines for a leave-one-fixture-out record (`fixture_validation`), printed after the verdict."""
    lines = []
    for r in (out or {}).get("fixtures", []):
        if r.get("error"):
            lines.append(f"  held-out fixture {r['fixture']}: not validated ({r['error']})")
        elif r["calibrated_rms_m"] is not None:
            lines.append(
                f"  held-out fixture {r['fixture']}: closure RMS {r['calibrated_rms_m'] * 1e3:.4g} mm "
                f"(nominal model {r['nominal_rms_m'] * 1e3:.4g} mm)" + (" WORSE" if r["worse"] else "")
            )
    return lines


# --------------------------------------------------------------------------- closedloop evaluate
def add_parser(sub) -> None:
    e = sub.add_parser(
        "evaluate",
        help="closure of one or more models on a log (robot untouched)",
        description="Each model's closure on the data, the robot untouched and the loops' own unknowns fitted.",
        epilog="example:\n" + __doc__.split("\n\n")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    e.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="MODEL [MODEL ...] LOG: models (URDF, MJCF, D-H), then the log (none when every loop "
        "names its own file, log=FILE)",
    )
    e.add_argument("--loop", action="append", default=[], metavar="SPEC", help="a loop, as for calibrate")
    e.add_argument("--joints", metavar="J1,J2,...", help="the column order of header-less CSV logs")
    e.add_argument("--label", action="append", default=[], help="a name per model for the table (default: file)")
    e.add_argument("--report", help="JSON report of the evaluation")
    e.add_argument("--degrees", action="store_true", help="the log is in degrees")
    e.add_argument(
        "--calibration",
        action="append",
        default=[],
        metavar="REPORT",
        help="a calibration's report.json: the model it wrote predicts with its tool points, instruments "
        "and sensor corrections (default: the <model>.sensors.yaml beside each model)",
    )
    e.add_argument(
        "--refit",
        action="store_true",
        help="fit every loop unknown on the evaluated rows (tool points and instruments too), as a fresh fit would",
    )
    e.set_defaults(func=cmd_evaluate)


def model_calibration(path: str, reports: dict[Path, dict], robot) -> tuple[dict, dict, str | None]:
    """(robot values, loop values, where from) for one evaluated model: the report that wrote it, else the
    sensor file beside it, else nothing (a nominal model)."""
    from closedloop.output.report import read_sensors, sensor_values, sensors_path

    rep = reports.get(Path(path).resolve())
    if rep is not None:
        params = rep.get("parameters") or []
        loops = {p["name"]: float(p["calibrated"]) for p in params if p.get("kind") == "loop"}
        values = {}
        for p in params:
            if p.get("kind") in ("scale", "compliance") and (robot.kind != "dh" or p["kind"] == "compliance"):
                values[p["name"]] = float(p["calibrated"])
        return values, loops, str(rep.get("_path"))
    side = sensors_path(path)
    if side.is_file():
        joints, loops = read_sensors(side)
        return sensor_values(joints, robot), loops, str(side)
    return {}, {}, None


def read_calibrations(paths: list[str], models: list[str]) -> dict[Path, dict]:
    """``--calibration`` reports by the model each wrote (``outputs.model``); one that wrote none of
    `models` is an input error."""
    from closedloop.io.schemas import read_text

    out = {}
    listed = {Path(m).resolve(): m for m in models}
    for p in paths:
        try:
            rep = json.loads(read_text(p, "calibration report", InputError))
        except json.JSONDecodeError as exc:
            raise InputError(f"--calibration {p}: not a JSON report ({exc.msg}, line {exc.lineno})") from None
        wrote = ((rep.get("outputs") or {}).get("model")) if isinstance(rep, dict) else None
        if not wrote or Path(wrote).resolve() not in listed:
            raise InputError(
                f"--calibration {p}: this report wrote {wrote or 'no model'}, which is not among the models "
                f"({', '.join(models)}); give the model it wrote"
            )
        rep["_path"] = p
        out[Path(wrote).resolve()] = rep
    return out


def lend_frames(robots: list, loops_specs: list[str]) -> list[str]:
    """Frames some models lack that another model has on a fixed joint (a calibrated model's written
    tool point or fixture), added to the models lacking them at the same place on the same parent
    frame; returns one note per frame lent."""
    import re

    import pinocchio as pin

    wanted = []
    for s in loops_specs:
        wanted += [
            v.strip().strip("\"'") for v in re.findall(r"(?:^|,)\s*(?:frame|to)\s*=\s*([^,]+)", s.partition(":")[2])
        ]
    from closedloop.model.robot import find_frame

    notes = []
    for name in dict.fromkeys(wanted):
        have = [r for r in robots if r.model.existFrame(name)]
        lack = [r for r in robots if not r.model.existFrame(name)]
        if not have or not lack:
            continue
        src = have[0].model
        f = src.frames[find_frame(src, name)]
        for r in lack:
            parent = src.frames[f.parentFrame]  # the nearest frame up the tree that this model has too
            while parent.name != "universe" and not r.model.existFrame(parent.name):
                parent = src.frames[parent.parentFrame]
            if parent.parentJoint != f.parentJoint:
                continue  # a joint between them: not a fixed frame of a shared parent
            rel = parent.placement.inverse() * f.placement  # the frame on its parent frame
            pid = find_frame(r.model, parent.name)
            p = r.model.frames[pid]
            r.model.addFrame(pin.Frame(name, p.parentJoint, pid, p.placement * rel, pin.FrameType.OP_FRAME))
            notes.append(f"frame '{name}' of {have[0].source} lent to {r.source} (on '{parent.name}')")
    return notes


def cmd_evaluate(args) -> int:
    from closedloop.io.files import atomic_write_text, check_outputs
    from closedloop.loops.spec import parse_loop
    from closedloop.model.robot import RobotModel
    from closedloop.validation.evaluate import compare_prediction, evaluate_model, prediction_lines, table

    if not args.loop:
        raise InputError("evaluate: give the loops (--loop ...), as for calibrate")
    if args.report:
        check_outputs({"--report": args.report}, args.files)
    own_logs = all("log=" in s for s in args.loop)
    models, log_path = (args.files, None) if own_logs else (args.files[:-1], args.files[-1])
    if not models:
        raise InputError("evaluate: give at least one model before the log")
    if args.label and len(args.label) != len(models):
        raise InputError(f"evaluate: {len(args.label)} --label for {len(models)} models")
    robots = [RobotModel.from_file(m) for m in models]
    reports = read_calibrations(args.calibration, models)
    for note in lend_frames(robots, args.loop):
        print(f"note: {note}", file=sys.stderr)
    loops0 = [parse_loop(s, robots[0]) for s in args.loop]
    lg = read_inputs(log_path, robots[0], loops0, args.degrees, _order(args))
    from closedloop.io.logs import check_loop_column

    check_loop_column(lg, [lp.name for lp in loops0])
    evals = []
    compared: list[list[dict]] = []
    for k, (path, robot) in enumerate(zip(models, robots)):
        loops = loops0 if k == 0 else [parse_loop(s, robot) for s in args.loop]
        label = args.label[k] if args.label else Path(path).name
        values, loop_values, source = model_calibration(path, reports, robot)
        ev = evaluate_model(robot, lg, loops, values, label, calibration=loop_values, refit=args.refit)
        if source and (ev.held or values):
            what = [f"{len(ev.held)} loop parameter(s) held"] if ev.held else []
            what += [f"{len(values)} joint scale/compliance value(s)"] if values else []
            print(f"note: {label}: {' and '.join(what)} from {source}", file=sys.stderr)
        evals.append(ev)
        rep_k = reports.get(Path(path).resolve())
        compared.append(compare_prediction(ev, rep_k, robot, lg, loops, values) if rep_k is not None else [])
    print(table(evals))
    for ev, rows in zip(evals, compared):  # a calibration's prediction beside what is observed
        for line in prediction_lines(ev.model, rows):
            print(line)
    if args.report:
        rep = {
            "log": str(lg.source),
            "configurations": len(lg),
            "refit": bool(args.refit),
            "models": [e.as_dict() | ({"prediction": rows} if rows else {}) for e, rows in zip(evals, compared)],
        }
        atomic_write_text(args.report, json.dumps(rep, indent=2) + "\n")
        print(f"wrote {args.report}", file=sys.stderr)
    return 0


def require_log(args) -> None:
    """calibrate without a log: only when every loop names its own file (--loop ...,log=FILE)."""
    if not args.log and not (args.loop and all("log=" in s for s in args.loop)):
        raise InputError(
            "calibrate: the following arguments are required: log (or give every loop its own "
            "file: --loop ...,log=FILE)"
        )
