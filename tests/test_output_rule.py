"""The output rule of every command (closedloop.io.files): an input is never overwritten, a device or a
named pipe is written into (never replaced), a full disk leaves the old files and no partial one."""

from __future__ import annotations

import errno
import os
import stat
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest

from closedloop.cli.main import main
from closedloop.errors import InputError
from closedloop.io.files import OutputSet, atomic_write_text, check_outputs, note_input, same_file, track_inputs

WELD = "weld:frame=panda_hand,name=fixture"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A mesh-free Panda and a 30-row weld log."""
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.loops import WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    d = tmp_path_factory.mktemp("rule")
    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(d / "panda.urdf")
    ds = make_dataset(
        robot, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 30, np.random.default_rng(5)
    )
    ds.log().write_csv(d / "log.csv")
    return d / "panda.urdf", d / "log.csv"


def calibrate(urdf: Path, log: Path, *extra: str) -> list[str]:
    return ["calibrate", str(urdf), str(log), "--loop", WELD, "--quiet", "--cv", "0", "--regions", "0", *extra]


def test_same_file_by_inode(tmp_path):
    a = tmp_path / "a.csv"
    a.write_text("x")
    os.link(a, tmp_path / "hard.csv")
    (tmp_path / "sym.csv").symlink_to(a)
    assert same_file(a, tmp_path / "hard.csv") and same_file(tmp_path / "sym.csv", a)
    assert same_file(tmp_path / "." / "a.csv", a)
    assert not same_file(a, tmp_path / "missing.csv")
    with pytest.raises(InputError, match=r"--report .*hard.csv: refusing to overwrite an input"):
        check_outputs({"--report": tmp_path / "hard.csv"}, [a])


def test_publication_refuses_a_noted_input_whatever_the_command(tmp_path):
    """The second guard: a reader noted the file as an input; an output set may not replace it."""
    a = tmp_path / "data.csv"
    a.write_text("input")
    os.link(a, tmp_path / "alias.csv")
    with track_inputs():
        note_input(a)
        with pytest.raises(InputError, match="refusing to overwrite an input of this run"):
            with OutputSet():
                atomic_write_text(tmp_path / "other.json", "fine")
                atomic_write_text(tmp_path / "alias.csv", "out")
    assert not (tmp_path / "other.json").exists()  # refused before anything was published
    assert a.read_text() == "input"
    atomic_write_text(tmp_path / "alias.csv", "out")  # outside a command's scope nothing is noted
    assert (tmp_path / "alias.csv").read_text() == "out" and a.read_text() == "input"  # a new file, not a write-through


def test_symlinked_output_updates_its_target(tmp_path):
    target = tmp_path / "real.json"
    target.write_text("old")
    (tmp_path / "link.json").symlink_to(target)
    atomic_write_text(tmp_path / "link.json", "new")
    assert (tmp_path / "link.json").is_symlink() and target.read_text() == "new"


def test_report_into_a_named_pipe_reaches_its_reader(files, tmp_path, capsys):
    urdf, log = files
    fifo = tmp_path / "report.fifo"
    os.mkfifo(fifo)
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    rc = main(calibrate(urdf, log, "--report", str(fifo)))
    reader.join(timeout=60)
    assert rc == 0, capsys.readouterr().err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still the pipe
    import json

    assert json.loads(got[0])["solver"]["status"] == "converged"  # the reader got the whole report


def test_report_onto_a_character_device_keeps_the_device(files, tmp_path, capsys):
    urdf, log = files
    dev = tmp_path / "null"
    try:
        os.mknod(dev, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # a /dev/null node of our own (root)
    except PermissionError:
        dev = Path("/dev/null")
    rc = main(calibrate(urdf, log, "--report", str(dev)))
    assert rc == 0, capsys.readouterr().err
    assert stat.S_ISCHR(os.stat(dev).st_mode)
    assert not list(tmp_path.glob(".closedloop-*"))


@pytest.fixture()
def small_disk(tmp_path, monkeypatch):
    """A 64 KiB file system (tmpfs, as root); else os.write fails with ENOSPC past 16 KiB per file.

    Yields (folder, how) with how 'tmpfs' or 'simulated'."""
    d = tmp_path / "disk"
    d.mkdir()
    mounted = (
        os.geteuid() == 0
        and subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)], capture_output=True).returncode
        == 0
    )
    if not mounted:
        import closedloop.io.files as f

        real = os.write
        written: dict[int, int] = {}

        def write(fd, data):
            written[fd] = written.get(fd, 0) + len(data)
            if written[fd] > 16384:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(fd, data)

        monkeypatch.setattr(f.os, "write", write)
    try:
        yield d, "tmpfs" if mounted else "simulated"
    finally:
        if mounted:
            subprocess.run(["umount", str(d)], check=True)


def test_full_disk_leaves_the_old_files_and_no_partial_one(files, small_disk, capsys):
    urdf, log = files
    d, how = small_disk
    old = '{"old": "' + "x" * 40000 + '"}'  # 40 kB: the new report (35 kB) and model do not fit beside it
    (d / "r.json").write_text(old)
    rc = main(calibrate(urdf, log, "--report", str(d / "r.json"), "--out", str(d / "cal.urdf")))
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, (how, err)
    assert "No space left on device" in err and str(d) in err
    assert (d / "r.json").read_text() == old  # the old report, whole
    assert sorted(p.name for p in d.iterdir()) == ["r.json"]  # no new model, no temporary
