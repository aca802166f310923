"""The wrong loop type: a weld given for ball-joint data, with and without the pre-fit check.

Simulates the user's case (an arm in a ball socket, `closedloop simulate --robot ... --loop point:...`),
then calibrates it as a weld: once as shipped (the pre-fit check, `Loop.mismatch`, exits at once) and once
with the check switched off (the fit runs to its `failed` verdict; its restarts stop early,
`solve._hopeless`).  Prints wall and CPU seconds and the verdict's first reasons.

    python benchmarks/wrong_loop.py --robot path/to/panda.urdf --frame panda_hand
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine import machine  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from closedloop import ClosedLoopError, RobotModel, calibrate, read_log
    from closedloop.cli.main import main as cli
    from closedloop.loops.spec import parse_loop
    from closedloop.loops.weld import WeldLoop

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", required=True, help="a URDF (e.g. example-robot-data's panda.urdf)")
    ap.add_argument("--frame", required=True, help="the tool frame held in the socket")
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"# machine: {machine()}", flush=True)
    out = Path(tempfile.mkdtemp(prefix="wrong_loop_")) / "sock"
    loop = f"point:frame={args.frame},name=socket"
    cli(
        ["simulate", "--robot", args.robot, "--loop", loop, "--n", str(args.n), "--seed", str(args.seed)]
        + ["--out", str(out), "--quiet"]
    )
    robot = RobotModel.from_file(out / "nominal.urdf")
    log = read_log(out / "log.csv", robot.joint_names)
    spec = f"weld:frame={args.frame},name=fixture"
    for check in (True, False):
        if not check:
            WeldLoop.mismatch = lambda self, Ts, meas=None: None
        t, c = time.perf_counter(), time.process_time()
        try:
            res = calibrate(robot, log, [parse_loop(spec, robot)])
            what = f"verdict {res.verdict.status}: {'; '.join(res.verdict.reasons[:3])}"
        except ClosedLoopError as exc:
            what = f"{type(exc).__name__}: {exc}"
        print(
            f"pre-fit check {'on ' if check else 'off'}: {time.perf_counter() - t:6.1f} s wall "
            f"{time.process_time() - c:6.1f} s CPU  {what[:400]}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
