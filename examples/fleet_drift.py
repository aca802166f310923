"""A small fleet re-calibrated on several dates: `closedloop batch` flags a drifting joint offset only
when the change exceeds its uncertainty.

Two simulated Pandas (the same true robot, as two arms from one production batch), each holding a
fixture, 60 configurations spread over the self-motion, 1e-4 rad joint noise, logged on five dates.
On arm1 the offset of joint 4 creeps by 10 and 20 urad (below the ~50 urad standard error of a
change between two calibrations), then jumps by 400 urad (a collision), then stays; arm2 does not
drift.  The batch calibrates the ten logs independently (2 local worker processes), validates each
(3-fold) and compares consecutive dates of each robot: z = change / sqrt(se1^2 + se2^2), flagged
when |z| > 3.

    python examples/fleet_drift.py [--out out/fleet] [--jobs 2] [--ray auto]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
import yaml

from closedloop.cli.main import main as closedloop
from closedloop.io.logs import JointLog
from closedloop.studies.montecarlo import panda_urdf, weld_scenario

NOISE = 1e-4
JOINT = "panda_joint4"
DRIFT = {"arm1": [0.0, 10e-6, 20e-6, 420e-6, 420e-6], "arm2": [0.0] * 5}  # offset change since the first date (rad)
DATES = ["2026-03-02", "2026-03-09", "2026-03-16", "2026-03-23", "2026-03-30"]


def write_logs(out: Path, seed: int = 7) -> Path:
    """Logs and the batch manifest; returns the manifest path."""
    sc = weld_scenario(n=1, seed=3, pool="manifold", n_pool=60)
    rng = np.random.default_rng(seed)
    k, scale = sc.joints.index(JOINT), sc.truth[f"{JOINT}.scale"]
    jobs = []
    for robot, drifts in DRIFT.items():
        for date, d in zip(DATES, drifts):
            th = sc.pool.copy()
            th[:, k] -= d / scale  # the offset grew by d: the same pose reads d / scale less
            th += rng.normal(0.0, NOISE, th.shape)
            name = f"{robot}-{date}"
            JointLog(list(sc.joints), th).write_csv(out / "logs" / f"{name}.csv")
            job = {"name": name, "robot": robot, "date": date, "log": f"logs/{name}.csv", "out": f"calibrated/{name}"}
            if robot == "arm2" and date >= DATES[3]:  # another gauge: calibrate chooses the length held
                job["options"] = {"noise": NOISE}
            jobs.append(job)
    manifest = out / "fleet.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "defaults": {
                    "model": panda_urdf(),
                    "loops": ["weld:frame=panda_hand,name=fixture"],
                    "cv": 3,
                    "options": {"noise": NOISE, "fix": ["panda_joint4.x"]},
                },  # one length sets the scale
                "jobs": jobs,
            },
            sort_keys=False,
        )
    )
    return manifest


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/fleet")
    ap.add_argument("--jobs", default="2")
    ap.add_argument("--ray", help="run on a Ray cluster ('auto', or an address)")
    args = ap.parse_args()
    out = Path(args.out)
    manifest = write_logs(out)
    argv = ["batch", str(manifest), "--jobs", args.jobs, "--quiet"] + (["--ray", args.ray] if args.ray else [])
    code = closedloop(argv)
    with open(out / "fleet.summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    print(f"\n{'job':<22}{'status':>7}{'verdict':>9}{'after mm':>10}{'cv mm':>9}{'max |z|':>9}  drift flagged")
    for r in rows:
        print(
            f"{r['name']:<22}{r['status']:>7}{r['verdict']:>9}{float(r['rms_after_mm']):>10.3g}"
            f"{float(r['cv_test_mm']):>9.3g}"
            + (f"{float(r['drift_max_z']):>9.2f}" if r["drift_max_z"] else " " * 9)
            + f"  {r['drift_flagged']}"
        )
    with open(out / "fleet.summary.drift.csv") as fh:
        offs = [d for d in csv.DictReader(fh) if d["parameter"] == f"{JOINT}.offset"]
    print(
        f"\n{JOINT}.offset between consecutive dates (true change: arm1 +10, +10, +400, 0 urad; arm2 none, "
        "another gauge from the fourth date):"
    )
    for d in offs:
        print(
            f"  {d['after']:<22} change {float(d['change']) * 1e6:+7.1f} urad, se {float(d['se']) * 1e6:5.1f} urad,"
            f" z {float(d['z']):+6.1f}  {'FLAGGED' if d['flagged'] == 'True' else ''}"
        )
    return code


if __name__ == "__main__":
    sys.exit(main())
