"""What a rig calibration prints and reports (leftovers): configurations without distance rows, no
held-out line for a distance, shared loop groups not among the robot's corrections, a shared camera's K."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import example_robot_data_dir
from closedloop.cli.calibrate import print_summary
from closedloop.io.camera_info import camera_infos_from_result
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop
from closedloop.output.html import robot_corrections
from closedloop.problem.distances import DistanceLoop

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rig_result(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("ball_socket_rig", ROOT / "examples" / "ball_socket_rig.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("ball_socket_rig", mod)
    spec.loader.exec_module(mod)
    rig = mod.make_rig(seed=1, n=20, places=3, sigma_task=2e-4, sigma_q=2e-5)
    tmp = tmp_path_factory.mktemp("rig")
    (tmp / "nominal.urdf").write_text(rig.nominal)
    robot = RobotModel.from_file(tmp / "nominal.urdf")
    names = rig.loop_names()
    n = rig.readings[names[0]].shape[0]
    log = JointLog(rig.joints, np.vstack([rig.readings[k] for k in names]), None, np.repeat(names, n))
    loops = [parse_loop(f"point:frame=ball,name={k},tip=@ball", robot) for k in names]
    loops += [DistanceLoop(loops, f"place{p}_a.point", f"place{p}_b.point", 0.05) for p in (1, 2, 3)]
    return calibrate(robot, log, loops, CalibrationOptions()), names, len(log)


@pytest.mark.slow
def test_summary_counts_configurations_not_distance_rows(rig_result, capsys):
    res, names, n_rows = rig_result
    distances = [b.loop.name for b in res.problem.blocks if getattr(b.loop, "parameter_only", False)]
    used = n_rows - len(res.outliers.rejected)  # configurations in the final fit
    assert len(distances) == 3 and sum(r.n for r in res.fit.residuals_after) == used + 3
    cv = {"k": 5, "test": [{"loop": k, "rms_m": 2e-4} for k in names + distances]}
    print_summary(res, 1.0, SimpleNamespace(out=None, report=None), {"validation": cv})
    out = capsys.readouterr().out
    assert f"parameters from {used} configurations" in out
    held = [ln for ln in out.splitlines() if "5-fold validation" in ln]
    assert len(held) == len(names) and not any(d in ln for d in distances for ln in held)


@pytest.mark.slow
def test_shared_ball_is_not_a_robot_correction(rig_result):
    res, _, _ = rig_result
    tips = [res.fit.names.index(f"ball.tip_{a}") for a in "xyz"]
    assert all(res.fit.status[k] == "estimated" for k in tips)
    idx = robot_corrections(res)
    assert idx and not set(idx) & set(tips)
    assert all(k < res.problem.n_robot for k in idx)
    assert set(idx) == {k for k in res.fit.estimated if k < res.problem.n_robot}


def test_camera_info_of_a_camera_shared_with_a_group():
    robot = RobotModel.from_file(example_robot_data_dir() / "ur_description/urdf/ur5_robot.urdf")
    loop = parse_loop("camera:frame=tool0,name=c,cam1=@head,dist=k1", robot)
    K = {"fx": 610.0, "fy": 605.0, "cx": 321.0, "cy": 239.0, "k1": -0.12}
    names = [f"head.cam1.{f}" for f in K]
    infos = camera_infos_from_result(
        SimpleNamespace(fit=SimpleNamespace(names=names, values=np.array(list(K.values())))), loop
    )
    assert len(infos) == 1
    np.testing.assert_array_equal(infos[0].K, [610.0, 605.0, 321.0, 239.0])
    assert infos[0].D[0] == -0.12
