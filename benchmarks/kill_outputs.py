"""40 SIGKILLs at random moments of `closedloop calibrate` and `closedloop simulate`.

    python benchmarks/kill_outputs.py [--kills 40] [--seed 0]

Half the kills hit `calibrate --out --report` over an existing output set, half `simulate --replace`
over an existing dataset; after each, every output file is classified as the old set's or the new
set's (tests/test_kill.py: by content, a torn file matches neither), and the directory is listed for
temporaries.  Prints how many kills left the old set, the new set, a mix, or a temporary file.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "tests")]

from machine import header  # noqa: E402
from test_kill import kill_calibrate, kill_simulate, whole  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=40, help="SIGKILLs in all (half calibrate, half simulate)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(header())
    rng = np.random.default_rng(args.seed)
    bad = 0
    for name, fn in (("calibrate", kill_calibrate), ("simulate", kill_simulate)):
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as d:
            states = fn(Path(d), args.kills // 2, rng)
        killed = [s for s in states if s["returncode"] == -signal.SIGKILL]
        tags = [next(v for k, v in s.items() if k not in ("returncode", "stray", "old", "new")) for s in states]
        n_old = sum(whole(s) and t == s["old"] for s, t in zip(states, tags))
        n_new = sum(whole(s) and t == s["new"] for s, t in zip(states, tags))
        mixed = sum(not whole(s) and not s["stray"] for s in states)
        stray = sum(bool(s["stray"]) for s in states)
        bad += mixed + stray
        print(
            f"{name}: {len(states)} runs, {len(killed)} killed by SIGKILL: old set {n_old}, new set {n_new}, "
            f"mixed {mixed}, temporary left {stray}  ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        for s in states:
            if not whole(s):
                print("   ", s)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
