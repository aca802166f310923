"""Robot files as users bring them (example-robot-data), through ``simulate --robot`` and ``calibrate``.

* iCub's URDF gives 14 links (legs, head, a wrist) a positive mass and a zero inertia, which MuJoCo
  refuses: the simulator repairs them with one note naming them, and a weld between the two hands
  simulates, calibrates and checks against the truth;
* ``simulate`` says on its summary line and in its exit code when it recorded fewer configurations
  than asked (none: exit 3, nothing written; some: exit 3, the files written);
* joint-limit margins are in each joint's own unit (a prismatic finger of 4 cm range is driven), an
  unlimited revolute joint is driven within one turn;
* a loop on a joint ``simulate`` held fixed in ``nominal.urdf`` is refused by ``calibrate`` before any
  work, naming the joint;
* a point loop whose contact point lies on the last joint's axis is refused by ``simulate --robot``
  (the fix: ``--tool``) and named by ``calibrate`` before any work.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import mujoco
import pytest

from closedloop.assets.catalog import clean_urdf_tree, example_robot_data_dir, repair_inertias
from closedloop.cli.main import main

ERD = example_robot_data_dir()
_NO_FUSE = '<mujoco><compiler fusestatic="false" discardvisual="true"/></mujoco>'
ICUB = ERD / "icub_description" / "robots" / "icub_reduced.urdf"


def _simulate(robot, loop, out, n=30, seed=1, extra=()):
    return main(
        ["simulate", "--robot", str(robot), "--loop", loop, "--n", str(n), "--seed", str(seed), "--out", str(out)]
        + list(extra)
    )


def test_zero_inertias_are_repaired_and_named():
    root = ET.parse(ICUB).getroot()
    repaired = repair_inertias(root)
    assert "l_ankle_2" in repaired and len(repaired) == 14
    assert repair_inertias(root) == []  # repaired once, valid after
    # the cleaned tree compiles in MuJoCo (the original does not: 'inertia must have positive eigenvalues')
    text = ET.tostring(clean_urdf_tree(ET.parse(ICUB).getroot()), encoding="unicode")
    raw = ET.parse(ICUB).getroot()
    for link in raw.findall("link"):  # the meshes are not the point: the inertias are
        for el in link.findall("visual") + link.findall("collision"):
            link.remove(el)
    with pytest.raises(ValueError, match="positive eigenvalues"):
        mujoco.MjModel.from_xml_string(ET.tostring(raw, encoding="unicode"))
    model = mujoco.MjModel.from_xml_string(text.replace("</robot>", _NO_FUSE + "</robot>"))
    ankle = model.body("l_ankle_2").id
    assert model.body_mass[ankle] == pytest.approx(0.2675)  # the mass kept, the moments raised
    assert min(model.body_inertia[ankle]) >= 0.4 * 0.2675 * 0.01**2 * (1 - 1e-9)


def test_icub_two_hand_weld_simulates_calibrates_and_checks(tmp_path, capsys, caplog):
    sim = tmp_path / "sim"
    assert _simulate(ICUB, "weld:frame=l_hand,to=r_hand,name=grasp", sim, n=40) == 0
    notes = [r.getMessage() for r in caplog.records if "inertia" in r.getMessage()]
    assert len(notes) == 1 and "l_ankle_2" in notes[0]
    assert "simulated 40 configurations" in capsys.readouterr().out
    report = tmp_path / "report.json"
    assert (
        main(
            [
                "calibrate",
                str(sim / "nominal.urdf"),
                str(sim / "log.csv"),
                "--loop",
                "weld:frame=l_hand,to=r_hand,name=grasp",
                "--report",
                str(report),
                "--quiet",
            ]
        )
        == 0
    )
    assert json.loads(report.read_text())["verdict"]["status"] in ("ok", "suspect")
    assert main(["check", str(sim / "truth.json"), str(report)]) == 0


PANDA = ERD / "panda_description" / "urdf" / "panda.urdf"
CENTAURO = ERD / "centauro_description" / "urdf" / "centauro.urdf"
ROMEO = ERD / "romeo_description" / "urdf" / "romeo_small.urdf"
ALEX = ERD / "alex_description" / "urdf" / "alex_nub_hands.urdf"


def test_nothing_recorded_is_exit_3_with_nothing_written(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "panda_weld", "--n", "3", "--seed", "1", "--set", "max_steps=10", "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "no configuration recorded of the 3 asked" in err and "--set max_steps=50" in err
    assert not out.exists() or not any(out.iterdir())


def test_fewer_recorded_than_asked_is_said_and_exit_3_with_the_files(tmp_path, capsys, monkeypatch):
    from closedloop.sims import tracking

    sample, calls = tracking.Settler.sample, []

    def two_then_unsettled(self, ctrl, target):  # the robot settles twice, then never again
        calls.append(1)
        if len(calls) <= 2:
            return sample(self, ctrl, target)
        return False, 0, ctrl

    monkeypatch.setattr(tracking.Settler, "sample", two_then_unsettled)
    out = tmp_path / "sim"
    assert main(["simulate", "panda_weld", "--n", "5", "--seed", "1", "--out", str(out)]) == 3
    cap = capsys.readouterr()
    assert "simulated 2 of 5 configurations of panda_weld" in cap.out
    assert "simulated only 2 of 5" in cap.err and "did not come to rest" in cap.err
    assert len((out / "log.csv").read_text().splitlines()) == 1 + 2
    assert (out / "truth.json").is_file()


def test_prismatic_finger_margins_in_metres(tmp_path, capsys):
    """The Panda's finger (0.04 m of travel) ends the chain: driven, not refused for a radian margin."""
    out = tmp_path / "sim"
    loop = "point:frame=panda_leftfinger,name=socket"
    assert _simulate(PANDA, loop, out, n=8, extra=["--tool", "0.02 0 0.05"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["joint_names"][-1] == "panda_finger_joint1"
    log = [ln.split(",") for ln in (out / "log.csv").read_text().splitlines()]
    finger = [float(row[log[0].index("panda_finger_joint1")]) for row in log[1:]]
    assert all(-0.002 <= v <= 0.042 for v in finger)  # metres, within the finger's range


def test_revolute_joint_without_limits_turns(tmp_path):
    """Centauro's wheel: a revolute joint written without lower/upper is driven within one turn."""
    out = tmp_path / "sim"
    assert _simulate(CENTAURO, "point:frame=wheel_1,name=socket", out, n=6, extra=["--tool", "0.05 0.05 0"]) == 0
    wheel = [j for j in ET.parse(out / "nominal.urdf").getroot().findall("joint") if j.get("name") == "j_wheel_1"]
    limit = wheel[0].find("limit")
    assert limit is not None and float(limit.get("lower")) == pytest.approx(-3.141592653589793)


def test_a_loop_through_held_joints_is_refused_before_any_work(tmp_path, capsys):
    from closedloop.model.robot import RobotModel

    sim = tmp_path / "sim"
    arm = "LShoulderPitch,LShoulderYaw,LElbowRoll,LElbowYaw,LWristRoll,LWristYaw,LWristPitch"  # the trunk held
    assert _simulate(ROMEO, "weld:frame=l_wrist,name=fixture", sim, n=6, extra=["--joints", arm]) == 0
    capsys.readouterr()
    assert (
        RobotModel.from_file(sim / "nominal.urdf").held_on_chain(["l_wrist"]) == []
    )  # the simulated loop: rigid trunk, as in truth
    spec = "weld:frame=r_wrist,name=fixture"
    assert main(["calibrate", str(sim / "nominal.urdf"), str(sim / "log.csv"), "--loop", spec, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RShoulderPitch" in err[0] and "held fixed" in err[0] and spec in err[0]


def test_contact_point_on_the_last_axis_refused_at_simulate(tmp_path, capsys):
    assert _simulate(ALEX, "point:frame=leftNub,name=socket", tmp_path / "sim", n=5) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "LeftGripperYaw" in err[0] and "--tool" in err[0]


def test_contact_point_on_the_last_axis_named_at_calibrate(tmp_path, monkeypatch):
    """Data with the contact on LeftGripperYaw's axis (simulated with the check switched off): calibrate's
    check before the fit names the joint and the fix; the same robot with a 5 cm stylus passes it."""
    from closedloop.io.logs import read_log
    from closedloop.loops.geometry import check_loop_geometry
    from closedloop.loops.spec import parse_loop
    from closedloop.model.robot import RobotModel
    from closedloop.sims import robot_scenario

    def warnings(sim, spec):
        robot = RobotModel.from_file(sim / "nominal.urdf")
        lg = read_log(sim / "log.csv", robot.joint_names)
        return check_loop_geometry(sim / "nominal.urdf", robot, lg, [parse_loop(spec, robot)], [spec])

    loop = "point:frame=leftNub,name=socket"
    with monkeypatch.context() as m:
        m.setattr(robot_scenario, "blind_joints", lambda *a, **k: [])
        assert _simulate(ALEX, loop, tmp_path / "on", n=12) == 0
    (line,) = warnings(tmp_path / "on", loop)
    assert "LeftGripperYaw" in line and "stylus off the axis" in line
    off = tmp_path / "off"
    assert _simulate(ALEX, loop, off, n=12, extra=["--tool", "0.05 0 0"]) == 0
    assert warnings(off, "point:frame=leftNub_tip,name=socket") == []
    assert warnings(off, loop) == []  # leftNub with the tip unknown: the pivot puts it 5 cm off the axis


def _odd_urdf() -> str:
    """A legal URDF as they come: a floating base, a second root link, a mimic finger, meshes nowhere."""

    def link(n):
        return (
            f'<link name="{n}"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" '
            f'ixz="0" iyz="0"/></inertial><visual><geometry><mesh filename="package://nowhere/{n}.stl"/>'
            "</geometry></visual></link>"
        )

    def rev(n, p, c, xyz, axis, extra=""):
        return (
            f'<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/><origin xyz="{xyz}"/>'
            f'<axis xyz="{axis}"/><limit lower="-3" upper="3" effort="1" velocity="1"/>{extra}</joint>'
        )

    links = "".join(link(n) for n in ["world", "base", "l1", "l2", "l3", "l4", "l5", "tool", "table", "f1", "f2"])
    joints = (
        '<joint name="float" type="floating"><parent link="world"/><child link="base"/></joint>'
        + rev("j1", "base", "l1", "0 0 0.1", "0 0 1")
        + rev("j2", "l1", "l2", "0 0 0.1", "0 1 0")
        + rev("j3", "l2", "l3", "0 0 0.3", "0 1 0")
        + rev("j4", "l3", "l4", "0 0 0.3", "0 0 1")
        + rev("j5", "l4", "l5", "0 0 0.1", "0 1 0")
        + '<joint name="jt" type="fixed"><parent link="l5"/><child link="tool"/><origin xyz="0.05 0 0.1"/></joint>'
        + rev("f1j", "l5", "f1", "0 0.02 0.1", "1 0 0")
        + rev("f2j", "l5", "f2", "0 -0.02 0.1", "1 0 0", '<mimic joint="f1j" multiplier="-1"/>')
    )
    return f'<robot name="odd">{links}{joints}</robot>'


def test_a_robot_file_as_they_come_simulates(tmp_path, capsys, caplog):
    robot = tmp_path / "odd.urdf"
    robot.write_text(_odd_urdf())
    assert _simulate(robot, "point:frame=tool,name=socket", tmp_path / "sim", n=5) == 0
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    assert truth["joint_names"] == ["j1", "j2", "j3", "j4", "j5"]  # the base stands still, the fingers held
    notes = [r.getMessage() for r in caplog.records if "root links" in r.getMessage()]
    assert len(notes) == 1 and "table" in notes[0]


@pytest.mark.slow
def test_every_example_robot_data_file_compiles_in_mujoco_once_cleaned():
    """The simulator's cleaning (inertias repaired, visuals dropped) makes every URDF of example-robot-data
    one MuJoCo compiles (the floating bases fixed and a root 'world' dropped, as `prepare_robot` does)."""
    tag = '<mujoco><compiler fusestatic="false" discardvisual="true" balanceinertia="true"/></mujoco>'
    files = sorted(ERD.rglob("*.urdf"))
    assert len(files) >= 40
    for f in files:
        root = clean_urdf_tree(ET.parse(f).getroot())
        for j in root.findall("joint"):
            if j.get("type") in ("floating", "planar"):
                j.set("type", "fixed")
        children = {j.find("child").get("link") for j in root.findall("joint")}
        roots = [lk for lk in root.findall("link") if lk.get("name") not in children]
        if len(roots) == 1 and roots[0].get("name") == "world":
            for j in [j for j in root.findall("joint") if j.find("parent").get("link") == "world"]:
                root.remove(j)
            root.remove(roots[0])
        model = mujoco.MjModel.from_xml_string(
            ET.tostring(root, encoding="unicode").replace("</robot>", tag + "</robot>")
        )
        assert model.nbody >= 1, f


def test_a_mimic_joint_on_the_chain_is_refused_with_the_joints_that_leave_it_out(tmp_path, capsys):
    pr2 = ERD / "pr2_description" / "urdf" / "pr2.urdf"
    loop = "point:frame=l_gripper_l_finger_tip_link,name=socket"
    assert _simulate(pr2, loop, tmp_path / "sim", n=5, extra=["--tool", "0.03 0.02 0.05"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "l_gripper_l_finger_tip_joint mimics" in err and "--joints torso_lift_joint," in err
    assert "l_gripper_l_finger_tip_joint" not in err.split("--joints")[1]


def test_a_model_file_is_parsed_once_for_the_same_bytes(tmp_path):
    """`parse_xml` hands back the tree parsed before while the file's bytes are the same, and parses again
    when they change (a file rewritten at once with the same size included)."""
    from closedloop.io.robot_files import parse_xml

    path = tmp_path / "m.urdf"
    path.write_text('<robot name="a"><link name="base"/></robot>')
    first = parse_xml(path)
    assert parse_xml(path) is first and first.get("name") == "a"
    path.write_text('<robot name="b"><link name="base"/></robot>')  # the same size
    assert parse_xml(path).get("name") == "b"
    path.write_text('<robot name="a"')
    with pytest.raises(ET.ParseError):
        parse_xml(path)
