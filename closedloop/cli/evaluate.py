"""``closedloop evaluate``: each model's closure on a log, the robot untouched.

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
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from closedloop.errors import InputError


def _order(args) -> list[str] | None:
    text = getattr(args, "joints", None)
    return [j.strip() for j in text.split(",") if j.strip()] if text else None


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
        for p in params:  # those the calibration set (a value left at its nominal is no calibration's)
            if p.get("kind") in ("scale", "compliance") and (robot.kind != "dh" or p["kind"] == "compliance"):
                if p.get("status") == "estimated" or p.get("calibrated") != p.get("initial"):
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
    from closedloop.io.joint_log import read_joint_log
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
    notes: list[str] = []
    lg = read_joint_log(log_path, robots[0], loops0, args.degrees, _order(args), notes)
    lg = robots[0].with_gravity_torques(lg)
    for note in notes:
        print(f"  {note}", file=sys.stderr)
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
