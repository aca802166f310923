"""Command-line helpers for a user's own robot and data (printing allowed: CLI code).

* ``closedloop loops``: the loop types of :data:`closedloop.loops.spec.LOOP_TYPES`
  with their keys and an example each (also the epilog of ``calibrate --help``);
* ``closedloop extract``: quasi-static samples of a ROS bag written as the CSV log
  (:mod:`closedloop.io.bags`); ``calibrate`` also takes a bag in place of the CSV;
* ``--config FILE.yaml``: every option of a subcommand in one YAML mapping
  (keys are the long option names, ``-`` or ``_``; positionals by name);
  options given on the command line win;
* ``--html`` / ``--plots``: :mod:`closedloop.output.html` after a calibration.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path
from typing import Any

from closedloop.errors import InputError

#: An example per loop type (the registry gives the keys; a loop module's factory docstring the syntax).
LOOP_EXAMPLES = {
    "weld": "weld:frame=panda_hand_tcp,name=fixture   (tool clamped to a fixture at an unknown pose)",
    "point": "point:frame=stylus_tip,name=socket        (tip in a ball socket; tip and socket unknown)",
    "plane": "plane:frame=stylus_tip,name=table         (tip touching an unknown plane)",
    "hinge": "hinge:frame=tool0,name=door               (tool on a door handle, hinge unknown)",
    "passive": "passive:frame=tool0,task=door.urdf,task_frame=handle,name=door",
    "measured_pose": "measured_pose:frame=tool0,name=tracker,sigma_t=1e-4,sigma_r=1e-3   "
    "(log columns tracker:x .. tracker:rz)",
    "measured_point": "measured_point:frame=stylus_tip,name=tracker   (log columns tracker:x tracker:y tracker:z)",
    "camera": 'camera:frame=marker,cameras=2,K1="600 600 320 240",K2="600 600 320 240"   (log columns <name>:u1 ..)',
}


def _registry() -> dict:
    from closedloop.loops.spec import all_loop_types  # every type of the one table, spec.LOOP_TYPES

    return all_loop_types()


def loop_help(width: int = 100) -> str:
    """One paragraph per registered loop type: keys, syntax and an example."""
    lines = ["loop types (--loop TYPE:key=value,...; repeatable; 'closedloop loops' for details):"]
    for kind, (factory, keys) in sorted(_registry().items()):
        lines.append(f"  {kind:<15} keys: {', '.join(sorted(keys))}")
    return "\n".join(textwrap.fill(ln, width, subsequent_indent=" " * 18) if len(ln) > width else ln for ln in lines)


def cmd_loops(args) -> int:
    """Print every loop type with its keys, syntax and an example."""
    for kind, (factory, keys) in sorted(_registry().items()):
        print(f"{kind}")
        print(f"  keys:    {', '.join(sorted(keys))}")
        doc = (factory.__doc__ or "").strip().splitlines()
        if doc:
            print(f"  syntax:  {doc[0].strip()}")
        print(f"  example: --loop {LOOP_EXAMPLES.get(kind, kind + ':frame=<tool frame>')}")
    from closedloop.loops.spec import GENERIC_KEYS

    print(
        f"Every loop type also takes: {', '.join(sorted(GENERIC_KEYS))}, and KEY=@GROUP (an unknown shared "
        "by several loops)."
    )
    print("Frames are the model's frame names (closedloop inspect MODEL lists them); 'to' defaults to the world.")
    return 0


# --------------------------------------------------------------------------- ROS bags
def read_log_or_bag(path: str, robot, degrees: bool = False, bag_options=None):
    """A CSV log, or the quasi-static samples of a ROS bag (:func:`closedloop.io.bags.extract`)."""
    if Path(path).suffix.lower() == ".csv":  # the bag reader is not loaded for a CSV log
        bag = False
    else:
        from closedloop.io.bags import is_bag

        bag = is_bag(path)
    if bag:
        from closedloop.io.bags import extract

        lg, samples = extract(path, robot.joint_names, bag_options)
        print(f"  {path}: {len(samples)} standstills extracted", file=sys.stderr)
        return lg
    from closedloop.io.logs import read_log

    return read_log(
        path,
        robot.joint_names,
        degrees=degrees,
        linear=[j for j, info in robot.joints.items() if info.kind == "prismatic"],
    )


def cmd_extract(args) -> int:
    from closedloop.io.bags import ExtractOptions, extract, parse_windows
    from closedloop.io.files import check_outputs
    from closedloop.model.robot import RobotModel

    if args.model:
        joints = RobotModel.from_file(args.model).joint_names
    elif args.joints:
        joints = [j.strip() for j in args.joints.split(",") if j.strip()]
    else:
        raise InputError("extract: say which joints to keep: --model ROBOT.urdf|.xml or --joints j1,j2,...")
    check_outputs({"--out": args.out}, [args.bag])  # not the bag, a writable place, a pipe written in place
    from closedloop.io.schemas import check_number

    for opt, name in (
        ("--threshold", "threshold"),
        ("--settle", "settle"),
        ("--window-s", "window_s"),
        ("--spread", "spread"),
        ("--gap", "gap"),
    ):
        setattr(args, name, check_number(opt, getattr(args, name), 0.0, 1e6, lo_open=True))
    split = args.split
    if args.window and split != "window":
        raise InputError("--window is for --split window (a loop per time window): give both, or neither")
    names = None
    if args.names:
        items = [n.strip() for n in args.names.split(",")]
        names = dict(n.split("=", 1) for n in items) if split == "topic" and all("=" in n for n in items) else items
    opts = ExtractOptions(
        threshold=args.threshold,
        settle=args.settle,
        window=args.window_s,
        spread=args.spread,
        topics=args.topic or None,
        split=split,
        gap=args.gap,
        windows=parse_windows(args.window),
        names=names,
    )
    lg, samples = extract(args.bag, joints, opts)
    lg.write_csv(args.out)
    groups = ""
    if lg.loop is not None:
        import numpy as np

        u, c = np.unique(lg.loop, return_counts=True)
        groups = " (" + ", ".join(f"{a}: {b}" for a, b in zip(u, c)) + ")"
    print(f"extracted {len(samples)} quasi-static samples of {len(joints)} joints{groups} -> {args.out}")
    return 0


def add_extract_parser(sub) -> None:
    e = sub.add_parser(
        "extract",
        help="quasi-static joint samples of a ROS bag -> CSV log",
        description="Find the standstills in a ROS 1 (.bag) or ROS 2 (sqlite3, MCAP) bag of "
        "sensor_msgs/JointState and write one CSV row per standstill.",
    )
    e.add_argument("bag", help="ROS 1 .bag file, or ROS 2 bag directory (metadata.yaml) / .mcap / .db3")
    e.add_argument("--model", help="robot model: its joints are matched by name in the messages")
    e.add_argument("--joints", help="joint names (comma-separated), instead of --model")
    e.add_argument("--out", required=True, help="CSV log to write")
    e.add_argument("--topic", action="append", default=[], help="JointState topic (repeatable; default: all)")
    e.add_argument("--threshold", type=float, default=0.01, help="standstill: speed below this (rad/s, default 0.01)")
    e.add_argument("--settle", type=float, default=0.5, help="standstill: for at least this long (s, default 0.5)")
    e.add_argument(
        "--spread",
        type=float,
        default=1e-3,
        help="a standstill splits where the position jumps by more than this (rad, default 1e-3)",
    )
    e.add_argument(
        "--window-s",
        type=float,
        default=0.2,
        help="finite-difference window when messages carry no velocities (s, default 0.2)",
    )
    e.add_argument(
        "--split",
        choices=["topic", "gap", "window"],
        help="several fixtures: one loop per topic, per gap between standstills, or per time window",
    )
    e.add_argument("--gap", type=float, default=5.0, help="--split gap: seconds between fixtures (default 5)")
    e.add_argument(
        "--window",
        action="append",
        default=[],
        metavar="NAME=T0:T1",
        help="--split window: loop NAME from T0 to T1 s after the bag start (repeatable)",
    )
    e.add_argument("--names", help="loop names: in order (gap) or TOPIC=NAME,... (topic)")
    e.add_argument("--config", help="YAML file holding these options")
    e.set_defaults(func=cmd_extract)


# --------------------------------------------------------------------------- --config
def _subcommand(parser: argparse.ArgumentParser, argv: list[str]):
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for tok in argv:
        if tok in subs.choices:
            return tok, subs.choices[tok]
    return None, None


def _config_path(argv: list[str]) -> str | None:
    for k, tok in enumerate(argv):
        if tok == "--config" and k + 1 < len(argv):
            return argv[k + 1]
        if tok.startswith("--config="):
            return tok.split("=", 1)[1]
    return None


def _converted(act: argparse.Action, text: str) -> Any:
    """`text` converted by the option's own ``type=`` (none: the text itself)."""
    return act.type(text) if callable(act.type) else text


def load_config(path: str, sub: argparse.ArgumentParser, command: str) -> dict:
    """The YAML mapping of ``path`` checked against the options of ``sub`` (dest -> value)."""
    from closedloop.io.schemas import load_yaml  # strict YAML: only true/false are booleans, no 1_000

    data = load_yaml(path, "config")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{path}: a config is a mapping of option: value")
    actions = {a.dest: a for a in sub._actions if a.dest not in ("help", "config", "func")}
    out = {}
    for key, value in data.items():
        dest = str(key).lstrip("-").replace("-", "_")
        act = actions.get(dest)
        if act is None:
            raise InputError(
                f"{path}: unknown option '{key}' for {command} "
                f"(known: {', '.join(sorted(a.replace('_', '-') for a in actions))})"
            )
        if isinstance(act, argparse._AppendAction):
            value = [_converted(act, str(v)) for v in (value if isinstance(value, list) else [value])]
        elif isinstance(act, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            if not isinstance(value, bool):
                raise InputError(f"{path}: option '{key}' takes true or false")
        elif value is not None:
            if isinstance(value, (bool, dict)) or (isinstance(value, list) and act.nargs is None and act.type):
                want = "a number" if act.type not in (None, str) else "a text value (a path, a name)"
                raise InputError(f"{path}: option '{key}' takes {want}, got {_shown(value)}")
            if isinstance(value, list):
                value = ",".join(str(v) for v in value)
            try:
                value = _converted(act, str(value))
            except (TypeError, ValueError):
                raise InputError(f"{path}: option '{key}': '{value}' is not valid") from None
            if act.choices is not None and value not in act.choices:
                raise InputError(f"{path}: option '{key}' takes one of {', '.join(map(str, act.choices))}")
        out[dest] = value
    return out


def _shown(value) -> str:
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    return "a mapping" if isinstance(value, dict) else "a list" if isinstance(value, list) else repr(value)


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None):
    """``parser.parse_args`` with a subcommand's ``--config FILE`` applied first (command line wins)."""
    import logging

    # kinematics only: yourdfpy's warnings about mesh files it cannot resolve (package://...) are noise here
    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    argv = list(sys.argv[1:] if argv is None else argv)
    command, sub = _subcommand(parser, argv)
    path = _config_path(argv)
    if sub is not None and path is not None:
        try:
            cfg = load_config(path, sub, command)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        positional = [a.dest for a in sub._actions if not a.option_strings and a.dest in cfg]
        for a in sub._actions:  # what the config gives is no longer required on the command line
            if a.dest in positional:
                a.nargs = "?"
            elif a.dest in cfg:
                a.required = False
        sub.set_defaults(**cfg)
    return parser.parse_args(argv)


# --------------------------------------------------------------------------- --html / --plots
def sensor_corrections(res, model_out: str | None = None) -> dict | None:
    """What a URDF or MJCF cannot carry (`closedloop.output.report.sensor_corrections`)."""
    from closedloop.output.report import sensor_corrections as corrections

    return corrections(res, model_out)


def write_figures(res, report: dict, args, row_name=None, accuracy=None) -> None:
    """The HTML page and the PNG figures (the sensor file beside the model, `closedloop.output.report.write_sensors`,
    is published with the model and the report)."""
    quiet = bool(getattr(args, "quiet", False))
    html = getattr(args, "html", None)
    plots = getattr(args, "plots", None)
    if not html and not plots:
        return
    from closedloop.output.html import write_html, write_plots

    snr = float(getattr(args, "snr", 1.0) or 1.0)
    if html:
        write_html(res, report, html, snr, row_name=row_name, accuracy=accuracy)
        if not quiet:
            print(f"  wrote {html}")
    if plots:
        files = write_plots(res, report, plots, snr, accuracy)
        if not quiet:
            print(f"  wrote {len(files)} figures to {plots}")


# --------------------------------------------------------------------------- simulate any robot
def scenario_help() -> str:
    """Every named scenario (`closedloop.sims.scenarios.scenario_catalog`: the shipped files and the
    head-camera scenarios, read without loading the simulator)."""
    from closedloop.sims.scenarios import scenario_catalog

    lines = ["scenarios (closedloop/sims/scenarios/*.yaml and the head cameras; or your own YAML file, or --robot):"]
    for name, (loop, description) in scenario_catalog().items():
        lines.append(f"  {name:<17} {loop}")
        lines.append(f"  {'':<17} {description}")
    lines.append("simulate your robot: closedloop simulate --robot arm.urdf --loop weld:frame=tool0 --out out/sim")
    return "\n".join(lines)


def _numbers(text: str, what: str, n: int | None = None, limit: float = 1e3) -> list[float]:
    """Decimal numbers separated by spaces or commas, finite, |v| <= `limit` (exactly `n` of them if given)."""
    from closedloop.io.schemas import parse_number

    values = [parse_number(v, f"{what} {text}") for v in text.replace(",", " ").split()]
    if n is not None and len(values) != n:
        raise InputError(f"{what} {text}: expected {n} numbers separated by spaces or commas")
    if any(abs(v) > limit for v in values):
        raise InputError(f"{what} {text}: out of range (each value within +-{limit:g})")
    return values


#: longest stylus `simulate --tool` adds (m): beyond it no arm closes a loop on it
MAX_TOOL = 2.0


def resolve_scenario(args) -> str:
    """The scenario name ``simulate`` runs: a built-in, a YAML file, or ``--robot`` + ``--loop``."""
    from closedloop.sims.scenario_files import SCENARIOS, load_scenario, parse_sim_loop, scenario_from_dict

    if getattr(args, "robot", None):
        if args.scenario:
            raise InputError(f"simulate: give a scenario ({args.scenario}) or --robot, not both")
        if not args.loop:
            raise InputError(
                "simulate --robot: say how the loop closes, e.g. --loop weld:frame=tool0 "
                "(closedloop inspect ROBOT lists the frames)"
            )
        loop_type = parse_sim_loop(args.loop)[0]
        data: dict = {
            "robot": str(Path(args.robot).resolve()),
            "loop": args.loop,
            "name": args.name or f"{Path(args.robot).stem}_{loop_type}",
            "description": f"{Path(args.robot).name} with a {args.loop} loop",
        }
        if args.q0:
            data["q0"] = _numbers(args.q0, "--q0")
        if args.tool:
            xyz = _numbers(args.tool, "--tool", 3, limit=float("inf"))
            if sum(v * v for v in xyz) ** 0.5 > MAX_TOOL:
                raise InputError(f"--tool {args.tool}: a stylus longer than {MAX_TOOL:g} m (metres expected)")
            data["tool"] = {"xyz": xyz}
        if args.joints:
            data["joints"] = [j.strip() for j in args.joints.split(",") if j.strip()]
        sc = scenario_from_dict(data, data["name"], "--robot")
        SCENARIOS[sc.name] = sc
        return sc.name
    if not args.scenario:
        raise InputError("simulate: give a scenario (see closedloop simulate --help) or --robot ROBOT --loop SPEC")
    if args.scenario.endswith((".yaml", ".yml")):
        return load_scenario(args.scenario).name
    return args.scenario


def add_simulate_robot_options(s) -> None:
    s.add_argument("--robot", help="simulate your robot: a URDF or MJCF (.xml) file (with --loop)")
    s.add_argument(
        "--loop",
        help="with --robot: the loop, as for calibrate: TYPE:frame=LINK[,to=LINK][,name=NAME], TYPE a "
        "simulated type of 'closedloop loops' (weld, point, hinge, plane, measured_point)",
    )
    s.add_argument("--q0", help="with --robot: grasp configuration (radians; default: chosen automatically)")
    s.add_argument(
        "--tool",
        metavar='"X Y Z"',
        help="with --robot: add a stylus link at this offset in the loop frame (the loop then closes on it)",
    )
    s.add_argument("--joints", help="with --robot: driven joints (default: every joint moving the loop frame)")
    s.add_argument("--name", help="with --robot: scenario name (default ROBOT_LOOPTYPE)")
    s.add_argument("--config", help="YAML file holding these options")
