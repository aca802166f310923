"""Calibration accuracy on MuJoCo datasets as a function of loop stiffness, servo preload and gravity.

For each scenario and setting: simulate N configurations, calibrate with the
core (default options), and report the true closure violation (RMS), the
largest error of the identifiable robot parameters (lengths in m, angles and
offsets in rad) and whether `closedloop check` passes at its default
tolerance (1 mm, 5 mrad).  The README table comes from this script.

    python benchmarks/sim_accuracy.py [--n 200] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import read_log
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel
from closedloop.output.report import build_report
from closedloop.sims import SCENARIOS, simulate
from closedloop.validation.check import check_report

SETTINGS = {
    "default (stiff loop, compliant servo, relaxed)": {},
    "soft loop (MuJoCo default solref/solimp)": {"soft": True},
    "stiff servo, preloaded (kp=2000, no relax)": {"kp": 2000.0, "kv": 60.0, "relax": False},
    "stiff servo, preloaded, soft loop": {"kp": 2000.0, "kv": 60.0, "relax": False, "soft": True},
    "gravity off": {"gravity": False},
    "gravity on, no gravity compensation": {"gravcomp": False},
}
LOOPS = {
    "panda_weld": "weld:frame=panda_hand_tcp,name=fixture",
    "ur5_socket": "point:frame=stylus_tip,name=socket",
    "ur5_door": "hinge:frame=tool0,name=door",
    "utah_hand": "weld:frame=finger_tip,to=thumb_tip,name=grasp",
    "ur5_plane": "plane:frame=stylus_tip,name=plane",
    # open loop: the tracker noise (default 1e-5 m) is given, the joints are noise free (see OPTIONS)
    "ur5_tracker": "measured_point:frame=stylus_tip,name=tracker,sigma_t=1e-5",
}
# calibration options per scenario (default: CalibrationOptions()); with noise-free joints the default
# estimates the joint noise from the residual and reads the tracker noise as joint noise
OPTIONS = {"ur5_tracker": {"noise": 1e-9}}


def run(scenario: str, overrides: dict, n: int, seed: int) -> dict:
    with tempfile.TemporaryDirectory() as d:
        res_sim = simulate(scenario, n, seed, Path(d), **overrides)
        truth = json.loads((Path(d) / "truth.json").read_text())
        robot = RobotModel.from_file(Path(d) / "nominal.urdf")
        log = read_log(Path(d) / "log.csv", robot.joint_names)
        res = calibrate(
            robot, log, [parse_loop(LOOPS[scenario], robot)], CalibrationOptions(**OPTIONS.get(scenario, {}))
        )
        report = build_report(res)
        _, ok = check_report(truth, report, tol_m=1e-3, tol_rad=5e-3, tol_scale=5e-3)
        err_m = err_rad = 0.0
        for p in report["parameters"]:
            if p["status"] != "estimated" or p["kind"] not in ("placement", "offset"):
                continue
            e = abs(p["calibrated"] - truth["parameters"].get(p["name"], 0.0))
            if p["unit"] == "m":
                err_m = max(err_m, e)
            else:
                err_rad = max(err_rad, e)
        v = truth["violation"]
        return {
            "viol_m": v["rms_m"],
            "viol_rad": v["rms_rad"],
            "err_m": err_m,
            "err_rad": err_rad,
            "check": ok,
            "cps": res_sim.configs_per_second,
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenario", nargs="*", default=list(LOOPS))
    args = ap.parse_args()
    print("| scenario | setting | violation RMS | max param error | check (1 mm, 5 mrad) |")
    print("|---|---|---|---|---|")
    for sc in args.scenario:
        for label, ov in SETTINGS.items():
            r = run(sc, ov, args.n, args.seed)
            # point-like loops (socket, plane puck) and the tracker (measurement error) have no rotation
            rot = (
                f", {r['viol_rad'] * 1e3:.3g} mrad"
                if SCENARIOS[sc].loop_type not in ("point", "plane", "measured_point")
                else ""
            )
            print(
                f"| {sc} | {label} | {r['viol_m'] * 1e6:.3g} um{rot} | {r['err_m'] * 1e3:.3g} mm, "
                f"{r['err_rad'] * 1e3:.3g} mrad | {'pass' if r['check'] else 'FAIL'} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
