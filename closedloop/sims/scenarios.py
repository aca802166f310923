"""Scenario registry, simulation settings and the draw of the true robot.

A *scenario* is a robot (a cleaned nominal URDF from :mod:`closedloop.models`),
a loop type that closes its chain on the environment, an initial grasp
configuration and default :class:`SimSettings`.

Loop types (the MuJoCo equality constraint that closes the loop):

``weld``
    The tool frame is welded to a fixture fixed in the world (6 constraints).
    Closure parameters ``<loop>.x .y .z .rx .ry .rz``: pose of the fixture
    (= pose of the tool frame when closed) in the world frame, translation in
    metres, rotation vector ``pin.log3(R)``.  With a ``target_frame`` the tool
    frame is welded to that other frame of the same robot (e.g. the two tips of
    a hand holding an object); the closure parameters are then the pose of the
    tool frame in the target frame when closed.
``point``
    The tool point (stylus tip) sits in a ball socket (MuJoCo ``connect``, 3
    constraints).  Closure parameters ``<loop>.x .y .z``: socket centre in the world.
``hinge``
    The tool is welded to the handle of a door that turns on a passive hinge:
    the tool frame moves on a 1-DOF rotation about a fixed axis (5 constraints
    on the arm).  Closure parameters ``<loop>.x ... .rz``: pose of the tool frame
    in the world when the door angle is zero; the hinge axis is in ``truth.json``
    under ``loop.hinge_axis``.
``plane``
    The tool point (stylus tip) touches an unknown plane: it is connected
    (MuJoCo ``connect``) to the centre of a passive *puck* that slides on the
    plane (two slide joints spanning it) and turns freely (ball joint), so the
    tip keeps 5 DOF and loses one (the distance to the plane).  The plane is
    tilted and placed at a pose drawn per seed, through the true tip at ``q0``.
    Closure parameters (names of ``closedloop.loops.PlaneLoop`` with its default
    reference normal e_z): ``<loop>.tip_x .tip_y .tip_z`` (0: the stylus tip),
    ``<loop>.nrx .nry`` (normal n = exp3([nrx, nry, 0]) e_z, n_z > 0) and
    ``<loop>.d`` (= n . p for every point p of the plane, world frame); the
    plane is also given as point + normal in ``truth.json`` under ``loop.plane``.
``measured_point``
    No loop constraint (open loop, thesis 3.2): the robot moves freely to random
    configurations and an external tracker at an unknown pose (drawn per seed)
    measures the tool point in its own frame with Gaussian noise (setting
    ``tracker_noise``).  Log columns ``<loop>:x .y .z``; closure parameters
    (names of ``closedloop.loops.MeasuredPointLoop``): ``<loop>.x .y .z .rx .ry
    .rz`` pose of the tracker frame in the robot base (world), ``<loop>.tip_x
    .tip_y .tip_z`` the measured point in the tool frame (0: the stylus tip).

Truth model (:func:`perturbable_parameters`, :func:`draw_errors`): the true
robot equals the nominal one plus uniform random errors, per parameter kind

* ``translation`` (``<joint>.x .y .z``) U(-m, m) metres, default m = 2 mm;
* ``rotation`` (``<joint>.rx .ry .rz``) U(-m, m) rad, default m = 2 mrad;
* ``offset`` (``<joint>.offset``) U(-m, m) rad, default m = 0.02 rad;
* ``scale`` (``<joint>.scale``) 1 + U(-m, m), default m = 0 (not perturbed).

A joint placement error is a right twist in the joint's own frame:
``M = M0 * exp6([x, y, z, rx, ry, rz])``.  Sensor model (thesis eq. 4.4):
``theta_true = scale * reading + offset``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pinocchio as pin

__all__ = [
    "LoopType",
    "SimSettings",
    "Scenario",
    "DoorGeometry",
    "PlaneGeometry",
    "TrackerGeometry",
    "SCENARIOS",
    "perturbable_parameters",
    "draw_errors",
]

LoopType = Literal["weld", "point", "hinge", "plane", "measured_point"]

_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class SimSettings:
    """Settings of a simulated calibration experiment (all overridable in ``simulate``).

    Physics:
        timestep: MuJoCo time step [s].
        integrator: MuJoCo integrator name (``implicitfast``, ``implicit``, ``Euler``, ``RK4``).
        gravity: gravity on (``True``, -9.81 m/s^2 along world z) or off.
        gravcomp: the servos compensate the robot's weight (as Panda and UR
            controllers do; MuJoCo ``gravcomp`` computed on the true model and
            added to the actuator torque).  Without it the arm's weight loads
            the loop and the violation grows (see the README numbers).
        solref: loop constraint ``(timeconst [s], dampratio)``; MuJoCo's soft
            constraint behaves like a spring-damper of time constant ``timeconst``
            (MuJoCo clamps it to at least 2 * timestep).  Default ``(0.008, 1.0)``
            = 2 * timestep, the stiffest MuJoCo allows.  ``soft=True`` selects
            MuJoCo's own defaults ``(0.02, 1)``, ``(0.9, 0.95, ...)``, a loop that
            opens by tens of microradians to milliradians under the same load
            (accuracy table: README, ``benchmarks/sim_accuracy.py``).
        solimp: loop constraint impedance ``(dmin, dmax, width, midpoint, power)``;
            the closer ``dmin``/``dmax`` are to 1 the stiffer.  Default
            ``(0.99, 0.999, 0.001, 0.5, 2)``.
        armature: reflected rotor inertia added to every arm joint [kg m^2]
            (realistic for geared robots; also keeps the position servos
            stable at large time steps).
        kp: position servo stiffness [N m / rad]; ``tau = kp (ctrl - q) - kv qdot``.
            Default 100: a compliant (impedance-mode) servo, as used when a robot
            holds a fixture; a stiff servo commanded from the wrong nominal
            model preloads the loop (kp=2000 gives ~1 mrad of loop opening).
        kv: position servo damping [N m s / rad].
    Settling and sampling:
        vel_tol: a configuration is settled when max |qdot| < vel_tol [rad/s].
        move_vel_tol: with ``relax``, the move to a waypoint and every relax pass
            but the last stop at max |qdot| < move_vel_tol [rad/s] (the last
            pass settles to ``vel_tol``).
        min_steps, max_steps: bounds on simulation steps per sample.
        ramp_steps: steps over which the command is interpolated to the next waypoint.
        step_rad: largest planned change of any joint between samples [rad].
        target_span: random targets are drawn within +/- target_span of the
            initial configuration (and inside the limits) [rad].
        retarget_every: a new random target is drawn after this many samples
            (or earlier when the self-motion stalls).
        select: plan the samples with pose selection (``closedloop.sims.selection``):
            a method of ``closedloop.poses.select_poses`` (``greedy``, ``detmax``,
            ``greedy-a``); ``None`` (default): the planner's waypoints are the samples.
        select_pool: candidate pool of pose selection, in multiples of n.
        limit_margin: the planner keeps joints this far inside their limits [rad].
        limit_flag: samples with a true joint closer than this to a limit are
            flagged (``at_limit`` column) and dropped if ``drop_flagged`` [rad].
        drop_flagged: drop flagged (at-limit or unsettled) samples.
        relax: after settling, command the measured joint positions and settle
            again before recording, so the servos stop fighting the loop (the
            robot driven by its wrong nominal model preloads the closed chain
            with hundreds of newtons; a real calibration holds the fixture in a
            compliant, low-preload state).  Off: the preload stays and opens the
            loop by ~1 mrad (see README table).
        relax_passes: how many times the relax is done (each releases most of the
            preload the previous one left: ~50x on the Panda weld).
    Truth:
        translation, rotation, offset, scale: error magnitudes (see module doc).
    Sensor model:
        compliance: joint compliance c = 1/K of every arm joint [rad / N m]
            (default 0: rigid joints).  The encoders are on the motor side, so
            a reading sees the link angle plus the deflection c * tau under the
            actuator torque tau (logged as ``tau:<joint>``); with gravity this
            is what biases a purely geometric calibration (identify
            ``compliance`` to remove it).
        noise: standard deviation of Gaussian reading noise [rad] (default 0).
        tracker_noise: standard deviation of the Gaussian noise of each measured
            coordinate of an external tracker (``measured_point`` loops) [m].
        quantization: reading quantum [rad]; 0 disables quantization (default).
            ``reading = round(((q - offset) / scale + N(0, noise)) / quantum) * quantum``.
    """

    timestep: float = 0.004
    integrator: str = "implicitfast"
    gravity: bool = True
    gravcomp: bool = True
    solref: tuple[float, float] = (0.008, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.99, 0.999, 0.001, 0.5, 2.0)
    armature: float = 0.1
    kp: float = 100.0
    kv: float = 6.3
    vel_tol: float = 3e-3
    move_vel_tol: float = 3e-2
    min_steps: int = 10
    max_steps: int = 300
    ramp_steps: int = 4
    step_rad: float = 0.15
    target_span: float = 1.5
    retarget_every: int = 10
    select: str | None = None
    select_pool: float = 10.0
    limit_margin: float = 0.1
    limit_flag: float = 0.02
    drop_flagged: bool = True
    relax: bool = True
    relax_passes: int = 3
    translation: float = 0.002
    rotation: float = 0.002
    offset: float = 0.02
    scale: float = 0.0
    compliance: float = 0.0
    noise: float = 0.0
    quantization: float = 0.0
    tracker_noise: float = 1e-5

    #: settings written to truth.json only for the loop types that use them (the
    #: other scenarios' truth.json stays as it was)
    LOOP_SPECIFIC = {"tracker_noise": ("measured_point",)}

    @classmethod
    def stiff(cls, **kw: Any) -> "SimSettings":
        """Settings with a nearly rigid loop (``solref=(2*timestep, 1)``, ``solimp`` close to 1)."""
        base = cls(**kw)
        return dataclasses.replace(
            base,
            solref=(2.0 * base.timestep, 1.0),
            solimp=(0.99, 0.999, 0.001, 0.5, 2.0),
        )

    def replace(self, **overrides: Any) -> "SimSettings":
        """Copy with some fields replaced; unknown names raise ``TypeError``."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise TypeError(f"unknown simulation setting(s) {unknown}; known: {sorted(names)}")
        fixed = {}
        for k, v in overrides.items():
            fixed[k] = tuple(v) if isinstance(v, list) else v
        return dataclasses.replace(self, **fixed)

    def as_dict(self, loop_type: str | None = None) -> dict[str, Any]:
        """JSON-friendly dict of the settings (with ``loop_type``: only the settings that loop type uses)."""
        out = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}
        if loop_type is not None:
            for k, types in self.LOOP_SPECIFIC.items():
                if loop_type not in types:
                    out.pop(k, None)
        return out


@dataclass(frozen=True)
class DoorGeometry:
    """Placement of the door relative to the grasp (hinge scenarios only).

    The hinge axis is vertical (world z).  The hinge lies ``radius`` metres from
    the handle along the horizontal direction perpendicular to the line from
    the robot base to the handle, so opening the door (positive angle) pulls the
    handle towards the robot.

    Attributes:
        radius: distance from the hinge axis to the grasped handle [m].
        angle_range: door angles the planner may use [rad] (door closed = 0).
    """

    radius: float = 0.45
    angle_range: tuple[float, float] = (-0.6, 0.6)


@dataclass(frozen=True)
class PlaneGeometry:
    """Draw of the unknown plane (plane loops), per seed.

    The plane passes through the true tool point at ``q0``; its normal is the
    world z axis tilted by an angle drawn in ``tilt`` about a random horizontal
    axis, and its in-plane axes are turned by a random angle about the normal.

    Attributes:
        tilt: range of the tilt of the normal from the world z axis [rad].
        puck_mass: mass of the passive puck [kg] (gravity-compensated with the robot).
        slide_range: travel of the puck along each in-plane axis [m].
    """

    tilt: tuple[float, float] = (0.2, 0.6)
    puck_mass: float = 0.05
    slide_range: float = 2.0


@dataclass(frozen=True)
class TrackerGeometry:
    """Draw of the external tracker's frame (measured_point loops), per seed.

    The tracker stands ``distance`` metres from the robot base at a random
    azimuth and ``height`` metres up; its frame has a uniformly random orientation.
    """

    distance: tuple[float, float] = (1.5, 2.5)
    height: tuple[float, float] = (0.0, 1.5)


@dataclass(frozen=True)
class Scenario:
    """A simulated closed-loop calibration experiment.

    Attributes:
        name: registry key.
        description: one line.
        robot: key of :data:`closedloop.models.ROBOTS`.
        loop_type: ``weld``, ``point`` or ``hinge``.
        loop_name: name of the loop (prefix of its closure parameters).
        tool_frame: Pinocchio frame (URDF link) closing the loop.
        target_frame: weld loops only: the robot frame (URDF link) the tool is
            welded to; ``None`` welds it to a fixture in the world.
        q0: true joint angles when the loop is closed (grasp configuration), Pinocchio order.
        settings: default settings.
        door: door geometry (hinge loops).
        plane: plane draw (plane loops).
        tracker: tracker draw (measured_point loops).
        min_joint_range: the smallest range every loop joint covers in a dataset
            (the coverage check of the tests) [rad].  0.1 by default; lower only
            where the closed mechanism itself hardly moves a joint (stated per
            scenario).
    """

    name: str
    description: str
    robot: str
    loop_type: LoopType
    loop_name: str
    tool_frame: str
    q0: tuple[float, ...]
    settings: SimSettings = field(default_factory=SimSettings)
    door: DoorGeometry | None = None
    target_frame: str | None = None
    min_joint_range: float = 0.1
    plane: PlaneGeometry | None = None
    tracker: TrackerGeometry | None = None


#: scenario name -> scenario; filled with the shipped YAML files (``closedloop/sims/scenarios/*.yaml``) by
#: :mod:`closedloop.sims.scenario_files` when ``closedloop.sims`` is imported, and by ``load_scenario``
SCENARIOS: dict[str, Scenario] = {}


def _axis_component(axis: np.ndarray) -> int | None:
    """Index 0/1/2 of the coordinate axis a unit joint axis is aligned with, else None."""
    a = np.abs(np.asarray(axis, dtype=float))
    i = int(np.argmax(a))
    return i if a[i] > 1.0 - 1e-9 else None


def perturbable_parameters(model: pin.Model, joint_names: list[str], scale: bool = False) -> list[str]:
    """Names of the parameters that are perturbed in the true robot.

    The fixed rule for a serial chain of revolute joints welded to an unknown
    fixture (the core's automatic reduction may replace it):

    * the first joint's placement is not perturbed (base gauge, absorbed by the
      unknown closure) and neither is its offset;
    * for every other joint, the placement components along the joint axis are
      not perturbed: rotation about the axis (duplicates the offset) and
      translation along it (absorbed by the next joint).  For axis z these are
      ``.rz`` and ``.z``; for an axis along x or y, ``.rx``/``.x`` or ``.ry``/``.y``;
    * fixed joints (tool, flanges) are never perturbed;
    * offsets of all joints but the first are perturbed; scales of all joints
      only when ``scale`` is true.

    Args:
        model: nominal Pinocchio model.
        joint_names: the movable 1-DOF joints of the chain, in Pinocchio order.
        scale: include ``<joint>.scale`` parameters.
    """
    names: list[str] = []
    for k, jn in enumerate(joint_names):
        jid = model.getJointId(jn)
        jm = model.joints[jid]
        short = jm.shortname()
        if short in ("JointModelRX", "JointModelRY", "JointModelRZ"):
            skip_axis: int | None = "XYZ".index(short[-1])
        elif short == "JointModelRevoluteUnaligned":
            skip_axis = _axis_component(jm.axis)
        else:
            skip_axis = None
        if k > 0:
            for c, comp in enumerate(_COMPONENTS):
                if skip_axis is not None and c % 3 == skip_axis:
                    continue
                names.append(f"{jn}.{comp}")
            names.append(f"{jn}.offset")
        if scale:
            names.append(f"{jn}.scale")
    return names


def identifiable_parameters(nominal_path, sc: "Scenario", joint_names: list[str], scale: bool = False) -> list[str]:
    """The parameters to perturb: those the calibration core estimates for this loop.

    Errors in structurally redundant parameters are indistinguishable from
    errors in the parameters that absorb them, so a truth that `closedloop
    check` can compare parameter by parameter is drawn in the identifiable set
    (`closedloop.truth.identifiable_names`, the core's own reduction on nominal
    self-motion data through the grasp configuration).  Loop types the core
    has no loop class for yet fall back to :func:`perturbable_parameters`.
    """
    from closedloop.calibration import CalibrationOptions
    from closedloop.robot import RobotModel
    from closedloop.truth import identifiable_names

    loop = core_loop(sc, nominal_path)
    if loop is None:
        model = pin.buildModelFromUrdf(str(nominal_path))
        return perturbable_parameters(model, joint_names, scale=scale)
    robot = RobotModel.from_file(nominal_path)
    identify = ["placement", "offset", "loop"] + (["scale"] if scale else [])
    if sc.loop_type == "measured_point":
        names = _measured_identifiable_names(robot, loop, CalibrationOptions(identify=identify))
    else:
        names = identifiable_names(robot, [loop], np.asarray(sc.q0, dtype=float)[None, :],
                                   CalibrationOptions(identify=identify))
    return [n for n in names if n.rsplit(".", 1)[0] in joint_names]


def _measured_identifiable_names(robot, loop, options, n: int = 40, seed: int = 0) -> list[str]:
    """Names `calibrate` estimates for a measured (open) loop, on nominal data.

    `closedloop.truth.identifiable_names` walks the loop's self-motion from one
    configuration, which an open loop does not have (every configuration is
    allowed, and the measurements are log columns it cannot make up).  Instead:
    ``n`` random configurations within the nominal joint limits (fixed seed),
    the nominal tool point measured exactly by a tracker at the identity pose,
    and the core's own reduction on that data.
    """
    from closedloop.calibration import calibrate
    from closedloop.data import JointLog

    model = robot.model
    data = model.createData()
    rng = np.random.default_rng(seed)
    lo = np.maximum(model.lowerPositionLimit, -np.pi)
    hi = np.minimum(model.upperPositionLimit, np.pi)
    q = rng.uniform(lo, hi, size=(n, model.nq))
    fid = model.getFrameId(loop.frame_a)
    pts = np.empty((n, 3))
    for i in range(n):
        pin.framesForwardKinematics(model, data, q[i])
        pts[i] = data.oMf[fid].translation
    joints = list(robot.joint_names)
    extra = {c: pts[:, k] for k, c in enumerate(loop.columns())}
    res = calibrate(robot, JointLog(joints, q, None, None, extra), [loop], options)
    return [n_ for n_, s in zip(res.names, res.status) if s == "estimated" and not n_.startswith(loop.name + ".")]


_GENERIC_PLANE_NORMAL = np.array([0.3, -0.2, 0.93])


def core_loop(sc: "Scenario", nominal_path=None):
    """The calibration core's loop for a scenario, or None if the core has none for it.

    The hinge loop gets the door axis of the NOMINAL robot at the grasp
    configuration as its reference (only the structure matters here).
    """
    from closedloop.loops import HingeLoop, PointLoop, WeldLoop

    if sc.loop_type == "plane":
        from closedloop.loops.plane import PlaneLoop

        # A generic tilted normal: `identifiable_names` starts from one point, where the plane gets the
        # reference normal; a horizontal plane (e_z, parallel to the UR5's first axis) hides more than
        # the tilted planes the scenario draws (the names only depend on the plane being generic).
        return PlaneLoop(sc.loop_name, sc.tool_frame, normal=_GENERIC_PLANE_NORMAL)
    if sc.loop_type == "measured_point":
        from closedloop.loops.measured import MeasuredPointLoop

        return MeasuredPointLoop(sc.loop_name, sc.tool_frame)
    if sc.loop_type == "weld":
        return WeldLoop(sc.loop_name, sc.tool_frame, sc.target_frame or "universe")
    if sc.loop_type == "point":
        return PointLoop(sc.loop_name, sc.tool_frame)
    if sc.loop_type == "hinge" and nominal_path is not None and sc.door is not None:
        from .scene import _door_hinge_pose

        model = pin.buildModelFromUrdf(str(nominal_path))
        data = model.createData()
        pin.framesForwardKinematics(model, data, np.asarray(sc.q0, dtype=float))
        H = _door_hinge_pose(data.oMf[model.getFrameId(sc.tool_frame)], sc.door)
        return HingeLoop(sc.loop_name, sc.tool_frame, axis=(H.translation.copy(), H.rotation[:, 2].copy()))
    return None


def _kind(name: str) -> str:
    comp = name.rsplit(".", 1)[1]
    if comp in ("x", "y", "z"):
        return "translation"
    if comp in ("rx", "ry", "rz"):
        return "rotation"
    return comp  # offset / scale


def draw_errors(names: list[str], rng: np.random.Generator, magnitudes: dict[str, float]) -> dict[str, float]:
    """Draw true parameter values: uniform in +/- magnitude per kind; scale = 1 + U(-m, m).

    Args:
        names: parameter names (see :func:`perturbable_parameters`).
        rng: random generator (one uniform draw per name, in order).
        magnitudes: magnitude per kind (``translation``, ``rotation``, ``offset``, ``scale``).
    """
    out: dict[str, float] = {}
    for name in names:
        kind = _kind(name)
        m = float(magnitudes.get(kind, 0.0))
        u = float(rng.uniform(-1.0, 1.0))
        out[name] = (1.0 + m * u) if kind == "scale" else m * u
    return out
