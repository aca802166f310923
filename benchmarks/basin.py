"""Basin of convergence on the thesis's chapter 3 examples.

For each example of `tests/thesis_examples.py` (Example 1: 7-DOF arm welded to the ground;
Example 2: two 6-DOF arms grasping, 12 joints; the door of 3.4.2 with the hinge unknown; point
contact 3.4.1), N random thesis-sized starting guesses (lengths +-0.1, twists +-0.3 rad, offsets
+-0.6 rad; the fixed length kept) are calibrated with closedloop's defaults on exact data, and a
start counts as recovered when the calibrated mechanism is the true one to 1e-6 (gauge-free, see
`thesis_examples.mechanism_error`) and the verdict is not 'failed'.  Prints per start and a markdown
table: recovered (and how many of those carry a 'suspect' warning), right but 'failed' (false
alarms), refused (wrong, verdict not ok), confidently wrong (wrong, verdict ok).

    python benchmarks/basin.py                 # 100 starts per example
    python benchmarks/basin.py --starts 20 --examples example1,example2 --weighting none
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import thesis_examples as te  # noqa: E402
from machine import machine  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    from closedloop import CalibrationOptions

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", default=",".join(te.EXAMPLES))
    ap.add_argument("--starts", type=int, default=100)
    ap.add_argument("--first", type=int, default=0, help="first start number")
    ap.add_argument("--weighting", default=None, help="CalibrationOptions.weighting (default: the library's)")
    ap.add_argument("--max-iter", type=int, default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    print(f"# machine: {machine()}", flush=True)
    summary = {}
    for name in args.examples.split(","):
        ex = te.EXAMPLES[name]()
        outs, t0 = [], time.perf_counter()
        for seed in range(args.first, args.first + args.starts):
            opt = CalibrationOptions()
            if args.weighting:
                opt.weighting = args.weighting
            if args.max_iter:
                opt.max_iter = args.max_iter
            o = te.run_start(ex, seed, opt)
            print(o.line(), flush=True)
            outs.append(o)
        summary[name] = (outs, time.perf_counter() - t0)
    print(
        "\n| example | starts | recovered | of which flagged | right but failed | refused | confidently wrong "
        "| crash | median time |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (outs, dt) in summary.items():
        c = Counter(
            "recovered"
            if o.accepted
            else "right_failed"
            if o.recovered
            else "refused"
            if o.refused
            else "crash"
            if o.status == "crash"
            else "wrong"
            for o in outs
        )
        flagged = sum(o.accepted and o.status == "suspect" for o in outs)
        med = sorted(o.seconds for o in outs)[len(outs) // 2]
        print(
            f"| {name} | {len(outs)} | {c['recovered']} ({100 * c['recovered'] / len(outs):.0f} %) | {flagged} | "
            f"{c['right_failed']} | {c['refused']} | {c['wrong']} | {c['crash']} | {med:.2f} s |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
