"""A MuJoCo camera scenario: a UR5 with a marker on its tool, tracked by a head with two panning cameras.

The thesis's hand-eye system (chapter 5, Fig. 5-3): an arm and a stereo head
whose cameras each turn on their own sensed joint, calibrated together from
joint readings and image points alone.  The robot (``head_urdf``) is the
nominal UR5 plus a head fixed in front of it: ``head_base`` 1.3 m away facing
the arm, and per eye a pan joint (``cam_left_pan``, ``cam_right_pan``, axes
vertical, 18 cm apart, or verging by ``verge`` rad about the head's forward
axis), a link and a ROS optical frame (``cam_left_optical``: z along the line
of sight, x right, y down).

``simulate_head`` draws the truth per seed: the UR5's and the pan joints'
placement errors and offsets (only those a calibration on nominal data
estimates, so that the truth is in the identifiable parameterisation; 1 mm /
1 mrad / 10 mrad as in the other scenarios; the pan joints' translations stay
as built: the head is the length reference, as in the thesis's 5.5 where one
camera length is fixed, so whichever head length the calibration holds to set
the scale is exact), each camera's mounting error in its optical frame
(5 mm, 20 mrad) and the marker on the tool.  The true robot is loaded in
MuJoCo with a MuJoCo camera per eye (``fovy`` 50 deg, 640 x 480 px) and a
marker site; the arm goes to random configurations, the nominal model turns
each camera towards where it believes the marker is, and the image points
come from MuJoCo's own camera model: the marker in the camera frame
(``cam_xpos``, ``cam_xmat``), f = (H/2) / tan(fovy/2), principal point
((W-1)/2, (H-1)/2) in pixel-index coordinates (``tests/test_camera_scene.py``
checks this against a rendered frame), Gaussian pixel noise (0.1 px); a marker outside
an image is a missing view (NaN).  Joint readings get Gaussian noise.

Files: ``log.csv`` (joint readings, ``cam:u1 v1 u2 v2``), ``nominal.urdf``,
``truth.json`` (parameters and the intrinsics, camera poses, marker),
``left.yaml``/``right.yaml`` (the true intrinsics as ROS camera_info files),
``scene.xml``.  Calibrate with ``CALIBRATE_LOOP`` and compare with
``closedloop check`` at the documented tolerances (``CHECK_TOLERANCES``:
3 mm, 10 mrad, 1 px; 150 configurations).  Looser than the arm scenarios'
1 mm / 5 mrad because of what the cameras see: the arm's base is 1.3 m from
two cameras 18 cm apart, and at 0.1 px its position across the line of sight
has a standard error of ~1.4 mm (the report's own), a camera's position in
its optical frame ~0.6 mm.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.assets.catalog import ROBOTS, nominal_urdf
from closedloop.model.robot import find_frame
from closedloop.sims.outputs import with_visuals
from closedloop.sims.scenarios import CAMERA_LOOP, CAMERA_SCENARIOS, CameraScenario

CAMERAS = ("left", "right")
CAMERA_FILES = tuple(f"{c}.yaml" for c in CAMERAS)  # their camera_info files
FOVY_DEG = 50.0
WIDTH, HEIGHT = 640, 480
HEAD_XYZ = (1.3, 0.0, 0.9)
HEAD_PITCH = 0.35  # the head looks down at the workspace (rad)
EYE_SEPARATION = 0.18
MARKER = np.array([0.03, -0.02, 0.09])  # the true marker in tool0 (unknown to the calibration)
LOOP_NAME = "cam"
CALIBRATE_LOOP = CAMERA_LOOP  # its name is LOOP_NAME
CHECK_TOLERANCES = {"tol_m": 3e-3, "tol_rad": 1e-2, "tol_px": 1.0}  # see the module docstring
_OPTICAL_RPY = (-np.pi / 2, 0.0, -np.pi / 2)  # link (x forward, z up) -> optical (z forward, x right, y down)


def mujoco_intrinsics(fovy_deg: float = FOVY_DEG, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """(fx, fy, cx, cy) of a MuJoCo camera: square pixels, f = (H/2)/tan(fovy/2), centre ((W-1)/2, (H-1)/2)."""
    f = 0.5 * height / np.tan(0.5 * np.deg2rad(fovy_deg))
    return np.array([f, f, 0.5 * (width - 1), 0.5 * (height - 1)])


def head_urdf(verge: float = 0.0, robot: str = "ur5") -> str:
    """The nominal UR5 (``closedloop.assets``) plus the head: two pan joints, two optical frames.

    ``verge``: each pan axis is turned by +-verge about the head's forward
    axis (0: parallel axes, the thesis's 5.4 case).
    """
    root = ET.fromstring(nominal_urdf(robot))

    def link(name: str) -> None:
        el = ET.SubElement(root, "link", name=name)
        inertial = ET.SubElement(el, "inertial")
        ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(inertial, "mass", value="0.1")
        ET.SubElement(inertial, "inertia", ixx="1e-4", ixy="0", ixz="0", iyy="1e-4", iyz="0", izz="1e-4")

    def joint(name: str, kind: str, parent: str, child: str, xyz, rpy, axis=None) -> None:
        el = ET.SubElement(root, "joint", name=name, type=kind)
        ET.SubElement(el, "parent", link=parent)
        ET.SubElement(el, "child", link=child)
        ET.SubElement(
            el, "origin", xyz=" ".join(repr(float(v)) for v in xyz), rpy=" ".join(repr(float(v)) for v in rpy)
        )
        if axis is not None:
            ET.SubElement(el, "axis", xyz=" ".join(str(v) for v in axis))
            ET.SubElement(el, "limit", effort="10", lower="-1.5", upper="1.5", velocity="2")

    link("head_base")
    joint("head_mount", "fixed", "base_link", "head_base", HEAD_XYZ, (0.0, HEAD_PITCH, np.pi))
    for side, sgn in (("left", 1.0), ("right", -1.0)):
        link(f"cam_{side}_link")
        link(f"cam_{side}_optical")
        joint(
            f"cam_{side}_pan",
            "revolute",
            "head_base",
            f"cam_{side}_link",
            (0.0, sgn * EYE_SEPARATION / 2, 0.0),
            (sgn * verge, 0.0, 0.0),
            axis=(0, 0, 1),
        )
        joint(
            f"cam_{side}_optical_joint",
            "fixed",
            f"cam_{side}_link",
            f"cam_{side}_optical",
            (0.0, 0.0, 0.0),
            _OPTICAL_RPY,
        )
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")


def pan_towards(robot, q: np.ndarray, joints: list[str], point_world: np.ndarray, side: str) -> float:
    """The pan angle that turns camera `side`'s optical axis towards a world point (pan about its own axis)."""
    model = robot.model
    data = model.createData()
    pin.forwardKinematics(model, data, q)
    jid = model.getJointId(f"cam_{side}_pan")
    # the pan joint frame at zero angle: parent placement * joint placement
    T0 = data.oMi[model.parents[jid]] * model.jointPlacements[jid]
    p = T0.actInv(point_world)
    return float(np.arctan2(p[1], p[0]))


# --------------------------------------------------------------------------- the MuJoCo scene
def _mujoco_scene(true_urdf_text: str, mounts: list[pin.SE3], fovy: float):
    """The true robot in MuJoCo with a camera per eye (at its true mounting) and a marker site on tool0."""
    import mujoco

    tag = '<mujoco><compiler fusestatic="false" discardvisual="true" angle="radian"/></mujoco>'
    root = ET.fromstring(true_urdf_text)
    root.insert(0, ET.fromstring(tag))
    spec = mujoco.MjSpec.from_string(ET.tostring(root, encoding="unicode"))
    spec.visual.global_.offwidth, spec.visual.global_.offheight = WIDTH, HEIGHT
    flip = np.diag([1.0, -1.0, -1.0])  # optical (z forward, y down) -> MuJoCo camera (looks along -z, y up)
    for side, X in zip(CAMERAS, mounts):
        body = spec.body(f"cam_{side}_optical")
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(X.rotation @ flip).reshape(9))
        cam = body.add_camera()
        cam.name, cam.pos, cam.quat, cam.fovy = side, X.translation, q, fovy
    tool = spec.body("tool0")
    site = tool.add_site()
    site.name, site.pos = "marker", MARKER
    geom = tool.add_geom()
    geom.type, geom.size, geom.pos = mujoco.mjtGeom.mjGEOM_SPHERE, [0.004, 0, 0], MARKER
    geom.rgba, geom.contype, geom.conaffinity = [1, 1, 1, 1], 0, 0
    light = spec.worldbody.add_light()
    light.pos, light.dir = [0.5, 0, 3.0], [0, 0, -1]
    model = spec.compile()
    return spec, model


def mujoco_pixels(model, data) -> np.ndarray:
    """(cameras, 2) image points of the marker site from MuJoCo's camera data (cam_xpos, cam_xmat, fovy).

    In the camera frame (x right, y up, looking along -z): u = cx + f x/(-z),
    v = cy - f y/(-z), f = (H/2)/tan(fovy/2), (cx, cy) = ((W-1)/2, (H-1)/2);
    NaN when the marker is behind the camera or outside the image.
    """
    import mujoco

    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "marker")
    x = data.site_xpos[sid]
    out = np.full((len(CAMERAS), 2), np.nan)
    for c, side in enumerate(CAMERAS):
        cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, side)
        k = mujoco_intrinsics(float(model.cam_fovy[cid]))
        p = data.cam_xmat[cid].reshape(3, 3).T @ (x - data.cam_xpos[cid])
        if p[2] >= -1e-3:
            continue
        u, v = k[2] + k[0] * p[0] / -p[2], k[3] - k[1] * p[1] / -p[2]
        if 0 <= u <= WIDTH - 1 and 0 <= v <= HEIGHT - 1:
            out[c] = u, v
    return out


def _identifiable(robot, theta: np.ndarray) -> list[str]:
    """Robot parameters a calibration estimates on exact pixels of the nominal robot (the truth's support).

    The camera loop's problem on the readings `theta` with the nominal marker's exact image points,
    its unknowns closing them, and the structural reduction there (:mod:`closedloop.studies.identifiable`).
    """
    from closedloop.loops.camera.loop import CameraLoop
    from closedloop.loops.spec import parse_loop
    from closedloop.studies.identifiable import closing_values, estimated_indices, loop_joints, nominal_problem

    names = robot.joint_names
    loop = parse_loop(CALIBRATE_LOOP, robot)
    assert isinstance(loop, CameraLoop)  # CALIBRATE_LOOP is a camera loop's spec
    theta = np.asarray(theta, dtype=float)[:, [names.index(j) for j in loop_joints(robot, [loop])]]
    prob = nominal_problem(robot, [loop], [theta], [np.zeros((len(theta), len(loop.columns())))])
    Ts = prob.loop_frame_poses(prob.nominal, 0)
    K = mujoco_intrinsics()
    cols = {}
    for c, (f, T) in enumerate(zip(loop.camera_frames, Ts[1:])):
        pc = np.einsum("nji,nj->ni", T[:, :3, :3], Ts[0][:, :3, :3] @ MARKER + Ts[0][:, :3, 3] - T[:, :3, 3])
        cols[f"{LOOP_NAME}:u{c + 1}"] = K[0] * pc[:, 0] / pc[:, 2] + K[2]
        cols[f"{LOOP_NAME}:v{c + 1}"] = K[1] * pc[:, 1] / pc[:, 2] + K[3]
    meas = loop.measurements(cols, np.arange(len(theta)))
    problem = nominal_problem(robot, [loop], [theta], [meas])
    own = LOOP_NAME + "."
    kept = estimated_indices(problem, closing_values(problem))
    return [problem.names[k] for k in kept if not problem.names[k].startswith(own)]


def _readings(robot, sc: CameraScenario, n: int, rng: np.random.Generator) -> np.ndarray:
    """Arm readings around q0; each pan turned (nominal model) towards the nominal marker, + tracking jitter."""
    names = robot.joint_names
    m = robot.model
    d = m.createData()
    th = np.zeros((n, len(names)))
    arm = [i for i, j in enumerate(names) if not j.startswith("cam_")]
    for i in range(n):
        th[i, arm] = np.asarray(sc.q0) + rng.uniform(-sc.arm_range, sc.arm_range, len(arm))
        q = robot.configurations(th[i : i + 1], names)[0]
        pin.framesForwardKinematics(m, d, q)
        x = d.oMf[find_frame(m, "tool0")].act(MARKER)
        for side in CAMERAS:
            th[i, names.index(f"cam_{side}_pan")] = pan_towards(robot, q, names, x, side) + rng.uniform(
                -sc.jitter, sc.jitter
            )
    return th


def simulate_head(scenario: str, n: int, seed: int, out_dir: Path | str) -> dict:
    """Write a head-camera dataset (module docstring) to `out_dir`, published whole (`io.files.OutputSet`:
    the old dataset or the new one, truth.json last); returns a summary dict."""
    import tempfile

    from closedloop.io.files import OutputSet

    out = Path(out_dir)
    files = OutputSet(order=[out / f for f in ("nominal.urdf", "scene.xml", "log.csv", *CAMERA_FILES, "truth.json")])
    with tempfile.TemporaryDirectory(prefix="closedloop-sim-") as scratch:  # the nominal model read back
        summary = _simulate_head(scenario, n, seed, out, Path(scratch) / "nominal.urdf", files)
    files.commit()
    return summary


def _simulate_head(scenario: str, n: int, seed: int, out: Path, nominal_path: Path, files) -> dict:
    import mujoco

    from closedloop.io.camera_info import CameraInfo, camera_info_text
    from closedloop.io.logs import write_log_csv
    from closedloop.model.robot import RobotModel
    from closedloop.sims.scene import true_urdf

    sc = CAMERA_SCENARIOS[scenario]
    rng_truth, rng_plan, rng_noise = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    nominal_path.write_text(head_urdf(sc.verge))
    robot = RobotModel.from_file(nominal_path)
    names = robot.joint_names
    readings = _readings(robot, sc, n, rng_plan)
    truth: dict[str, float] = {}
    for name in _identifiable(robot, readings[: min(n, 60)]):
        kind = name.rsplit(".", 1)[1]
        if name.startswith("cam_") and kind in ("x", "y", "z"):
            continue  # the head's lengths as built: the length reference (thesis 5.5 fixes a camera length)
        mag = sc.offset if kind == "offset" else sc.translation if kind in ("x", "y", "z") else sc.rotation
        truth[name] = float(rng_truth.uniform(-mag, mag))
    mounts = [
        pin.SE3(pin.exp3(rng_truth.uniform(-sc.mount_r, sc.mount_r, 3)), rng_truth.uniform(-sc.mount_t, sc.mount_t, 3))
        for _ in CAMERAS
    ]
    spec, model = _mujoco_scene(true_urdf(nominal_path, truth), mounts, FOVY_DEG)
    data = mujoco.MjData(model)
    offsets = np.array([truth.get(f"{j}.offset", 0.0) for j in names])
    qadr = [model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in names]
    uv = np.empty((n, 2 * len(CAMERAS)))
    for i in range(n):
        data.qpos[qadr] = readings[i] + offsets  # theta_true = reading + offset (scale 1)
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        uv[i] = mujoco_pixels(model, data).reshape(-1)
    seen = np.isfinite(uv)
    uv = uv + rng_noise.normal(scale=sc.sigma_px, size=uv.shape)
    logged = readings + rng_noise.normal(scale=sc.sigma_q, size=readings.shape)
    cols = [f"{LOOP_NAME}:{a}{c + 1}" for c in range(len(CAMERAS)) for a in ("u", "v")]
    columns = {j: logged[:, k] for k, j in enumerate(names)} | {c: uv[:, k] for k, c in enumerate(cols)}
    write_log_csv(out / "log.csv", columns, files)  # a missed view: empty cells
    K = mujoco_intrinsics()
    params = dict(truth)
    for c, X in enumerate(mounts):
        pre = f"{LOOP_NAME}.cam{c + 1}."
        v = np.concatenate([X.translation, pin.log3(X.rotation)])
        params |= {pre + f: float(x) for f, x in zip(("x", "y", "z", "rx", "ry", "rz"), v)}
        params |= {pre + f: float(x) for f, x in zip(("fx", "fy", "cx", "cy"), K)}
        files.add(out / f"{CAMERAS[c]}.yaml", camera_info_text(CameraInfo(K, np.zeros(5), WIDTH, HEIGHT, CAMERAS[c])))
    params |= {f"{LOOP_NAME}.tip_{a}": float(x) for a, x in zip("xyz", MARKER)}
    doc = {
        "scenario": scenario,
        "seed": seed,
        "n": n,
        "parameters": params,
        "cameras": {"fovy_deg": FOVY_DEG, "width": WIDTH, "height": HEIGHT, "intrinsics": K.tolist()},
        "noise": {"sigma_px": sc.sigma_px, "sigma_q": sc.sigma_q},
        "missing_views": int(np.sum(~seen[:, 0::2])),
        "calibrate_loop": CALIBRATE_LOOP,
        "check_tolerances": CHECK_TOLERANCES,
    }
    files.add(out / "truth.json", json.dumps(doc, indent=1))
    files.add(out / "scene.xml", spec.to_xml())
    # the nominal file a viewer shows: the UR5's visuals put back (the head's links have none), same kinematics
    files.add(out / "nominal.urdf", with_visuals(nominal_path.read_text(), ROBOTS["ur5"].path))
    return {"n": n, "missing_views": doc["missing_views"], "out": str(out)}
