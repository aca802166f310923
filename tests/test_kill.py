"""SIGKILL at random moments of `closedloop calibrate` and `closedloop simulate`: the output set is the old
one or the new one, never a mix, never a temporary file.

The old set is written first by a complete run; then runs that would write a different new set are
killed after a random delay drawn over the whole run (biased towards its end, where the files are
published).  After each kill every file is classified old / new by its content.  A few kills here
(`KILLS_*`); `benchmarks/kill_outputs.py` does 40.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

KILLS_CALIBRATE = 5
KILLS_SIMULATE = 5
WELD = "weld:frame=panda_hand,name=fixture"


def _run(args: list[str], kill_after: float | None = None, cwd: Path | None = None) -> tuple[int, float]:
    """Run the CLI; with `kill_after`, SIGKILL it then (if still running).  Returns (returncode, seconds)."""
    t0 = time.perf_counter()
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    p = subprocess.Popen(
        [sys.executable, "-m", "closedloop.cli.main", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        cwd=cwd,
        env=env,
    )
    if kill_after is not None:
        try:
            p.wait(timeout=kill_after)
        except subprocess.TimeoutExpired:
            p.send_signal(signal.SIGKILL)
    _, err = p.communicate()
    if kill_after is None:
        assert p.returncode == 0, err.decode()
    return p.returncode, time.perf_counter() - t0


def make_calibration_inputs(d: Path) -> tuple[Path, Path, Path]:
    """A mesh-free Panda and two 30-row weld logs (different truths: different calibrated models)."""
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.loops import WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    d.mkdir(parents=True, exist_ok=True)
    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(d / "panda.urdf")
    q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]
    for name, seed in (("old.csv", 5), ("new.csv", 6)):
        ds = make_dataset(
            robot,
            WeldLoop("fixture", "panda_hand"),
            q0,
            30,
            np.random.default_rng(seed),
            perturb=["panda_joint2.x", "panda_joint3.offset", "panda_joint4.y"],
        )
        ds.log().write_csv(d / name)
    return d / "panda.urdf", d / "old.csv", d / "new.csv"


def _numbers(data: bytes) -> np.ndarray:
    return np.array([float(t) for t in re.findall(rb"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?", data)])


def classify(data: bytes, refs: dict[str, bytes]) -> str:
    """'old' or 'new': the reference whose numbers `data` matches (same count, nearest values); else 'other'.

    (By numbers rather than bytes: a torn file has fewer numbers, and the last digits of a simulation
    need not repeat across machines.)
    """
    x = _numbers(data)
    dist = {
        k: float(np.max(np.abs(x - _numbers(r)), initial=0.0)) for k, r in refs.items() if _numbers(r).shape == x.shape
    }
    if not dist:
        return "other"
    best = min(dist, key=dist.get)
    others = [v for k, v in dist.items() if k != best]
    return best if not others or dist[best] <= 0.01 * min(others) else "other"


def _classify_file(path: Path, refs: dict[str, bytes]) -> str:
    """A report by the log it names (its timings differ run to run), any other file by its numbers."""
    if not path.exists():
        return "missing"
    data = path.read_bytes()
    if path.name == "report.json":
        try:
            log = json.loads(data)["log"]  # a torn report does not parse
        except (ValueError, KeyError):
            return "other"
        return next((k for k, r in refs.items() if json.loads(r)["log"] == log), "other")
    return classify(data, refs)


def _publish_states(out: Path, names: tuple[str, ...], refs: dict[str, dict[str, bytes]]) -> dict:
    """Each file of the set classified old/new, and any other name in the directory (a temporary).

    (A dataset's nominal.urdf is the same in both sets: present, not classified.)
    """
    st = {n: _classify_file(out / n, {k: r[n] for k, r in refs.items()}) for n in names}
    st["stray"] = sorted(p.name for p in out.iterdir() if p.name not in names and p.name != "nominal.urdf")
    return st


def _kill_runs(out: Path, names: tuple[str, ...], args, kills: int, rng: np.random.Generator) -> list[dict]:
    """References for the two sets ('a', 'b'), then runs writing the set not in place, each killed at a random
    moment (uniform over 0.5..1.1 of a full run: most fall in the computation, some at publishing), until
    `kills` runs died by SIGKILL (at most 3 * kills runs; a run that finished first leaves the new set)."""
    refs, seconds = {}, 0.0
    for tag in ("b", "a"):  # set 'a' is in place after this
        _, seconds = _run(args(tag))
        refs[tag] = {n: (out / n).read_bytes() for n in names}
    in_place, states = "a", []
    while sum(st["returncode"] == -signal.SIGKILL for st in states) < kills and len(states) < 3 * kills:
        target = "b" if in_place == "a" else "a"
        rc, elapsed = _run(args(target), kill_after=float(rng.uniform(0.5, 1.1)) * seconds)
        if rc == 0:  # it finished first: follow the machine's speed
            seconds = 0.5 * (seconds + elapsed)
        st = _publish_states(out, names, refs)
        tags = {st[n] for n in names}
        st.update(returncode=rc, old=in_place, new=target)
        states.append(st)
        if tags == {target}:
            in_place = target
    return states


def kill_calibrate(work: Path, kills: int, rng: np.random.Generator) -> list[dict]:
    """`kills` SIGKILLs of calibrate (--out and --report) over an existing output set."""
    model, log_a, log_b = make_calibration_inputs(work / "in")
    out = work / "out"

    def args(tag: str) -> list[str]:
        return [
            "calibrate",
            str(model),
            str(log_a if tag == "a" else log_b),
            "--loop",
            WELD,
            "--quiet",
            "--cv",
            "0",
            "--out",
            str(out / "cal.urdf"),
            "--report",
            str(out / "report.json"),
        ]

    return _kill_runs(out, ("cal.urdf", "cal.sensors.yaml", "report.json"), args, kills, rng)


def kill_simulate(work: Path, kills: int, rng: np.random.Generator) -> list[dict]:
    """`kills` SIGKILLs of `simulate --replace` over an existing dataset (seeds 1 and 2)."""
    out = work / "sim"

    def args(tag: str) -> list[str]:
        return [
            "simulate",
            "panda_weld",
            "--n",
            "3",
            "--seed",
            "1" if tag == "a" else "2",
            "--out",
            str(out),
            "--quiet",
            "--replace",
        ]

    return _kill_runs(out, ("scene.xml", "log.csv", "truth.json"), args, kills, rng)


def whole(state: dict) -> bool:
    """Every file of the set the old one or every one the new one; nothing else in the directory."""
    tags = {v for k, v in state.items() if k not in ("returncode", "stray", "old", "new")}
    return len(tags) == 1 and tags <= {state["old"], state["new"]} and not state["stray"]


def test_classify_tells_sets_and_torn_files_apart():
    a, b = b"x,y\n0.1,0.2\n0.3,0.4\n", b"x,y\n0.5,0.2\n0.3,0.9\n"
    refs = {"a": a, "b": b}
    assert classify(a, refs) == "a" and classify(b, refs) == "b"
    assert classify(a[:-5], refs) == "other" and classify(b"x,y\n0.1,0.2\n0.3,0.9\n", refs) == "other"


@pytest.mark.slow
@pytest.mark.parametrize("which", ["calibrate", "simulate"])
def test_sigkill_leaves_old_or_new_set(which, tmp_path):
    rng = np.random.default_rng(13)
    states = (
        kill_calibrate(tmp_path, KILLS_CALIBRATE, rng)
        if which == "calibrate"
        else kill_simulate(tmp_path, KILLS_SIMULATE, rng)
    )
    assert all(whole(s) for s in states), states
    assert any(s["returncode"] == -signal.SIGKILL for s in states), states  # the kills are real
