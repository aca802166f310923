"""Ctrl-C and SIGTERM at any moment of a command, its imports included: one line, exit 130 (143 for
SIGTERM), the previous outputs intact, no temporary left.  And a batch on a 2-worker pool killed with
SIGKILL, SIGINT or SIGTERM while its jobs run leaves no process behind and no half-written job folder.

The Ctrl-C sweep sends its signal once `main` has taken over the signals (the child's SIGTERM disposition is
caught: /proc/PID/status), then after a delay drawn over the whole run: while the numerical libraries load, in
the fit, at publication, or after the end (either outcome is checked).  (Before that, within the interpreter's
own start, Ctrl-C is Python's.)  The tests that must interrupt the work itself wait until the process says it
is running (`closedloop.io.marker`: the line `calibrate` in the file named by CLOSEDLOOP_RUNNING_MARKER), never
for a fixed time that a faster or slower machine outruns.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from closedloop.io.marker import RUNNING_MARKER

WELD = "weld:frame=panda_hand,name=fixture"


def _caught(pid: int, sig: int) -> bool:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("SigCgt:"):
                return bool(int(line.split()[1], 16) >> (sig - 1) & 1)
    except OSError:
        pass
    return False


def _start(args: list[str], cwd: Path, marker: Path | None = None) -> subprocess.Popen:
    """The CLI in its own process group, SIGINT at its default (a background job would inherit SIG_IGN);
    with `marker`, the file it marks its work in (`closedloop.io.marker`)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    if marker is not None:
        env[RUNNING_MARKER] = str(marker)
    return subprocess.Popen(
        [sys.executable, "-m", "closedloop.cli.main", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=env,
        preexec_fn=lambda: (os.setpgid(0, 0), signal.signal(signal.SIGINT, signal.SIG_DFL)),
    )


def _marked(marker: Path, what: str) -> bool:
    try:
        return what in marker.read_text().split()
    except OSError:
        return False


def _wait_for_mark(p: subprocess.Popen, marker: Path, what: str, timeout: float = 300.0) -> None:
    """Until the process has marked `what` (its work is running): generous, a loaded machine is slow."""
    t0 = time.monotonic()
    while not _marked(marker, what):
        assert p.poll() is None, f"the command ended before marking {what!r}: {p.stderr.read() if p.stderr else ''}"
        assert time.monotonic() - t0 < timeout, f"the command never marked {what!r} within {timeout} s"
        time.sleep(0.002)


def _wait_for_main(p: subprocess.Popen, timeout: float = 30.0) -> None:
    t0 = time.monotonic()
    while not _caught(p.pid, signal.SIGTERM):
        assert p.poll() is None and time.monotonic() - t0 < timeout, "the command never reached main()"
        time.sleep(0.002)


def test_running_marker_appends_a_line_only_when_asked(tmp_path, monkeypatch):
    """`mark_running` appends its line to the file the environment names (several marks, several lines, the file
    never truncated), and writes nothing where the variable is unset."""
    from closedloop.io.marker import mark_running

    marker = tmp_path / "running"
    monkeypatch.delenv(RUNNING_MARKER, raising=False)
    mark_running("calibrate")
    assert not marker.exists()
    marker.write_text("before\n")
    monkeypatch.setenv(RUNNING_MARKER, str(marker))
    mark_running("calibrate")
    mark_running("simulate")
    assert marker.read_text() == "before\ncalibrate\nsimulate\n"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, panda_weld):
    """A mesh-free Panda and a 200-row weld log (a calibration of a few seconds): the suite's Panda weld
    (conftest `panda_weld`, computed once per worker)."""
    from closedloop.assets.catalog import nominal_urdf

    d = tmp_path_factory.mktemp("signals")
    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    panda_weld.log().write_csv(d / "log.csv")
    return d


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.2, 0.6, 1.5, 3.0])
def test_ctrl_c_during_calibrate_imports_included(inputs, tmp_path, delay):
    old = '{"old": true}\n'
    (tmp_path / "r.json").write_text(old)
    args = ["calibrate", str(inputs / "panda.urdf"), str(inputs / "log.csv"), "--loop", WELD, "--quiet"]
    p = _start(args + ["--report", str(tmp_path / "r.json"), "--cv", "5"], tmp_path)
    _wait_for_main(p)
    time.sleep(delay)
    os.killpg(p.pid, signal.SIGINT)  # as Ctrl-C: the whole process group
    _, err = p.communicate(timeout=120)
    if p.returncode == 0:  # finished first: the new report, whole
        assert json.loads((tmp_path / "r.json").read_text())["solver"]["status"] == "converged"
    else:
        assert p.returncode == 130, err
        assert err.strip().splitlines() == ["interrupted; outputs not yet published were discarded"], err
        assert (tmp_path / "r.json").read_text() == old
    assert sorted(q.name for q in tmp_path.iterdir()) == ["r.json"]


def test_sigterm_during_calibrate(inputs, tmp_path):
    old = '{"old": true}\n'
    (tmp_path / "r.json").write_text(old)
    args = ["calibrate", str(inputs / "panda.urdf"), str(inputs / "log.csv"), "--loop", WELD, "--quiet"]
    marker = tmp_path / "running"
    p = _start(args + ["--report", str(tmp_path / "r.json"), "--cv", "5"], tmp_path, marker)
    _wait_for_mark(p, marker, "calibrate")  # in the fit (the fit and 5 folds still to go)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    assert err.strip().splitlines() == ["interrupted (signal 15); outputs not yet published were discarded"]
    assert (tmp_path / "r.json").read_text() == old


# ----------------------------------------------------------------------------- batch with workers
def _descendants(pid: int) -> set[int]:
    from closedloop.fleet.batch import descendants

    return set(descendants(pid))


def _alive(pids: set[int]) -> list[int]:
    out = []
    for q in pids:
        try:
            if Path(f"/proc/{q}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.append(q)
        except OSError:
            pass
    return out


@pytest.fixture(scope="module")
def fleet(inputs, tmp_path_factory):
    """Four jobs of a few seconds each (200 rows, 10 folds)."""
    d = tmp_path_factory.mktemp("fleet")
    jobs = [{"name": f"j{i}", "out": f"out/j{i}"} for i in range(4)]
    doc = {
        "defaults": {"model": str(inputs / "panda.urdf"), "log": str(inputs / "log.csv"), "loops": [WELD], "cv": 10},
        "jobs": jobs,
    }
    (d / "m.yaml").write_text(yaml.safe_dump(doc))
    return d / "m.yaml"


@pytest.mark.slow
@pytest.mark.parametrize("how", ["SIGKILL", "SIGINT-group", "SIGTERM"])
def test_killed_batch_leaves_no_process_and_no_half_job(fleet, tmp_path, how):
    m = tmp_path / "m.yaml"
    m.write_text(fleet.read_text())
    err_file = tmp_path / "err.txt"
    marker = tmp_path / "running"
    with err_file.open("w") as err:
        p = subprocess.Popen(
            [sys.executable, "-m", "closedloop.cli.main", "batch", str(m), "--jobs", "2", "--quiet"],
            stdout=subprocess.DEVNULL,
            stderr=err,  # (a pipe would be held open by a leftover worker: a file tells no lies)
            cwd=tmp_path,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1", RUNNING_MARKER: str(marker)},
            preexec_fn=lambda: (os.setpgid(0, 0), signal.signal(signal.SIGINT, signal.SIG_DFL)),
        )
        seen: set[int] = set()
        t0 = time.monotonic()
        # until a worker has started a job's fit (`closedloop.io.marker`) and the pool is up (the fork server and 2
        # workers, and the resource tracker); a worker may still be starting: the rest is collected as it shows
        while time.monotonic() - t0 < 300 and not (_marked(marker, "calibrate") and len(seen) >= 3):
            assert p.poll() is None, "the batch ended before a job was running"
            seen |= _descendants(p.pid)
            time.sleep(0.01)
        assert _marked(marker, "calibrate") and len(seen) >= 3, f"no job running after 300 s ({len(seen)} processes)"
        assert not (tmp_path / "out").exists() or not any(
            (q / "done.json").exists() for q in (tmp_path / "out").iterdir()
        ), "a job finished before the signal: the jobs are too short to interrupt"
        seen |= _descendants(p.pid)
        sig = getattr(signal, how.split("-")[0])
        os.killpg(p.pid, sig) if how.endswith("group") else p.send_signal(sig)
        p.wait(timeout=60)
    out = tmp_path / "out"
    folders = sorted(q.name for q in out.iterdir()) if out.exists() else []
    t0 = time.monotonic()
    while _alive(seen) and time.monotonic() - t0 < 60:  # the workers end on their own (within milliseconds here)
        time.sleep(0.01)
    assert _alive(seen) == [], f"{how}: processes left: {_alive(seen)}"
    assert (sorted(q.name for q in out.iterdir()) if out.exists() else []) == folders  # no job finished after
    err_text = err_file.read_text()
    if how == "SIGKILL":
        assert p.returncode == -signal.SIGKILL
    else:
        assert p.returncode == (130 if how.startswith("SIGINT") else 143), err_text
        assert err_text.strip().splitlines() == [
            "interrupted" + (" (signal 15)" if how == "SIGTERM" else "") + "; outputs not yet published were discarded"
        ], err_text
    for job in folders:  # a job folder is whole (with its marker), never half written
        assert job.startswith(".") or (out / job / "done.json").exists(), job
