"""Fuzz every loader and option parser with >= 10,000 examples each.

    python benchmarks/fuzz_loaders.py [--examples 10000] [--only dh,log,...]

Runs the properties of tests/fuzz_properties.py (tests/test_fuzz_loaders.py runs 200 derandomized examples of
each): a loader either returns a valid result or raises closedloop's own InputError; any other
exception is a crash, and hypothesis stops on it and prints the smallest input that shows it.
Prints per loader: examples, loaded / refused counts, crashes (0 or the failing example), seconds.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "tests")]

from fuzz_properties import PROPERTIES, run_property  # noqa: E402
from machine import header  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=10_000)
    ap.add_argument("--only", default=",".join(sorted(PROPERTIES)))
    args = ap.parse_args()
    print(header())
    print(f"{'loader':<10}{'examples':>10}{'loaded':>9}{'refused':>9}{'crashes':>9}{'seconds':>9}")
    total_crashes = 0
    for name in args.only.split(","):
        t0 = time.perf_counter()
        try:
            counts = run_property(name, args.examples)
            crashes = 0
        except Exception as exc:  # hypothesis re-raises the (shrunk) crash
            counts, crashes = {}, 1
            print(f"{name}: CRASH {type(exc).__name__}: {exc}")
        total_crashes += crashes
        n = sum(counts.values())
        print(
            f"{name:<10}{n:>10}{counts.get('loaded', 0):>9}{counts.get('refused', 0):>9}{crashes:>9}"
            f"{time.perf_counter() - t0:>9.1f}",
            flush=True,
        )
    sys.exit(1 if total_crashes else 0)


if __name__ == "__main__":
    main()
