"""A day of logging through the command line: 100,000 configurations of the main job, in bounded memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest


@pytest.mark.slow
def test_100000_configurations_calibrate_within_2_gb(tmp_path):
    """The main job's 1,000 simulated configurations tiled to 100,000 with 1e-4 rad of fresh noise: the
    calibration ends ok with the noise it was given back (1e-4 rad), and its peak memory (the child's
    maximum resident set) stays under 2 GB (an N x N step would need 75 GB); the region validation's
    refits say the sample they trained on and that they started at the calibration's solution."""
    cli = [sys.executable, "-m", "closedloop.cli"]
    sim = tmp_path / "sim"
    subprocess.run(
        [*cli, "simulate", "panda_weld", "--n", "1000", "--seed", "1", "--out", str(sim), "--quiet"], check=True
    )
    header = (sim / "log.csv").read_text().splitlines()[0].split(",")
    cols = [i for i, h in enumerate(header) if h.startswith("panda_joint")]
    base = np.loadtxt(sim / "log.csv", delimiter=",", skiprows=1)[:, cols]
    th = np.tile(base, (100, 1)) + np.random.default_rng(0).normal(0.0, 1e-4, (100_000, len(cols)))
    log = tmp_path / "log.csv"
    np.savetxt(log, th, delimiter=",", header=",".join(header[i] for i in cols), comments="", fmt="%.17g")
    cmd = [*cli, "calibrate", str(sim / "nominal.urdf"), str(log), "--loop", "weld:frame=panda_hand_tcp,name=fixture"]
    cmd += ["--cv", "0", "--quiet", "--out", str(tmp_path / "cal.urdf"), "--report", str(tmp_path / "report.json")]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE)
    _, status, use = os.wait4(proc.pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, proc.stderr.read().decode() if proc.stderr else ""
    assert use.ru_maxrss * 1024 < 2 * 1024**3
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["verdict"]["status"] == "ok"
    assert report["noise"]["joint_sigma"] == pytest.approx(1e-4, rel=0.05)
    # the region validation's refits: each on an even sample of 4,096 training rows, started at the solution
    regions = report["accuracy"]["regions"]
    assert regions["train_rows"] == [4096] * regions["k"] and regions["test_rows"] == [4096] * regions["k"]
    assert all(regions["folds_warm"]) and all(regions["folds_converged"])
    assert 1e-4 < regions["test"][0]["rms_m"] < 1e-3  # a held-out closure of the noise's size (0.1-0.3 mm)
