"""Loops keep no per-dataset state: measurements are arguments, noise estimates stay in the problem."""

from __future__ import annotations

import copy
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import example_robot_data_dir
from closedloop.calibration.pipeline import build_problem
from closedloop.errors import LoopError
from closedloop.io.logs import JointLog
from closedloop.loops.measured import MeasuredPointLoop
from closedloop.loops.spec import parse_loop
from closedloop.studies.truth import draw_truth

ROOT = Path(__file__).resolve().parents[1]
X_TRUE = pin.SE3(pin.exp3(np.array([0.1, -0.2, 0.3])), np.array([0.8, -0.3, 0.2]))
TIP_TRUE = np.array([0.01, -0.02, 0.12])


def _rig():
    spec = importlib.util.spec_from_file_location("ball_socket_rig", ROOT / "examples" / "ball_socket_rig.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("ball_socket_rig", mod)
    spec.loader.exec_module(mod)
    return mod


def _state(loop) -> dict:
    """Every attribute of a loop, arrays and poses as plain numbers (for an exact comparison)."""
    out = {}
    for k, v in vars(loop).items():
        if isinstance(v, pin.SE3):
            v = v.homogeneous
        out[k] = np.asarray(v).tolist() if isinstance(v, np.ndarray) or isinstance(v, pin.SE3) else copy.deepcopy(v)
    return out


@pytest.mark.slow
def test_calibrate_twice_same_loops_same_result(tmp_path):
    """Six point loops sharing a ball, task-space noise estimated per loop: two calls give the same numbers
    and leave the loops as they were (the estimated noise is in the result's problem, not on the loops)."""
    rigmod = _rig()
    rig = rigmod.make_rig(seed=0, n=20, places=3, sigma_task=2e-4, sigma_q=2e-5)
    (tmp_path / "nominal.urdf").write_text(rig.nominal)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    names = rig.loop_names()
    n = rig.readings[names[0]].shape[0]
    log = JointLog(rig.joints, np.vstack([rig.readings[k] for k in names]), None, np.repeat(names, n))
    loops = [parse_loop(f"point:frame=ball,name={k},tip=@ball", robot) for k in names]
    before = [_state(lp) for lp in loops]
    first = calibrate(robot, log, loops, CalibrationOptions())
    assert [_state(lp) for lp in loops] == before
    assert not any(hasattr(lp, a) for lp in loops for a in ("task_var", "task_estimated", "own_cov", "meas"))
    second = calibrate(robot, log, loops, CalibrationOptions())
    assert np.array_equal(first.fit.values, second.fit.values)
    assert first.noise.noise_model == second.noise.noise_model
    # the play is estimated (a variance component) in both calls, per loop, near the simulated 0.2 mm
    assert all(d["task_estimated"] for d in first.noise.noise_model)
    sig = np.array([d["task_sigma_m"] for d in first.noise.noise_model])
    assert sig.size == len(names) and np.all(np.abs(sig / 2e-4 - 1.0) < 0.35), sig
    assert all(nz.estimated for nz in first.problem.noise)


def _measured_log(seed: int = 3, n: int = 40, sigma_t: float = 2e-5):
    robot = RobotModel.from_file(example_robot_data_dir() / "ur_description/urdf/ur5_robot.urdf")
    joints = robot.supporting_joints("tool0")
    rng = np.random.default_rng(seed)
    th = rng.uniform(-1.5, 1.5, (n, 6))
    cols = [f"m:{a}" for a in "xyz"]
    zeros = {c: np.zeros(n) for c in cols}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    truth = prob.nominal
    for k, v in draw_truth(
        robot,
        [
            "shoulder_lift_joint.offset",
            "elbow_joint.offset",
            "wrist_1_joint.offset",
            "elbow_joint.x",
            "wrist_1_joint.y",
        ],
        rng,
    ).items():
        truth[prob.index[k]] = v
    TA, TB = prob.loop_poses(truth, 0)
    pts = np.array([X_TRUE.actInv(pin.SE3(b).actInv(pin.SE3(a)).act(TIP_TRUE)) for a, b in zip(TA, TB)])
    pts += rng.normal(scale=sigma_t, size=pts.shape)
    return robot, joints, th, cols, pts, dict(zip(prob.names, truth))


def test_measurements_are_arguments_and_rows_follow_a_rejection():
    """A measured-point log with one gross error: the row is rejected and the measurements of the other
    rows stay with their configurations (the problem is sliced, no loop re-bound); the loop holds none."""
    robot, joints, th, cols, pts, truth = _measured_log()
    bad = 7
    pts[bad] += [4e-3, -3e-3, 5e-3]
    log = JointLog(joints, th, None, None, {c: pts[:, k] for k, c in enumerate(cols)})
    loop = MeasuredPointLoop("m", "tool0", sigma_t=2e-5)
    prob = build_problem(robot, log, [loop])
    assert not hasattr(loop, "meas") and prob.blocks[0].meas.shape == (len(th), 3)
    np.testing.assert_array_equal(prob.blocks[0].meas, pts)
    # a sliced problem evaluates the rows it keeps exactly as the whole one
    sub = prob.without_rows([bad + 1])
    r_all = prob.evaluate(prob.nominal, False)[0].r
    r_sub = sub.evaluate(sub.nominal, False)[0].r
    np.testing.assert_array_equal(r_sub, np.delete(r_all, bad, axis=0))
    res = calibrate(robot, log, [loop], CalibrationOptions(noise=1e-7))
    assert [rj.row for rj in res.outliers.rejected] == [bad + 1]
    assert (
        res.fit.residuals_after[0].n == len(th) - 1 and res.fit.residuals_after[0].rms_m < 5e-5
    )  # |3 x 2e-5| ~ 3.5e-5
    # the same as a calibration of the log without that row
    keep = np.delete(np.arange(len(th)), bad)
    clean = JointLog(joints, th[keep], None, None, {c: pts[keep, k] for k, c in enumerate(cols)})
    ref = calibrate(robot, clean, [loop], CalibrationOptions(noise=1e-7))
    assert (
        ref.outliers.rejected == []
        and ref.fit.names == res.fit.names
        and list(ref.fit.estimated) == list(res.fit.estimated)
    )
    np.testing.assert_allclose(res.fit.values, ref.fit.values, rtol=0, atol=1e-8)
    assert np.allclose([res.value(f"m.tip_{a}") for a in "xyz"], TIP_TRUE, atol=2e-3)


def test_measured_loop_checks_its_measurement_argument():
    """No measurements, or measurements of another length: one clear LoopError naming the loop."""
    robot, joints, th, cols, pts, _ = _measured_log(n=8)
    loop = MeasuredPointLoop("m", "tool0", tip=TIP_TRUE)
    prob = build_problem(robot, JointLog(joints, th, None, None, {c: pts[:, k] for k, c in enumerate(cols)}), [loop])
    TA, TB = prob.loop_poses(prob.nominal, 0)
    p = prob.initialize_loop(prob.nominal, 0)
    assert np.allclose(p, loop.initialize(TA, TB, pts))
    with pytest.raises(LoopError, match="loop 'm': no measurements given"):
        loop.evaluate(TA, TB, p)
    with pytest.raises(LoopError, match="loop 'm': 8 configurations but measurements of shape"):
        loop.evaluate(TA, TB, p, pts[:5])
