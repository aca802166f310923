"""`closedloop simulate`: a scenario (built-in, a YAML file or --robot + --loop) to a dataset in MuJoCo.

Every named scenario is in one list (`closedloop.sims.scenarios.scenario_catalog`), read by
``simulate --help`` and by the unknown-scenario error; the loop types are the registry's
(`closedloop.loops.spec.LOOP_TYPES`) that the simulator simulates.  After the run the
``calibrate`` and ``check`` commands for the dataset are printed (`closedloop.sims.outputs.next_commands`).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from closedloop.cli.calibrate import Progress
from closedloop.cli.parse import sim_overrides
from closedloop.errors import EXIT_FAILED, ClosedLoopError, EmptySimulationError, NotIdentifiableError, ScenarioError
from closedloop.io.schemas import check_number


def cmd_simulate(args) -> int:
    try:
        from closedloop.sims import SCENARIOS, simulate
    except ImportError as exc:  # pragma: no cover - packaging error
        raise ClosedLoopError(f"the simulator is not installed ({exc})") from None
    from closedloop.cli.tools import resolve_scenario
    from closedloop.sims.scenarios import CAMERA_SCENARIOS, unknown_scenario

    if getattr(args, "scenario", None) in CAMERA_SCENARIOS:  # the head-camera scenarios (sims/camera_scene.py)
        from closedloop.sims.camera_scene import simulate_cli as camera_simulate

        code = camera_simulate(args)
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
    prog = Progress(args.quiet)
    t0 = time.perf_counter()
    try:
        result = simulate(
            args.scenario,
            n=args.n,
            seed=args.seed,
            out_dir=Path(args.out),
            progress=lambda i, n: prog("simulating", i, n),
            **overrides,
        )
    except NotIdentifiableError as exc:  # the scenario's loop cannot close: its robot, loop, --q0 or --tool
        raise ScenarioError(f"simulate {args.scenario}: {exc} (check the loop frame, --q0 and --tool)") from None
    except EmptySimulationError as exc:  # nothing recorded, nothing written: exit 3, as a failed calibration
        prog.done()
        print(f"error: simulated nothing: {exc}", file=sys.stderr)
        return EXIT_FAILED
    prog.done()
    recorded = len(result.readings)
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
