"""The command line loads what its run needs: the parser of its own subcommand, no figure library without
--html/--plots, no simulator, no fleet code (timings: benchmarks/bench_cli.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.studies.truth import make_dataset

WATCHED = (
    "matplotlib",
    "closedloop.output.html",
    "closedloop.fleet",
    "closedloop.cli.impedance",
    "closedloop.impedance",
    "closedloop.sims",
    "mujoco",
    "closedloop.io.bags",
)

RUN = """
import json, sys
from closedloop.cli.main import main
rc = main(sys.argv[2:])
with open(sys.argv[1], "w") as fh:
    json.dump({"rc": rc, "modules": sorted(sys.modules)}, fh)
"""


def _loaded(tmp_path, *argv: str) -> tuple[int, list[str], list[str]]:
    """The exit code, the `WATCHED` modules a fresh interpreter running `closedloop *argv` loaded, and every
    module it loaded."""
    out = tmp_path / "modules.json"
    p = subprocess.run([sys.executable, "-c", RUN, str(out), *argv], capture_output=True, text=True, timeout=600)
    assert out.exists(), p.stderr
    res = json.loads(out.read_text())
    return res["rc"], [m for m in res["modules"] if m.startswith(WATCHED)], res["modules"]


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    from closedloop.model.robot import RobotModel

    robot = RobotModel.from_file(ROBOTS["panda"].path)
    ds = make_dataset(
        robot, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 30, np.random.default_rng(2)
    )
    path = tmp_path_factory.mktemp("startup") / "log.csv"
    JointLog(list(ds.joints), ds.readings).write_csv(path)
    return path


def test_calibrate_loads_no_figure_library_simulator_or_fleet_code(log, tmp_path):
    """Not vacuous: the list the run reports holds the calibration code it did load."""
    rc, mods, every = _loaded(
        tmp_path,
        "calibrate",
        str(ROBOTS["panda"].path),
        str(log),
        "--loop",
        "weld:frame=panda_hand,name=fixture",
        "--report",
        str(tmp_path / "r.json"),
        "--cv",
        "0",
        "--quiet",
    )
    assert rc == 0
    assert json.loads((tmp_path / "r.json").read_text())["verdict"]["status"] in ("ok", "suspect")
    assert mods == [], mods
    assert {"closedloop.cli.calibrate", "closedloop.calibration.pipeline", "numpy", "pinocchio"} <= set(every)


@pytest.mark.slow  # the watched list's own check is the test above's; --html's page: test_html_report.py
def test_calibrate_with_html_loads_the_figure_code(log, tmp_path):
    """The figure code is loaded where the run needs it: --html loads matplotlib and the page's writer."""
    pytest.importorskip("matplotlib")
    rc, mods, _ = _loaded(
        tmp_path,
        "calibrate",
        str(ROBOTS["panda"].path),
        str(log),
        "--loop",
        "weld:frame=panda_hand,name=fixture",
        "--html",
        str(tmp_path / "r.html"),
        "--cv",
        "0",
        "--regions",
        "0",
        "--quiet",
    )
    assert rc == 0 and (tmp_path / "r.html").stat().st_size > 10_000
    assert "matplotlib" in mods and "closedloop.output.html" in mods


def test_top_level_help_still_lists_every_subcommand(tmp_path):
    p = subprocess.run(
        [sys.executable, "-m", "closedloop.cli.main", "--help"], capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0
    for cmd, words in (("calibrate", "calibrate a model"), ("batch", "manifest"), ("impedance", "impedance")):
        line = next(ln for ln in p.stdout.splitlines() if ln.strip().startswith(cmd + " "))
        assert words in line, line
