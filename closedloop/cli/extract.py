"""``closedloop extract``: the quasi-static samples of a ROS bag written as the CSV log
(:mod:`closedloop.io.bags`); ``calibrate`` also takes a bag in place of the CSV."""

from __future__ import annotations

from closedloop.errors import InputError


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
    from closedloop.run.options import check_number

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
