"""A user's URDF given to the simulator: a joint that does not name its links is a one-line input error."""

from pathlib import Path

import pytest

from closedloop.errors import InputError
from closedloop.sims.robot_scenario import prepare_robot

URDF = """<robot name="arm">
  <link name="base"/>
  <link name="upper"/>
  <link name="tool0"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/>{child}
    <axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/>
  </joint>
  <joint name="wrist" type="revolute">
    <parent link="upper"/>
    <child link="tool0"/>
    <origin xyz="0.3 0 0"/>
    <axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/>
  </joint>
</robot>
"""


@pytest.mark.parametrize("child", ["", "\n    <child/>"])
def test_a_joint_without_its_child_link_names_file_and_joint(tmp_path: Path, child: str) -> None:
    path = tmp_path / "arm.urdf"
    path.write_text(URDF.format(child=child))
    with pytest.raises(InputError) as err:
        prepare_robot(path, "point", "tool0")
    assert str(err.value) == f"{path}: joint 'shoulder': no <child link=...>"  # as calibrate and inspect say it


def _leg(side: str) -> str:
    """Three revolute joints from the base to ``<side>3`` (a quadruped's leg)."""
    out = f'<link name="{side}1"/><link name="{side}2"/><link name="{side}3"/>'
    for i, (parent, axis, xyz) in enumerate(
        [
            ("base", "1 0 0", f"0 {0.1 if side == 'a' else -0.1} 0"),
            (f"{side}1", "0 1 0", "0 0 -0.05"),
            (f"{side}2", "0 1 0", "0 0 -0.2"),
        ],
        start=1,
    ):
        out += (
            f'<joint name="{side}j{i}" type="revolute"><parent link="{parent}"/><child link="{side}{i}"/>'
            f'<origin xyz="{xyz}"/><axis xyz="{axis}"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        )
    return out


def test_a_loop_that_leaves_no_motion_names_only_the_loops_that_would_leave_some(tmp_path: Path) -> None:
    path = tmp_path / "legs.urdf"
    path.write_text(f'<robot name="legs"><link name="base"/>{_leg("a")}{_leg("b")}</robot>')
    with pytest.raises(InputError) as err:
        prepare_robot(path, "point", "a3", tool={"xyz": [0.0, 0.0, -0.02]})  # a foot in a socket: 3 of 3
    msg = str(err.value)
    assert "leaves the closed chain no motion" in msg and "its 3 driven joint(s)" in msg
    assert msg.endswith("use a loop with fewer constraints (plane: 1, measured_point: 0), or a robot with more joints")
    with pytest.raises(InputError) as err:
        prepare_robot(path, "weld", "a3", to="b3")  # the two feet welded: 6 of 6
    assert str(err.value).endswith(
        "use a loop on one of the two frames with fewer constraints (only a weld closes two chains) "
        "(point: 3, plane: 1, measured_point: 0), or a robot with more joints"
    )
