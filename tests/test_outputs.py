"""Calibrated models reload in Pinocchio and MuJoCo and reproduce the fit; CLI behaviour on bad input."""

from __future__ import annotations

import io
import json
import subprocess
import sys
import warnings

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from closedloop.assets.catalog import nominal_urdf
from closedloop.calibration.pipeline import calibrate
from closedloop.cli.main import main
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.output.urdf import write_urdf
from closedloop.studies.truth import make_dataset

Q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A mesh-free Panda, a noise-free weld dataset with offsets AND scale errors, its calibration."""
    d = tmp_path_factory.mktemp("cal")
    nominal = d / "panda.urdf"
    nominal.write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(nominal)
    ds = make_dataset(robot, WeldLoop("fixture", "panda_hand"), Q0, 120, np.random.default_rng(5))
    res = calibrate(robot, ds.log(), [WeldLoop("fixture", "panda_hand")])
    out = d / "calibrated.urdf"
    write_urdf(robot, res.as_dict(), out)
    return robot, ds, res, nominal, out


def test_calibrated_urdf_reproduces_fit_in_pinocchio(calibrated):
    robot, ds, res, _, out = calibrated
    model = pin.buildModelFromUrdf(str(out))
    data = model.createData()
    fid = model.getFrameId("panda_hand")
    # the calibrated model's own prediction of the tool pose (offsets applied, k = 1)
    prob = res.problem
    TA, _ = prob.loop_poses(res.fit.values, 0)
    for i in range(0, 120, 7):
        q = robot.configurations(ds.readings[i : i + 1], prob.joints)[0]
        pin.framesForwardKinematics(model, data, q)
        assert np.abs(data.oMf[fid].homogeneous - TA[i]).max() < 1e-9
    # and the loop closes to the fitted residual
    X = pin.SE3(
        pin.exp3(np.array([res.value(f"fixture.r{a}") for a in "xyz"])),
        np.array([res.value(f"fixture.{a}") for a in "xyz"]),
    )
    worst = 0.0
    for i in range(120):
        q = robot.configurations(ds.readings[i : i + 1], prob.joints)[0]
        pin.framesForwardKinematics(model, data, q)
        worst = max(worst, np.linalg.norm(pin.log6(X.inverse() * data.oMf[fid]).vector))
    assert worst < 1e-9


def test_calibrated_urdf_loads_in_mujoco_with_same_kinematics(calibrated):
    robot, ds, _, _, out = calibrated
    m = mujoco.MjModel.from_xml_path(str(out))
    d = mujoco.MjData(m)
    model = pin.buildModelFromUrdf(str(out))
    data = model.createData()
    for i in (0, 40, 80):
        q = robot.configurations(ds.readings[i : i + 1], robot.supporting_joints("panda_hand"))[0]
        for j in range(1, model.njoints):
            d.qpos[m.joint(model.names[j]).qposadr[0]] = q[model.joints[j].idx_q]
        mujoco.mj_kinematics(m, d)
        pin.framesForwardKinematics(model, data, q)
        T = data.oMf[model.getFrameId("panda_link7")]
        b = m.body("panda_link7").id
        assert np.abs(d.xpos[b] - T.translation).max() < 1e-9
        assert np.abs(d.xmat[b].reshape(3, 3) - T.rotation).max() < 1e-9


@pytest.mark.slow
def test_cli_calibrate_writes_urdf_report_and_check_passes(calibrated, tmp_path):
    robot, ds, _, nominal, _ = calibrated
    log = tmp_path / "log.csv"
    ds.log().write_csv(log)
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"parameters": ds.truth_dict()}))
    out, rep = tmp_path / "out.urdf", tmp_path / "report.json"
    rc = main(
        [
            "calibrate",
            str(nominal),
            str(log),
            "--loop",
            "weld:frame=panda_hand,name=fixture",
            "--out",
            str(out),
            "--report",
            str(rep),
            "--quiet",
        ]
    )
    assert rc == 0 and out.exists()
    report = json.loads(rep.read_text())
    assert report["solver"]["status"] == "converged"
    assert report["residuals"]["after"][0]["rms_m"] < 1e-9
    dropped = {d["name"] for d in report["identifiability"]["dropped"]}
    assert "panda_joint1.x" in dropped
    est = [p for p in report["parameters"] if p["status"] == "estimated"]
    assert est and all(p["std_error"] is not None for p in est)
    assert main(["check", str(truth), str(rep), "--tol-m", "1e-8", "--tol-rad", "1e-8"]) == 0
    # a wrong truth fails the check
    bad = ds.truth_dict()
    bad["panda_joint3.offset"] += 0.01
    truth.write_text(json.dumps({"parameters": bad}))
    assert main(["check", str(truth), str(rep)]) == 1


def _run(capfd, args):
    """The command run in this process: its exit code, what it wrote to stdout and to stderr (file descriptors:
    the C++ libraries' lines too) and the warnings a fresh interpreter would print there (Python's default
    filters).  The program's own start-up is checked in test_cli_startup.py, its exits in test_signals.py."""
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for quiet in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
            warnings.simplefilter("ignore", quiet)
        rc = main(list(args))
    out, err = capfd.readouterr()
    return rc, out, err + "".join(warnings.formatwarning(w.message, w.category, w.filename, w.lineno) for w in caught)


def _run_program(args):
    """The command run as a program (a fresh interpreter): where its start-up is part of what is checked."""
    p = subprocess.run([sys.executable, "-m", "closedloop.cli.main", *args], capture_output=True, text=True)
    return p.returncode, p.stdout, p.stderr


@pytest.fixture()
def files(calibrated, tmp_path):
    robot, ds, _, nominal, _ = calibrated
    log = tmp_path / "log.csv"
    ds.log().write_csv(log)
    return nominal, log, tmp_path


@pytest.mark.parametrize(
    "mutate,expect",
    [
        (lambda text: text.replace("panda_joint4,", "elbow,", 1), "missing column(s) for loop joint(s) panda_joint4"),
        (lambda text: text.replace("\n", "\nnan,0,0,0,0,0,0\n", 1), "line 2, column 'panda_joint1': value is nan"),
        (lambda text: text.split("\n")[0] + "\n", "no data rows"),
        (lambda text: "\n".join(text.split("\n")[:3]) + "\n", "rows give 12 equations, no more than the 12 parameters"),
        (lambda text: text.replace("\n", "\n1,2\n", 1), "line 2 has 2 fields"),
    ],
)
def test_bad_logs_one_line_exit_2(files, mutate, expect, capfd):
    nominal, log, tmp = files
    bad = tmp / "bad.csv"
    bad.write_text(mutate(log.read_text()))
    rc, _, err = _run(capfd, ["calibrate", str(nominal), str(bad), "--loop", "weld:frame=panda_hand", "--quiet"])
    assert rc == 2, err
    assert expect in err and str(bad) in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


@pytest.mark.parametrize(
    "args,expect",
    [
        (["--loop", "weld:frame=panda_hnd"], "unknown frame 'panda_hnd' (did you mean 'panda_hand'"),
        (["--loop", "hinge2:frame=panda_hand"], "unknown loop type 'hinge2'"),
        (["--loop", "weld:frame=panda_hand", "--fix", "panda_joint9.x"], "no parameter named 'panda_joint9.x'"),
        (["--loop", "weld:frame=panda_hand", "--fix", "panda_joint2.x=abc"], "'abc' is not a number"),
        ([], "no --loop given"),
    ],
)
def test_bad_options_one_line_exit_2(files, args, expect, capfd):
    nominal, log, _ = files
    rc, _, err = _run(capfd, ["calibrate", str(nominal), str(log), *args, "--quiet"])
    assert rc == 2 and expect in err and "Traceback" not in err, err


def test_never_overwrites_input(files, capfd):
    nominal, log, _ = files
    before = nominal.read_text()
    rc, _, err = _run(
        capfd,
        ["calibrate", str(nominal), str(log), "--loop", "weld:frame=panda_hand", "--out", str(nominal), "--quiet"],
    )
    assert rc == 2 and "refusing to overwrite" in err
    assert nominal.read_text() == before


def test_missing_model_file(tmp_path, capfd):
    rc, _, err = _run(
        capfd, ["calibrate", str(tmp_path / "nope.urdf"), str(tmp_path / "x.csv"), "--loop", "weld:frame=a"]
    )
    assert rc == 2 and "no such model file" in err


def test_inspect_lists_joints_and_parameters(files, capfd):
    nominal, _, _ = files
    rc, out, _ = _run(capfd, ["inspect", str(nominal), "--json"])
    info = json.loads(out)
    assert rc == 0 and [j["name"] for j in info["joints"]][:2] == ["panda_joint1", "panda_joint2"]
    assert "panda_joint3.offset" in info["parameters"] and "panda_hand" in info["frames"]


@pytest.mark.slow
def test_a_urdf_model_is_not_written_as_a_dh_table(tmp_path):
    """`write_dh` on a model not read from a D-H table: a ModelError naming the file, nothing written."""
    from closedloop.errors import ModelError
    from closedloop.output.urdf import write_dh

    src = tmp_path / "panda.urdf"
    src.write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(src)
    out = tmp_path / "panda.yaml"
    with pytest.raises(ModelError, match=r"panda\.urdf: a urdf model, not a D-H table"):
        write_dh(robot, {}, out)
    assert not out.exists()


@pytest.mark.slow
def test_dh_input_gives_calibrated_dh_yaml(tmp_path):
    """D-H input -> D-H YAML output in the input's units, carrying the calibrated values."""
    import yaml

    from closedloop.studies.hand import table_4_1_path, thesis_hand_dataset

    _, readings, _ = thesis_hand_dataset(tmp_path, n=60)
    robot = RobotModel.from_file(table_4_1_path())
    log = tmp_path / "hand.csv"
    from closedloop.io.logs import JointLog

    JointLog(robot.joint_names, readings).write_csv(log)
    out, rep = tmp_path / "calibrated.yaml", tmp_path / "report.json"
    rc = main(
        [
            "calibrate",
            str(table_4_1_path()),
            str(log),
            "--identify",
            "theta_off,s,a,alpha,k",
            "--fix",
            "j0.s",
            "--fix",
            "j7.k",
            "--weighting",
            "none",
            "--out",
            str(out),
            "--report",
            str(rep),
            "--cv",
            "0",
            "--quiet",
        ]
    )
    assert rc == 0
    doc = yaml.safe_load(out.read_text())
    assert doc["units"]["length"] == "in" and doc["closes"] is True
    cal = {p["name"]: p["calibrated"] for p in json.loads(rep.read_text())["parameters"]}
    again = RobotModel.from_file(out)
    for row in again.dh.rows:
        assert row.s == pytest.approx(cal[f"{row.name}.s"], abs=1e-9)
        assert row.theta_off == pytest.approx(cal[f"{row.name}.theta_off"], abs=1e-9)


def test_mjcf_input(tmp_path, capfd):
    """An MJCF arm loads through Pinocchio's parser and exposes the same parameter names."""
    xml = tmp_path / "arm.xml"
    xml.write_text("""<mujoco model="arm"><worldbody>
      <body name="l1" pos="0 0 0.1"><joint name="j1" type="hinge" axis="0 0 1"/>
        <geom type="capsule" size="0.02" fromto="0 0 0 0.3 0 0" mass="1"/>
        <body name="l2" pos="0.3 0 0"><joint name="j2" type="hinge" axis="0 1 0"/>
          <geom type="capsule" size="0.02" fromto="0 0 0 0.25 0 0" mass="1"/>
          <site name="tip" pos="0.25 0 0"/></body></body></worldbody></mujoco>""")
    robot = RobotModel.from_file(xml)
    assert robot.kind == "mjcf" and robot.joint_names == ["j1", "j2"]
    rc, out, _ = _run(capfd, ["inspect", str(xml), "--json"])
    assert rc == 0 and "j2.offset" in json.loads(out)["parameters"]


@pytest.mark.parametrize(
    "setting, expect",
    [
        ("foo=1", "unknown setting 'foo'"),
        ("gravity=maybe", "'gravity' takes true or false"),
        ("tracker_noise=abc", "'tracker_noise' takes a number"),
        ("solref=[1]", "'solref' takes a list of 2 numbers"),
        ("min_steps=2.5", "'min_steps' takes a whole number"),
        ("noise", "expected KEY=VALUE"),
    ],
)
def test_bad_simulation_settings_one_line_exit_2(tmp_path, setting, expect, capfd):
    rc, _, err = _run(capfd, ["simulate", "panda_weld", "--n", "2", "--out", str(tmp_path / "o"), "--set", setting])
    assert rc == 2 and expect in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists()  # nothing simulated


def test_check_uses_the_tolerance_of_each_unit():
    from closedloop.validation.check import check_report

    def p(name, unit, cal, kind="loop"):
        return {"name": name, "kind": kind, "unit": unit, "calibrated": cal, "initial": 0.0, "status": "estimated"}

    truth = {"parameters": {"cam.cam1.fx": 800.0, "cam.tip_x": 0.1, "j1.compliance": 1e-5}}
    report = {
        "parameters": [
            p("cam.cam1.fx", "px", 800.6),
            p("cam.tip_x", "m", 0.1004),
            p("j1.compliance", "rad/Nm", 3e-5, "compliance"),
        ]
    }
    rows, ok = check_report(truth, report, tol_m=1e-3, tol_rad=5e-3, tol_scale=5e-3, tol_px=1.0)
    res = {r["name"]: r["result"] for r in rows}
    assert ok and res["cam.cam1.fx"] == "ok" and res["cam.tip_x"] == "ok"
    assert res["j1.compliance"].startswith("not compared (no tolerance for unit rad/Nm")
    _, ok = check_report(truth, report, tol_m=1e-3, tol_rad=5e-3, tol_scale=5e-3, tol_px=0.5)
    assert not ok  # 0.6 px off


def _stl(path) -> None:
    """A binary STL tetrahedron (MuJoCo reads binary STL)."""
    import struct

    v = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], dtype=np.float32)
    faces = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
    body = b"".join(struct.pack("<12fH", *([0.0] * 3), *v[a], *v[b], *v[c], 0) for a, b, c in faces)
    path.write_bytes(b"\0" * 80 + struct.pack("<I", len(faces)) + body)


def test_written_urdf_finds_its_meshes_from_another_folder(tmp_path):
    """Relative mesh paths are rewritten for the output's folder; package:// and absolute ones stay."""
    src = tmp_path / "robot"
    (src / "meshes").mkdir(parents=True)
    _stl(src / "meshes" / "link.stl")
    absolute = (src / "meshes" / "link.stl").resolve()
    text = nominal_urdf("panda")
    text = text.replace(
        '<link name="panda_link1">',
        '<link name="panda_link1"><visual><geometry><mesh filename="meshes/link.stl"/></geometry></visual>'
        '<collision><geometry><mesh filename="package://panda/meshes/link.stl"/></geometry></collision>'
        f'<visual><geometry><mesh filename="{absolute}"/></geometry></visual>',
        1,
    )
    (src / "panda.urdf").write_text(text)
    robot = RobotModel.from_file(src / "panda.urdf")
    out = tmp_path / "elsewhere" / "deeper" / "cal.urdf"
    out.parent.mkdir(parents=True)
    write_urdf(robot, {"panda_joint2.x": 1e-3}, out)
    import xml.etree.ElementTree as ET

    names = [m.get("filename") for m in ET.parse(out).getroot().iter("mesh")]
    assert names == ["../../robot/meshes/link.stl", "package://panda/meshes/link.stl", str(absolute)]
    assert (out.parent / names[0]).resolve() == absolute  # the same file, found from the output's folder
    write_urdf(robot, {"panda_joint2.x": 1e-3}, src / "cal.urdf")  # beside the input: kept as written
    assert [m.get("filename") for m in ET.parse(src / "cal.urdf").getroot().iter("mesh")][0] == "meshes/link.stl"


def test_written_mjcf_has_a_relative_meshdir_and_loads_from_another_folder(tmp_path):
    from closedloop.output.mjcf import write_mjcf

    src = tmp_path / "robot"
    (src / "assets").mkdir(parents=True)
    _stl(src / "assets" / "tet.stl")
    (src / "arm.xml").write_text(
        '<mujoco><compiler meshdir="assets"/><asset><mesh name="tet" file="tet.stl"/></asset><worldbody>'
        '<body name="l1"><joint name="j1" type="hinge" axis="0 0 1"/><geom type="mesh" mesh="tet"/>'
        '<body name="l2" pos="0.3 0 0"><joint name="j2" type="hinge" axis="0 1 0"/><geom type="mesh" mesh="tet"/>'
        '<body name="tool" pos="0.2 0 0"/></body></body></worldbody></mujoco>'
    )
    robot = RobotModel.from_file(src / "arm.xml")
    out = tmp_path / "out" / "cal.xml"
    out.parent.mkdir()
    tip = np.array([0.01, 0.02, 0.03])
    write_mjcf(robot, {"j2.x": 2e-3, "j1.offset": 0.01}, out, frames=[("ball_tip", "tool", tip)])
    import xml.etree.ElementTree as ET

    comp = ET.parse(out).getroot().find("compiler")
    assert comp.get("meshdir") == "../robot/assets"  # relative, not absolute
    m = mujoco.MjModel.from_xml_path(str(out))  # loads from its own folder
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    assert (
        np.abs(
            d.xpos[m.body("ball_tip").id] - d.xpos[m.body("tool").id] - d.xmat[m.body("tool").id].reshape(3, 3) @ tip
        ).max()
        < 1e-12
    )
    cal = RobotModel.from_file(out)  # and Pinocchio sees the tool point as a frame on the tool
    T = (
        cal.model.frames[cal.frame_id("tool")].placement.inverse()
        * cal.model.frames[cal.frame_id("ball_tip")].placement
    )
    assert np.abs(T.translation - tip).max() < 1e-12


# --------------------------------------------------------------------------- what the command line prints
def _calibrate_args(files, *extra):
    nominal, log, tmp = files
    return ["calibrate", str(nominal), str(log), "--loop", "weld:frame=panda_hand,name=fixture", *extra]


@pytest.mark.slow
def test_quiet_prints_nothing_and_a_log_gets_no_progress_lines(files):
    """--quiet: no summary; without it, the summary on stdout and no progress line in a non-terminal stderr."""
    _, _, tmp = files
    rc, out, err = _run_program(_calibrate_args(files, "--report", str(tmp / "r.json"), "--quiet"))
    assert rc == 0 and out == "" and err == "", (out, err)
    assert json.loads((tmp / "r.json").read_text())["verdict"]["status"] == "ok"
    rc, out, err = _run_program(_calibrate_args(files, "--report", str(tmp / "r2.json")))
    assert rc == 0 and out.startswith("verdict: ok") and f"wrote {tmp / 'r2.json'}" in out
    assert err == "", err  # no 'solving: iteration ...' lines left in a log


class _Terminal:
    """A stderr that says it is a terminal and keeps what is left on the screen (carriage returns applied)."""

    def __init__(self):
        self.text = ""

    def isatty(self) -> bool:
        return True

    def write(self, s: str) -> None:
        self.text += s

    def flush(self) -> None:
        pass

    def screen(self) -> list[str]:
        lines = []
        for line in self.text.split("\n"):
            cells: list[str] = []
            col = 0
            for ch in line:
                if ch == "\r":
                    col = 0
                    continue
                if col < len(cells):
                    cells[col] = ch
                else:
                    cells.append(ch)
                col += 1
            lines.append("".join(cells).rstrip())
        return lines


def test_progress_is_shown_on_a_terminal_and_erased_when_done():
    from closedloop.cli.progress import ProgressDisplay

    term = _Terminal()
    prog = ProgressDisplay(quiet=False, stream=term)
    prog("solving", 0, None, "cost 1.000e+00")
    prog("solving", 7, None, "cost 2.500e-03")
    prog.bar.refresh()  # (drawn at most every 0.1 s)
    assert term.screen()[-1].startswith("solving: 7 iterations") and "cost 2.500e-03" in term.screen()[-1]
    prog("simulating", 100, 200)
    prog.bar.refresh()
    assert term.screen()[-1].startswith("simulating:  50%") and "100/200" in term.screen()[-1]
    prog.close()
    assert term.screen() == [""]  # nothing stale left on the screen
    prog("validating", 3, 3)  # the last of a count: erased at once
    assert term.screen() == [""] and prog.bar is None
    silent = _Terminal()
    ProgressDisplay(quiet=True, stream=silent)("solving", 3, None, "cost 1")
    assert silent.text == ""


def test_job_progress_is_erased_when_the_last_job_ends_and_never_drawn_off_a_terminal():
    from closedloop.cli.progress import ProgressDisplay
    from closedloop.parallel.executor import run

    term = _Terminal()
    with ProgressDisplay(stream=term, prefix="simulate: ") as shown:
        assert run(abs, [-1, -2, -3], "serial", progress=shown, task="jobs") == [1, 2, 3]
        assert term.text.startswith("\r") and "simulate: jobs" in term.text
        assert term.screen() == [""]
    log = io.StringIO()  # not a terminal: nothing
    with ProgressDisplay(stream=log) as shown:
        run(abs, [-1], "serial", progress=shown)
    assert log.getvalue() == "" and shown.bar is None


def test_html_without_matplotlib_is_refused_before_the_fit(files, monkeypatch, capsys):
    import closedloop.calibration.pipeline as pipeline

    _, _, tmp = files
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError

    def no_fit(*a, **k):
        raise AssertionError("the fit started")

    monkeypatch.setattr(pipeline, "calibrate", no_fit)
    for opt, path in (("--html", tmp / "r.html"), ("--plots", tmp / "figs")):
        rc = main(_calibrate_args(files, opt, str(path), "--report", str(tmp / "r.json")))
        err = capsys.readouterr().err
        assert rc == 2, err
        assert err.startswith(f"error: {opt}: needs matplotlib") and 'pip install "closedloop[report]"' in err
        assert len(err.strip().splitlines()) == 1
        assert not path.exists() and not (tmp / "r.json").exists()


def test_check_names_the_verdict_once(tmp_path, capsys):
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({"parameters": {"j1.offset": 0.0}}))
    rep = tmp_path / "report.json"
    rep.write_text(
        json.dumps(
            {
                "parameters": [
                    {
                        "name": "j1.offset",
                        "initial": 0.0,
                        "calibrated": 1e-4,
                        "unit": "rad",
                        "kind": "offset",
                        "status": "estimated",
                    }
                ],
                "verdict": {"status": "suspect", "reasons": ["suspect: scale not set", "suspect: scale not set"]},
            }
        )
    )
    assert main(["check", str(truth), str(rep)]) == 0
    out = capsys.readouterr().out
    assert "note: the report's verdict is suspect: scale not set\n" in out
    assert "suspect: suspect:" not in out and out.count("scale not set") == 1


def test_a_quiet_sweep_prints_nothing_and_a_loud_one_its_summary(tmp_path, capsys):
    out = tmp_path / "sweep"
    args = ["simulate", "panda_weld", "--seeds", "0", "--n", "5", "--jobs", "1", "--out", str(out)]
    assert main(args + ["--quiet"]) == 0
    printed = capsys.readouterr()
    assert printed.out == "" and printed.err == ""
    assert (out / "seed_000" / "truth.json").exists()
    assert main(args) == 0  # run again: resumed, and said so
    said = capsys.readouterr().out
    assert said.startswith("0 dataset(s) simulated") and "1 finished earlier (not redone)" in said


def test_commanded_readings_fit_plain_least_squares_and_say_so(files, capsys):
    """--readings commanded: the residual is not reading noise, so plain least squares unless --weighting
    is given; the report records both, the summary says why."""
    nominal, log, tmp = files
    base = ["calibrate", str(nominal), str(log), "--loop", "weld:frame=panda_hand,name=fixture", "--cv", "0"]
    base += ["--regions", "0"]
    assert main([*base, "--readings", "commanded", "--report", str(tmp / "cmd.json")]) == 0
    rep = json.loads((tmp / "cmd.json").read_text())
    assert rep["inputs"] == {"readings": "commanded", "weighting": "none", "torques": None}
    assert rep["weighting"] == "none"
    assert "readings are commanded setpoints" in capsys.readouterr().out
    assert main([*base, "--readings", "commanded", "--weighting", "noise", "--report", str(tmp / "c2.json")]) == 0
    assert json.loads((tmp / "c2.json").read_text())["inputs"]["weighting"] == "noise"  # given: kept
    assert main([*base, "--report", str(tmp / "m.json")]) == 0
    assert json.loads((tmp / "m.json").read_text())["inputs"] == {
        "readings": "measured",
        "weighting": "noise",
        "torques": None,
    }


def test_the_csv_log_writer_reads_back_exactly(tmp_path):
    """`io.logs.write_log_csv`, the one CSV log writer: every double read back to the bit, a value that is
    not finite as an empty cell (an extra column's NaN), the loop column as written; staged in an output
    set, nothing is on disk before the set is published."""
    from closedloop.io.files import OutputSet
    from closedloop.io.logs import JointLog, log_csv, read_log, write_log_csv

    rng = np.random.default_rng(4)
    angles = rng.normal(size=(5, 2)) * 10.0 ** rng.integers(-9, 3, (5, 2))
    uv = rng.normal(size=5)
    uv[2] = np.nan
    lg = JointLog(["j1", "j2"], angles, loop=np.array(["a", "b", "a", "a", "b"]), extra={"cam:u1": uv})
    lg.write_csv(tmp_path / "log.csv")
    back = read_log(tmp_path / "log.csv", ["j1", "j2"])
    assert np.array_equal(back.angles, angles) and list(back.loop) == ["a", "b", "a", "a", "b"]
    assert np.array_equal(back.extra["cam:u1"], uv, equal_nan=True)
    assert log_csv({"j1": [0.1, np.inf], "x": [np.nan, 2]}) == "j1,x\n0.1,\n,2.0\n"
    files = OutputSet()
    write_log_csv(tmp_path / "staged.csv", {"j1": [1.0]}, files)
    assert not (tmp_path / "staged.csv").exists()
    files.commit()
    assert (tmp_path / "staged.csv").read_text() == "j1\n1.0\n"
