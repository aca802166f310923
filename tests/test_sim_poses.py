"""Recording given configurations in the simulator (``closedloop simulate --poses FILE``) and keeping
suggested configurations away from the joint stops (`closedloop.design.next_poses.inside_limits`).

The poses are played on the seed's true robot at the seed's fixture: the loop `calibrate --suggest`
asks for is the one the first dataset was recorded at, so its rows can be appended to that log."""

from __future__ import annotations

import json

import numpy as np

from closedloop.cli.main import main
from closedloop.design.next_poses import LIMIT_MARGIN, inside_limits
from closedloop.sims import simulate

SEED, NOISE = 2, 1e-4


def _table(path):
    lines = path.read_text().splitlines()
    return lines[0].split(","), np.array([[float(v) for v in row.split(",")] for row in lines[1:]])


def test_poses_are_recorded_on_the_seeds_robot_at_its_fixture(tmp_path, capsys):
    """Three readings of a UR5 socket dataset, in reverse order, played with `simulate --poses` and the
    same seed: the same true robot, each configuration recorded at the seed's socket (the true closure
    within 1e-5 m, as the planner's are; another socket would be centimetres away) and near the reading
    commanded, in a log with the first one's header (rows to append to it)."""
    first = simulate("ur5_socket", 3, SEED, tmp_path / "first", noise=NOISE)
    asked = first.readings[::-1]
    poses = tmp_path / "next.csv"
    poses.write_text(",".join(first.joint_names) + "\n" + "\n".join(",".join(f"{v:.12g}" for v in r) for r in asked))
    out_dir = tmp_path / "next"
    argv = ["simulate", "ur5_socket", "--seed", str(SEED), "--set", f"noise={NOISE}", "--poses", str(poses)]
    rc = main([*argv, "--out", str(out_dir)])
    out = capsys.readouterr().out
    assert rc == 0 and out.startswith("simulated 3 configurations of ur5_socket in ")
    assert f"closedloop check {out_dir / 'truth.json'}" in out
    assert f"  append:    (cat LOG; tail -n +2 {out_dir / 'log.csv'}) > more.csv   (LOG: the log of the seed-2" in out
    truth = json.loads((out_dir / "truth.json").read_text())
    assert truth["parameters"] == first.truth["parameters"]  # the seed's true robot
    assert truth["poses"]["configurations"] == 3
    header, table = _table(out_dir / "log.csv")
    assert header == _table(first.log_path)[0]
    readings = table[:, [header.index(j) for j in first.joint_names]]
    assert np.all(table[:, header.index("violation_m")] < 1e-5)  # at the seed's socket
    assert np.all(np.abs(readings - asked) < 0.03)  # settled near what was commanded


def test_suggested_readings_keep_off_the_joint_stops():
    """A reading 1 mrad inside a limit is not suggested (the robot may not reach it, or rests on the stop);
    0.15 rad inside is; a 4 cm prismatic travel keeps all but 4 mm at each end."""
    lo, hi = np.array([-2.0, 0.0]), np.array([2.0, 0.04])
    X = np.array(
        [
            [-2.0 + 1e-3, 0.02],
            [2.0 - 0.15, 0.02],
            [0.0, 0.003],
            [0.0, 0.0365],
            [-2.0 + LIMIT_MARGIN, 0.0045],
        ]
    )
    assert inside_limits(X, lo, hi).tolist() == [False, True, False, False, True]


def test_rows_not_recorded_are_named_by_file_and_line():
    """A pose the robot ended at a joint limit at, and one it did not come to rest at, are named by the line
    of the file they were read from, with why."""
    from closedloop.sims.dataset import _poses_shortfall
    from closedloop.sims.tracking import Recording

    rec = Recording.empty(4, 2, False, False)
    rec.done, rec.dropped, rec.unsettled = 2, 2, 1
    rec.dropped_at, rec.at_limit = [1, 3], {"knee": 1}
    where = [f"next.csv line {i + 2}" for i in range(4)]
    said = _poses_shortfall(rec, where, 300)
    assert said.startswith("next.csv line 3, next.csv line 5 not recorded (it ended at a joint limit (knee)")
    assert "did not come to rest within max_steps=300 steps" in said and "try --set max_steps=1200" in said
    rec.dropped_at = []
    assert _poses_shortfall(rec, where, 300) == ""


def test_a_pose_the_robot_comes_to_rest_away_from_is_not_recorded(tmp_path, capsys):
    """A reading off the seed's loop (a UR5 socket's second configuration with its shoulder turned 0.6 rad):
    the robot, commanded there, comes to rest elsewhere on the loop, more than `POSE_STRAY` from it on some
    joint.  That row is another configuration than the one asked for: not recorded, named by its line with
    why, exit 3; the rows recorded lie within `POSE_STRAY` of their readings."""
    from closedloop.sims.dataset import POSE_STRAY

    first = simulate("ur5_socket", 3, SEED, tmp_path / "first", noise=NOISE)
    asked = first.readings.copy()
    asked[1, 1] += 0.6
    poses = tmp_path / "next.csv"
    poses.write_text(",".join(first.joint_names) + "\n" + "\n".join(",".join(f"{v:.12g}" for v in r) for r in asked))
    out_dir = tmp_path / "next"
    argv = ["simulate", "ur5_socket", "--seed", str(SEED), "--set", f"noise={NOISE}", "--poses", str(poses)]
    assert main([*argv, "--out", str(out_dir)]) == 3
    err = capsys.readouterr().err
    assert f"{poses} line 3 not recorded (1 came to rest up to " in err and "from the reading asked" in err, err
    header, table = _table(out_dir / "log.csv")
    got = table[:, [header.index(j) for j in first.joint_names]]
    assert got.shape == (2, len(first.joint_names))
    assert np.max(np.abs(got - asked[[0, 2]])) < POSE_STRAY
