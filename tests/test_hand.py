"""Thesis chapter 4: the Utah-MIT thumb-finger loop, its URDF, the palm frame, and Baxter's dual-arm grasp."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from support import calibrated_names, relative_fk_error  # noqa: E402

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.loops.spec import default_loops
from closedloop.model.robot import RobotModel
from closedloop.studies.hand import (
    INCH,
    TABLE_4_1_FIXED,
    TABLE_4_2,
    _loop_problem,
    nominal_closed_pose,
    palm_frame_parameters,
    staged_calibration,
    thesis_hand_dataset,
    thesis_stages,
)
from closedloop.studies.synthetic import self_motion
from closedloop.studies.truth import make_dataset

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "closedloop" / "assets" / "dh" / "utah_mit_thumb_finger.yaml"
URDF = ROOT / "closedloop" / "assets" / "utah_mit_hand.urdf"
FIELDS = ("theta_off", "s", "a", "alpha", "k")


@pytest.fixture(scope="module")
def true_hand(tmp_path_factory):
    """TRUE hand: Table 4.2 with offset errors clipped to 0.5 rad and k to [0.85, 1]; readings on its self-motion."""
    truth, readings, _ = thesis_hand_dataset(tmp_path_factory.mktemp("hand"), n=100, seed=5)
    return truth, readings


def test_table_4_1_as_printed():
    robot = RobotModel.from_file(TABLE)
    rows = robot.dh.rows
    assert [r.convention for r in rows] == ["hayati", "hayati", "dh", "hayati", "dh", "hayati", "hayati", "dh"]
    assert rows[0].s == pytest.approx(-1.3 * INCH) and rows[7].theta_off == 3.1415
    assert rows[3].a == pytest.approx(0.4094)  # a Hayati 'a' is an angle: not converted
    assert rows[2].a == pytest.approx(-0.45 * INCH)
    assert default_loops(robot)[0].known is not None  # closes: true -> identity weld


@pytest.mark.slow
def test_staged_hand_calibration_recovers_true_hand(true_hand):
    """Staged (4.2.6) from the nominal Table 4.1, k identified, s_0 = -1.3 in and k_7 = 1 fixed.

    Measured: closure RMS 1.21 in / 0.99 rad -> 0.26 in / 0.10 rad (stage 1: palm, tip and the
    ~ offsets) -> 9e-15 in / 1e-15 rad (stage 2: all 38 parameters); max parameter error 7e-14.
    Thesis on the real hand: 0.578 in / 0.46 rad -> 0.020 in / 0.029 rad.
    """
    truth, readings = true_hand
    robot = RobotModel.from_file(TABLE)
    log = JointLog(robot.joint_names, readings)
    res1, res2 = staged_calibration(robot, log, default_loops(robot), thesis_stages(robot))
    before, mid, after = res1.fit.residuals_before[0], res1.fit.residuals_after[0], res2.fit.residuals_after[0]
    assert before.rms_m > 0.5 * INCH and before.rms_rad > 0.4  # the nominal table is far off
    assert mid.rms_m < 0.5 * before.rms_m  # stage 1 alone helps
    assert after.rms_m < 0.1 * before.rms_m and after.rms_rad < 0.1 * before.rms_rad
    assert after.rms_m < 1e-10 and after.rms_rad < 1e-10
    # stage 1 moved only the poorly known parameters
    moved = {n for n, v0, v in zip(res1.fit.names, res1.fit.initial, res1.fit.values) if abs(v - v0) > 0}
    assert moved and moved <= set(thesis_stages(robot)[0].identify)
    # every identifiable parameter recovered: 8 x 5 - 2 fixed = 38 estimated, nothing dropped or weak
    assert res2.converged and not res2.identifiability.dropped and not res2.identifiability.weak
    assert len(res2.fit.estimated) == 38
    for n, v in TABLE_4_1_FIXED.items():
        assert res2.fit.status[res2.fit.names.index(n)] == "fixed" and res2.value(n) == pytest.approx(v)
    err = max(abs(res2.fit.values[k] - truth[res2.fit.names[k]]) for k in res2.fit.estimated)
    assert err < 1e-8, err


def test_palm_frame_reproduces_tables_4_3_and_4_4():
    """Table 4.2 converted to the palm frame 2' gives the printed Tables 4.3 and 4.4."""
    robot = RobotModel.from_file(TABLE)
    values = {}
    for row, vals in zip(robot.dh.rows, TABLE_4_2):
        for f, v in zip(FIELDS, vals):
            values[f"{row.name}.{f}"] = v * INCH if f == "s" or (f == "a" and row.convention == "dh") else v
    pf = palm_frame_parameters(robot, values)
    finger = [r.in_units() for r in pf.finger]
    assert [f["label"] for f in finger] == ["-1", "0", "1", "2", "3"]
    assert [finger[0][f] for f in ("s", "a", "alpha")] == pytest.approx([1.8050, 0.5755, 0.2890])
    assert [finger[1][f] for f in FIELDS] == pytest.approx([0.1389, 1.7151, 1.3356, -1.5836, 1.0125])
    assert finger[4]["s"] is None and finger[4]["k"] == 1.0  # tip unknown
    thumb = [r.in_units() for r in pf.thumb]
    assert [t["label"] for t in thumb] == ["0", "1'", "1", "2", "3"]
    assert [thumb[0][f] for f in ("theta_off", "s", "a", "alpha")] == pytest.approx([1.7824, 0, 0.3097, -1.6207])
    assert thumb[1]["convention"] == "translation_z" and thumb[1]["s"] == pytest.approx(-0.1604)  # s'_1
    assert [thumb[2][f] for f in ("theta_off", "s", "a", "alpha")] == pytest.approx([0.0943, 1.5085, 0.1515, 0.0480])
    assert [thumb[3][f] for f in ("theta_off", "s", "a", "alpha")] == pytest.approx([-0.0850, 1.3, -0.0069, -0.0668])
    # our k is the k of the joint the row turns (Table 4.4 prints them one row lower)
    assert [t["k"] for t in thumb] == [0.9579, None, 0.9336, 0.8596, 0.9508]
    assert any("s'" in n for n in pf.notes)


def test_palm_frame_chains_meet_at_closed_configurations(tmp_path):
    """Finger chain (+ the identified closing link) and reversed thumb chain give the same base pose (six
    configurations along the true hand's self-motion: the module's 100-configuration walk is the slow test's)."""
    truth, readings, _ = thesis_hand_dataset(tmp_path, n=21, seed=5)
    robot = RobotModel.from_file(TABLE)
    pf = palm_frame_parameters(robot, truth)
    for th in readings[::4]:
        rd = dict(zip(robot.joint_names, th))
        F = pf.chain(pf.finger, rd) @ pf.closing_link.transform()
        T = pf.chain(pf.thumb, rd)
        assert np.abs(F - T).max() < 1e-12


def test_urdf_hand_is_the_dh_loop():
    """The URDF tips welded = the D-H loop: on nominal closed readings finger_tip in thumb_tip is constant."""
    robot = RobotModel.from_file(TABLE)
    prob = _loop_problem(robot)
    readings = self_motion(prob, prob.nominal, nominal_closed_pose(robot), 10, np.random.default_rng(1))
    hand = RobotModel.from_file(URDF)
    names = ["thumb_j0", "thumb_j1", "thumb_j2", "thumb_j3", "finger_j4", "finger_j5", "finger_j6", "finger_j7"]
    m, d = hand.model, hand.model.createData()
    X = []
    for q in hand.configurations(readings, names):
        pin.framesForwardKinematics(m, d, q)
        X.append((d.oMf[m.getFrameId("thumb_tip")].inverse() * d.oMf[m.getFrameId("finger_tip")]).homogeneous)
    assert np.abs(np.array(X) - X[0]).max() < 1e-9  # the URDF prints 10 significant digits
    import mujoco

    assert mujoco.MjModel.from_xml_path(str(URDF)).njnt == 8


@pytest.mark.slow
def test_urdf_hand_tip_to_tip_weld_calibrates():
    """Pure-kinematic data on the URDF hand, tips welded with an unknown grasp: recovered to 1e-8."""
    robot = RobotModel.from_file(URDF)
    loop = WeldLoop("grasp", "finger_tip", "thumb_tip")
    nom = RobotModel.from_file(TABLE)
    th = nominal_closed_pose(nom)[0]
    q0 = dict(
        zip(["thumb_j0", "thumb_j1", "thumb_j2", "thumb_j3", "finger_j4", "finger_j5", "finger_j6", "finger_j7"], th)
    )
    joints = [j for j in robot.joint_names if j in q0]
    # One length fixed in truth and calibration alike (the length gauge, 3.3: the core would otherwise
    # pick the longest free length, which may differ between the nominal and the true data).
    opts = CalibrationOptions(fix={"finger_j6.x": None})
    theta0 = np.array([q0[j] for j in joints])
    names = calibrated_names(robot, [loop], theta0, opts)
    ds = make_dataset(
        robot,
        loop,
        theta0,
        80,
        np.random.default_rng(2),
        perturb=names,
        magnitudes={"translation": 5e-4, "rotation": 5e-3, "offset": 0.05},
    )
    res = calibrate(robot, ds.log(noisy=False), [WeldLoop("grasp", "finger_tip", "thumb_tip")], opts)
    truth = ds.truth_dict()
    assert res.converged
    assert not res.identifiability.weak
    assert res.fit.residuals_before[0].rms_m > 1e-4 and res.fit.residuals_after[0].rms_m < 1e-10
    ok = [
        k for k in res.fit.estimated if res.fit.status[k] == "estimated" and not res.fit.names[k].startswith("grasp.r")
    ]
    assert len(ok) >= 28
    err = max(abs(res.fit.values[k] - truth[res.fit.names[k]]) for k in ok)
    assert err < 1e-8, err


def test_dual_arm_baxter_example():
    spec = importlib.util.spec_from_file_location("dual_arm_baxter", ROOT / "examples" / "dual_arm_baxter.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.run(n=20, seed=0, verbose=False)  # 55 estimated from 20 as from 40 (weak 0, 48 dropped)
    assert out["converged"] and out["weak"] == 0
    res, truth = out["result"], out["dataset"].truth_dict()
    # judged by what the two arms do (the grasp frame in the other gripper), up to the length scale
    pos, rot, _ = relative_fk_error(
        res, [truth.get(n, v) for n, v in zip(res.fit.names, res.fit.initial)], "left_gripper", "right_gripper"
    )
    assert pos < 1e-8 and rot < 1e-8
    assert out["after"].rms_m < 1e-10 and out["before"].rms_m > 1e-3
    assert out["estimated"] == 55 and out["dropped"] > 0
