"""Loops keep no per-dataset state: preparing, initialising and evaluating a loop leave the
object as it was; what a loop reads off the data (the hinge's chart) lives in the copy `prepare` returns,
which the problem and the result hold (`CalibrationResult.loops`)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import ROBOTS
from closedloop.io.logs import JointLog
from closedloop.loops.spec import LOOP_TYPES, parse_loop

TASKS = Path(__file__).resolve().parents[1] / "closedloop" / "assets" / "tasks"
Q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
SPECS = {
    "weld": "weld:frame=panda_hand",
    "point": "point:frame=panda_hand",
    "plane": "plane:frame=panda_hand",
    "sphere": "sphere:frame=panda_hand,distance=0.08",
    "face": "face:frame=panda_hand",
    "hinge": "hinge:frame=panda_hand",
    "passive": f'passive:frame=panda_hand,task={TASKS / "door.urdf"},task_frame=grip,q0="0.3 0.1"',
    "measured_point": "measured_point:frame=panda_hand",
    "measured_pose": "measured_pose:frame=panda_hand",
}


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.shape == b.shape
            and bool(np.array_equal(a, b, equal_nan=True))
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if hasattr(a, "homogeneous"):  # pin.SE3
        return bool(np.array_equal(a.homogeneous, b.homogeneous))
    try:
        return bool(a == b)
    except Exception:  # noqa: BLE001 - objects without equality (models, data): identity
        return a is b


def _state(lp) -> dict:
    return {k: v for k, v in vars(lp).items()}


@pytest.fixture(scope="module")
def panda():
    return RobotModel.from_file(ROBOTS["panda"].path)


def test_every_loop_type_is_covered():
    assert set(SPECS) | {"camera"} == set(LOOP_TYPES)  # camera: tests/test_loops_camera.py's data


@pytest.mark.parametrize("kind", sorted(SPECS))
def test_loop_is_unchanged_by_prepare_initialize_evaluate(panda, kind):
    from closedloop.analysis.selection import initial_values
    from closedloop.calibration.pipeline import build_problem

    rng = np.random.default_rng(0)
    lp = parse_loop(SPECS[kind], panda)
    before = copy.copy(_state(lp))
    before = {k: copy.deepcopy(v) if isinstance(v, (np.ndarray, list, dict, tuple)) else v for k, v in before.items()}
    th = Q0 + rng.normal(0.0, 0.05, (12, 7))
    extra = {c: rng.normal(0.0, 0.1, len(th)) for c in lp.columns()}
    log = (
        JointLog([f"panda_joint{i}" for i in range(1, 8)], th, None, None, extra)
        if extra
        else JointLog([f"panda_joint{i}" for i in range(1, 8)], th)
    )
    problem = build_problem(panda, log, [lp])
    x = initial_values(problem, {})
    problem.evaluate(x, True)
    problem.evaluate(x + 1e-3, False)
    after = _state(lp)
    assert before.keys() == after.keys()
    changed = [k for k in before if not _same(before[k], after[k])]
    assert not changed, f"{kind}: {changed}"


@pytest.mark.slow
def test_results_carry_the_prepared_hinge(panda):
    """Two calibrations with one hinge loop object on data from two different doors: each result's
    values are read in its own loop's chart, and the caller's object is never touched."""
    from closedloop.loops.hinge import HingeLoop

    lp = parse_loop("hinge:frame=panda_hand,name=door", panda)
    assert isinstance(lp, HingeLoop) and not lp.fitted
    logs = []
    for k, axis in enumerate(
        [
            (np.array([0.5, 0.4, 0.6]), np.array([0.0, 0.0, 1.0])),
            (np.array([0.2, -0.5, 0.4]), np.array([0.3, 0.1, 1.0])),
        ]
    ):
        from closedloop.problem.problem import CalibrationProblem, LoopBlock
        from closedloop.studies.synthetic import self_motion

        truth_loop = HingeLoop("door", "panda_hand", axis=axis)
        joints = [f"panda_joint{i}" for i in range(1, 8)]
        prob = CalibrationProblem(panda, joints, [LoopBlock(truth_loop, Q0[None], np.arange(1))])
        x = prob.nominal
        x[prob.loop_slices[0]] = truth_loop.initialize(*prob.loop_poses(x, 0))
        th = self_motion(prob, x, Q0[None], 30, np.random.default_rng(k))
        logs.append((JointLog(joints, th), truth_loop, x[prob.loop_slices[0]]))
    lines = []
    for lg, truth_loop, p_true in logs:
        res = calibrate(panda, lg, [lp], CalibrationOptions(identify=["loop"]))
        assert res.loops[0] is not lp and res.loops[0].fitted
        sl = res.problem.loop_slices[0]
        pt, dt = truth_loop.line(p_true)
        pc, dc = res.loops[0].line(res.fit.values[sl])
        assert np.abs(pc - pt).max() < 1e-8 and abs(abs(dc @ dt) - 1.0) < 1e-12
        lines.append(pc)
    assert not lp.fitted and np.array_equal(lp.H0.homogeneous, np.eye(4))  # the caller's object, untouched
    assert np.abs(lines[0] - lines[1]).max() > 0.1  # two different doors indeed
