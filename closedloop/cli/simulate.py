"""`closedloop simulate`: a scenario (built-in, a YAML file or --robot + --loop) to a dataset in MuJoCo.

Every named scenario is in one list (`closedloop.sims.scenarios.scenario_catalog`), read by
``simulate --help`` and by the unknown-scenario error; the loop types are the registry's
(`closedloop.loops.spec.LOOP_TYPES`) that the simulator simulates.  After the run the
``calibrate`` and ``check`` commands for the dataset are printed (`closedloop.sims.outputs.next_commands`).
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from pathlib import Path

from closedloop.cli.parse import sim_overrides
from closedloop.cli.progress import ProgressDisplay
from closedloop.errors import EXIT_FAILED, EmptySimulationError, InputError, NotIdentifiableError, ScenarioError
from closedloop.run.options import check_number

#: configurations recorded when --n is not given
DEFAULT_N = 200


def simulate_camera(args) -> int:
    """``closedloop simulate ur5_head --n N --seed S --out DIR`` (`sims.camera_scene`): one summary line."""
    from closedloop.sims.camera_scene import simulate_head

    if args.n is None:
        args.n = DEFAULT_N
    if getattr(args, "poses", None):
        raise InputError(f"--poses: the camera scenario {args.scenario} plans its own configurations")
    if not (isinstance(args.n, int) and args.n >= 1):
        raise InputError(f"--n {args.n}: expected a positive integer")
    if getattr(args, "set", None):
        raise InputError(f"--set: the camera scenario {args.scenario} has no settings to override")
    t0 = time.perf_counter()
    summary = simulate_head(args.scenario, args.n, int(args.seed), args.out)
    print(
        f"simulated {args.n} configurations of {args.scenario} in {time.perf_counter() - t0:.1f} s -> {args.out} "
        f"({summary['missing_views']} missing views)"
    )
    return 0


def cmd_simulate(args) -> int:
    from closedloop.sims import SCENARIOS, simulate
    from closedloop.sims.scenarios import CAMERA_SCENARIOS, unknown_scenario

    if getattr(args, "scenario", None) in CAMERA_SCENARIOS:  # the head-camera scenarios (sims/camera_scene.py)
        code = simulate_camera(args)
        if not getattr(args, "quiet", False):
            print_next_commands(Path(args.out))
        return code
    args.scenario = resolve_scenario(args)  # a built-in, a scenario YAML, or --robot + --loop
    if args.scenario not in SCENARIOS:
        raise unknown_scenario(args.scenario)
    from closedloop.io.files import check_outputs
    from closedloop.sims.outputs import check_dataset_dir

    poses = getattr(args, "poses", None)
    if poses and args.n is not None:
        raise InputError(f"--n {args.n} and --poses {poses}: the poses file sets the configurations (one per row)")
    if poses and not Path(poses).is_file():
        raise InputError(
            f"--poses {poses}: no such file (a CSV log of joint readings, e.g. calibrate's --suggest file)"
        )
    args.n = check_number("--n", DEFAULT_N if args.n is None else args.n, 1, 10**7, integer=True)
    args.seed = check_number("--seed", args.seed, 0, 2**63 - 1, integer=True)
    check_outputs({"--out": args.out}, directory=True)
    check_dataset_dir(Path(args.out), replace=getattr(args, "replace", False))
    overrides = sim_overrides(args.set, SCENARIOS[args.scenario].settings)
    prog = ProgressDisplay(args.quiet)
    t0 = time.perf_counter()
    try:
        result = simulate(
            args.scenario,
            n=args.n,
            seed=args.seed,
            out_dir=Path(args.out),
            progress=prog,
            poses=Path(poses) if poses else None,
            **overrides,
        )
    except NotIdentifiableError as exc:  # the scenario's loop cannot close: its robot, loop, --q0 or --tool
        raise ScenarioError(f"simulate {args.scenario}: {exc} (check the loop frame, --q0 and --tool)") from None
    except EmptySimulationError as exc:  # nothing recorded, nothing written: exit 3, as a failed calibration
        prog.close()
        print(f"error: simulated nothing: {exc}", file=sys.stderr)
        return EXIT_FAILED
    prog.close()
    recorded = len(result.readings)
    args.n = result.n_asked  # with --poses, the file's rows
    short = recorded < args.n  # some recorded: the files are written, the exit code says the dataset is short
    if short:
        print(
            f"error: simulated only {recorded} of {args.n} configurations of {args.scenario} "
            f"(files written to {args.out}): {result.shortfall}",
            file=sys.stderr,
        )
    if args.quiet:  # errors and warnings only
        return EXIT_FAILED if short else 0
    print(
        f"simulated {recorded}{f' of {args.n}' if short else ''} configurations of {args.scenario} "
        f"in {time.perf_counter() - t0:.1f} s -> {args.out}"
    )
    if poses:  # the rows extend a dataset of this seed: say how to join them to its log
        new_log = shlex.quote(str(Path(args.out) / "log.csv"))
        print(
            f"  append:    (cat LOG; tail -n +2 {new_log}) > more.csv   (LOG: the log of the seed-{args.seed} dataset "
            "these poses extend; calibrate more.csv)"
        )
    print_next_commands(Path(args.out))
    summary = getattr(result, "summary", None)
    if callable(summary):
        print(summary())
    return EXIT_FAILED if short else 0


def print_next_commands(out: Path) -> None:
    """Print the ``calibrate`` and ``check`` commands for the dataset in `out` (read from its truth.json)."""
    from closedloop.sims.outputs import next_commands

    try:
        truth = json.loads((out / "truth.json").read_text())
    except (OSError, ValueError):
        return
    commands = next_commands(out, truth) if isinstance(truth, dict) else []
    for what, line in zip(("calibrate", "check"), commands):
        print(f"  {what + ':':<10} {line}")


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
    s.add_argument(
        "--poses",
        metavar="FILE",
        help="record at these joint readings instead of planning (a CSV log with a column per driven joint, e.g. "
        "calibrate's --suggest file): with the --seed and --set of the dataset it extends, the same true robot "
        "and fixture, fresh noise",
    )
