"""The simulator's loop types: one class per type of the loop registry, registered under its name.

The loop registry is `closedloop.loops.spec.LOOP_TYPES`, the one table the parser, ``closedloop
loops`` and the calibrator read.  A simulator class registers itself under a type name of that
table with the decorator :func:`simulates` (a name the table lacks is refused), into `SIM_LOOPS`;
:func:`sim_loop` refuses a type the simulator lacks in one line listing the simulated ones, and an
unknown type exactly as the parser does.  A new loop type costs its module in ``closedloop/loops/``,
its entry in `LOOP_TYPES` and its class here (``docs/architecture/adding-a-loop-type.md``).

A loop type says, for its own loop and nothing else:

* **MuJoCo**: where its target goes (:meth:`SimLoop.place`: a fixture site, a socket, a door, a
  plane's puck, a tracker) and which equality closes it (`equality`: weld, connect or none);
* **the nominal loop** the robot plans on: its target frame (:meth:`SimLoop.nominal_target`) and its
  residual ``e(q)`` with ``de/dq`` (:meth:`SimLoop.nominal_residual`, see :mod:`closedloop.sims.driver`);
* **the truth**: the calibration core's parameters of the loop at their true values
  (:meth:`SimLoop.truth_parameters`), the loop's record in ``truth.json`` (:meth:`SimLoop.truth_record`)
  and the core's loop class for this scenario (:meth:`SimLoop.core_loop`);
* its defaults: the loop name, settings it needs whatever the robot, its geometry record, its
  number of independent constraints on the driven joints (thesis Lemma 4).

``weld``
    The tool frame is welded to a fixture fixed in the world (6 constraints).  Closure parameters
    ``<loop>.x .y .z .rx .ry .rz``: pose of the fixture (= pose of the tool frame when closed) in
    the world, translation in metres, rotation vector ``pin.log3(R)``.  With a ``target_frame`` the
    tool frame is welded to that other frame of the same robot (two tips of a hand holding an
    object); the closure parameters are then the tool's pose in the target frame when closed.
``point``
    The tool point (stylus tip) sits in a ball socket (MuJoCo ``connect``, 3 constraints).
    Parameters of ``PointLoop``: ``<loop>.px .py .pz`` the socket centre, ``<loop>.tip_*`` 0.
``hinge``
    The tool is welded to the handle of a door that turns on a passive hinge: the tool frame moves
    on a 1-DOF rotation about a fixed axis (5 constraints on the arm).  The hinge axis is in
    ``truth.json`` under ``loop.hinge_axis`` (the HingeLoop's chart is relative to an axis fitted
    from data, so its parameters are not comparable with a fixed truth).
``plane``
    The stylus tip is connected (``connect``) to the centre of a passive puck that slides on a
    tilted plane drawn per seed through the true tip at ``q0`` (two slide joints, a ball joint): 1
    constraint.  Parameters of ``PlaneLoop`` with its reference normal e_z: ``<loop>.tip_*`` (0),
    ``<loop>.nrx .nry`` (n = exp3([nrx, nry, 0]) e_z, n_z > 0) and ``<loop>.d`` (= n . p on the plane).
``measured_point``
    No constraint (open loop, thesis 3.2): the robot moves to random configurations and an external
    tracker at a pose drawn per seed measures the tool point in its own frame with Gaussian noise
    (``tracker_noise``).  Log columns ``<loop>:x .y .z``; parameters of ``MeasuredPointLoop``:
    ``<loop>.x .. .rz`` the tracker frame in the base, ``<loop>.tip_*`` (0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError, ScenarioError
from closedloop.loops.spec import LOOP_TYPES, loop_type
from closedloop.model.robot import find_frame
from closedloop.sims.environment import (
    DOOR_JOINT,
    DOOR_PREFIX,
    TARGET_SITE,
    add_puck,
    door_hinge_pose,
    draw_plane,
    draw_tracker,
    quat_wxyz,
)
from closedloop.sims.scenarios import DoorGeometry, PlaneGeometry, Scenario, SimSettings, TrackerGeometry

if TYPE_CHECKING:
    import mujoco

__all__ = ["SimLoop", "Placement", "SIM_LOOPS", "simulates", "sim_loop", "simulated_types", "pose_params"]

_COMPS = ("x", "y", "z", "rx", "ry", "rz")
#: a generic tilted plane normal for the identifiability of a plane loop (see `PlaneSim.core_loop`)
GENERIC_PLANE_NORMAL = np.array([0.3, -0.2, 0.93])


def pose_params(prefix: str, pose: pin.SE3, rotation: bool = True) -> dict[str, float]:
    """``<prefix>.x .y .z [.rx .ry .rz]`` of a pose (translation, rotation vector)."""
    vals = list(pose.translation) + (list(pin.log3(pose.rotation)) if rotation else [])
    return {f"{prefix}.{c}": float(v) for c, v in zip(_COMPS, vals)}


def _zero_tip(prefix: str) -> dict[str, float]:
    return {f"{prefix}.tip_{a}": 0.0 for a in "xyz"}


@dataclass
class Placement:
    """What a loop type put in the scene: the closure (robot-robot welds), a hinge or a plane frame."""

    closure: pin.SE3 | None = None
    hinge_pose: pin.SE3 | None = None
    plane_pose: pin.SE3 | None = None


#: the simulator's loop types by their name in `closedloop.loops.spec.LOOP_TYPES` (filled by `simulates`)
SIM_LOOPS: dict[str, SimLoop] = {}


def simulates(kind: str):
    """Class decorator: register a `SimLoop` subclass as the simulator of registry loop type `kind`.

    `kind` must be an entry of `closedloop.loops.spec.LOOP_TYPES` (a `LoopError` says to add it
    there otherwise); the class gets ``kind`` and one instance goes into `SIM_LOOPS`.
    """
    if kind not in LOOP_TYPES:
        raise LoopError(f"loop type '{kind}' has no entry in closedloop.loops.spec.LOOP_TYPES (add it there)")

    def deco(cls: type[SimLoop]) -> type[SimLoop]:
        cls.kind = kind
        SIM_LOOPS[kind] = cls()
        return cls

    return deco


def simulated_types() -> list[str]:
    """The registry's loop types the simulator simulates, sorted."""
    return sorted(SIM_LOOPS)


def sim_loop(kind: str) -> SimLoop:
    """The simulator's class of registry loop type `kind`.

    An unknown type is refused as the parser refuses it (`closedloop.loops.spec.loop_type`), a
    registry type the simulator lacks in one line naming the simulated types (`ScenarioError`).
    """
    if kind in SIM_LOOPS:
        return SIM_LOOPS[kind]
    try:
        loop_type(kind)
    except LoopError as exc:
        raise ScenarioError(f"{exc}; the simulator simulates: {', '.join(simulated_types())}") from None
    raise ScenarioError(f"the simulator has no '{kind}' loop (it simulates: {', '.join(simulated_types())})")


class SimLoop:
    """One loop type of the simulator (module docstring).  Defaults: a weld to a world fixture."""

    #: its name in `closedloop.loops.spec.LOOP_TYPES` (set by `simulates`)
    kind: ClassVar[str] = ""
    default_name: ClassVar[str] = ""
    #: independent constraints on the driven joints (the self-motion check of robot_scenario)
    constraints: ClassVar[int] = 6
    #: the constraint has rotation rows (the grasp-pose choice weighs them by the reach)
    pose_rows: ClassVar[bool] = True
    #: rows of the nominal residual e(q)
    residual_rows: ClassVar[int] = 6
    #: MuJoCo equality between the tool site and the target site: ``weld``, ``connect`` (``mjtEq.mjEQ_<NAME>``)
    #: or None (no constraint)
    equality: ClassVar[str | None] = "weld"
    #: the violation is a distance only (the tool may turn about the contact)
    point_contact: ClassVar[bool] = False
    #: False: an open loop (no constraint; random configurations; a tracker measures the tool)
    closed: ClassVar[bool] = True
    #: may close on another frame of the robot (``to=``)
    two_chains: ClassVar[bool] = False
    #: its environment (plane, tracker) is drawn from the fourth random stream
    draws_environment: ClassVar[bool] = False
    #: the target site's pose is the loop's closure pose (truth)
    target_is_closure: ClassVar[bool] = True
    #: the Scenario field of its geometry and that geometry's class (a default is filled in)
    geometry: ClassVar[tuple[str, type] | None] = None
    #: settings it needs whatever the robot (a scenario's own settings win)
    settings: ClassVar[dict[str, Any]] = {}
    #: a passive joint of the environment whose angle is logged (``door_angle``)
    env_joint: ClassVar[str | None] = None
    #: settings only this loop type uses: written to truth.json only for it (the others' stays as it was)
    own_settings: ClassVar[tuple[str, ...]] = ()

    def independent(self, rank: int) -> int:
        """Independent constraints given the rank of the loop's constraint Jacobian on the robot."""
        return min(rank, self.constraints)

    # ------------------------------------------------------------------ MuJoCo
    def place(
        self,
        spec: mujoco.MjSpec,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        scenario: Scenario,
        tool: pin.SE3,
        settings: SimSettings,
        rng: np.random.Generator | None,
    ) -> Placement:
        """Add the loop's target site (and what carries it) with the loop closed at the true tool pose."""
        spec.worldbody.add_site(
            name=TARGET_SITE, pos=tool.translation, quat=quat_wxyz(tool.rotation), size=[0.02, 0.02, 0.02]
        )
        return Placement()

    # ------------------------------------------------------------------ nominal loop
    def nominal_target(
        self,
        loop,
        data,
        oMt0: pin.SE3,
        hinge: pin.SE3 | None,
        door_range: tuple[float, float],
        target_frame: str | None,
    ) -> int:
        """The frame the nominal loop closes on (added to ``loop.model``): the nominal tool at the grasp."""
        if target_frame is not None:
            raise ScenarioError("a robot target frame needs a weld loop")
        return loop.model.addFrame(pin.Frame("loop_target", 0, oMt0, pin.FrameType.OP_FRAME))

    def nominal_residual(self, loop, d, oMt: pin.SE3, jt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``e = log6(oMh^-1 oMt)``, ``de/dq = Jlog6(hMt) (J_t - Ad(tMh) J_h)`` (LOCAL Jacobians)."""
        oMh = loop.target_placement  # d.oMf[loop.target]
        hMt = oMh.actInv(oMt)
        e = pin.log6(hMt).vector
        if loop.target_fixed:  # a fixture in the world: J_h = 0
            return e, pin.Jlog6(hMt) @ jt
        jh = pin.getFrameJacobian(loop.model, d, loop.target, pin.ReferenceFrame.LOCAL)
        return e, pin.Jlog6(hMt) @ (jt - hMt.inverse().action @ jh)

    # ------------------------------------------------------------------ truth
    def truth_parameters(self, name: str, scene) -> dict[str, float]:
        """The core loop's parameters at their true values."""
        return pose_params(name, scene.closure)

    def truth_record(self, name: str, scene, settings: SimSettings, measured: list[str]) -> dict[str, Any]:
        """What ``truth.json`` says of the loop beyond its type, frames and name."""
        return {}

    def calibrate_keys(self, settings: SimSettings) -> dict[str, str]:
        """Keys of the ``calibrate --loop`` spec beyond frame, to and name (a measurement's noise)."""
        return {}

    def core_loop(self, sc: Scenario, nominal_path=None, sigma_t: float | None = None):
        """The calibration core's loop for the scenario (None when it needs what is not given)."""
        from closedloop.loops import WeldLoop

        return WeldLoop(sc.loop_name, sc.tool_frame, sc.target_frame or "universe")


@simulates("weld")
class WeldSim(SimLoop):
    """``weld``: the tool welded to a world fixture, or to another frame of the robot (``target_frame``)."""

    default_name = "fixture"
    two_chains = True

    def place(self, spec, model, data, scenario, tool, settings, rng) -> Placement:
        if scenario.target_frame is None:
            return super().place(spec, model, data, scenario, tool, settings, rng)
        target_body = spec.body(scenario.target_frame)
        if target_body is None:
            raise ScenarioError(f"{scenario.name}: target link {scenario.target_frame!r} missing from the MuJoCo model")
        bid = model.body(scenario.target_frame).id
        body = pin.SE3(data.xmat[bid].reshape(3, 3).copy(), data.xpos[bid].copy())
        closure = body.actInv(tool)  # relpose: the tool in the target body at q0
        target_body.add_site(
            name=TARGET_SITE, pos=closure.translation, quat=quat_wxyz(closure.rotation), size=[0.01, 0.01, 0.01]
        )
        return Placement(closure=closure)

    def nominal_target(self, loop, data, oMt0, hinge, door_range, target_frame) -> int:
        if target_frame is None:
            return super().nominal_target(loop, data, oMt0, hinge, door_range, target_frame)
        model = loop.model
        if not model.existFrame(target_frame):
            raise ScenarioError(f"frame {target_frame!r} not in the nominal model")
        fb = model.frames[find_frame(model, target_frame)]
        placement = fb.placement * data.oMf[find_frame(model, target_frame)].actInv(oMt0)
        return model.addFrame(pin.Frame("loop_target", fb.parentJoint, placement, pin.FrameType.OP_FRAME))


@simulates("point")
class PointSim(SimLoop):
    """``point``: the stylus tip in a ball socket fixed in the world."""

    default_name = "socket"
    constraints = 3
    pose_rows = False
    residual_rows = 3
    equality = "connect"
    point_contact = True

    def nominal_residual(self, loop, d, oMt, jt):
        """``e = p_t - p`` (3 rows), ``de/dq = R_t J_t[:3]``."""
        return oMt.translation - loop.point, oMt.rotation @ jt[:3]

    def truth_parameters(self, name, scene):
        c = scene.target_pose.translation  # names of closedloop.loops.PointLoop: contact point, tip in the tool
        return {**{f"{name}.p{a}": float(v) for a, v in zip("xyz", c)}, **_zero_tip(name)}

    def core_loop(self, sc, nominal_path=None, sigma_t=None):
        from closedloop.loops import PointLoop

        return PointLoop(sc.loop_name, sc.tool_frame)


@simulates("hinge")
class HingeSim(SimLoop):
    """``hinge``: the tool welded to the handle of a door on a passive hinge."""

    default_name = "door"
    constraints = 5
    target_is_closure = False
    geometry = ("door", DoorGeometry)
    env_joint = DOOR_JOINT

    def independent(self, rank: int) -> int:
        return min(rank, 6) - 1  # the door's own angle takes one of the weld's six

    def place(self, spec, model, data, scenario, tool, settings, rng) -> Placement:
        import mujoco

        from closedloop.assets.catalog import model_file

        hinge_pose = door_hinge_pose(tool, scenario.door or DoorGeometry())
        door_spec = mujoco.MjSpec.from_file(str(model_file("door.xml")))
        frame = spec.worldbody.add_frame(pos=hinge_pose.translation, quat=quat_wxyz(hinge_pose.rotation))
        spec.attach(door_spec, prefix=DOOR_PREFIX, frame=frame)
        grasp = hinge_pose.actInv(tool)
        spec.body(DOOR_PREFIX + "door").add_site(
            name=TARGET_SITE, pos=grasp.translation, quat=quat_wxyz(grasp.rotation), size=[0.02, 0.02, 0.02]
        )
        return Placement(hinge_pose=hinge_pose)

    def nominal_target(self, loop, data, oMt0, hinge, door_range, target_frame) -> int:
        """A revolute joint ``door_hinge`` about the hinge's z axis; the handle at ``G = H^-1 FK_nom(r0)``."""
        if hinge is None:
            raise ScenarioError("hinge loops need the hinge pose")
        model = loop.model
        jid = model.addJoint(
            0,
            pin.JointModelRZ(),
            hinge,
            "door_hinge",
            np.array([1e3]),
            np.array([1e3]),
            np.array([door_range[0]]),
            np.array([door_range[1]]),
        )
        model.appendBodyToJoint(jid, pin.Inertia.FromBox(1.0, 0.8, 0.04, 1.0), pin.SE3.Identity())
        grasp = hinge.actInv(oMt0)
        return model.addFrame(pin.Frame("handle", jid, grasp, pin.FrameType.OP_FRAME))

    def truth_parameters(self, name, scene):
        return {}

    def truth_record(self, name, scene, settings, measured):
        return {
            "hinge_axis": {
                "point": [float(v) for v in scene.hinge_pose.translation],
                "direction": [float(v) for v in scene.hinge_pose.rotation[:, 2]],
                "frame": pose_params("hinge", scene.hinge_pose),
            }
        }

    def core_loop(self, sc, nominal_path=None, sigma_t=None):
        """The HingeLoop with the door axis of the NOMINAL robot at the grasp as its reference."""
        if nominal_path is None or sc.door is None:
            return None
        from closedloop.loops import HingeLoop

        model = pin.buildModelFromUrdf(str(nominal_path))
        data = model.createData()
        pin.framesForwardKinematics(model, data, np.asarray(sc.q0, dtype=float))
        H = door_hinge_pose(data.oMf[find_frame(model, sc.tool_frame)], sc.door)
        return HingeLoop(sc.loop_name, sc.tool_frame, axis=(H.translation.copy(), H.rotation[:, 2].copy()))


@simulates("plane")
class PlaneSim(SimLoop):
    """``plane``: the stylus tip on a passive puck sliding on a tilted plane (drawn per seed)."""

    default_name = "plane"
    constraints = 1
    pose_rows = False
    residual_rows = 1
    equality = "connect"
    point_contact = True
    draws_environment = True
    target_is_closure = False
    geometry = ("plane", PlaneGeometry)
    # a plane holds one direction only: the compliant servos need more damping to settle
    settings = {"kv": 20.0, "max_steps": 600}

    def place(self, spec, model, data, scenario, tool, settings, rng) -> Placement:
        if rng is None:
            raise ScenarioError(f"{scenario.name}: plane loops need a random generator for the plane")
        plane_pose = draw_plane(tool.translation, scenario.plane or PlaneGeometry(), rng)
        add_puck(spec, plane_pose, scenario.plane or PlaneGeometry(), settings.gravcomp)
        return Placement(plane_pose=plane_pose)

    def nominal_target(self, loop, data, oMt0, hinge, door_range, target_frame) -> int:
        """The world frame, and the plane through the nominal tip at the grasp: ``d = n . p_0``."""
        if loop.normal is None:
            raise ScenarioError("plane loops need the plane normal")
        loop.d = float(loop.normal @ oMt0.translation)
        return super().nominal_target(loop, data, oMt0, hinge, door_range, target_frame)

    def nominal_residual(self, loop, d, oMt, jt):
        """``e = n . p_t - d`` (1 row), ``de/dq = n^T R_t J_t[:3]``."""
        e = np.array([loop.normal @ oMt.translation - loop.d])
        return e, (loop.normal @ oMt.rotation @ jt[:3])[None, :]

    def truth_parameters(self, name, scene):
        """``PlaneLoop`` parameters of the plane frame (z = normal, n_z > 0) with the reference normal e_z."""
        from closedloop.loops.plane import PlaneLoop

        n = scene.plane_pose.rotation[:, 2]
        w = PlaneLoop(name, "tool").angles(n)
        return {
            f"{name}.nrx": float(w[0]),
            f"{name}.nry": float(w[1]),
            f"{name}.d": float(n @ scene.plane_pose.translation),
            **_zero_tip(name),
        }

    def truth_record(self, name, scene, settings, measured):
        return {
            "plane": {
                "point": [float(v) for v in scene.plane_pose.translation],
                "normal": [float(v) for v in scene.plane_pose.rotation[:, 2]],
                "frame": pose_params("plane", scene.plane_pose),
            }
        }

    def core_loop(self, sc, nominal_path=None, sigma_t=None):
        # A generic tilted normal: `identifiable_names` starts from one point, where the plane gets the
        # reference normal; a horizontal plane (e_z, parallel to the UR5's first axis) hides more than
        # the tilted planes the scenario draws (the names only depend on the plane being generic).
        from closedloop.loops.plane import PlaneLoop

        return PlaneLoop(sc.loop_name, sc.tool_frame, normal=GENERIC_PLANE_NORMAL)


@simulates("measured_point")
class MeasuredPointSim(SimLoop):
    """``measured_point``: no constraint; a tracker (drawn per seed) measures the tool point."""

    default_name = "measured_point"
    constraints = 0
    pose_rows = False
    residual_rows = 0
    equality = None
    point_contact = True
    closed = False
    draws_environment = True
    geometry = ("tracker", TrackerGeometry)
    # an open loop has no preload to relax; stiff, well damped servos settle its large free moves
    settings = {"kp": 2000.0, "kv": 120.0, "relax": False, "ramp_steps": 50, "max_steps": 2000, "target_span": 2.5}
    own_settings = ("tracker_noise",)

    def place(self, spec, model, data, scenario, tool, settings, rng) -> Placement:
        if rng is None:
            raise ScenarioError(f"{scenario.name}: measured_point loops need a random generator for the tracker")
        tracker_pose = draw_tracker(scenario.tracker or TrackerGeometry(), rng)
        # the tracker's frame as a world site (no constraint: the loop is closed by the measurement)
        spec.worldbody.add_site(
            name=TARGET_SITE,
            pos=tracker_pose.translation,
            quat=quat_wxyz(tracker_pose.rotation),
            size=[0.05, 0.05, 0.05],
        )
        return Placement()

    def nominal_target(self, loop, data, oMt0, hinge, door_range, target_frame) -> int:
        raise ScenarioError("a measured_point loop has no nominal loop to plan on (random configurations)")

    def truth_parameters(self, name, scene):
        """MeasuredPointLoop: the tracker frame in the base, the tip in the tool frame."""
        return {**pose_params(name, scene.target_pose), **_zero_tip(name)}

    def truth_record(self, name, scene, settings, measured):
        return {
            "tracker": {
                "frame": pose_params(name, scene.target_pose),
                "noise_m": float(settings.tracker_noise),
                "columns": list(measured),
            }
        }

    def calibrate_keys(self, settings):
        """The tracker's noise (``sigma_t``): what the calibration weighs the measurement by."""
        return {"sigma_t": f"{settings.tracker_noise:g}"} if settings.tracker_noise > 0 else {}

    def core_loop(self, sc, nominal_path=None, sigma_t=None):
        from closedloop.loops.measured import MeasuredPointLoop

        return MeasuredPointLoop(sc.loop_name, sc.tool_frame, sigma_t=sigma_t)
