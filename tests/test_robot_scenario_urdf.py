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
