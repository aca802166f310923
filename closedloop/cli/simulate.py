"""`closedloop simulate`: a scenario (built-in, a YAML file or --robot + --loop) to a dataset in MuJoCo.

Every named scenario is in one list (`closedloop.sims.scenarios.scenario_catalog`), read by
``simulate --help`` and by the unknown-scenario error; the loop types are the registry's
(`closedloop.loops.spec.LOOP_TYPES`) that the simulator simulates.  After the run the
``calibrate`` and ``check`` commands for the dataset are printed (`closedloop.sims.outputs.next_commands`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from closedloop.cli.parse import sim_overrides
from closedloop.cli.progress import ProgressDisplay
from closedloop.errors import InputError, NotIdentifiableError, ScenarioError
from closedloop.io.schemas import check_number


def simulate_camera(args) -> int:
    """``closedloop simulate ur5_head --n N --seed S --out DIR`` (`sims.camera_scene`): one summary line."""
    from closedloop.sims.camera_scene import simulate_head

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
    from closedloop.cli.tools import resolve_scenario
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

    args.n = check_number("--n", args.n, 1, 10**7, integer=True)
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
            **overrides,
        )
    except NotIdentifiableError as exc:  # the scenario's loop cannot close: its robot, loop, --q0 or --tool
        raise ScenarioError(f"simulate {args.scenario}: {exc} (check the loop frame, --q0 and --tool)") from None
    finally:
        prog.close()
    if args.quiet:  # errors and warnings only
        return 0
    print(f"simulated {args.n} configurations of {args.scenario} in {time.perf_counter() - t0:.1f} s -> {args.out}")
    print_next_commands(Path(args.out))
    summary = getattr(result, "summary", None)
    if callable(summary):
        print(summary())
    return 0


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
