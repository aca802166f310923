"""The structural reading of the identifiable set agrees with what a calibration estimates.

`make_dataset`, the Monte Carlo study and the loop tests draw their truth in the set that
`closedloop.studies.identifiable.identifiable_names` reads off the nominal robot's structure, without a
fit.  Here, for every robot, loop and start configuration they draw one for, a calibration of the same
exact nominal data (`support.calibrated_names`: the same walk) estimates exactly that set, in the same
order (the order decides which random number each parameter's error gets).

Where two parameters are redundant with each other the two readings may keep different members of the
pair (`TIES`): the sets then hold as many parameters and span the same directions of the closure's
Jacobian, so a truth drawn in either is one a calibration can recover.
"""

from __future__ import annotations

import site

import numpy as np
import pytest
from support import calibrated_names

from closedloop.analysis.selection import DEFAULT_IDENTIFY
from closedloop.assets.catalog import ROBOTS
from closedloop.loops import FaceLoop, PlaneLoop, PointLoop, WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.studies.identifiable import closing_values, identifiable_names, nominal_problem
from closedloop.studies.synthetic import self_motion

ERD = site.getsitepackages()[0] + "/cmeel.prefix/share/example-robot-data/robots/"
UR5 = ERD + "ur_description/urdf/ur5_robot.urdf"
BAXTER = ERD + "baxter_description/urdf/baxter.urdf"
PANDA_Q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]  # tests/conftest.py, make_dataset's callers, weld_scenario
PANDA_Q1 = [0.2, 0.3, -0.2, -2.0, 0.1, 2.0, 0.5]  # tests/test_loops_point_plane_measured.py, test_loops_face.py
UR5_Q0 = [0.3, -1.2, 1.4, -1.0, 1.2, 0.4]
UR5_Q1 = [0.3, -1.3, 1.7, -1.9, -1.57, 0.2]  # tests/test_observability_poses.py
# examples/dual_arm_baxter.py
BAXTER_GRASP_Q0 = [0.3, -0.4, -0.3, 1.3, 0.2, 0.6, 0.1, -0.3, -0.4, 0.3, 1.3, -0.2, 0.6, -0.1]
BAXTER_Q0 = [0.3, -0.5, -0.5, 1.5, 0.3, 0.8, 0.2, -0.3, -0.5, 0.5, 1.5, -0.3, 0.8, -0.2]

#: name -> (robot file, loops, start readings, configurations of the walk): every truth drawn that way
CASES = {
    "panda_weld": ("panda", lambda: [WeldLoop("fixture", "panda_hand")], PANDA_Q0, 30),
    "panda_socket": ("panda", lambda: [PointLoop("socket", "panda_hand")], PANDA_Q0, 30),
    "panda_ball": ("panda", lambda: [PointLoop("ball", "panda_hand")], PANDA_Q1, 40),
    "panda_palm": ("panda", lambda: [FaceLoop("palm", "panda_hand")], PANDA_Q1, 12),
    "ur5_ball": (UR5, lambda: [PointLoop("ball", "tool0")], UR5_Q0, 40),
    "ur5_ball_80": (UR5, lambda: [PointLoop("ball", "tool0")], UR5_Q0, 80),
    "ur5_floor": (UR5, lambda: [PlaneLoop("floor", "tool0")], UR5_Q0, 120),
    "ur5_socket_tip": (UR5, lambda: [PointLoop("socket", "tool0", tip=np.array([0.0, 0.05, 0.1]))], UR5_Q1, 30),
    "ur5_two_planes": (
        UR5,
        lambda: [
            PlaneLoop("floor", "tool0", tip=[0.0, 0.0, 0.1]),
            PlaneLoop("wall", "tool0", tip=[0.0, 0.0, 0.1], normal=[1.0, 0.0, 0.0]),
        ],
        [UR5_Q0],
        60,
    ),
    "baxter_grasp": (BAXTER, lambda: [WeldLoop("grasp", "left_gripper", "right_gripper")], BAXTER_GRASP_Q0, 30),
    "baxter_touch": (BAXTER, lambda: [PointLoop("touch", "left_gripper", "right_gripper")], BAXTER_Q0, 40),
    "baxter_pads": (BAXTER, lambda: [FaceLoop("pads", "left_gripper", "right_gripper")], BAXTER_Q0, 30),
}


#: the cases where the structure and the calibration keep different members of redundant pairs (Baxter's two
#: arms joined, welded or touching: the wrists' w0.z and w1.x of one arm for the other's)
TIES = {"baxter_grasp", "baxter_touch"}


def robot_of(path: str) -> RobotModel:
    return RobotModel.from_file(ROBOTS[path].path if path in ROBOTS else path)


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_structure_names_what_a_calibration_estimates(case):
    path, make, q0, n = CASES[case]
    robot = robot_of(path)
    q0 = np.atleast_2d(q0)
    structural = identifiable_names(robot, make(), q0, DEFAULT_IDENTIFY[robot.kind], n=n)
    calibrated = calibrated_names(robot, make(), q0, n=n)
    assert len(structural) >= 13  # the robot's own parameters, not an empty set that agrees trivially
    if case not in TIES:
        assert structural == calibrated
        return
    assert structural != calibrated and len(structural) == len(calibrated)
    # the same directions: the closure's Jacobian on the walk has the rank of either set with the other added
    start = nominal_problem(robot, make(), [q0])
    x = start.nominal
    x[start.loop_slices[0]] = start.initialize_loop(x, 0)
    walk = self_motion(start, x, q0, n, np.random.default_rng(0))
    problem = nominal_problem(robot, make(), [walk])
    x = closing_values(problem)
    J = np.vstack([ev.J.reshape(-1, x.size) for ev in problem.evaluate(x, True)])
    loop = [int(k) for c in problem.loop_columns for k in c]
    rank = [
        np.linalg.matrix_rank(J[:, loop + [problem.index[m] for m in names]], tol=1e-8 * np.abs(J).max())
        for names in (structural, calibrated, list(dict.fromkeys(structural + calibrated)))
    ]
    assert rank[0] == rank[1] == rank[2] == len(loop) + len(structural), rank


@pytest.mark.slow
def test_structure_names_what_a_calibration_estimates_on_a_mjcf_model(tmp_path):
    """The Panda as a MuJoCo model (tests/test_mjcf_export.py): placement errors of the MJCF bodies."""
    from test_mjcf_export import panda_mjcf

    robot = panda_mjcf(tmp_path / "panda.xml", anchor=[0.0, 0.0, 0.04])
    loops = [WeldLoop("fixture", "panda_hand")]
    structural = identifiable_names(robot, loops, np.atleast_2d(PANDA_Q0), DEFAULT_IDENTIFY[robot.kind])
    assert structural == calibrated_names(robot, [WeldLoop("fixture", "panda_hand")], np.atleast_2d(PANDA_Q0))
    assert len(structural) >= 13
