"""Tests of the MuJoCo dataset generator (closedloop.sims).

Tolerances: with the stiff loop preset (``stiff=True``) the true closure
violation stays below 1e-4 m (measured: ~1e-5 m) for every scenario.  For the
open loop (``ur5_tracker``) the "violation" is the tracker's measurement error,
|N(0, (1e-5 m)^2 I3)| (measured max ~3e-5 m over 30 samples).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from closedloop.assets.catalog import nominal_urdf
from closedloop.sims import SCENARIOS, SimSettings, perturbable_parameters, sensor_readings, simulate
from closedloop.sims.scene import apply_placement_errors, build_scene, site_pose
from closedloop.sims.true_robot import identifiable_parameters

N = 30
STIFF_TOL_M = 1e-4


@pytest.fixture(scope="module", params=sorted(SCENARIOS))
def stiff_run(request, tmp_path_factory):
    name = request.param
    out = tmp_path_factory.mktemp(name)
    calls: list[tuple[int, int]] = []
    res = simulate(name, N, 0, out, stiff=True, progress=lambda task, i, n, note="": calls.append((i, n)))
    return name, res, calls


def _read_log(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as f:
        rows = list(csv.reader(f))
    return rows[0], np.array(rows[1:], dtype=float)


def test_scenarios_registry():
    assert {"panda_weld", "ur5_socket", "ur5_door", "utah_hand", "ur5_tracker", "ur5_plane"} <= set(SCENARIOS)
    for sc in SCENARIOS.values():
        assert sc.description and "\n" not in sc.description


def test_outputs_and_log_format(stiff_run):
    name, res, calls = stiff_run
    for f in ("log.csv", "truth.json", "nominal.urdf", "scene.xml"):
        assert (res.out_dir / f).is_file()
    header, data = _read_log(res.log_path)
    nj = len(res.joint_names)
    assert header[:nj] == res.joint_names
    assert f"tau:{res.joint_names[0]}" in header
    assert {"violation_m", "violation_rad", "constraint_force_n"} <= set(header)
    assert data.shape == (N, len(header))
    np.testing.assert_array_equal(data[:, :nj], res.readings)
    # nominal.urdf: the simulator's nominal kinematics, with the robot file's visuals (meshes by absolute path)
    model = pin.buildModelFromUrdf(str(res.nominal_path))
    assert [model.names[j] for j in range(1, model.njoints)] == res.joint_names
    if name != "utah_hand":  # the hand's file (generated from Table 4.1) has no visuals
        visual = pin.buildGeomFromUrdf(model, str(res.nominal_path), pin.GeometryType.VISUAL)
        meshes = [g.meshPath for g in visual.geometryObjects if g.meshPath]
        assert meshes and all(Path(m).is_absolute() and Path(m).is_file() for m in meshes), name
    assert calls == [(i, N) for i in range(1, N + 1)]
    # the nominal URDF's movable joints are the log's joints, in Pinocchio order
    model = pin.buildModelFromXML(res.nominal_path.read_text())
    assert list(model.names[1:]) == res.joint_names
    # the saved scene compiles
    mujoco.MjModel.from_xml_path(str(res.scene_path))


def test_violation_small_with_stiff_loop(stiff_run):
    name, res, _ = stiff_run
    assert res.violation_m.max() < STIFF_TOL_M, (name, res.violation_m.max())
    v = res.truth["violation"]
    assert v["max_m"] == pytest.approx(res.violation_m.max())
    if SCENARIOS[name].loop_type != "point":
        assert res.violation_rad.max() < 2e-3


def test_every_loop_joint_moves(stiff_run):
    name, res, _ = stiff_run
    span = res.q_true.max(axis=0) - res.q_true.min(axis=0)
    assert np.all(span > SCENARIOS[name].min_joint_range), dict(zip(res.joint_names, span.round(3)))
    assert np.sum(span > 0.1) >= len(span) - 2  # at most two joints below 0.1 rad (the hand's, see scenarios.py)
    if SCENARIOS[name].loop_type == "hinge":
        assert np.ptp(res.door_angle) > 0.1


def test_truth_names(stiff_run):
    name, res, _ = stiff_run
    sc = SCENARIOS[name]
    truth = json.loads(res.truth_path.read_text())
    assert truth["scenario"] == name and truth["seed"] == 0
    assert truth["loop"] == {**truth["loop"], "type": sc.loop_type, "frame": sc.tool_frame, "name": sc.loop_name}
    assert truth["loop"].get("to") == sc.target_frame
    params = truth["parameters"]
    expected = set(identifiable_parameters(res.nominal_path, sc, res.joint_names))
    comps = {
        "point": ("px", "py", "pz", "tip_x", "tip_y", "tip_z"),
        "weld": ("x", "y", "z", "rx", "ry", "rz"),
        "hinge": (),  # hinge: the true axis is in truth["loop"]["hinge_axis"]
        "plane": ("tip_x", "tip_y", "tip_z", "nrx", "nry", "d"),  # PlaneLoop, reference normal e_z
        "measured_point": ("x", "y", "z", "rx", "ry", "rz", "tip_x", "tip_y", "tip_z"),  # MeasuredPointLoop
    }[sc.loop_type]
    expected |= {f"{sc.loop_name}.{c}" for c in comps}
    assert set(params) == expected
    first = res.joint_names[0]
    # the first joint's placement is the base gauge; welded to the world its offset is too, but in a
    # loop between two branches of the robot (hand) it is not (the other branch's placement absorbs it)
    assert not any(k.startswith(first + ".") and (sc.target_frame is None or k != first + ".offset") for k in params)
    for k, v in params.items():
        if k.endswith((".x", ".y", ".z")) and not k.startswith(sc.loop_name + "."):
            assert abs(v) <= 0.002
        if k.endswith(".offset"):
            assert abs(v) <= 0.02
    assert set(truth["violation"]) == {"rms_m", "max_m", "rms_rad", "max_rad"}


def test_perturbation_rule_panda():
    model = pin.buildModelFromXML(nominal_urdf("panda"))
    joints = list(model.names[1:])
    names = perturbable_parameters(model, joints)
    assert not any(n.startswith("panda_joint1.") for n in names)
    assert not any(n.endswith((".z", ".rz")) for n in names)  # all Panda axes are z
    assert "panda_joint2.offset" in names and "panda_joint7.ry" in names
    assert len(names) == 6 * 5
    ur = pin.buildModelFromXML(nominal_urdf("ur5"))
    names = perturbable_parameters(ur, list(ur.names[1:]), scale=True)
    assert "shoulder_lift_joint.ry" not in names and "shoulder_lift_joint.rz" in names  # axis y
    assert "shoulder_pan_joint.scale" in names


def test_true_closure_matches_true_kinematics(stiff_run):
    """Closure parameters = true FK (Pinocchio on the true URDF) of the tool at the grasp."""
    name, res, _ = stiff_run
    sc = SCENARIOS[name]
    truth = res.truth
    urdf = apply_placement_errors(res.nominal_path.read_text(), truth["parameters"])
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    pin.framesForwardKinematics(model, data, np.array(truth["q0"]))
    tool = data.oMf[model.getFrameId(sc.tool_frame)]
    if sc.target_frame is not None:  # welded to another robot frame: the tool in that frame
        tool = data.oMf[model.getFrameId(sc.target_frame)].actInv(tool)
    p = truth["parameters"]
    if sc.loop_type == "hinge":
        from closedloop.sims.environment import door_hinge_pose as _door_hinge_pose

        H = _door_hinge_pose(tool, sc.door)
        np.testing.assert_allclose(truth["loop"]["hinge_axis"]["point"], H.translation, atol=1e-9)
        np.testing.assert_allclose(truth["loop"]["hinge_axis"]["direction"], H.rotation[:, 2], atol=1e-9)
        return
    if sc.loop_type == "plane":  # the true tip at q0 lies on the plane; PlaneLoop's chart with reference e_z
        from closedloop.loops.plane import PlaneLoop

        plane = truth["loop"]["plane"]
        n = np.array(plane["normal"])
        np.testing.assert_allclose(plane["point"], tool.translation, atol=1e-9)
        assert n[2] > 0 and np.linalg.norm(n) == pytest.approx(1.0)
        np.testing.assert_allclose(
            PlaneLoop("x", "t").normal([p[f"{sc.loop_name}.nrx"], p[f"{sc.loop_name}.nry"]]), n, atol=1e-12
        )
        assert p[f"{sc.loop_name}.d"] == pytest.approx(float(n @ tool.translation), abs=1e-12)
        # every recorded tip (true model, true joints) stays on the plane (stiff loop: ~1e-6 m)
        fid = model.getFrameId(sc.tool_frame)
        dist = []
        for q in res.q_true:
            pin.framesForwardKinematics(model, data, q)
            dist.append(float(n @ data.oMf[fid].translation) - p[f"{sc.loop_name}.d"])
        assert np.max(np.abs(dist)) < STIFF_TOL_M
        return
    if sc.loop_type == "measured_point":  # measurements = true tip in the true tracker frame + N(0, noise)
        X = pin.SE3(
            pin.exp3(np.array([p[f"{sc.loop_name}.r{c}"] for c in "xyz"])),
            np.array([p[f"{sc.loop_name}.{c}"] for c in "xyz"]),
        )
        header, logd = _read_log(res.log_path)
        cols = [header.index(f"{sc.loop_name}:{c}") for c in "xyz"]
        assert truth["loop"]["tracker"]["columns"] == [header[c] for c in cols]
        fid = model.getFrameId(sc.tool_frame)
        err = []
        for q, m in zip(res.q_true, logd[:, cols]):
            pin.framesForwardKinematics(model, data, q)
            err.append(m - X.actInv(data.oMf[fid].translation))
        err = np.array(err)
        sigma = truth["settings"]["tracker_noise"]
        assert 0.6 * sigma < err.std() < 1.4 * sigma and abs(err.mean()) < 0.5 * sigma
        assert all(p[f"{sc.loop_name}.tip_{c}"] == 0.0 for c in "xyz")
        return
    point = sc.loop_type == "point"  # PointLoop names: contact point p*, tool tip (0 in the tool frame)
    np.testing.assert_allclose(
        [p[f"{sc.loop_name}.{'p' if point else ''}{c}"] for c in "xyz"], tool.translation, atol=1e-9
    )
    if point:
        assert all(p[f"{sc.loop_name}.tip_{c}"] == 0.0 for c in "xyz")
    else:
        r = pin.exp3(np.array([p[f"{sc.loop_name}.r{c}"] for c in "xyz"]))
        np.testing.assert_allclose(r, tool.rotation, atol=1e-9)


def test_mujoco_matches_pinocchio_true_model():
    """The MuJoCo scene of a perturbed URDF has the same tool kinematics as Pinocchio."""
    sc = SCENARIOS["panda_weld"]
    nom = nominal_urdf("panda")
    model0 = pin.buildModelFromXML(nom)
    joints = list(model0.names[1:])
    rng = np.random.default_rng(3)
    values = {n: float(rng.uniform(-0.01, 0.01)) for n in perturbable_parameters(model0, joints)}
    values["panda_joint1.x"] = 0.005  # any joint, any component
    urdf = apply_placement_errors(nom, values)
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    scene = build_scene(urdf, sc, sc.settings, joints, np.array(sc.q0))
    for _ in range(5):
        q = rng.uniform(-1.0, 1.0, model.nq)
        scene.data.qpos[scene.qpos_adr] = q
        mujoco.mj_kinematics(scene.model, scene.data)
        pin.framesForwardKinematics(model, data, q)
        np.testing.assert_allclose(
            site_pose(scene.model, scene.data, scene.tool_site).homogeneous,
            data.oMf[model.getFrameId(sc.tool_frame)].homogeneous,
            atol=1e-12,
        )
    # placement convention M = M0 * exp6(v)
    j2 = model0.getJointId("panda_joint2")
    v = np.array([values.get(f"panda_joint2.{c}", 0.0) for c in ("x", "y", "z", "rx", "ry", "rz")])
    expected = model0.jointPlacements[j2] * pin.exp6(pin.Motion(v[:3], v[3:]))
    np.testing.assert_allclose(model.jointPlacements[j2].homogeneous, expected.homogeneous, atol=1e-12)


def test_placement_errors_match_core_export(tmp_path):
    export = pytest.importorskip("closedloop.output.urdf")
    robot_mod = pytest.importorskip("closedloop.model.robot")
    path = tmp_path / "nominal.urdf"
    path.write_text(nominal_urdf("ur5"))
    robot = robot_mod.RobotModel.from_file(path)
    values = {"elbow_joint.x": 0.002, "wrist_1_joint.rz": -0.003, "wrist_2_joint.y": 0.001}
    export.write_urdf(robot, values, tmp_path / "core.urdf", fold_offsets=False)
    a = pin.buildModelFromXML((tmp_path / "core.urdf").read_text())
    b = pin.buildModelFromXML(apply_placement_errors(path.read_text(), values))
    for j in range(1, a.njoints):
        np.testing.assert_allclose(a.jointPlacements[j].homogeneous, b.jointPlacements[j].homogeneous, atol=1e-12)


@pytest.mark.parametrize("name", ["ur5_tracker", "ur5_plane"])
def test_determinism_new_scenarios(name, tmp_path):
    a = simulate(name, 6, 7, tmp_path / "a")
    b = simulate(name, 6, 7, tmp_path / "b")
    c = simulate(name, 6, 8, tmp_path / "c")
    assert a.log_path.read_bytes() == b.log_path.read_bytes()
    assert a.truth_path.read_text() == b.truth_path.read_text()
    assert a.log_path.read_bytes() != c.log_path.read_bytes()
    assert a.truth["loop"] != c.truth["loop"] or name == "ur5_tracker"  # the plane is drawn per seed
    if name == "ur5_tracker":  # so is the tracker
        assert a.truth["loop"]["tracker"]["frame"] != c.truth["loop"]["tracker"]["frame"]


def test_old_scenarios_ignore_new_settings(tmp_path):
    """The tracker setting is written only for measured loops (older truth.json files unchanged)."""
    res = simulate("ur5_socket", 2, 0, tmp_path)
    assert "tracker_noise" not in res.truth["settings"]


def test_determinism(tmp_path):
    a = simulate("ur5_socket", 10, 7, tmp_path / "a")
    b = simulate("ur5_socket", 10, 7, tmp_path / "b")
    c = simulate("ur5_socket", 10, 8, tmp_path / "c")
    assert a.log_path.read_bytes() == b.log_path.read_bytes()
    assert a.truth_path.read_text() == b.truth_path.read_text()
    assert a.log_path.read_bytes() != c.log_path.read_bytes()


@pytest.mark.parametrize("name", ["panda_weld", "ur5_socket"])
def test_planning_ahead_gives_the_same_dataset(name, tmp_path, monkeypatch):
    """Waypoints planned in blocks before they are driven (tracking._AHEAD) = planned one at a time:
    the same log and truth.json byte for byte, the planner's counters included (no waypoint planned
    but not driven), with blocks shorter than the dataset (several blocks, the last one cut short)."""
    import closedloop.sims.tracking as tracking

    runs = {}
    for ahead in (1, 4, 256):
        monkeypatch.setattr(tracking, "_AHEAD", ahead)
        runs[ahead] = simulate(name, 10, 7, tmp_path / str(ahead))
    one = runs[1]
    assert one.truth["samples"]["qp_solves"] >= 10
    for res in (runs[4], runs[256]):
        assert res.log_path.read_bytes() == one.log_path.read_bytes()
        assert res.truth_path.read_text() == one.truth_path.read_text()


def test_sensor_model(tmp_path):
    """readings = (q_true - offset) / scale (+ noise, quantized) against MuJoCo qpos."""
    res = simulate("ur5_socket", 12, 1, tmp_path / "exact", scale=0.01)
    p = res.truth["parameters"]
    off = np.array([p.get(f"{j}.offset", 0.0) for j in res.joint_names])
    sca = np.array([p.get(f"{j}.scale", 1.0) for j in res.joint_names])
    assert np.any(sca != 1.0) and np.any(off != 0.0) and off[0] == 0.0
    np.testing.assert_allclose(res.readings, (res.q_true - off) / sca, rtol=0, atol=1e-15)
    np.testing.assert_allclose(sca * res.readings + off, res.q_true, atol=1e-12)  # thesis eq. 4.4

    quantum = 1e-4
    res_q = simulate("ur5_socket", 12, 1, tmp_path / "quant", scale=0.01, quantization=quantum)
    exact = (res_q.q_true - off) / sca
    steps = res_q.readings / quantum
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert np.max(np.abs(res_q.readings - exact)) <= quantum / 2 + 1e-12

    noise = 1e-3
    res_n = simulate("ur5_socket", 40, 1, tmp_path / "noise", noise=noise)
    pn = res_n.truth["parameters"]
    off_n = np.array([pn.get(f"{j}.offset", 0.0) for j in res_n.joint_names])
    resid = res_n.readings - (res_n.q_true - off_n)
    assert 0.7 * noise < resid.std() < 1.3 * noise
    assert abs(resid.mean()) < 0.3 * noise


def test_sensor_readings_function():
    q = np.array([0.1, -0.2])
    r = sensor_readings(q, np.array([0.01, 0.0]), np.array([1.0, 1.1]), 0.0, 0.0, None)
    np.testing.assert_allclose(r, [(0.1 - 0.01), -0.2 / 1.1])
    with pytest.raises(ValueError):
        sensor_readings(q, np.zeros(2), np.ones(2), 0.1, 0.0, None)


def test_settings_overrides_and_errors(tmp_path):
    with pytest.raises(TypeError):
        simulate("ur5_socket", 2, 0, tmp_path, no_such_setting=1)
    with pytest.raises(KeyError):
        simulate("nope", 2, 0, tmp_path)
    s = SimSettings.stiff()
    assert s.solref[0] == pytest.approx(2 * s.timestep)
    res = simulate("ur5_door", 5, 0, tmp_path / "g", gravity=False)
    assert res.truth["settings"]["gravity"] is False
    xml = res.scene_path.read_text()
    assert 'gravity="0 0 0"' in xml


def test_simulate_does_not_print(tmp_path, capsys):
    simulate("ur5_socket", 3, 0, tmp_path)
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""


def test_box_qp_is_exact():
    """The planner's active-set box QP solves min 1/2 x'Px + c'x, lb <= x <= ub exactly (KKT), as OSQP does."""
    import warnings

    import scipy.sparse as sp
    from qpsolvers import solve_qp

    from closedloop.sims.driver import solve_box_qp

    rng = np.random.default_rng(0)
    active = 0
    for _ in range(300):
        n = int(rng.integers(1, 10))
        jac = rng.normal(size=(int(rng.integers(1, n + 1)), n))
        P = np.eye(n) + 10 ** rng.uniform(0, 4) * jac.T @ jac
        c = rng.normal(size=n) * rng.uniform(0.01, 3.0)
        lb = -rng.uniform(0.0, 0.3, n) * (rng.uniform(size=n) < 0.7)
        ub = rng.uniform(0.0, 0.3, n)
        if rng.uniform() < 0.2:  # a start outside the box (0 infeasible)
            lb[0], ub[0] = 0.05, max(ub[0], 0.1)
        x = solve_box_qp(P, c, lb, ub)
        assert x is not None and np.all(x >= lb) and np.all(x <= ub)
        g = P @ x + c
        free = (x > lb) & (x < ub)
        active += int(np.sum(~free))
        assert np.all(np.abs(g[free]) < 1e-9 * (1 + np.abs(P).max()))
        assert np.all(g[x == lb] >= -1e-9) and np.all(g[x == ub] <= 1e-9)  # multipliers of active bounds
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            y = solve_qp(
                sp.csc_matrix(P),
                c,
                lb=lb,
                ub=ub,
                solver="osqp",
                eps_abs=1e-10,
                eps_rel=1e-10,
                verbose=False,
                max_iter=100000,
            )
        if y is not None:
            np.testing.assert_allclose(x, y, atol=1e-6)
    assert active > 300  # the bounds were active in many problems
    assert solve_box_qp(np.eye(2), np.zeros(2), np.array([1.0, 0.0]), np.array([0.0, 1.0])) is None  # lb > ub


def test_relax_passes_unload_the_loop(tmp_path):
    """Each relax pass releases most of the preload left by the previous one (measured: 3 passes load the Panda's
    weld 78x (position) and 108x (rotation) less than 1 pass, n = 20, seed 0)."""
    one = simulate("panda_weld", 20, 0, tmp_path / "one", relax_passes=1).truth["violation"]
    three = simulate("panda_weld", 20, 0, tmp_path / "three").truth["violation"]
    assert three["rms_m"] * 20 < one["rms_m"] and three["rms_rad"] * 20 < one["rms_rad"]
    assert three["rms_m"] < 2e-8 and three["rms_rad"] < 5e-7


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_truth_support_is_what_a_calibration_estimates(name, tmp_path):
    """The simulator reads the identifiable set off the structure (`closedloop.studies.identifiable`, no fit);
    a calibration of the same loop on the same exact nominal data estimates exactly that set, in order
    (scale factors included: one is held when all are free)."""
    from support import calibrated_names

    from closedloop.assets.catalog import nominal_urdf
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.io.logs import JointLog
    from closedloop.model.robot import RobotModel
    from closedloop.sims.loop_types import sim_loop
    from closedloop.studies.identifiable import tool_points

    sc = SCENARIOS[name]
    path = tmp_path / "nominal.urdf"
    path.write_text(nominal_urdf(sc.robot))
    robot = RobotModel.from_file(path)
    joints = list(robot.joint_names)
    kind = sim_loop(sc.loop_type)
    loop = kind.core_loop(sc, path)
    for scale in (False, True):
        options = CalibrationOptions(identify=["placement", "offset", "loop"] + (["scale"] if scale else []))
        if kind.closed:
            expected = calibrated_names(robot, [loop], np.asarray(sc.q0)[None, :], options)
        else:  # the same random configurations, the tool point measured exactly at the base
            model = robot.model
            q = np.random.default_rng(0).uniform(
                np.maximum(model.lowerPositionLimit, -np.pi),
                np.minimum(model.upperPositionLimit, np.pi),
                (40, model.nq),
            )
            pts = tool_points(robot, loop.frame_a, q)
            log = JointLog(joints, q, None, None, {c: pts[:, k] for k, c in enumerate(loop.columns())})
            res = calibrate(robot, log, [loop], options)
            expected = [
                n for n, s in zip(res.fit.names, res.fit.status) if s == "estimated" and n.rsplit(".", 1)[0] in joints
            ]
        assert identifiable_parameters(path, sc, joints, scale) == expected, (name, scale)
        assert len(expected) >= 13
