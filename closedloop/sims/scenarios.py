"""Scenarios as data: the registry, the simulation settings and the loop geometries.

A *scenario* is a robot (a cleaned nominal URDF from :mod:`closedloop.assets.catalog`),
a loop type that closes its chain on the environment, an initial grasp
configuration and default :class:`SimSettings`.

The loop types themselves (their MuJoCo equality, nominal residual and truth) are the classes of
:mod:`closedloop.sims.loop_types`; the draw of the true robot is :mod:`closedloop.sims.true_robot`.

Every scenario ``simulate`` runs by name is in one list, :func:`scenario_catalog`: the shipped
YAML files (``closedloop/sims/scenarios/*.yaml``, read without loading the simulator), the
head-camera scenarios (:data:`CAMERA_SCENARIOS`, run by :mod:`closedloop.sims.camera_scene`) and
any registered since (a user's YAML file, ``--robot``).  ``simulate --help`` and the
unknown-scenario error both read it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from closedloop.errors import SettingError, UnknownScenarioError

__all__ = [
    "LoopType",
    "SimSettings",
    "Scenario",
    "DoorGeometry",
    "PlaneGeometry",
    "TrackerGeometry",
    "CameraScenario",
    "SCENARIOS",
    "CAMERA_SCENARIOS",
    "SCENARIO_DIR",
    "scenario_catalog",
    "unknown_scenario",
]

#: a loop type name of the registry (``closedloop.loops.spec.LOOP_TYPES``) that the simulator simulates
LoopType = str
#: the shipped scenario files
SCENARIO_DIR = Path(__file__).with_name("scenarios")


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
            but the final standstill at max |qdot| < move_vel_tol [rad/s] (the last
            pass settles to ``vel_tol``).
        min_steps, max_steps: bounds on simulation steps per sample.
        ramp_steps: steps over which the command is interpolated to the next waypoint.
        step_rad: largest planned change of any joint between samples [rad].
        target_span: random targets are drawn within +/- target_span of the
            initial configuration (and inside the limits) [rad].
        retarget_every: a new random target is drawn after this many samples
            (or earlier when the self-motion stalls).
        select: plan the samples with pose selection (``closedloop.sims.selection``):
            a method of ``closedloop.design.poses.select_poses`` (``greedy``, ``detmax``,
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
        truth: which parameters the errors are drawn in: ``identifiable`` (default: those a
            calibration of the loop estimates, so ``check --parameters`` compares them one by one)
            or ``all`` (every placement component of every driven joint, the first joint's and
            those along each axis included, and every joint's offset: the held length that sets the
            overall size is wrong too, as in a real robot file, so a calibration's size can be
            wrong; judge it with ``check``'s kinematic view).
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
    truth: str = "identifiable"
    compliance: float = 0.0
    noise: float = 0.0
    quantization: float = 0.0
    tracker_noise: float = 1e-5

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
        """Copy with some fields replaced; unknown names raise `SettingError` (a ``TypeError``)."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise SettingError(f"unknown simulation setting(s) {unknown}; known: {sorted(names)}")
        fixed: dict[str, Any] = {}
        for k, v in overrides.items():
            fixed[k] = tuple(v) if isinstance(v, list) else v
        return dataclasses.replace(self, **fixed)

    def as_dict(self, drop: tuple[str, ...] | set[str] = ()) -> dict[str, Any]:
        """JSON-friendly dict of the settings, without those named in `drop`."""
        return {
            k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items() if k not in drop
        }


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
        robot: key of :data:`closedloop.assets.catalog.ROBOTS`.
        loop_type: a loop type of the registry the simulator simulates (:data:`closedloop.sims.loop_types.SIM_LOOPS`).
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


#: scenario name -> scenario: the shipped YAML files (``closedloop/sims/scenarios/*.yaml``, registered when
#: :mod:`closedloop.sims.scenario_files` is imported: ``closedloop.sims.SCENARIOS`` and ``simulate`` import
#: it), and what ``load_scenario`` or ``--robot`` registered
SCENARIOS: dict[str, Scenario] = {}


@dataclass
class CameraScenario:
    """Settings of a head-camera scenario (:data:`CAMERA_SCENARIOS`, run by :mod:`closedloop.sims.camera_scene`)."""

    name: str
    description: str
    verge: float = 0.0  # rad: each pan axis turned by +-verge (0: parallel pan axes)
    sigma_px: float = 0.1  # pixel noise (px): a round marker's centroid, found to a tenth of a pixel
    sigma_q: float = 2e-5  # joint-reading noise (rad)
    jitter: float = 0.3  # tracking error of the pans (rad): spreads the marker over the images
    arm_range: float = 0.6  # arm readings: Q0 +- this (rad)
    translation: float = 1e-3  # placement errors (m)
    rotation: float = 1e-3  # (rad)
    offset: float = 0.01  # joint offsets (rad)
    mount_t: float = 5e-3  # camera mounting error in its optical frame (m)
    mount_r: float = 0.02  # (rad)
    q0: tuple[float, ...] = (0.0, -1.6, 1.6, -1.6, -1.57, 0.0)
    extra: dict = field(default_factory=dict)


#: the head-camera scenarios: a UR5 and a stereo head on pan joints (thesis ch. 5)
CAMERA_SCENARIOS: dict[str, CameraScenario] = {
    s.name: s
    for s in (
        CameraScenario(
            "ur5_head",
            "UR5 with a marker on its tool, tracked by a head of two cameras on parallel pan joints (thesis ch. 5)",
        ),
        CameraScenario(
            "ur5_head_verging",
            "the same with verging pan axes (each tilted 0.2 rad about the head's forward axis)",
            verge=0.2,
        ),
    )
}
#: the loop a head-camera dataset is calibrated with (its log columns ``cam:u1 v1 u2 v2``)
CAMERA_LOOP = "camera:frame=tool0,name=cam,to=cam_left_optical+cam_right_optical,sigma_px=0.1"


def scenario_catalog() -> dict[str, tuple[str, str]]:
    """Every scenario ``simulate`` runs by name -> (its loop, its description), sorted by name.

    The shipped YAML files (read here, without the simulator), the head-camera scenarios, and the
    scenarios registered in :data:`SCENARIOS` since (a user's YAML file, ``--robot``).
    """
    import yaml

    out: dict[str, tuple[str, str]] = {}
    for f in sorted(SCENARIO_DIR.glob("*.yaml")):
        try:
            data = yaml.safe_load(f.read_text()) or {}
        except yaml.YAMLError:
            data = {}
        out[str(data.get("name", f.stem))] = (str(data.get("loop", "")), str(data.get("description", "")))
    for name, cs in CAMERA_SCENARIOS.items():
        out[name] = (CAMERA_LOOP, cs.description)
    for name, sc in SCENARIOS.items():
        out.setdefault(name, (f"{sc.loop_type}:frame={sc.tool_frame}", sc.description))
    return dict(sorted(out.items()))


def unknown_scenario(name: str) -> UnknownScenarioError:
    """The error for a scenario name no list holds, naming every one of :func:`scenario_catalog`."""
    return UnknownScenarioError(f"unknown scenario '{name}' (known: {', '.join(scenario_catalog())})")
