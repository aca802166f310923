"""Play a joint log as a recorded ROS bag of sensor_msgs/JointState (a demo input for `closedloop extract`).

Each row of the CSV log is held for HOLD seconds, with smooth moves of MOVE seconds between rows, at
RATE Hz, Gaussian reading noise on every message (and on the velocities when --velocities): what a
robot driven through its calibration poses and recorded with `ros2 bag record /joint_states` gives.

    python examples/log_to_bag.py MODEL LOG.csv OUT [--format mcap|sqlite3|ros1] [--noise 2e-5]

OUT is a bag directory for ROS 2 (mcap, sqlite3) and a .bag file for ROS 1.  Needs `rosbags`
(pip install ".[ros]" in the checkout).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from closedloop.io.logs import read_log
from closedloop.model.robot import RobotModel


def trajectory(Q: np.ndarray, rate: float, hold: float, move: float):
    """(t, q, qdot): hold each row, move between rows with a half-cosine velocity profile."""
    ts, qs, vs = [], [], []
    t, dt = 0.0, 1.0 / rate
    for i, q in enumerate(Q):
        for _ in range(int(hold * rate)):
            ts.append(t), qs.append(q), vs.append(np.zeros_like(q))
            t += dt
        if i + 1 < len(Q):
            nxt = Q[i + 1]
            for k in range(1, int(move * rate)):
                s = k / (move * rate)
                ts.append(t), qs.append(q + (nxt - q) * 0.5 * (1 - np.cos(np.pi * s)))
                vs.append((nxt - q) * 0.5 * np.pi / move * np.sin(np.pi * s))
                t += dt
    return np.array(ts), np.array(qs), np.array(vs)


def write_bag(
    out: Path,
    fmt: str,
    joints: list[str],
    t: np.ndarray,
    q: np.ndarray,
    v: np.ndarray | None,
    topic: str = "/joint_states",
    t0_ns: int = 1_700_000_000_000_000_000,
) -> None:
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    js = "sensor_msgs/msg/JointState"
    JointState, Header = store.types[js], store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    if fmt == "ros1":
        from rosbags.rosbag1 import Writer

        writer = Writer(out)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
    with writer:
        conn = writer.add_connection(topic, js, typestore=store)
        for k in range(len(t)):
            ns = t0_ns + int(round(t[k] * 1e9))
            stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            hdr = Header(seq=k, stamp=stamp, frame_id="") if fmt == "ros1" else Header(stamp=stamp, frame_id="")
            msg = JointState(
                header=hdr,
                name=list(joints),
                position=q[k],
                velocity=v[k] if v is not None else np.zeros(0),
                effort=np.zeros(0),
            )
            raw = store.serialize_ros1(msg, js) if fmt == "ros1" else store.serialize_cdr(msg, js)
            writer.write(conn, ns, raw)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("log")
    ap.add_argument("out")
    ap.add_argument("--format", choices=["mcap", "sqlite3", "ros1"], default="mcap")
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--hold", type=float, default=1.0)
    ap.add_argument("--move", type=float, default=0.6)
    ap.add_argument("--noise", type=float, default=2e-5)
    ap.add_argument("--velocities", action="store_true", help="publish velocities (else positions only)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    robot = RobotModel.from_file(a.model)
    lg = read_log(a.log, robot.joint_names)
    t, q, v = trajectory(lg.angles, a.rate, a.hold, a.move)
    rng = np.random.default_rng(a.seed)
    q = q + rng.normal(0.0, a.noise, q.shape)
    v = v + rng.normal(0.0, a.noise * a.rate * 0.1, v.shape) if a.velocities else None
    write_bag(Path(a.out), a.format, lg.joints, t, q, v)
    print(f"wrote {len(t)} JointState messages ({len(lg)} standstills, {t[-1]:.0f} s) -> {a.out}")


if __name__ == "__main__":
    main()
