"""The outlier screen's false rejections on clean data, and what it still catches on corrupted data.

Each case is calibrated with the defaults of `closedloop.calibrate` (``robust='auto'``: the screen,
the robust refit, the rejection and the re-check at the solution) and the rejected rows are compared
with the rows the generator corrupted.  Groups:

* ``tracker``: the MuJoCo ``ur5_tracker`` scenario (`closedloop.sims`), 120 configurations, the tracker
  noise stated (``sigma_t=1e-5``), the joint noise left to the calibration (the simulator's servo
  error: a few microradians);
* ``zoo-clean``: `tests/zoo.py` robots x loops with joint noise (1e-4 rad, 1e-5 rad) and, for the
  ``measured_point`` loop, a tracker with its own noise (``sigma_t=1e-5``, stated);
* ``zoo-rows5`` / ``zoo-rows20``: the same with 5 % / 20 % of the rows replaced by random readings;
* ``weld-corrupt5`` / ``weld-corrupt20``: the Panda weld of `benchmarks/bench_calibrate.py`
  (1e-4 rad joint noise, 300 configurations) with 5 % / 20 % of the rows carrying one reading off by
  0.05-0.2 rad.

Per group: the clean rows rejected (the false-rejection rate, against the Bonferroni screen's own
expectation: ``alpha`` = 0.01 per calibration, i.e. 0.01 / N per row), the corrupted rows rejected,
the verdicts and (zoo) how many calibrated robots are right.  ``--json`` writes every case, so that
two versions of the code can be compared case by case (``--compare``).

    python benchmarks/outlier_screen.py                       # everything (~40 min on 2 cores at load 6)
    python benchmarks/outlier_screen.py --groups tracker --seeds 10
    python benchmarks/outlier_screen.py --json out/after.json --compare out/before.json
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))  # zoo_judge, after sys.modules['zoo']
from machine import load, machine, tests_zoo  # noqa: E402

zoo = tests_zoo()

ZOO_CASES = [  # robot, loop, configurations
    ("ur5", "point", 60),
    ("ur5", "plane", 100),
    ("ur5", "measured_point", 60),
    ("ur5", "hinge", 40),
    ("panda", "weld", 60),
    ("panda", "point", 60),
    ("panda", "measured_point", 60),
    ("xarm7", "measured_point", 60),
    ("kinova", "point", 60),
]
GROUPS = ["tracker", "zoo-clean", "zoo-rows5", "zoo-rows20", "weld-corrupt5", "weld-corrupt20"]


def _record(group: str, label: str, n: int, bad: np.ndarray, res, right: bool | None, error: str = "") -> dict:
    """One case's outcome: rows rejected (0-based), corrupted rows, verdict."""
    rej = sorted(int(r.row) - 1 for r in res.outliers.rejected) if res is not None else []
    bad_set = {int(b) for b in bad}
    return {
        "group": group,
        "case": label,
        "rows": n,
        "corrupted": len(bad_set),
        "rejected": len(rej),
        "clean_rejected": sum(1 for r in rej if r not in bad_set),
        "corrupted_rejected": sum(1 for r in rej if r in bad_set),
        "verdict": str(res.verdict.status) if res is not None else ("error: " + error),
        "right": right,
    }


def tracker_cases(seeds: int) -> list[dict]:
    """The MuJoCo ur5_tracker scenario, 120 configurations per seed (seeds 1 ..)."""
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.io.logs import read_log
    from closedloop.loops.spec import parse_loop
    from closedloop.model.robot import RobotModel
    from closedloop.sims import simulate

    out = []
    for seed in range(1, seeds + 1):
        with tempfile.TemporaryDirectory() as d:
            simulate("ur5_tracker", 120, seed, Path(d))
            robot = RobotModel.from_file(Path(d) / "nominal.urdf")
            log = read_log(Path(d) / "log.csv", robot.joint_names)
            loop = parse_loop("measured_point:frame=stylus_tip,name=tracker,sigma_t=1e-5", robot)
            res = calibrate(robot, log, [loop], CalibrationOptions())
        out.append(_record("tracker", f"ur5_tracker/s{seed}", 120, np.zeros(0, int), res, None))
        print(_line(out[-1]), flush=True)
    return out


def zoo_cases(group: str, seeds: int) -> list[dict]:
    """`ZOO_CASES` with joint noise (1e-4 rad on even seeds, 1e-5 on odd ones), clean or with rows replaced."""
    corrupt = {"zoo-clean": 0.0, "zoo-rows5": 0.05, "zoo-rows20": 0.20}[group]
    out = []
    for robot, loop, n in ZOO_CASES:
        for seed in range(seeds):
            sigma = 1e-4 if seed % 2 == 0 else 1e-5
            kw = {"sigma_t": 1e-5} if loop == "measured_point" else {}
            try:
                case = zoo.make_case(robot, loop, n=n, sigma=sigma, seed=seed, corrupt_rows=corrupt, **kw)
            except RuntimeError as exc:
                print(f"{robot}/{loop}/s{seed}: no data ({exc})", flush=True)
                continue
            o = zoo.run_case(case)
            label = f"{robot}/{loop}/s{seed}/sigma={sigma:g}"
            out.append(_record(group, label, n, case.corrupted, o.result, bool(o.right), o.error or ""))
            print(_line(out[-1]), flush=True)
    return out


def weld_cases(group: str, seeds: int) -> list[dict]:
    """The Panda weld of bench_calibrate.py (300 of its exact configurations, 1e-4 rad noise), rows corrupted."""
    from bench_calibrate import _log  # benchmarks/bench_calibrate.py

    from closedloop.assets.catalog import ROBOTS
    from closedloop.calibration.pipeline import calibrate
    from closedloop.loops import WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    corrupt = {"weld-corrupt5": 0.05, "weld-corrupt20": 0.20}[group]
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    out = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        theta0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]
        ds = make_dataset(robot, WeldLoop("fixture", "panda_hand"), theta0, 300, rng, stride=1)
        log, bad = _log(ds, 300, rng, corrupt)
        res = calibrate(robot, log, [WeldLoop("fixture", "panda_hand")])
        out.append(_record(group, f"panda_weld/s{seed}", 300, bad, res, None))
        print(_line(out[-1]), flush=True)
    return out


def _line(r: dict) -> str:
    return (
        f"{r['group']:>14} {r['case']:<40} rows {r['rows']:>4}  rejected {r['rejected']:>3} "
        f"(clean {r['clean_rejected']:>3}, corrupted {r['corrupted_rejected']:>3} of {r['corrupted']:>3})  "
        f"{r['verdict']}" + ("" if r["right"] is None else ("  right" if r["right"] else "  WRONG"))
    )


def table(rows: list[dict]) -> str:
    """Per group: cases, clean rows rejected (rate), corrupted rows rejected, verdicts, right."""
    out = [
        "| group | cases | clean rows rejected | cases with a clean row rejected | corrupted rows rejected "
        "| verdicts | right |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in dict.fromkeys(r["group"] for r in rows):
        rs = [r for r in rows if r["group"] == g]
        clean = sum(r["rows"] - r["corrupted"] for r in rs)
        fr = sum(r["clean_rejected"] for r in rs)
        bad = sum(r["corrupted"] for r in rs)
        caught = sum(r["corrupted_rejected"] for r in rs)
        verdicts = ", ".join(f"{k} {v}" for k, v in sorted(Counter(r["verdict"] for r in rs).items()))
        judged = [r["right"] for r in rs if r["right"] is not None]
        out.append(
            f"| {g} | {len(rs)} | {fr} of {clean} ({100.0 * fr / max(clean, 1):.2f} %) "
            f"| {sum(1 for r in rs if r['clean_rejected'])} | "
            + (f"{caught} of {bad}" if bad else "-")
            + f" | {verdicts} | "
            + (f"{sum(judged)} of {len(judged)}" if judged else "-")
            + " |"
        )
    return "\n".join(out)


def compare(rows: list[dict], before: list[dict]) -> str:
    """Cases whose verdict or rightness differs from an earlier run's (`--json` of another version)."""
    old = {(r["group"], r["case"]): r for r in before}
    lines = []
    for r in rows:
        o = old.get((r["group"], r["case"]))
        if o is None:
            continue
        if o["verdict"] != r["verdict"] or o["right"] != r["right"]:
            lines.append(
                f"{r['group']} {r['case']}: verdict {o['verdict']} -> {r['verdict']}, right {o['right']} -> {r['right']}"
            )
    return "\n".join(lines) if lines else "no verdict or rightness changed"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", default=",".join(GROUPS))
    ap.add_argument("--seeds", type=int, default=None, help="seeds per case (default: 20 tracker, 4 zoo, 4 weld)")
    ap.add_argument("--json", default=None, help="write every case's outcome here")
    ap.add_argument("--compare", default=None, help="an earlier --json: list the verdicts that changed")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    print(f"# machine: {machine()}; {load()}", flush=True)
    t0 = time.perf_counter()
    rows: list[dict] = []
    for g in args.groups.split(","):
        if g == "tracker":
            rows += tracker_cases(args.seeds or 20)
        elif g.startswith("zoo-"):
            rows += zoo_cases(g, args.seeds or 4)
        elif g.startswith("weld-"):
            rows += weld_cases(g, args.seeds or 4)
        else:
            raise SystemExit(f"unknown group {g!r} (one of {', '.join(GROUPS)})")
    print(f"\n{len(rows)} cases in {time.perf_counter() - t0:.0f} s; {load()}\n")
    print(table(rows))
    if args.compare:
        print("\n" + compare(rows, json.loads(Path(args.compare).read_text())))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
