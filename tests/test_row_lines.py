"""Rows of a log named by file and line in every message (``place1_b.csv line 7``), not by a count over
the files joined together."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.errors import LogError
from closedloop.io.logs import JointLog, check_angle_units, check_loop_column, read_log, read_loop_logs
from closedloop.validation.kfold import subset

JOINTS = ["j1", "j2"]


def _write(path, lines: list[str]):
    path.write_text("\n".join(lines) + "\n")
    return path


def test_rows_keep_the_file_line_they_were_read_from(tmp_path):
    f = _write(tmp_path / "log.csv", ["# a comment", "j1,j2", "0.1,0.2", "", "# between", "0.3,0.4", "0.5,0.6"])
    lg = read_log(f, JOINTS)
    assert len(lg) == 3
    assert [lg.where(i) for i in range(3)] == [f"{f} line 3", f"{f} line 6", f"{f} line 7"]


def test_a_bad_cell_is_named_by_its_line_in_the_file(tmp_path):
    f = _write(tmp_path / "log.csv", ["# recorded 2026-11-26", "j1,j2", "0.1,0.2", "", "0.3,abc"])
    with pytest.raises(LogError) as exc:
        read_log(f, JOINTS)
    assert str(exc.value).startswith(f"{f} line 5, column 'j2'")
    f = _write(tmp_path / "short.csv", ["j1,j2", "0.1,0.2", "0.3"])
    with pytest.raises(LogError, match=r"short.csv line 3 has 1 fields, the header has 2"):
        read_log(f, JOINTS)


def test_header_less_logs_count_every_line(tmp_path):
    f = _write(tmp_path / "raw.csv", ["0.1,0.2", "0.3,0.4"])
    lg = read_log(f, JOINTS, order=JOINTS)
    assert [lg.where(i) for i in range(2)] == [f"{f} line 1", f"{f} line 2"]


def test_rows_of_several_loop_files_are_named_by_their_own_file(tmp_path):
    a = _write(tmp_path / "front_h1.csv", ["j1,j2", "0.1,0.2", "0.3,0.4"])
    b = _write(tmp_path / "front_h2.csv", ["j1,j2", "# moved", "0.5,0.6", "0.7,0.8", "0.9,1.0"])
    lg = read_loop_logs([("h1", a), ("h2", b)], JOINTS)
    assert len(lg) == 5 and list(lg.loop) == ["h1", "h1", "h2", "h2", "h2"]
    assert lg.where(1) == f"{a} line 3"
    assert lg.where(2) == f"{b} line 3"  # not 'row 3' of the files joined
    assert lg.where(4) == f"{b} line 5"
    part = subset(lg, np.array([4, 0]))  # a k-fold training set keeps them
    assert [part.where(0), part.where(1)] == [f"{b} line 5", f"{a} line 2"]


def test_loop_column_and_unit_errors_name_the_line(tmp_path, panda):
    f = _write(tmp_path / "log.csv", ["j1,j2,loop", "0.1,0.2,front", "0.3,0.4,fornt"])
    lg = read_log(f, JOINTS)
    with pytest.raises(LogError, match=rf"^{f} line 3, column 'loop': no loop named 'fornt'"):
        check_loop_column(lg, ["front"])
    names = panda.joint_names
    deg = _write(tmp_path / "deg.csv", [",".join(names)] + [",".join(["0"] + ["100"] * (len(names) - 1))] * 3)
    with pytest.raises(LogError, match=rf"\({deg} line 2: 100\)"):
        check_angle_units(read_log(deg, names), panda, degrees=False)


def test_a_log_made_in_memory_is_named_by_row():
    lg = JointLog(JOINTS, np.zeros((3, 2)))
    assert lg.where(2) == "log row 3"


@pytest.fixture(scope="module")
def corrupted_log(tmp_path_factory, panda):
    """A weld log written with a comment line on top, its row 10 (0-based) corrupted by 0.03 rad."""
    from closedloop.loops import WeldLoop
    from closedloop.studies.truth import make_dataset

    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 60, np.random.default_rng(3)
    )
    theta = np.array(ds.readings, float)
    theta[10, 1] += 0.03
    path = tmp_path_factory.mktemp("rows") / "log.csv"
    JointLog(list(ds.joints), theta).write_csv(path)
    path.write_text("# bench 2, 26 Nov\n" + path.read_text())
    return path  # row 10: line 13 (comment, header, then rows 0..)


@pytest.mark.slow
@pytest.mark.parametrize(
    "robust, said",
    [
        ("auto", "rejected: {log} line 13 (loop fixture)"),
        ("cauchy", "note: suspect configuration: {log} line 13 (loop fixture)"),
    ],
)
def test_rejected_and_suspect_rows_are_named_by_file_and_line(corrupted_log, robust, said, capsys):
    from closedloop.assets.catalog import ROBOTS
    from closedloop.cli.main import main

    rc = main(
        [
            "calibrate",
            str(ROBOTS["panda"].path),
            str(corrupted_log),
            "--loop",
            "weld:frame=panda_hand,name=fixture",
            "--robust",
            robust,
            "--cv",
            "0",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert said.format(log=corrupted_log) in out, out
    assert "log row" not in out


def test_the_task_noise_of_several_loops_is_one_note():
    """Six loops with one pooled task-space noise: one sentence naming them, not six (the rig)."""
    from closedloop.estimate.variance import noise_notes

    names = ["place1_a", "place1_b", "place2_a", "place2_b", "place3_a", "place3_b"]
    summary = [
        {
            "loop": n,
            "task_sigma_m": 2.02e-4,
            "joint_sigma_m": 1.33e-5 + 3e-7 * k,
            "task_estimated": True,
            "task_pooled": True,
            "dominant": "task",
        }
        for k, n in enumerate(names)
    ]
    notes = noise_notes(summary)
    assert notes == [
        f"loops {', '.join(names)}: task-space noise 0.202 mm (estimated, one for the loops whose estimates "
        "agree) against 0.0133 to 0.0148 mm from the joint noise: the task noise dominates"
    ]
    summary[0] = summary[0] | {"task_sigma_m": 5e-4, "task_pooled": False}  # a loop with its own estimate
    notes = noise_notes(summary)
    assert len(notes) == 2 and notes[0].startswith(
        "loop place1_a: task-space noise 0.5 mm (estimated) against 0.0133 mm"
    )
    assert notes[1].startswith("loops place1_b, place2_a, place2_b, place3_a, place3_b: task-space noise 0.202 mm")


def test_a_log_in_radians_given_degrees_is_refused(tmp_path, panda):
    """Radians read as degrees shrink every range by 57: no revolute joint moves 0.05 rad any more."""
    names = panda.joint_names
    rng = np.random.default_rng(0)
    rows = rng.uniform(-1.0, 1.0, (20, len(names)))  # radians, up to 2 rad of range per joint
    f = _write(tmp_path / "rad.csv", [",".join(names)] + [",".join(f"{v:.6f}" for v in r) for r in rows])
    with pytest.raises(LogError, match=r"with --degrees no revolute joint moves more than 0\.0[0-9]+ rad.*radians\?"):
        check_angle_units(read_log(f, names, degrees=True), panda, degrees=True)
    check_angle_units(read_log(f, names), panda)  # the same log in radians passes
    deg = _write(tmp_path / "deg.csv", [",".join(names)] + [",".join(f"{v:.4f}" for v in np.degrees(r)) for r in rows])
    check_angle_units(read_log(deg, names, degrees=True), panda, degrees=True)  # and in degrees with --degrees
