"""`gauge.kinematic_changes` (the frames' motion per parameter step, read by the length gauge and the size
per parameter) against central differences of Pinocchio's own frame placements on the perturbed models."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from closedloop.analysis.gauge import kinematic_changes, random_configurations
from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import build_problem
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.loops.spec import default_loops
from closedloop.model.robot import RobotModel

TABLE = Path(__file__).resolve().parents[1] / "closedloop" / "assets" / "dh" / "utah_mit_thumb_finger.yaml"


def _finite_differences(problem, x, V, q, h=1e-6):
    """dP by central differences of world positions and rotation vectors (an independent derivative)."""
    frames = sorted({problem.robot.frame_id(f) for b in problem.blocks for f in b.loop.frames} - {0})

    def poses(xv):
        state = problem.rp.apply(xv[: problem.n_robot])
        out = []
        for qi in q:
            pin.forwardKinematics(state.model, state.data, qi)
            out.append([pin.updateFramePlacement(state.model, state.data, f).copy() for f in frames])
        return out

    cols = []
    for v in V.T:
        plus, minus = poses(x + h * v), poses(x - h * v)
        rows = []
        for Mp, Mm in zip(plus, minus):
            for a, b in zip(Mp, Mm):
                rows.append(
                    np.concatenate(
                        [(a.translation - b.translation) / (2 * h), pin.log3(a.rotation @ b.rotation.T) / (2 * h)]
                    )
                )
        cols.append(np.concatenate(rows))
    return np.column_stack(cols)


@pytest.mark.parametrize("case", ["panda", "dh_hand"])
def test_kinematic_changes_match_finite_differences(case):
    rng = np.random.default_rng(3)
    if case == "panda":
        robot = RobotModel.from_file(ROBOTS["panda"].path)
        loops = [WeldLoop("fixture", "panda_hand")]
    else:  # D-H rows: the last row's constant part is the end frame's placement (its own generator)
        robot = RobotModel.from_file(TABLE)
        loops = default_loops(robot)
    log = JointLog(robot.joint_names, rng.uniform(-0.5, 0.5, (20, len(robot.joint_names))))
    problem = build_problem(robot, log, loops)
    x = problem.nominal + 0.02 * rng.standard_normal(len(problem.params)) * (
        np.arange(len(problem.params)) < problem.n_robot
    )
    V = rng.standard_normal((len(problem.params), 5))
    q = random_configurations(problem, 6, seed=1)
    dP, A = kinematic_changes(problem, x, V, q)
    ref = _finite_differences(problem, x, V, q)
    assert dP.shape == ref.shape and A.shape[0] == dP.shape[0]
    assert np.abs(ref).max() > 1e-2  # the steps move the frames
    np.testing.assert_allclose(dP, ref, rtol=0, atol=1e-7 * np.abs(ref).max())
