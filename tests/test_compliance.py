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
    for name, value, status, p in zip(res.fit.names, res.fit.values, res.fit.status, res.problem.params):
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


def test_gravity_torques_are_mujocos_bias_forces(datasets, tmp_path):
    """The model's gravity torques (Pinocchio's RNEA on the URDF's inertials) are MuJoCo's bias forces at
    rest on the same file, an independent implementation."""
    import mujoco

    robot, log, _ = datasets[True]
    joints = [f"panda_joint{i}" for i in range(1, 8)]
    g = robot.gravity_torques(log.angles[:20], log.joints)
    m = mujoco.MjModel.from_xml_path(str(robot.source))
    d = mujoco.MjData(m)
    for i in range(20):
        d.qpos[:] = 0.0
        for k, j in enumerate(log.joints):
            d.qpos[m.joint(j).qposadr[0]] = log.angles[i, k]
        mujoco.mj_forward(m, d)
        bias = np.array([d.qfrc_bias[m.joint(j).dofadr[0]] for j in joints])
        assert np.abs(g[i, [log.joints.index(j) for j in joints]] - bias).max() < 1e-9
    # and they are what the simulator logged at its settled poses, to 2 % of the largest
    tau = log.torques(joints)[:20]
    assert np.abs(tau - g[:, [log.joints.index(j) for j in joints]]).max() < 0.02 * np.abs(tau).max()


@pytest.mark.slow
def test_compliance_from_gravity_when_the_log_has_no_torques(datasets, tmp_path):
    """A log without tau:<joint> columns: calibrate computes gravity torques from the URDF's inertials, says
    so, and recovers the loaded joints' compliance as with the logged torques."""
    from closedloop.cli.main import main
    from closedloop.io.logs import JointLog

    robot, log, _ = datasets[True]
    csv = tmp_path / "no_torques.csv"
    JointLog(log.joints, log.angles).write_csv(csv)
    assert "tau:" not in csv.read_text().split("\n")[0]
    rep = tmp_path / "rep.json"
    argv = ["calibrate", str(robot.source), str(csv), "--loop", "weld:frame=panda_hand_tcp,name=fixture"]
    argv += ["--identify", "placement,offset,compliance,loop", "--report", str(rep), "--cv", "0", "--quiet"]
    assert main(argv) == 0
    report = json.loads(rep.read_text())
    assert report["inputs"]["torques"] == "gravity"
    assert any("gravity from the model's inertials" in n for n in report["identifiability"]["notes"])
    for j in (2, 3, 4):
        assert abs(report["compliance"][f"panda_joint{j}.compliance"] / C - 1.0) < 0.3
