"""The calibrated MJCF (`closedloop.output.mjcf`): reloads in MuJoCo and reproduces the fit.

The Panda as an MJCF (MuJoCo's own conversion of the nominal URDF) is calibrated on exact weld data;
the written MJCF must (1) load in MuJoCo, (2) put the tool where the calibrated Pinocchio model puts it
(MuJoCo forward kinematics at the raw readings: offsets folded, joint anchors honoured), (3) close the
loop, reloaded as a model, to the fit's own residual, and (4) to the same residual as the calibrated
URDF of the same robot calibrated from its URDF.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from closedloop.assets.catalog import nominal_urdf
from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate, residual_stats
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.output.mjcf import write_mjcf
from closedloop.output.urdf import write_urdf
from closedloop.studies.truth import make_dataset

Q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]


def panda_mjcf(path, anchor=None) -> RobotModel:
    spec = mujoco.MjSpec.from_string(
        nominal_urdf("panda").replace(
            "</robot>", '<mujoco><compiler fusestatic="false" discardvisual="true"/></mujoco></robot>'
        )
    )
    if anchor is not None:
        spec.joint("panda_joint4").pos = anchor  # an anchor off the body origin (MJCF allows it, URDF does not)
    path.write_text(spec.to_xml())
    return RobotModel.from_file(path)


def closure_rms(robot: RobotModel, log: JointLog, loop: WeldLoop, values: dict) -> tuple[float, float]:
    """Closure of `robot` as it is (nominal parameters), with the loop's fitted closure."""
    prob = build_problem(robot, log, [loop])
    x = prob.nominal
    for k, n in enumerate(prob.names):
        if n.startswith(loop.name + "."):
            x[k] = values[n]
    s = residual_stats(prob, prob.evaluate(x, False))[0]
    return s.rms_m, s.rms_rad


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("mjcf")
    robot = panda_mjcf(d / "panda.xml", anchor=[0.0, 0.0, 0.04])
    loop = WeldLoop("fixture", "panda_hand")
    ds = make_dataset(robot, loop, Q0, 40, np.random.default_rng(4))
    log = ds.log(noisy=False)
    res = calibrate(robot, log, [loop], CalibrationOptions(identify=["placement", "offset", "loop"], noise=1e-6))
    assert res.converged
    return d, robot, loop, log, res, ds


def test_calibrated_mjcf_reloads_and_moves_like_the_fit(fitted):
    d, robot, loop, log, res, ds = fitted
    out = d / "calibrated.xml"
    write_mjcf(robot, res.as_dict(), out)
    m = mujoco.MjModel.from_xml_path(str(out))  # (1) MuJoCo loads it
    data = mujoco.MjData(m)
    prob = res.problem
    TA, _ = prob.loop_frame_poses(res.fit.values, 0) if hasattr(prob, "loop_frame_poses") else (None, None)
    # (2) MuJoCo FK of the calibrated MJCF at the raw readings = the calibrated Pinocchio model's tool pose
    cal = prob.rp.apply(res.fit.values).model
    cd = cal.createData()
    fid = cal.getFrameId("panda_hand")
    k, off = res.fit.values[prob.rp.scale_index()], res.fit.values[prob.rp.offset_index()]
    bid = m.body("panda_hand").id
    qadr = [m.jnt_qposadr[m.joint(j).id] for j in prob.joints]
    worst = 0.0
    for theta in log.angles[:10]:
        data.qpos[qadr] = theta
        mujoco.mj_kinematics(m, data)
        pin.framesForwardKinematics(cal, cd, robot.configurations(theta * k + off, prob.joints)[0])
        T = cd.oMf[fid]
        worst = max(
            worst, np.abs(T.translation - data.xpos[bid]).max(), np.abs(T.rotation - data.xmat[bid].reshape(3, 3)).max()
        )
    assert worst < 1e-9
    # joint ranges shifted by -offset
    m0 = mujoco.MjModel.from_xml_path(str(robot.source))
    j = "panda_joint4"
    np.testing.assert_allclose(
        m.jnt_range[m.joint(j).id], m0.jnt_range[m0.joint(j).id] - res.value(f"{j}.offset"), atol=1e-12
    )
    # (3) reloaded as a model, it closes the loop as the fit did
    rms = closure_rms(RobotModel.from_file(out), log, WeldLoop("fixture", "panda_hand"), res.as_dict())
    after = res.fit.residuals_after[0]
    assert rms[0] < 1e-8 and rms[1] < 1e-8
    assert abs(rms[0] - after.rms_m) < 1e-9 and abs(rms[1] - after.rms_rad) < 1e-9
    before = res.fit.residuals_before[0]
    assert before.rms_m > 1e-4  # the nominal model did not close it


def test_mjcf_and_urdf_calibrations_close_alike(tmp_path):
    """The same robot and data from its URDF and from its MJCF: both calibrated files close the loop alike."""
    urdf = tmp_path / "panda.urdf"
    urdf.write_text(nominal_urdf("panda"))
    ru = RobotModel.from_file(urdf)
    rm = panda_mjcf(tmp_path / "panda.xml")
    loop = WeldLoop("fixture", "panda_hand")
    log = make_dataset(ru, loop, Q0, 30, np.random.default_rng(9)).log(noisy=False)
    opts = CalibrationOptions(identify=["placement", "offset", "loop"], noise=1e-6)
    res_u = calibrate(ru, log, [loop], opts)
    res_m = calibrate(rm, log, [WeldLoop("fixture", "panda_hand")], opts)
    write_urdf(ru, res_u.as_dict(), tmp_path / "cal.urdf")
    write_mjcf(rm, res_m.as_dict(), tmp_path / "cal.xml")
    cu = closure_rms(
        RobotModel.from_file(tmp_path / "cal.urdf"), log, WeldLoop("fixture", "panda_hand"), res_u.as_dict()
    )
    cm = closure_rms(
        RobotModel.from_file(tmp_path / "cal.xml"), log, WeldLoop("fixture", "panda_hand"), res_m.as_dict()
    )
    assert max(cu) < 1e-8 and max(cm) < 1e-8
    assert abs(cu[0] - cm[0]) < 1e-9 and abs(cu[1] - cm[1]) < 1e-9
    # the same motion of the tool between configurations (the base placement is a gauge of the weld)
    pu = RobotModel.from_file(tmp_path / "cal.urdf")
    pm = RobotModel.from_file(tmp_path / "cal.xml")
    rel = []
    for r in (pu, pm):
        dd = r.model.createData()
        poses = []
        for th in log.angles[:5]:
            pin.framesForwardKinematics(r.model, dd, r.configurations(th, log.joints)[0])
            poses.append(dd.oMf[r.model.getFrameId("panda_hand")].copy())
        rel.append([poses[0].actInv(p) for p in poses[1:]])
    for a, b in zip(*rel):
        assert np.abs(a.homogeneous - b.homogeneous).max() < 1e-8


def test_mjcf_export_refuses_other_inputs(tmp_path):
    from closedloop.errors import ModelError
    from closedloop.output.mjcf import calibrated_mjcf

    urdf = tmp_path / "panda.urdf"
    urdf.write_text(nominal_urdf("panda"))
    with pytest.raises(ModelError, match="only be written for MJCF input"):
        calibrated_mjcf(RobotModel.from_file(urdf), {})


ARM = """<mujoco model="arm3">
  <compiler angle="degree"/>
  <worldbody>
    <body name="base">
      <body name="l1" pos="0 0 0.3" euler="0 0 30">
        <joint name="j1" axis="0 0 1" range="-170 170"/>
        <geom type="capsule" size="0.03" fromto="0 0 0 0.3 0 0"/>
        <body name="l2" pos="0.3 0 0" axisangle="1 0 0 90">
          <joint name="j2" axis="0 0 1" pos="0.02 0 0.01" range="-120 120"/>
          <geom type="capsule" size="0.03" fromto="0 0 0 0.25 0 0"/>
          <body name="l3" pos="0.25 0 0">
            <joint name="j3" type="slide" axis="1 0 0" range="-0.1 0.1"/>
            <geom type="box" size="0.02 0.02 0.02"/>
            <body name="tool" pos="0.1 0 0"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_degrees_euler_anchor_and_slide(tmp_path):
    """Any correction of a hand-written MJCF (degrees, euler/axis-angle bodies, an anchor, a slide joint)."""
    from closedloop.model.parameters import RobotParameters

    src = tmp_path / "arm3.xml"
    src.write_text(ARM)
    robot = RobotModel.from_file(src)
    rp = RobotParameters(robot, robot.joint_names)
    rng = np.random.default_rng(1)
    values = {p.name: (p.nominal + rng.uniform(-0.05, 0.05)) for p in rp.params if p.kind in ("placement", "offset")}
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "arm3_calibrated.xml"
    write_mjcf(robot, values, out)
    m = mujoco.MjModel.from_xml_path(str(out))
    d = mujoco.MjData(m)
    x = np.array([values.get(p.name, p.nominal) for p in rp.params])
    cal = rp.apply(x).model
    cd = cal.createData()
    off = x[rp.offset_index()]
    for theta in rng.uniform(-0.1, 0.1, size=(5, 3)):
        d.qpos[:] = theta
        mujoco.mj_kinematics(m, d)
        pin.framesForwardKinematics(cal, cd, robot.configurations(theta + off, robot.joint_names)[0])
        T = cd.oMf[cal.getFrameId("tool")]
        b = m.body("tool").id
        assert np.abs(T.translation - d.xpos[b]).max() < 1e-12
        assert np.abs(T.rotation - d.xmat[b].reshape(3, 3)).max() < 1e-12
    m0 = mujoco.MjModel.from_xml_path(str(src))
    np.testing.assert_allclose(m.jnt_range, m0.jnt_range - off[:, None], atol=1e-12)  # radians and metres


def test_cli_writes_the_calibrated_mjcf(fitted, capsys):
    import json

    from closedloop.cli.main import main

    d, robot, loop, log, res, ds = fitted
    csv, out, rep = d / "log.csv", d / "cli_calibrated.xml", d / "cli_report.json"
    log.write_csv(csv)
    assert (
        main(
            [
                "calibrate",
                str(robot.source),
                str(csv),
                "--loop",
                "weld:frame=panda_hand,name=fixture",
                "--out",
                str(out),
                "--report",
                str(rep),
                "--cv",
                "0",
                "--regions",
                "0",
            ]
        )
        == 0
    )
    assert f"wrote {out}" in capsys.readouterr().out
    m = mujoco.MjModel.from_xml_path(str(out))
    assert m.nbody == mujoco.MjModel.from_xml_path(str(robot.source)).nbody + 1  # and the fixture, in the world
    fitted_values = {p["name"]: p["calibrated"] for p in json.loads(rep.read_text())["parameters"]}
    assert np.abs(m.body("fixture_fixture").pos - [fitted_values[f"fixture.{a}"] for a in "xyz"]).max() < 1e-12
    rms = closure_rms(RobotModel.from_file(out), log, WeldLoop("fixture", "panda_hand"), fitted_values)
    assert rms[0] < 1e-8 and rms[1] < 1e-8
