"""Calibrating each MuJoCo scenario's dataset recovers the truth (issue 3, default settings).

Tolerances: the `closedloop check` defaults (1 mm, 5 mrad) must pass, and the
measured accuracy of the defaults is asserted with a margin (README table:
Panda weld ~0.1 mm / ~1 mrad, limited by its one-dimensional self-motion;
UR5 socket and door below 0.01 mm / 0.05 mrad).
"""

from __future__ import annotations

import json

import pytest

from closedloop.calibration import calibrate
from closedloop.check import check_report
from closedloop.data import read_log
from closedloop.loops.spec import parse_loop
from closedloop.report import build_report
from closedloop.robot import RobotModel
from closedloop.sims import SCENARIOS, simulate

CASES = {  # scenario: (loop spec, max length error [m], max angle error [rad])
    "panda_weld": ("weld:frame=panda_hand_tcp,name=fixture", 3e-4, 3e-3),
    "ur5_socket": ("point:frame=stylus_tip,name=socket", 1e-5, 5e-5),
    "ur5_door": ("hinge:frame=tool0,name=door", 1e-5, 5e-5),
    "utah_hand": ("weld:frame=finger_tip,to=thumb_tip,name=grasp", 1e-3, 5e-3),
}


@pytest.mark.parametrize("scenario", [s for s in CASES if s in SCENARIOS])
def test_default_scenario_calibrates_to_truth(scenario, tmp_path):
    spec, tol_m, tol_rad = CASES[scenario]
    simulate(scenario, 150, 1, tmp_path)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    log = read_log(tmp_path / "log.csv", robot.joint_names)
    res = calibrate(robot, log, [parse_loop(spec, robot)])
    assert res.converged
    truth = json.loads((tmp_path / "truth.json").read_text())
    report = build_report(res)
    rows, ok = check_report(truth, report, tol_m=1e-3, tol_rad=5e-3, tol_scale=5e-3)
    assert ok, [r for r in rows if r["result"] == "FAIL"]
    compared = [r for r in rows if r["result"] == "ok"]
    assert len(compared) >= 15
    for p in report["parameters"]:
        if p["status"] == "estimated" and p["kind"] in ("placement", "offset"):
            err = abs(p["calibrated"] - truth["parameters"].get(p["name"], 0.0))
            assert err < (tol_m if p["unit"] == "m" else tol_rad), (p["name"], err)
