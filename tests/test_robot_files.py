"""Robot files as users bring them (example-robot-data), through ``simulate --robot`` and ``calibrate``.

* iCub's URDF gives 14 links (legs, head, a wrist) a positive mass and a zero inertia, which MuJoCo
  refuses: the simulator repairs them with one note naming them, and a weld between the two hands
  simulates, calibrates and checks against the truth;
* ``simulate`` says on its summary line and in its exit code when it recorded fewer configurations
  than asked (none: exit 3, nothing written; some: exit 3, the files written);
* joint-limit margins are in each joint's own unit (a prismatic finger of 4 cm range is driven), an
  unlimited revolute joint is driven within one turn;
* a loop on a joint ``simulate`` held fixed in ``nominal.urdf`` is refused by ``calibrate`` before any
  work, naming the joint;
* a point loop whose contact point lies on the last joint's axis is refused before any work (simulate
  and calibrate), naming the joint and the fix (``tip=`` / ``--tool``).
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import mujoco
import pytest

from closedloop.cli.main import main
from closedloop.models import clean_urdf_tree, example_robot_data_dir, repair_inertias

ERD = example_robot_data_dir()
_NO_FUSE = '<mujoco><compiler fusestatic="false" discardvisual="true"/></mujoco>'
ICUB = ERD / "icub_description" / "robots" / "icub_reduced.urdf"


def _simulate(robot, loop, out, n=30, seed=1, extra=()):
    return main(
        ["simulate", "--robot", str(robot), "--loop", loop, "--n", str(n), "--seed", str(seed), "--out", str(out)]
        + list(extra)
    )


def test_zero_inertias_are_repaired_and_named():
    root = ET.parse(ICUB).getroot()
    repaired = repair_inertias(root)
    assert "l_ankle_2" in repaired and len(repaired) == 14
    assert repair_inertias(root) == []  # repaired once, valid after
    # the cleaned tree compiles in MuJoCo (the original does not: 'inertia must have positive eigenvalues')
    text = ET.tostring(clean_urdf_tree(ET.parse(ICUB).getroot()), encoding="unicode")
    raw = ET.parse(ICUB).getroot()
    for link in raw.findall("link"):  # the meshes are not the point: the inertias are
        for el in link.findall("visual") + link.findall("collision"):
            link.remove(el)
    with pytest.raises(ValueError, match="positive eigenvalues"):
        mujoco.MjModel.from_xml_string(ET.tostring(raw, encoding="unicode"))
    model = mujoco.MjModel.from_xml_string(text.replace("</robot>", _NO_FUSE + "</robot>"))
    ankle = model.body("l_ankle_2").id
    assert model.body_mass[ankle] == pytest.approx(0.2675)  # the mass kept, the moments raised
    assert min(model.body_inertia[ankle]) >= 0.4 * 0.2675 * 0.01**2 * (1 - 1e-9)


def test_icub_two_hand_weld_simulates_calibrates_and_checks(tmp_path, capsys, caplog):
    sim = tmp_path / "sim"
    assert _simulate(ICUB, "weld:frame=l_hand,to=r_hand,name=grasp", sim, n=40) == 0
    notes = [r.getMessage() for r in caplog.records if "inertia" in r.getMessage()]
    assert len(notes) == 1 and "l_ankle_2" in notes[0]
    assert "simulated 40 configurations" in capsys.readouterr().out
    report = tmp_path / "report.json"
    assert (
        main(
            [
                "calibrate",
                str(sim / "nominal.urdf"),
                str(sim / "log.csv"),
                "--loop",
                "weld:frame=l_hand,to=r_hand,name=grasp",
                "--report",
                str(report),
                "--quiet",
            ]
        )
        == 0
    )
    assert json.loads(report.read_text())["verdict"]["status"] in ("ok", "suspect")
    assert main(["check", str(sim / "truth.json"), str(report)]) == 0
