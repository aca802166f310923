"""True robot URDF and the MuJoCo scene that closes its loop.

:func:`true_urdf` writes the true robot (nominal URDF with joint placement
errors ``M = M0 * exp6(v)``) through the core's ``closedloop.output.urdf.write_urdf``;
:func:`apply_placement_errors` states the same convention on the XML alone (the tests check the two
agree).  Offsets and scales are *not* folded into the true URDF: they are
sensor properties applied by the sensor model.

:func:`build_scene` converts the true URDF to MJCF with ``MjSpec`` and adds

* a position servo per arm joint (``tau = kp (ctrl - q) - kv qdot``), armature,
  and (setting ``gravcomp``) gravity compensation of the robot's bodies routed
  through the servos (MuJoCo ``gravcomp`` + ``actuatorgravcomp``);
* the loop: a ``weld`` between the tool site and a world fixture site (or a
  site on another body of the robot, the scenario's ``target_frame``), a
  ``connect`` between the stylus-tip site and a world socket site, or a ``weld``
  between the tool site and the handle site of a hinged door (``assets/door.xml``),
  a ``connect`` between the stylus-tip site and the centre of a passive puck
  that slides on a tilted plane (two slide joints and a ball joint; plane
  loops), or, for a measured (open) loop, no constraint but a world site at the
  external tracker's frame;
* physics options (timestep, integrator, gravity; contacts disabled).

The loop is built *closed* at the true grasp configuration ``q0``: the fixture,
socket, handle or robot target site is placed at the true tool pose at ``q0``
(MuJoCo forward kinematics of the true robot; a robot target site gets the
tool's pose relative to its body, ``relpose`` made explicit).  Site-based equality constraints make the two
sites coincide, so no ``relpose`` ambiguity arises.
"""

from __future__ import annotations

import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin

from closedloop.errors import ScenarioError
from closedloop.sims.environment import LOOP_EQ, TARGET_SITE, TOOL_SITE
from closedloop.sims.loop_types import Placement, SimLoop, sim_loop
from closedloop.sims.scenarios import Scenario, SimSettings

__all__ = ["Scene", "apply_placement_errors", "true_urdf", "build_scene", "site_pose"]

_MUJOCO_TAG = (
    '<mujoco><compiler fusestatic="false" discardvisual="true" balanceinertia="true" angle="radian"/></mujoco>'
)


def _vec(s: str | None) -> np.ndarray:
    return np.array([float(v) for v in (s or "0 0 0").split()], dtype=float)


def apply_placement_errors(urdf: str, values: dict[str, float]) -> str:
    """URDF text with joint origins ``M0`` replaced by ``M0 * exp6([x, y, z, rx, ry, rz])``.

    Only names ``<joint>.x .y .z .rx .ry .rz`` of joints present in the URDF are
    used; other names (offsets, scales, closure parameters) are ignored.
    """
    root = ET.fromstring(urdf)
    comps = ("x", "y", "z", "rx", "ry", "rz")
    for joint in root.findall("joint"):
        jn = joint.get("name")
        v = np.array([values.get(f"{jn}.{c}", 0.0) for c in comps], dtype=float)
        if not np.any(v):
            continue
        origin = joint.find("origin")
        if origin is None:
            origin = ET.SubElement(joint, "origin")
        m0 = pin.SE3(pin.rpy.rpyToMatrix(_vec(origin.get("rpy"))), _vec(origin.get("xyz")))
        m = m0 * pin.exp6(pin.Motion(v[:3], v[3:]))
        origin.set("xyz", " ".join(repr(float(a)) for a in m.translation))
        origin.set("rpy", " ".join(repr(float(a)) for a in pin.rpy.matrixToRpy(m.rotation)))
    return ET.tostring(root, encoding="unicode")


def true_urdf(nominal_urdf_path: Path, values: dict[str, float]) -> str:
    """The true robot's URDF text (placement errors applied, offsets not folded)."""
    from closedloop.model.robot import RobotModel
    from closedloop.output.urdf import write_urdf

    robot = RobotModel.from_file(nominal_urdf_path)
    known = set(robot.joint_names)
    placement = {
        k: v for k, v in values.items() if k.rsplit(".", 1)[0] in known and not k.endswith((".offset", ".scale"))
    }
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "true.urdf"
        write_urdf(robot, placement, out, fold_offsets=False)
        return out.read_text()


def site_pose(model: mujoco.MjModel, data: mujoco.MjData, site: int | str) -> pin.SE3:
    """World pose of a MuJoCo site (after ``mj_kinematics``/``mj_forward``)."""
    sid = site if isinstance(site, int) else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    return pin.SE3(data.site_xmat[sid].reshape(3, 3).copy(), data.site_xpos[sid].copy())


@dataclass
class Scene:
    """A compiled MuJoCo scene of the true robot with its loop closed.

    Attributes:
        spec: the ``MjSpec`` (``spec.to_xml()`` is the simulated scene).
        model, data: compiled model and its data, at the closed grasp configuration.
        joint_names: arm joints (Pinocchio order).
        qpos_adr, dof_adr: qpos/qvel addresses of the arm joints (matched by name).
        actuator_ids: servo of each arm joint.
        jnt_range: (n, 2) true joint limits.
        tool_site, target_site: site ids of the loop's two sides.
        eq_id: id of the loop equality constraint (-1: none, measured_point loops).
        door_qpos_adr: qpos address of the door hinge (hinge loops) else -1.
        target_pose: world pose of the target site at the start (fixture, socket or handle).
        hinge_pose: world pose of the door hinge frame (hinge loops) else None.
        closure: pose of the tool in the loop's target frame when closed (world for
            fixtures and sockets, the robot's ``target_frame`` for robot-robot welds);
            measured_point loops: the tracker frame in the world; plane loops: None.
        plane_pose: world pose of the plane frame (z = normal; plane loops) else None.
    """

    spec: mujoco.MjSpec
    model: mujoco.MjModel
    data: mujoco.MjData
    joint_names: list[str]
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    actuator_ids: np.ndarray
    jnt_range: np.ndarray
    tool_site: int
    target_site: int
    eq_id: int
    door_qpos_adr: int
    target_pose: pin.SE3
    hinge_pose: pin.SE3 | None
    closure: pin.SE3 | None = None
    plane_pose: pin.SE3 | None = None

    def to_xml(self) -> str:
        """MJCF text of the simulated scene."""
        return self.spec.to_xml()


def build_scene(
    urdf: str,
    scenario: Scenario,
    settings: SimSettings,
    joint_names: list[str],
    q0: np.ndarray,
    rng: np.random.Generator | None = None,
) -> Scene:
    """Build the MuJoCo scene of the true robot ``urdf`` with its loop closed at ``q0``.

    Args:
        urdf: true robot URDF text.
        scenario: the scenario (loop type, tool frame, its geometry); the loop type
            (:mod:`closedloop.sims.loop_types`) places its target and names its equality.
        settings: physics settings.
        joint_names: arm joints in Pinocchio order (MuJoCo joints are matched by name).
        q0: true joint angles at which the loop is closed.
        rng: draws the plane (plane loops) or the tracker pose (measured_point loops).
    """
    spec = _robot_spec(urdf, scenario, settings, joint_names)
    # true tool pose at q0
    model = spec.compile()
    data = mujoco.MjData(model)
    qadr = np.array([model.jnt_qposadr[model.joint(jn).id] for jn in joint_names])
    data.qpos[qadr] = q0
    mujoco.mj_kinematics(model, data)
    tool = site_pose(model, data, TOOL_SITE)

    kind = sim_loop(scenario.loop_type)
    if scenario.target_frame is not None and not kind.two_chains:
        raise ScenarioError(f"{scenario.name}: a robot target frame needs a weld loop")
    placed = kind.place(spec, model, data, scenario, tool, settings, rng)  # the target site (and what carries it)
    equality = kind.equality
    if equality is not None:
        eq = spec.add_equality()
        eq.name = LOOP_EQ
        eq.type = getattr(mujoco.mjtEq, f"mjEQ_{equality.upper()}")
        eq.objtype = mujoco.mjtObj.mjOBJ_SITE
        eq.name1 = TOOL_SITE
        eq.name2 = TARGET_SITE
        eq.solref = list(settings.solref)
        eq.solimp = list(settings.solimp)

    return _closed_scene(spec, joint_names, q0, kind, placed, equality is not None)


def _robot_spec(urdf: str, scenario: Scenario, settings: SimSettings, joint_names: list[str]) -> mujoco.MjSpec:
    """The true robot as an ``MjSpec``: physics options, a position servo per arm joint, gravity
    compensation through the servos (setting ``gravcomp``), and the tool site on the loop's frame."""
    text = urdf.replace("</robot>", _MUJOCO_TAG + "</robot>")
    spec = mujoco.MjSpec.from_string(text)
    spec.modelname = f"closedloop_{scenario.name}"
    opt = spec.option
    opt.timestep = settings.timestep
    opt.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{settings.integrator.upper()}")
    opt.gravity = [0.0, 0.0, -9.81] if settings.gravity else [0.0, 0.0, 0.0]
    opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    # one loop = one constraint island: island discovery only costs time (~5% of a step, same trajectory)
    if hasattr(mujoco.mjtDisableBit, "mjDSBL_ISLAND"):
        opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ISLAND)

    for jn in joint_names:
        j = spec.joint(jn)
        if j is None:
            raise ScenarioError(f"{scenario.name}: joint {jn!r} missing from the MuJoCo model")
        j.armature = settings.armature
        j.damping = np.zeros_like(np.atleast_1d(j.damping))
        j.frictionloss = 0.0
        act = spec.add_actuator()
        act.name = f"servo_{jn}"
        act.target = jn
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.set_to_position(kp=settings.kp, kv=settings.kv)

    if settings.gravcomp:
        # gravity compensation of the robot's bodies, routed through the servos
        robot_joints = {jn for jn in joint_names}
        for body in spec.bodies:
            if body.name != "world":
                body.gravcomp = 1.0
        for jn in robot_joints:
            spec.joint(jn).actgravcomp = True

    tool_body = spec.body(scenario.tool_frame)
    if tool_body is None:
        raise ScenarioError(f"{scenario.name}: tool link {scenario.tool_frame!r} missing from the MuJoCo model")
    tool_body.add_site(name=TOOL_SITE, size=[0.01, 0.01, 0.01])

    return spec


def _closed_scene(
    spec: mujoco.MjSpec, joint_names: list[str], q0: np.ndarray, kind: SimLoop, placed: Placement, has_eq: bool
) -> Scene:
    """Compile the closed loop with a start keyframe at ``q0`` (servos holding ``q0``) and index the scene."""
    # start keyframe: closed loop at q0, servos holding q0
    key = spec.add_key()
    key.name = "grasp"

    model = spec.compile()
    data = mujoco.MjData(model)
    qadr = np.array([model.jnt_qposadr[model.joint(jn).id] for jn in joint_names])
    dadr = np.array([model.jnt_dofadr[model.joint(jn).id] for jn in joint_names])
    act_ids = np.array([model.actuator(f"servo_{jn}").id for jn in joint_names])
    data.qpos[qadr] = q0
    data.ctrl[act_ids] = q0
    door_adr = -1 if kind.env_joint is None else int(model.jnt_qposadr[model.joint(kind.env_joint).id])
    key.qpos = data.qpos.copy()
    key.ctrl = data.ctrl.copy()
    model = spec.compile()  # recompile so that the keyframe is part of the model and the XML
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    jnt_range = np.array([model.jnt_range[model.joint(jn).id] for jn in joint_names])
    target_pose = site_pose(model, data, TARGET_SITE)
    closure = placed.closure
    if closure is None and kind.target_is_closure:
        closure = target_pose
    return Scene(
        spec=spec,
        model=model,
        data=data,
        joint_names=list(joint_names),
        qpos_adr=qadr,
        dof_adr=dadr,
        actuator_ids=act_ids,
        jnt_range=jnt_range,
        tool_site=model.site(TOOL_SITE).id,
        target_site=model.site(TARGET_SITE).id,
        eq_id=model.equality(LOOP_EQ).id if has_eq else -1,
        door_qpos_adr=door_adr,
        target_pose=target_pose,
        hinge_pose=placed.hinge_pose,
        closure=closure,
        plane_pose=placed.plane_pose,
    )
