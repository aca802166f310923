"""`closedloop simulate`: a scenario (built-in, a YAML file or --robot + --loop) to a dataset in MuJoCo."""

from __future__ import annotations

import time
from pathlib import Path

from closedloop.cli.calibrate import Progress
from closedloop.cli.parse import sim_overrides
from closedloop.errors import ClosedLoopError, InputError, NotIdentifiableError, ScenarioError
from closedloop.io.schemas import check_number


def cmd_simulate(args) -> int:
    try:
        from closedloop.sims import SCENARIOS, simulate
    except ImportError as exc:  # pragma: no cover - packaging error
        raise ClosedLoopError(f"the simulator is not installed ({exc})") from None
    from closedloop.cli.tools import resolve_scenario
    from closedloop.sims.camera_scene import SCENARIOS as CAMERA_SCENARIOS
    from closedloop.sims.camera_scene import simulate_cli as camera_simulate

    if getattr(args, "scenario", None) in CAMERA_SCENARIOS:  # the head-camera scenarios (sims/camera_scene.py)
        return camera_simulate(args)
    args.scenario = resolve_scenario(args)  # a built-in, a scenario YAML, or --robot + --loop
    if args.scenario not in SCENARIOS:
        raise InputError(f"unknown scenario '{args.scenario}' (known: {', '.join(sorted(SCENARIOS))})")
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
    prog.done()
    print(f"simulated {args.n} configurations of {args.scenario} in {time.perf_counter() - t0:.1f} s -> {args.out}")
    loop_hint(Path(args.out) / "truth.json")
    summary = getattr(result, "summary", None)
    if callable(summary):
        print(summary())
    return 0


def loop_hint(truth_path: Path) -> None:
    """Print the loop the dataset closes, as calibrate takes it (a --tool adds a link: its frame is new)."""
    import json

    try:
        lp = json.loads(truth_path.read_text()).get("loop")
    except (OSError, ValueError):
        return
    if isinstance(lp, dict) and lp.get("type") and lp.get("frame"):
        keys = [f"frame={lp['frame']}"] + [f"{k}={lp[k]}" for k in ("to", "name") if lp.get(k)]
        print(f"  the loop: --loop {lp['type']}:{','.join(keys)}")
