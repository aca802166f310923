"""The passive task-chain loop on a MuJoCo dataset: the UR5 door scenario
calibrated with the door given as a one-joint task URDF, its geometry identified with the robot."""

from __future__ import annotations

import json

import pytest

from closedloop.assets.catalog import model_file
from closedloop.calibration.pipeline import calibrate
from closedloop.io.logs import read_log
from closedloop.loops import PassiveChainLoop
from closedloop.model.robot import RobotModel
from closedloop.output.report import build_report
from closedloop.sims import simulate
from closedloop.validation.check import check_report


@pytest.mark.slow
def test_ur5_door_through_the_passive_chain_loop(tmp_path):
    simulate("ur5_door", 150, 1, tmp_path)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    log = read_log(tmp_path / "log.csv", robot.joint_names)
    loop = PassiveChainLoop("door", "tool0", model_file("tasks/hinged_door.urdf"), "grip")
    res = calibrate(robot, log, [loop])
    assert res.converged
    assert res.fit.residuals_before[0].rms_m > 3e-4 and res.fit.residuals_after[0].rms_m < 1e-6
    truth = json.loads((tmp_path / "truth.json").read_text())
    rows, ok = check_report(truth, build_report(res), tol_m=1e-4, tol_rad=1e-3, tol_scale=1e-3)
    assert ok, [r for r in rows if r["result"] == "FAIL"]
    assert sum(r["result"] == "ok" for r in rows) >= 15
