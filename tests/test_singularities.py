"""Thesis 3.3: the singular cases are detected and explained, not crashed into.

(The parallelogram four-bar, Singularity 4, is in tests/test_planar.py.)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.loops.spec import default_loops
from closedloop.model.robot import RobotModel
from closedloop.studies.synthetic import self_motion
from closedloop.studies.truth import make_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_hand import TABLE, _loop_problem, nominal_closed_pose  # noqa: E402


@pytest.mark.slow
def test_singularity_1_parallel_axes_in_plain_dh_rows(tmp_path):
    """The finger's parallel flexion axes (rows j5, j6) written as plain D-H rows (alpha = 0).

    z_4 || z_5 || z_6: the common normals are not unique, and s_5, s_6 only shift the
    links along parallel axes, i.e. move the same thing as the next row's s.  The core
    drops them as structurally redundant and names what absorbs them.
    """
    doc = yaml.safe_load(TABLE.read_text())
    rows = []
    for r in doc["joints"]:
        r = dict(r)
        if r["name"] in ("j5", "j6"):
            r.update(convention="dh", s=0.05, a=r["s"], alpha=0.0)
        rows.append(r)
    path = tmp_path / "parallel_dh.yaml"
    path.write_text(yaml.safe_dump({**doc, "joints": rows}))
    robot = RobotModel.from_file(path)
    prob = _loop_problem(robot)
    readings = self_motion(prob, prob.nominal, nominal_closed_pose(robot), 60, np.random.default_rng(0), step=0.05)
    res = calibrate(
        robot, JointLog(robot.joint_names, readings), default_loops(robot), CalibrationOptions(fix={"j0.s": None})
    )
    dropped = {d.name: d for d in res.identifiability.dropped}
    reported = set(dropped) | {n for c in res.identifiability.weak for n, _ in c.terms}
    assert {"j5.s", "j6.s"} <= reported, [d.describe() for d in res.identifiability.dropped]
    for n in ("j5.s", "j6.s"):
        assert res.fit.status[res.fit.names.index(n)] in ("dropped", "unidentifiable")
        assert dropped[n].absorbed_into  # and the report says what absorbs it
    hint = [n for n in res.notes if "Singularity 1" in n]
    assert hint and "j5" in hint[0] and "j6" in hint[0] and "convention: hayati" in hint[0]
    assert res.converged and res.fit.residuals_after[0].rms_m < 1e-10


ARM = """<?xml version="1.0"?>
<robot name="anthropomorphic">
  <link name="base"/>
  {links}
</robot>
"""


def _arm_urdf() -> str:
    """7R arm: spherical shoulder (z, y, z), elbow (y), spherical wrist (z, y, z), links 0.3 m."""
    spec = [
        ("s0", "0 0 1", "0 0 0.1"),
        ("s1", "0 1 0", "0 0 0"),
        ("s2", "0 0 1", "0 0 0"),
        ("elbow", "0 1 0", "0 0 0.3"),
        ("w0", "0 0 1", "0 0 0"),
        ("w1", "0 1 0", "0 0 0.3"),
        ("w2", "0 0 1", "0 0 0"),
    ]
    out, parent = [], "base"
    inertial = (
        '<inertial><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>'
    )
    for name, axis, xyz in spec:
        out.append(f'<link name="{name}_link">{inertial}</link>')
        out.append(
            f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{name}_link"/>'
            f'<origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="{axis}"/>'
            '<limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
        )
        parent = f"{name}_link"
    out.append(
        f'<link name="hand">{inertial}</link><joint name="hand_joint" type="fixed"><parent link="{parent}"/>'
        '<child link="hand"/><origin xyz="0 0 0.1" rpy="0 0 0"/></joint>'
    )
    return ARM.format(links="\n  ".join(out))


def test_singularity_5_elbow_of_an_arm_with_its_hand_fixed(tmp_path):
    """Lemma 6: spherical shoulder and wrist, hand welded: the shoulder-wrist distance is fixed, so the
    elbow cannot move; the only self-motion swings the elbow about the shoulder-wrist line."""
    path = tmp_path / "arm.urdf"
    path.write_text(_arm_urdf())
    robot = RobotModel.from_file(path)
    loop = WeldLoop("fixture", "hand")
    ds = make_dataset(
        robot, loop, np.array([0.2, 0.5, 0.3, 1.2, -0.4, 0.7, 0.1]), 40, np.random.default_rng(1), perturb=[], step=0.05
    )
    elbow = ds.joints.index("elbow")
    assert np.ptp(ds.readings[:, elbow]) < 1e-9  # exactly: the elbow never moves
    # Readings with a little sensor noise: the elbow reading changes, but no self-motion moves it.
    noisy = ds.readings + np.random.default_rng(2).normal(0, 1e-4, ds.readings.shape)
    res = calibrate(robot, JointLog(ds.joints, noisy), [WeldLoop("fixture", "hand")])
    immobile = [n for n in res.notes if "structurally immobile" in n]
    assert len(immobile) == 1 and "joint elbow " in immobile[0] and "Lemma 6" in immobile[0]
    # Exact readings: the elbow is reported as never moving (Singularity 5), not crashed into.
    res0 = calibrate(
        robot,
        ds.log(noisy=False),
        [WeldLoop("fixture", "hand")],
        CalibrationOptions(identify=["placement", "offset", "scale", "loop"]),
    )
    assert any("elbow never moves" in n and "Singularity 5" in n for n in res0.notes)
    assert res0.fit.status[res0.fit.names.index("elbow.scale")] in ("dropped", "fixed")


@pytest.mark.slow
def test_singularity_2_insufficient_excitation(panda):
    """A tiny motion range (0.02 rad of self-motion) with 1e-5 rad reading noise: the data cannot
    separate some parameters; they are named in `weak` and marked unidentifiable, not solved into noise."""
    rng = np.random.default_rng(3)
    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 30, rng, step=1e-3, stride=1
    )
    assert np.ptp(ds.readings, axis=0).max() < 0.05
    noisy = ds.readings + rng.normal(0, 1e-5, ds.readings.shape)
    res = calibrate(panda, JointLog(ds.joints, noisy), [WeldLoop("fixture", "panda_hand")])
    assert res.identifiability.weak
    names = {n for c in res.identifiability.weak for n, _ in c.terms}
    assert names and names <= set(res.fit.names)
    for n in names:
        assert res.fit.status[res.fit.names.index(n)] == "unidentifiable"
    assert all(c.describe() for c in res.identifiability.weak)
    # the same geometry with a wide walk is fine (see test_calibration): the problem is the data
