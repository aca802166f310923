"""Simulate any robot: a robot no scenario uses, from the command line, calibrated and checked.

Romeo's left arm (example-robot-data ``romeo_small.urdf``, a humanoid no other test or scenario
uses): ``simulate --robot ... --loop weld:frame=l_wrist`` picks the driven joints (the trunk yaw and
the seven arm joints; legs, head and the other arm held fixed) and the grasp pose by itself;
``calibrate`` on the written nominal URDF and log, then ``check`` against the simulation's truth:
the README's "Calibrate your own robot" commands.  Then the plain-words errors, the scenario YAML
files (the built-ins are such files) and an MJCF robot.
"""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from closedloop.assets.catalog import example_robot_data_dir
from closedloop.cli.main import main
from closedloop.sims.scenario_files import load_scenario
from closedloop.sims.scenarios import SCENARIOS

ROMEO = example_robot_data_dir() / "romeo_description" / "urdf" / "romeo_small.urdf"
SO101 = example_robot_data_dir() / "so_arm_description" / "urdf" / "so101.urdf"


def test_romeo_arm_simulated_calibrated_and_checked(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--robot",
                str(ROMEO),
                "--loop",
                "weld:frame=l_wrist,name=fixture",
                "--n",
                "60",
                "--seed",
                "1",
                "--out",
                str(sim),
            ]
        )
        == 0
    )
    assert "simulated 60 configurations of romeo_small_weld" in capsys.readouterr().out
    truth = json.loads((sim / "truth.json").read_text())
    assert truth["joint_names"] == [
        "TrunkYaw",
        "LShoulderPitch",
        "LShoulderYaw",
        "LElbowRoll",
        "LElbowYaw",
        "LWristRoll",
        "LWristYaw",
        "LWristPitch",
    ]
    assert truth["violation"]["max_m"] < 1e-7 and truth["violation"]["max_rad"] < 1e-6  # the loop stays closed
    assert truth["samples"]["recorded"] == 60
    q = np.loadtxt(sim / "log.csv", delimiter=",", skiprows=1, usecols=range(8))
    assert np.ptp(q, axis=0).min() > 0.05  # every driven joint moves in the 2-DOF self-motion
    out, report = tmp_path / "calibrated.urdf", tmp_path / "report.json"
    assert (
        main(
            [
                "calibrate",
                str(sim / "nominal.urdf"),
                str(sim / "log.csv"),
                "--loop",
                "weld:frame=l_wrist,name=fixture",
                "--out",
                str(out),
                "--report",
                str(report),
                "--cv",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    assert main(["check", str(sim / "truth.json"), str(report)]) == 0
    text = capsys.readouterr().out
    assert " 0 outside" in text
    rep = json.loads(report.read_text())
    after = rep["residuals"]["after"][0]
    assert after["rms_m"] < 1e-6 and rep["residuals"]["before"][0]["rms_m"] > 1e-4
    assert out.is_file()


def test_plain_words_when_a_loop_cannot_close(tmp_path, capsys):
    out = str(tmp_path / "x")
    # five arm joints cannot move under the six constraints of a weld
    assert main(["simulate", "--robot", str(SO101), "--loop", "weld:frame=gripper_frame_link", "--out", out]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "leaves the closed chain no motion" in err and "shoulder_pan" in err and "point: 3" in err
    assert main(["simulate", "--robot", str(SO101), "--loop", "point:frame=gripper_frame", "--out", out]) == 2
    assert "no link 'gripper_frame'" in (err := capsys.readouterr().err) and "gripper_frame_link" in err
    assert main(["simulate", "--robot", str(SO101), "--loop", "camera:frame=gripper_frame_link", "--out", out]) == 2
    assert "the simulator has no 'camera' loop" in capsys.readouterr().err
    assert (
        main(["simulate", "--robot", str(ROMEO), "--loop", "point:frame=l_wrist", "--joints", "LHipYaw", "--out", out])
        == 2
    )
    assert "LHipYaw do not move l_wrist" in capsys.readouterr().err
    assert main(["simulate", "--robot", str(ROMEO), "--loop", "weld:frame=l_wrist", "--q0", "0 0", "--out", out]) == 2
    assert "q0 has 2 values; l_wrist is driven by 8 joints" in capsys.readouterr().err


def test_builtin_scenarios_are_yaml_files_and_a_user_yaml_runs(tmp_path, capsys):
    shipped = Path(__file__).resolve().parents[1] / "closedloop" / "sims" / "scenarios"
    assert sorted(p.stem for p in shipped.glob("*.yaml")) == sorted(
        ["panda_weld", "ur5_socket", "ur5_door", "utah_hand", "ur5_plane", "ur5_tracker"]
    )
    assert SCENARIOS["utah_hand"].target_frame == "thumb_tip" and SCENARIOS["utah_hand"].settings.timestep == 0.001
    assert SCENARIOS["ur5_door"].loop_type == "hinge" and SCENARIOS["ur5_door"].door.radius == 0.45
    # a user's scenario: the SO-101 with a stylus 5 cm off its gripper frame in a socket (3 of 5 joints taken)
    (tmp_path / "robots").mkdir()
    (tmp_path / "robots" / "so101.urdf").write_text(SO101.read_text())
    yml = tmp_path / "so101_socket.yaml"
    yml.write_text(
        "description: SO-101 stylus in a socket\nrobot: robots/so101.urdf\n"
        "loop: point:frame=gripper_frame_link,name=socket\ntool: {xyz: [0.05, 0.0, 0.0]}\n"
        "settings: {step_rad: 0.1, target_span: 1.0}\n"
    )
    sc = load_scenario(yml)
    assert sc.tool_frame == "gripper_frame_link_tip" and len(sc.q0) == 5
    assert main(["simulate", str(yml), "--n", "15", "--out", str(tmp_path / "s"), "--quiet"]) == 0
    truth = json.loads((tmp_path / "s" / "truth.json").read_text())
    assert truth["scenario"] == "so101_socket" and truth["violation"]["max_m"] < 1e-6
    assert "gripper" not in truth["joint_names"]  # the jaw is not on the stylus's chain: held fixed
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: robots/so101.urdf\nloop: point:frame=gripper_frame_link\nsettings: {kpp: 3}\n")
    assert main(["simulate", str(bad), "--out", str(tmp_path / "b")]) == 2
    assert "unknown setting(s) kpp" in capsys.readouterr().err


def test_mjcf_robot(tmp_path):
    """An MJCF arm (the UR5 compiled by MuJoCo, joint anchors moved off the body origins) simulates as the URDF."""
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.sims import simulate
    from closedloop.sims.robot_scenario import prepare_robot

    spec = mujoco.MjSpec.from_string(
        nominal_urdf("ur5").replace(
            "</robot>", '<mujoco><compiler fusestatic="false" discardvisual="true"/></mujoco></robot>'
        )
    )
    spec.joint("wrist_1_joint").pos = [0.0, 0.0, 0.03]  # an anchor off the body origin (MJCF allows it)
    xml = tmp_path / "ur5.xml"
    xml.write_text(spec.to_xml())
    prepared = prepare_robot(xml, "point", "tool0", tool={"xyz": [0, 0.05, 0.1]})
    assert prepared.joints == (
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    )
    # the converted robot has the MJCF's kinematics: the tool pose at random configurations agrees
    import pinocchio as pin

    m = mujoco.MjModel.from_xml_path(str(xml))
    d = mujoco.MjData(m)
    pm = pin.buildModelFromUrdf(str(prepared.path))
    pd = pm.createData()
    rng = np.random.default_rng(0)
    for q in rng.uniform(-2, 2, size=(5, 6)):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        pin.framesForwardKinematics(pm, pd, q)
        b = m.body("tool0").id
        assert np.allclose(pd.oMf[pm.getFrameId("tool0")].translation, d.xpos[b], atol=1e-9)
        assert np.allclose(pd.oMf[pm.getFrameId("tool0")].rotation, d.xmat[b].reshape(3, 3), atol=1e-9)
    SCENARIOS["ur5_mjcf"] = __import__("dataclasses").replace(
        SCENARIOS["ur5_socket"], name="ur5_mjcf", robot=prepared.key, tool_frame=prepared.frame, q0=prepared.q0
    )
    res = simulate("ur5_mjcf", n=10, seed=0, out_dir=tmp_path / "m")
    assert res.violation_m.max() < 1e-6 and len(res.readings) == 10


def test_every_scenario_is_named_in_the_help_and_in_the_unknown_scenario_error(tmp_path, capsys):
    """One list (`scenario_catalog`): the shipped files and the head cameras, in the help and in the error."""
    from closedloop.sims.scenarios import CAMERA_SCENARIOS, scenario_catalog

    catalog = scenario_catalog()
    assert {"panda_weld", "ur5_socket", "ur5_door", "utah_hand", "ur5_plane", "ur5_tracker"} <= set(catalog)
    assert set(CAMERA_SCENARIOS) == {"ur5_head", "ur5_head_verging"} and set(CAMERA_SCENARIOS) <= set(catalog)
    assert main(["simulate", "--help"]) == 0
    out = capsys.readouterr().out
    for name, (loop, description) in catalog.items():
        assert f"  {name} " in out and loop in out and description in out, name
    assert "--robot" in out and "--loop" in out
    assert main(["simulate", "nosuch", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: unknown scenario 'nosuch' (known: {', '.join(catalog)})"


def test_simulate_prints_the_calibrate_command_for_its_tool_frame(tmp_path, capsys):
    """``--tool`` adds a link named ``<frame>_tip``: the printed calibrate command names that frame (the
    dataset's nominal.urdf has it), runs as printed, and check compares every parameter correctly.  The
    nominal.urdf keeps the robot's visuals, mesh files by absolute path."""
    import shlex

    import pinocchio as pin

    sim = tmp_path / "sim"
    urdf = example_robot_data_dir() / "ur_description/urdf/ur5_robot.urdf"
    args = ["--loop", "point:frame=tool0", "--tool", "0 0.05 0.1", "--n", "60", "--seed", "1", "--out", str(sim)]
    assert main(["simulate", "--robot", str(urdf), *args]) == 0
    lines = capsys.readouterr().out.splitlines()
    calibrate = shlex.split(next(ln for ln in lines if ln.strip().startswith("calibrate:")).split(":", 1)[1])
    check = shlex.split(next(ln for ln in lines if ln.strip().startswith("check:")).split(":", 1)[1])
    assert calibrate[calibrate.index("--loop") + 1] == "point:frame=tool0_tip,name=socket"
    assert calibrate[:4] == ["closedloop", "calibrate", str(sim / "nominal.urdf"), str(sim / "log.csv")]
    assert check == ["closedloop", "check", str(sim / "truth.json"), str(sim / "report.json")]
    assert main(calibrate[1:] + ["--quiet"]) == 0
    assert main(check[1:]) == 0
    out = capsys.readouterr().out
    assert "what the robots do" in out and " 0 outside" in out  # judged by what the robots do (the default)
    assert int(out.split(" within tolerance")[0].split()[-1]) >= 2  # the tool point's position and the size
    assert main(check[1:] + ["--parameters"]) == 0  # and parameter by parameter: the frame names agree
    out = capsys.readouterr().out
    assert " 0 outside" in out and int(out.split(" within tolerance")[0].split()[-1]) >= 15
    # the visuals: one per UR5 link, every mesh found; the kinematics those of the cleaned model
    model = pin.buildModelFromUrdf(str(sim / "nominal.urdf"))
    visual = pin.buildGeomFromUrdf(model, str(sim / "nominal.urdf"), pin.GeometryType.VISUAL)
    meshes = [g.meshPath for g in visual.geometryObjects]
    assert len(meshes) >= 7 and all(Path(m).is_absolute() and Path(m).is_file() for m in meshes)
    assert model.existFrame("tool0_tip") and model.nq == 6


def test_calibrate_help_and_loops_list_the_registry(capsys):
    from closedloop.loops.spec import REGISTRY

    assert main(["calibrate", "--help"]) == 0
    out = capsys.readouterr().out
    for kind, (_, keys) in REGISTRY.items():
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(kind + " "))
        assert all(k in out[out.index(line) :] for k in keys)
    assert "--html" in out and "--plots" in out and "--config" in out and "ROS bag" in out
    assert main(["loops"]) == 0
    out = capsys.readouterr().out
    for kind in REGISTRY:
        assert f"\n{kind}\n" in "\n" + out and f"example: --loop {kind}:" in out


def test_mesh_warnings_silenced(tmp_path, caplog):
    """A URDF whose package:// meshes do not resolve: yourdfpy's warnings are silenced (kinematics only)."""
    import logging

    import yourdfpy

    urdf = tmp_path / "romeo.urdf"
    urdf.write_text(ROMEO.read_text())  # away from its package: the mesh paths do not resolve

    def load():  # loading and writing it back, as a URDF editor built on yourdfpy does
        yourdfpy.URDF.load(
            str(urdf),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        ).write_xml()

    logging.getLogger("yourdfpy").setLevel(logging.NOTSET)  # as in a fresh process
    with caplog.at_level(logging.WARNING):
        load()
    assert any(r.name.startswith("yourdfpy") for r in caplog.records)  # the noise this test is about
    caplog.clear()
    assert main(["loops"]) == 0  # any command: the CLI silences yourdfpy below errors
    with caplog.at_level(logging.WARNING):
        load()
    assert not any(r.name.startswith("yourdfpy") for r in caplog.records)
    logging.getLogger("yourdfpy").setLevel(logging.NOTSET)


@pytest.mark.parametrize(
    "spec,urdf,extra",
    [
        ("hinge:frame=tool0,name=door", "ur_description/urdf/ur5_robot.urdf", []),
        ("plane:frame=tool0,name=table", "ur_description/urdf/ur5_robot.urdf", ["--tool", "0 0.05 0.1"]),
        ("measured_point:frame=tool0,name=tracker", "ur_description/urdf/ur5_robot.urdf", ["--tool", "0 0.05 0.1"]),
        ("weld:frame=left_gripper,to=right_gripper,name=grasp", "baxter_description/urdf/baxter.urdf", []),
    ],
)
def test_every_simulated_loop_type_on_a_robot_file(tmp_path, spec, urdf, extra):
    """Door, plane, tracker and two chains of one robot, from a robot file with the automatic choices."""
    out = tmp_path / "s"
    assert (
        main(
            [
                "simulate",
                "--robot",
                str(example_robot_data_dir() / urdf),
                "--loop",
                spec,
                *extra,
                "--n",
                "6",
                "--seed",
                "2",
                "--out",
                str(out),
                "--quiet",
            ]
        )
        == 0
    )
    truth = json.loads((out / "truth.json").read_text())
    assert truth["samples"]["recorded"] == 6 and truth["samples"]["dropped"] <= 2
    kind = spec.split(":")[0]
    assert truth["loop"]["type"] == kind
    limit = 1e-4 if kind == "measured_point" else 1e-6  # a tracker's "violation" is its measurement noise
    assert truth["violation"]["max_m"] < limit
    if "to=" in spec:  # both arms driven, nothing else (head, torso held)
        assert len(truth["joint_names"]) == 14 and all(j.startswith(("left_", "right_")) for j in truth["joint_names"])
