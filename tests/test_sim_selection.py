"""Pose selection in the simulator (setting ``select``, closedloop.sims.selection).

The simulator walks the nominal self-motion for a pool of 10 n candidates,
chooses n with closedloop.design.poses.select_poses on the nominal model, and drives
the robot through them.  Compared here with the default (the planner's
waypoints), same scenario, seed and n = 150, noise-free simulation; the
calibration is given a 1e-5 rad joint noise so that its covariance measures the
design alone (with the noise estimated from the residual, it would also measure
how well each dataset's loop happens to close).

Measured, trace of ``res.fit.covariance`` default / ``greedy-a`` (A-optimal greedy):
ur5_socket (3-DOF self-motion) 5.9x, 2.9x, 5.4x on seeds 1-3; panda_weld
(1-DOF self-motion: little to choose from) 1.68x, 1.60x, 1.62x.  Asserted:
2x and 1.4x on seed 1, and both datasets calibrate to truth within the
scenario tolerances of test_sim_calibration.
"""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin
import pytest
from test_sim_calibration import CASES

from closedloop.assets.catalog import nominal_urdf
from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import read_log
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel
from closedloop.output.report import build_report
from closedloop.sims import SCENARIOS, simulate
from closedloop.sims.driver import NominalLoop
from closedloop.sims.selection import bridge, order_path
from closedloop.validation.check import check_report

N = 150
NOISE = 1e-5


def _calibrate(scenario, out):
    spec, tol_m, tol_rad, *_ = CASES[scenario]
    robot = RobotModel.from_file(out / "nominal.urdf")
    res = calibrate(
        robot, read_log(out / "log.csv", robot.joint_names), [parse_loop(spec, robot)], CalibrationOptions(noise=NOISE)
    )
    assert res.converged
    truth = json.loads((out / "truth.json").read_text())
    report = build_report(res)
    rows, ok = check_report(truth, report, tol_m=1e-3, tol_rad=5e-3, tol_scale=5e-3)
    assert ok, [r for r in rows if r["result"] == "FAIL"]
    for p in report["parameters"]:
        if p["status"] == "estimated" and p["kind"] in ("placement", "offset"):
            err = abs(p["calibrated"] - truth["parameters"].get(p["name"], 0.0))
            assert err < (tol_m if p["unit"] == "m" else tol_rad), (p["name"], err)
    return res, truth


# The Panda weld's gain was 1.6x while its length scale was held by a barely seen shoulder offset, whose
# variance selection shrank; with the scale held by the 0.316 m upper arm (closedloop.analysis.gauge) the default
# samples already determine the model about as well: selection must not be worse there.
@pytest.mark.slow
@pytest.mark.parametrize("scenario, factor", [("ur5_socket", 2.0), ("panda_weld", 1.0)])
def test_selected_samples_shrink_the_covariance(scenario, factor, tmp_path):
    default = simulate(scenario, N, 1, tmp_path / "default")
    selected = simulate(scenario, N, 1, tmp_path / "selected", select="greedy-a")
    assert len(default.readings) == len(selected.readings) == N
    res_d, truth_d = _calibrate(scenario, tmp_path / "default")
    res_s, truth_s = _calibrate(scenario, tmp_path / "selected")
    assert truth_d["parameters"] == truth_s["parameters"]  # same truth: only the samples differ
    assert [res_d.fit.names[i] for i in res_d.fit.estimated] == [res_s.fit.names[i] for i in res_s.fit.estimated]
    ratio = np.trace(res_d.fit.covariance) / np.trace(res_s.fit.covariance)
    assert ratio >= factor, ratio
    # the choice is recorded
    assert truth_d["settings"]["select"] is None and "selection" not in truth_d
    assert truth_s["settings"]["select"] == "greedy-a" and truth_s["settings"]["select_pool"] == 10.0
    sel = truth_s["selection"]
    assert sel["method"] == "greedy-a" and sel["pool"] == 10 * N and sel["chosen"] == N
    assert set(sel["parameters"]) <= set(res_s.fit.names)


def test_selection_is_deterministic(tmp_path):
    a = simulate("ur5_socket", 12, 5, tmp_path / "a", select="greedy", select_pool=5)
    b = simulate("ur5_socket", 12, 5, tmp_path / "b", select="greedy", select_pool=5)
    assert a.log_path.read_bytes() == b.log_path.read_bytes()
    assert a.truth_path.read_text() == b.truth_path.read_text()
    assert a.truth["selection"]["pool"] == 60 and "select_s" in a.extra


def test_order_path_is_a_nearest_neighbour_tour():
    pts = np.array([[3.0], [1.0], [2.0], [-1.0]])
    np.testing.assert_array_equal(order_path(pts, np.array([0.0])), [1, 2, 0, 3])
    assert order_path(np.zeros((0, 2)), np.zeros(2)).size == 0


def test_bridge_stays_on_the_nominal_loop():
    sc = SCENARIOS["panda_weld"]
    model = pin.buildModelFromXML(nominal_urdf(sc.robot))
    q0 = np.array(sc.q0)
    loop = NominalLoop(model, sc.tool_frame, sc.loop_type, q0)
    # a far configuration on the same nominal loop: follow the self-motion (null vector) and project
    q, prev = q0.copy(), np.ones(7)
    for _ in range(12):
        _e, jac = loop.residual(q)
        v = np.linalg.svd(jac)[2][-1]
        prev = v if v @ prev > 0 else -v
        q = loop.project(q + 0.1 * prev)
    assert np.max(np.abs(q - q0)) > 0.4
    path = bridge(loop, q0, q, 0.1)
    assert len(path) >= 3
    for w in path:
        assert np.linalg.norm(loop.residual(w)[0]) < 1e-6
    steps = np.diff(np.vstack([q0, *path, q]), axis=0)
    assert np.max(np.abs(steps)) < 0.15
    assert bridge(loop, q0, q0 + 0.01, 0.1) == [] and bridge(None, q0, q, 0.1) == []
