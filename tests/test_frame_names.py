"""A joint and a link of one name (URDF allows it; Pinocchio then has a joint frame and a body frame of that
name): the loop's frame is the link, in the model and in the simulator."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.model.robot import RobotModel, find_frame

URDF = """<?xml version="1.0"?>
<robot name="twin">
  <link name="base"/>
  <link name="l1"><inertial><mass value="1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <link name="stylus"><inertial><mass value="0.1"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
    <origin xyz="0 0 0.1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="stylus" type="fixed"><parent link="l1"/><child link="stylus"/><origin xyz="0.3 0 0.05"/></joint>
</robot>
"""


def test_the_link_of_a_shared_name_is_the_loops_frame(tmp_path):
    path = tmp_path / "twin.urdf"
    path.write_text(URDF)
    robot = RobotModel.from_file(path)
    same = [f for f in robot.model.frames if f.name == "stylus"]
    assert len(same) == 2  # the case: a joint frame and a body frame of one name
    fid = robot.frame_id("stylus")
    assert robot.model.frames[fid].type == pin.FrameType.BODY and fid == find_frame(robot.model, "stylus")
    data = robot.model.createData()
    q = np.array([0.5])
    pin.framesForwardKinematics(robot.model, data, q)
    expected = np.array([0.3 * np.cos(0.5), 0.3 * np.sin(0.5), 0.15])  # the stylus link's origin
    assert np.allclose(data.oMf[fid].translation, expected, atol=1e-12)


def test_a_frame_id_follows_the_model_it_is_read_from(tmp_path):
    """`frame_id` keeps its lookups, for the model they were made in: a frame added later is found, and a model
    replaced by another (frames in another order) is read afresh."""
    path = tmp_path / "twin.urdf"
    path.write_text(URDF)
    robot = RobotModel.from_file(path)
    fid = robot.frame_id("stylus")
    assert robot.frame_id("stylus") == fid  # kept
    l1 = robot.model.frames[robot.frame_id("l1")]
    new = robot.model.addFrame(pin.Frame("tip", l1.parentJoint, l1.placement, pin.FrameType.OP_FRAME))
    assert robot.frame_id("tip") == new
    other = pin.Model()  # the same frames, the stylus's body frame first
    for f in [robot.model.frames[0], robot.model.frames[fid]]:
        other.addFrame(pin.Frame(f.name, 0, pin.SE3.Identity(), f.type))
    robot.model = other
    assert robot.frame_id("stylus") == 1 == find_frame(other, "stylus")
