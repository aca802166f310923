"""Joint compliance removes the gravity bias of a compliant, loaded loop.

MuJoCo Panda weld with joint compliance c = 2e-5 rad/Nm on every joint (the
encoders see the link angle plus c * tau).  Acceptance: with the compliance
model, the gravity-loaded dataset is calibrated to within 3x the accuracy of
the unloaded one, and better than a purely geometric fit of the same data.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import read_log
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.sims import simulate

C = 2e-5


def _errors(res, truth):
    """Max |error| of estimated placement lengths (m) and angles/offsets (rad)."""
    m, rad = 0.0, 0.0
    for name, value, status, p in zip(res.names, res.values, res.status, res.problem.params):
        if status != "estimated" or p.kind not in ("placement", "offset"):
            continue
        err = abs(value - truth.get(name, 0.0))
        if p.unit == "m":
            m = max(m, err)
        else:
            rad = max(rad, err)
    return m, rad


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    out = {}
    for gravity in (False, True):
        d = tmp_path_factory.mktemp(f"g{int(gravity)}")
        simulate("panda_weld", 200, 1, d, gravity=gravity, compliance=C)
        robot = RobotModel.from_file(d / "nominal.urdf")
        out[gravity] = (
            robot,
            read_log(d / "log.csv", robot.joint_names),
            json.loads((d / "truth.json").read_text())["parameters"],
        )
    return out


def test_gravity_loads_the_joints(datasets):
    _, log, _ = datasets[True]
    tau = log.torques([f"panda_joint{i}" for i in range(1, 8)])
    assert np.abs(tau[:, 1]).max() > 10.0  # shoulder carries the arm
    _, log0, _ = datasets[False]
    assert np.abs(log0.torques([f"panda_joint{i}" for i in range(1, 8)])).max() < 1.0


def test_compliance_model_removes_gravity_bias(datasets):
    loop = lambda: [WeldLoop("fixture", "panda_hand_tcp")]  # noqa: E731
    robot, log, truth = datasets[False]
    base_m, base_rad = _errors(calibrate(robot, log, loop()), truth)
    robot, log, truth = datasets[True]
    geo_m, geo_rad = _errors(calibrate(robot, log, loop()), truth)
    res = calibrate(robot, log, loop(), CalibrationOptions(identify=["placement", "offset", "compliance", "loop"]))
    comp_m, comp_rad = _errors(res, truth)
    assert res.converged
    assert comp_m <= 3.0 * base_m and comp_rad <= 3.0 * base_rad, (comp_m, base_m, comp_rad, base_rad)
    assert comp_m < geo_m and comp_rad < geo_rad
    # the heavily loaded joints' compliance itself is recovered
    for j in (2, 3, 4):
        assert abs(res.value(f"panda_joint{j}.compliance") / C - 1.0) < 0.3


def test_compliance_needs_torques(datasets):
    from closedloop.errors import LogError
    from closedloop.io.logs import JointLog

    robot, log, _ = datasets[True]
    with pytest.raises(LogError, match="tau:<joint>"):
        calibrate(
            robot,
            JointLog(log.joints, log.angles),
            [WeldLoop("fixture", "panda_hand_tcp")],
            CalibrationOptions(identify=["placement", "offset", "compliance", "loop"]),
        )
