"""ROS bags in: quasi-static samples of sensor_msgs/JointState bags written here with rosbags itself.

A true standstill sequence (exact Panda weld data, `closedloop.studies.truth.make_dataset`) is played as a
joint-state stream: each configuration held 1 s, smooth moves of 0.6 s between them, 100 Hz, Gaussian
reading noise on every message, the arm's joints shuffled among the gripper's.  Written as a ROS 2
sqlite3 bag, a ROS 2 MCAP bag and a ROS 1 bag; the extracted samples must match the standstills one
to one, and the calibration from a bag must equal the one from the equivalent CSV.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import build_problem, residual_stats
from closedloop.cli.main import main
from closedloop.io.bags import ExtractOptions, extract
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.truth import make_dataset

RATE = 100.0  # Hz
HOLD, MOVE = 1.0, 0.6  # s
NOISE = 2e-5  # rad per message
T0_NS = 1_700_000_000_000_000_000
EXTRA = ["panda_finger_joint1", "panda_finger_joint2"]


def stream(
    Q: np.ndarray,
    rng: np.random.Generator,
    velocities: bool,
    t_start: float = 0.0,
    pause_after: int | None = None,
    pause: float = 0.0,
):
    """(t [s], q, qdot) of a hold-move-hold... trajectory through the rows of Q (plus a pause)."""
    ts, qs, vs = [], [], []
    t = t_start
    dt = 1.0 / RATE
    for i, q in enumerate(Q):
        for _ in range(int(HOLD * RATE)):
            ts.append(t), qs.append(q), vs.append(np.zeros_like(q))
            t += dt
        if i == len(Q) - 1:
            break
        if pause_after is not None and i == pause_after:
            t += pause  # recording stopped while the fixture is moved
        nxt = Q[i + 1]
        for k in range(1, int(MOVE * RATE)):
            s = k / (MOVE * RATE)
            ts.append(t), qs.append(q + (nxt - q) * 0.5 * (1 - np.cos(np.pi * s)))
            vs.append((nxt - q) * 0.5 * np.pi / MOVE * np.sin(np.pi * s))
            t += dt
    q = np.array(qs) + rng.normal(0.0, NOISE, (len(qs), Q.shape[1]))
    v = np.array(vs) + rng.normal(0.0, NOISE * RATE * 0.1, (len(qs), Q.shape[1])) if velocities else None
    return np.array(ts), q, v


def write_bag(path: Path, fmt: str, topics: dict[str, tuple], joints: list[str], rng: np.random.Generator) -> Path:
    """Write JointState messages (names shuffled, with two joints the model lacks)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    js = "sensor_msgs/msg/JointState"
    JointState, Header = store.types[js], store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    if fmt == "ros1":
        from rosbags.rosbag1 import Writer

        path = path.with_suffix(".bag")
        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=8, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
    names = joints + EXTRA
    msgs = []
    for topic, (t, q, v) in topics.items():
        for k in range(len(t)):
            perm = rng.permutation(len(names))
            pos = np.concatenate([q[k], [0.02, 0.02]])[perm]
            vel = np.concatenate([v[k], [0.0, 0.0]])[perm] if v is not None else np.zeros(0)
            msgs.append((T0_NS + int(round(t[k] * 1e9)), topic, [names[p] for p in perm], pos, vel))
    msgs.sort(key=lambda m: m[0])
    with writer:
        conns = {tp: writer.add_connection(tp, js, typestore=store) for tp in topics}
        for seq, (t_ns, topic, nm, pos, vel) in enumerate(msgs):
            stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
            hdr = Header(seq=seq, stamp=stamp, frame_id="") if fmt == "ros1" else Header(stamp=stamp, frame_id="")
            msg = JointState(header=hdr, name=nm, position=pos, velocity=vel, effort=np.zeros(0))
            raw = store.serialize_ros1(msg, js) if fmt == "ros1" else store.serialize_cdr(msg, js)
            writer.write(conns[topic], t_ns, raw)
    return path


@pytest.fixture(scope="module")
def panda():
    return RobotModel.from_file(ROBOTS["panda"].path)


@pytest.fixture(scope="module")
def standstills(panda):
    """20 exact configurations of the Panda hand welded to a fixture (the true standstills)."""
    ds = make_dataset(
        panda,
        WeldLoop("fixture", "panda_hand"),
        [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8],
        20,
        np.random.default_rng(3),
        stride=6,
        step=0.06,
    )
    return ds


@pytest.mark.parametrize("fmt,velocities", [("sqlite3", True), ("mcap", False), ("ros1", False), ("ros1", True)])
def test_extracted_samples_match_standstills(tmp_path, standstills, fmt, velocities):
    rng = np.random.default_rng(11)
    Q = standstills.readings
    joints = standstills.joints
    bag = write_bag(tmp_path / f"bag_{fmt}", fmt, {"/joint_states": stream(Q, rng, velocities)}, joints, rng)
    lg, found = extract(bag, joints)
    assert lg.angles.shape == Q.shape  # one sample per standstill, none from the motion
    err = np.abs(lg.angles - Q).max()
    assert err < 5 * NOISE / np.sqrt(0.8 * HOLD * RATE)  # the mean over the standstill: noise / sqrt(n)
    held = np.array([s.t1 - s.t0 for s in found])
    assert np.all(held > 0.5) and np.all(held <= HOLD + 0.3)


def test_poses_a_few_milliradians_apart_stay_apart(tmp_path, standstills):
    """A 3 mrad move peaks at 8 mrad/s, below the speed threshold: the position jump still splits it."""
    rng = np.random.default_rng(4)
    Q = standstills.readings[:6].copy()
    Q[3] = Q[2] + 0.003
    bag = write_bag(tmp_path / "close", "mcap", {"/joint_states": stream(Q, rng, False)}, standstills.joints, rng)
    lg, _ = extract(bag, standstills.joints)
    assert lg.angles.shape == Q.shape
    assert np.abs(lg.angles - Q).max() < 1e-5


def test_calibration_from_bag_equals_csv(tmp_path, panda, standstills, capsys):
    """`calibrate` on the bag = on the extracted CSV; the result closes the true loop at the exact standstills."""
    rng = np.random.default_rng(5)
    Q, joints = standstills.readings, standstills.joints
    bag = write_bag(tmp_path / "arm", "mcap", {"/joint_states": stream(Q, rng, True)}, joints, rng)
    urdf = str(ROBOTS["panda"].path)
    csv = tmp_path / "extracted.csv"
    assert main(["extract", str(bag), "--model", urdf, "--out", str(csv)]) == 0
    assert "extracted 20 quasi-static samples" in capsys.readouterr().out
    loop = ["--loop", "weld:frame=panda_hand,name=fixture", "--cv", "0", "--regions", "0", "--quiet"]
    reports = {name: tmp_path / f"{name}.json" for name in ("bag", "csv")}
    assert main(["calibrate", urdf, str(csv), *loop, "--report", str(reports["csv"])]) == 0
    # the bag straight into calibrate, every option from a config file (as robot_calibration users keep them)
    cfg = tmp_path / "calib.yaml"
    cfg.write_text(
        f"model: {urdf}\nlog: {bag}\nloop:\n  - weld:frame=panda_hand,name=fixture\ncv: 0\nregions: 0\nquiet: true\n"
        f"report: {reports['bag']}\n"
    )
    assert main(["calibrate", "--config", str(cfg)]) == 0
    params = {k: {p["name"]: p for p in json.loads(v.read_text())["parameters"]} for k, v in reports.items()}
    assert sum(p["status"] == "estimated" for p in params["bag"].values()) >= 10
    for n, b in params["bag"].items():  # the bag and its extracted CSV: the same calibration
        c = params["csv"][n]
        assert b["status"] == c["status"], n
        assert abs(b["calibrated"] - c["calibrated"]) < 1e-9, n  # the same samples (CSV keeps 17 digits)
    # and the exact standstills: the robot calibrated from the bag closes the TRUE loop at the exact
    # standstills to the noise of the averaged samples (gauge-free: the parameters themselves may take
    # another gauge than the exact data's fit)
    prob = build_problem(panda, JointLog(list(joints), Q), [WeldLoop("fixture", "panda_hand")])
    values = np.array([params["bag"][n]["calibrated"] for n in prob.names])
    stats = residual_stats(prob, prob.evaluate(values, False))[0]
    assert stats.rms_m < 2e-5 and stats.rms_rad < 1e-4
    before = json.loads(reports["bag"].read_text())["residuals"]["before"][0]
    assert before["rms_m"] > 1e-3  # the nominal robot did not close it


def test_fixtures_split_by_topic_gap_and_window(tmp_path, standstills):
    rng = np.random.default_rng(8)
    Q, joints = standstills.readings, standstills.joints
    # two topics (two arms recorded separately): 12 and 8 standstills
    two = {"/left/joint_states": stream(Q[:12], rng, True), "/right/joint_states": stream(Q[12:], rng, True, 0.3)}
    bag = write_bag(tmp_path / "two", "sqlite3", two, joints, rng)
    lg, _ = extract(bag, joints, ExtractOptions(split="topic", names={"/left/joint_states": "a"}))
    assert sorted(np.unique(lg.loop, return_counts=True)[1]) == [8, 12]
    assert set(lg.loop) == {"a", "right_joint_states"}
    left = lg.angles[lg.loop == "a"]
    assert np.abs(left - Q[:12]).max() < 1e-5
    # one topic, the recording paused 20 s after the 7th standstill
    bag = write_bag(
        tmp_path / "gap", "ros1", {"/joint_states": stream(Q, rng, False, pause_after=6, pause=20.0)}, joints, rng
    )
    lg, found = extract(bag, joints, ExtractOptions(split="gap", gap=5.0))
    assert list(lg.loop) == ["fixture1"] * 7 + ["fixture2"] * 13
    # windows: only the standstills inside a window are kept
    t_mid = 0.5 * (found[9].t0 + found[10].t1)
    lg, _ = extract(bag, joints, ExtractOptions(split="window", windows={"first": (0.0, t_mid), "late": (40.0, 1e9)}))
    assert list(lg.loop[:10]) == ["first"] * 10 and set(lg.loop[10:]) == {"late"}
    assert np.abs(lg.angles[:10] - Q[:10]).max() < 1e-5


def test_bag_errors_are_one_line(tmp_path, standstills, capsys):
    rng = np.random.default_rng(1)
    Q, joints = standstills.readings[:3], standstills.joints
    bag = write_bag(tmp_path / "short", "mcap", {"/joint_states": stream(Q, rng, True)}, joints, rng)
    out = str(tmp_path / "x.csv")
    assert main(["extract", str(bag), "--joints", "panda_joint1,elbow", "--out", out]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "never reports joint(s) elbow" in err
    assert main(["extract", str(bag), "--joints", "panda_jiont1", "--out", out]) == 2  # a typo: what the bag has
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "any of the joint(s) asked (panda_jiont1); the bag's joints: panda_finger" in err
    assert err.rstrip().endswith("panda_joint4 and 3 more")  # 9 joints: 7 of the arm, 2 fingers
    assert main(["extract", str(bag), "--joints", "panda_joint1", "--topic", "/other", "--out", out]) == 2
    assert "no sensor_msgs/JointState messages on topic(s) /other" in capsys.readouterr().err
    assert main(["extract", str(bag), "--joints", "panda_joint1", "--settle", "5", "--out", out]) == 2
    assert "no standstill of at least 5" in capsys.readouterr().err
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"not a bag")
    assert main(["extract", str(broken), "--joints", "panda_joint1", "--out", out]) == 2
    assert "not a readable ROS bag" in capsys.readouterr().err
    shutil.rmtree(bag)
