"""The sphere loop (two spheres in contact, a known distance between two points): Jacobians, recovery."""

from __future__ import annotations

import numpy as np
import pytest
from support import central_difference_jacobian, relative_fk_error
from test_loops_point_plane_measured import BAXTER, BAXTER_Q0, PANDA, PANDA_Q0, _fd_problem, closed_experiment

from closedloop.errors import LoopError
from closedloop.loops.spec import parse_loop
from closedloop.loops.sphere import SphereLoop
from closedloop.model.robot import RobotModel

JAC_CASES = {
    "unknown": lambda: SphereLoop("s", "tool0"),
    "known_distance": lambda: SphereLoop("s", "tool0", distance=0.05),
    "known_tip_and_point": lambda: SphereLoop("s", "tool0", tip=[0.0, 0.01, 0.1], point=[0.3, 0.2, 0.1]),
    "two_branches": lambda: SphereLoop("s", "tool0", "upper_arm_link", distance=0.2),
}


@pytest.mark.parametrize("case", sorted(JAC_CASES))
def test_jacobian_matches_central_differences(case):
    J, Jn = central_difference_jacobian(*_fd_problem(JAC_CASES[case]()))
    assert np.abs(J - Jn).max() <= 1e-6 * np.abs(J).max()


@pytest.mark.slow
def test_two_hands_touching_with_spheres_baxter():
    """Baxter's grippers with spherical ends pressed together (5 passive DOF, one equation per configuration):
    the centre of the left sphere in the right gripper recovered to the length scale, noise-free."""
    res, truth = closed_experiment(
        BAXTER,
        lambda: SphereLoop("touch", "left_gripper", "right_gripper"),
        BAXTER_Q0,
        {"touch.tip_z": 0.03, "touch.pz": 0.03, "touch.d": 0.06},
        n=80,
    )
    assert res.fit.residuals_after[0].rms_m < 1e-9
    pos, _, _ = relative_fk_error(res, [truth[n] for n in res.fit.names], "left_gripper", "right_gripper", tip="touch")
    assert pos < 1e-7
    assert res.verdict.status != "failed", res.verdict.describe()


def test_a_known_distance_sets_the_size():
    """A ball on the Panda's hand rolling on a fixed ball, radii known: the loop sees the robot's size, so no
    length is held for it, and the closure is exact on exact data."""
    res, truth = closed_experiment(
        PANDA,
        lambda: SphereLoop("ball", "panda_hand", tip=[0.0, 0.0, 0.1], distance=0.08),
        PANDA_Q0,
        {},
        n=60,
    )
    assert res.fit.residuals_after[0].rms_m < 1e-9
    assert res.scale.gauge is None and not any("length scale" in n for n in res.notes), res.notes
    est = [i for i, s in enumerate(res.fit.status) if s == "estimated"]
    err = max(abs(res.fit.values[i] - truth[res.fit.names[i]]) for i in est)
    assert err < 1e-6, err


def test_spec_and_refusals():
    robot = RobotModel.from_file(PANDA)
    lp = parse_loop("sphere:frame=panda_hand,name=b,distance=0.08,tip=0 0 0.1", robot)
    assert isinstance(lp, SphereLoop) and lp.distance == 0.08 and not lp.scale_free
    assert parse_loop("sphere:frame=panda_hand,name=b", robot).scale_free
    with pytest.raises(LoopError, match="point loop"):
        parse_loop("sphere:frame=panda_hand,name=b,distance=0", robot)
