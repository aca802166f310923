"""Run a scenario: draw the true robot, simulate the closed loop, record and write a dataset.

Pipeline of :func:`simulate` (one function per step below; what depends on the loop type is a
method of its class in :mod:`closedloop.sims.loop_types`):

1. nominal URDF (cleaned, :func:`closedloop.assets.catalog.nominal_urdf`) and its
   Pinocchio model; arm joints = movable joints in Pinocchio order;
2. true parameters: :func:`~closedloop.sims.true_robot.identifiable_parameters`
   (with the setting ``truth=all``: :func:`~closedloop.sims.true_robot.all_parameters`, every joint
   origin) drawn by :func:`~closedloop.sims.true_robot.draw_errors`; the true URDF
   carries the placement errors (offsets/scales stay in the sensor model);
3. MuJoCo scene of the true robot with the loop closed at the true grasp
   configuration ``q0`` (:func:`~closedloop.sims.scene.build_scene`);
4. the robot reads ``r0 = sensor(q0)``, builds its nominal loop and plans
   waypoints along the nominal self-motion (:mod:`closedloop.sims.driver`);
   (with the setting ``select``: the waypoints are n configurations chosen from a
   pool of nominal self-motion configurations by pose selection, visited in a
   short path, :mod:`closedloop.sims.selection`); with ``poses`` (a CSV log of joint readings, e.g.
   what ``closedloop calibrate --suggest`` writes): the waypoints are those readings, in the file's
   order, the robot led between them along its nominal loop (:func:`poses_plan`); the true robot and
   the fixture are the seed's, the noise a fresh stream of the seed and the readings;
5. for every waypoint ``r`` the servos are commanded ``ctrl = scale * r + offset``
   (the servo acts on the encoder reading), ramped over ``ramp_steps`` steps;
   the simulation runs until ``max |qdot| < move_vel_tol``; then, ``relax_passes``
   times, the servos are commanded the measured joint positions (``relax``: the
   preload of the servos, driven by the wrong nominal model against the closed
   chain, is released) and the simulation runs until ``max |qdot|`` is below
   ``move_vel_tol`` (``vel_tol`` for the last pass: quasi-static point);
   without ``relax`` the move itself settles to ``vel_tol``;
6. recorded: readings ``sensor(q)``, actuator torques, the true closure
   violation (tool site vs target site) and the loop constraint force.

Sensor model: ``reading = Q((q_true - offset) / scale + N(0, noise))`` with
``Q(x) = quantum * round(x / quantum)`` (identity if quantum is 0).

Loops without a constraint (``measured_point``, thesis 3.2): step 4 draws random
configurations of the nominal model instead of a self-motion, and step 6 also
records the external tracker's measurement of the tool point in its own frame,
``X^-1 p_tool + N(0, tracker_noise^2 I)`` (log columns ``<loop>:x .y .z``; the
"violation" columns hold the measurement error).  The plane, the tracker pose and
the tracker noise come from a fourth random stream, so the other scenarios' draws
are unchanged.

Outputs in ``out_dir``: ``log.csv``, ``nominal.urdf``, ``truth.json``, ``scene.xml``.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from closedloop.assets.catalog import ROBOTS, nominal_urdf
from closedloop.errors import EmptySimulationError, ScenarioError
from closedloop.io.files import OutputSet
from closedloop.io.marker import mark_running
from closedloop.progress import ProgressReporter
from closedloop.sims.driver import NominalLoop, NominalLoopPlanner, RandomConfigurations
from closedloop.sims.loop_types import SimLoop, sim_loop
from closedloop.sims.outputs import DATASET_FILES, check_dataset_dir, truth_record, with_visuals, write_log
from closedloop.sims.scenario_files import SCENARIOS  # the shipped scenario files registered
from closedloop.sims.scenarios import CAMERA_SCENARIOS, Scenario, SimSettings, unknown_scenario
from closedloop.sims.scene import Scene, build_scene, true_urdf
from closedloop.sims.tracking import sensor_readings, track_and_record
from closedloop.sims.true_robot import all_parameters, draw_errors, identifiable_parameters

__all__ = ["SimResult", "simulate", "sensor_readings", "check_dataset_dir"]

log = logging.getLogger(__name__)


@dataclass
class SimResult:
    """Result of :func:`simulate`.

    Attributes:
        scenario: scenario name.
        seed: random seed.
        out_dir: output directory; ``log_path``, ``truth_path``, ``nominal_path``, ``scene_path`` inside.
        joint_names: arm joints (CSV header order = Pinocchio order).
        readings: (n, nj) recorded joint readings [rad].
        q_true: (n, nj) true joint angles (MuJoCo qpos) at the samples [rad].
        tau: (n, nj) actuator torques (servo + gravity compensation, ``qfrc_actuator``) [N m].
        violation_m, violation_rad: (n,) true closure violation (position, rotation).
        constraint_force_n: (n,) norm of the loop constraint force [N].
        door_angle: (n,) door angle (hinge loops) else empty.
        truth: contents of ``truth.json``.
        settings: settings used.
        n_dropped: samples dropped (at a joint limit or not settled).
        n_asked: configurations asked for; ``len(readings)`` may be fewer, ``shortfall`` then says why.
        shortfall: why fewer than ``n_asked`` were recorded and what to change ("" when all were).
        n_steps: total simulation steps.
        elapsed_s: wall time of the simulation loop [s] (excluding scene building; including
            the pose selection with ``select``, whose share is ``extra["select_s"]``).
    """

    scenario: str
    seed: int
    out_dir: Path
    joint_names: list[str]
    readings: np.ndarray
    q_true: np.ndarray
    tau: np.ndarray
    violation_m: np.ndarray
    violation_rad: np.ndarray
    constraint_force_n: np.ndarray
    door_angle: np.ndarray
    truth: dict[str, Any]
    settings: SimSettings
    n_dropped: int = 0
    n_asked: int = 0
    shortfall: str = ""
    n_steps: int = 0
    elapsed_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def log_path(self) -> Path:
        return self.out_dir / "log.csv"

    @property
    def truth_path(self) -> Path:
        return self.out_dir / "truth.json"

    @property
    def nominal_path(self) -> Path:
        return self.out_dir / "nominal.urdf"

    @property
    def scene_path(self) -> Path:
        return self.out_dir / "scene.xml"

    @property
    def configs_per_second(self) -> float:
        """Settled configurations recorded per second of simulation-loop wall time."""
        return len(self.readings) / self.elapsed_s if self.elapsed_s > 0 else float("nan")


@dataclass
class _Nominal:
    """Step 1: the nominal URDF (text and scratch file), its Pinocchio model and arm joints."""

    urdf: str
    path: Path
    model: pin.Model
    joint_names: list[str]


@dataclass
class _Truth:
    """Step 2: the true parameter values, the sensor offsets and scales, the true URDF."""

    values: dict[str, float]
    offset: np.ndarray
    scale: np.ndarray
    urdf: str


def simulate(
    scenario: str,
    n: int,
    seed: int,
    out_dir: Path | str,
    progress: ProgressReporter | None = None,
    poses: Path | str | None = None,
    **overrides: Any,
) -> SimResult:
    """Generate a closed-loop calibration dataset by simulation.

    Args:
        scenario: key of :data:`~closedloop.sims.scenarios.SCENARIOS`.
        n: number of recorded (settled, unflagged) configurations.
        seed: random seed (truth, targets, noise); the same seed gives an identical log.
        out_dir: output directory (created).
        progress: told ``("simulating", done, n)`` after each recorded sample (`closedloop.progress`).
        poses: a CSV log whose joint readings are recorded instead of planned waypoints (a column per
            driven joint; `n` is then its number of rows): the configurations a calibration suggested
            (``closedloop calibrate --suggest``), played on the seed's true robot at its fixture.
        **overrides: :class:`~closedloop.sims.scenarios.SimSettings` fields, plus
            ``stiff=True`` for the stiff-loop preset (``SimSettings.stiff``).

    Raises:
        EmptySimulationError: no configuration was recorded (nothing is written).

    Returns:
        the :class:`SimResult` (fewer than `n` configurations when some were dropped: ``shortfall``
        says why); files ``log.csv``, ``nominal.urdf``, ``truth.json``,
        ``scene.xml`` are written in ``out_dir``.
    """
    if scenario in CAMERA_SCENARIOS:
        raise ScenarioError(
            f"{scenario} is a head-camera scenario: closedloop.sims.camera_scene.simulate_head runs it "
            f"(closedloop simulate {scenario})"
        )
    try:
        sc: Scenario = SCENARIOS[scenario]
    except KeyError:
        raise unknown_scenario(scenario) from None
    if n < 1:
        raise ScenarioError(f"{scenario}: n must be >= 1, not {n}")
    settings = sc.settings
    if overrides.pop("soft", False):
        settings = settings.replace(solref=(0.02, 1.0), solimp=(0.9, 0.95, 0.001, 0.5, 2.0))
    if overrides.pop("stiff", False):
        settings = settings.replace(
            solref=(2.0 * overrides.get("timestep", settings.timestep), 1.0),
            solimp=(0.99, 0.999, 0.001, 0.5, 2.0),
        )
    settings = settings.replace(**overrides)
    out = Path(out_dir)
    poses = Path(poses) if poses is not None else None
    if poses is not None and settings.select:
        raise ScenarioError(f"{scenario}: poses are given: the setting select (which chooses them) does not apply")
    # the dataset is computed beside a scratch nominal.urdf, then published whole into `out` (truth.json last)
    files = OutputSet(order=[out / f for f in DATASET_FILES])
    with tempfile.TemporaryDirectory(prefix="closedloop-sim-") as scratch:
        result = _simulate(sc, settings, n, seed, out, Path(scratch), files, progress, poses)
    files.commit()
    return result


def _simulate(
    sc: Scenario,
    settings: SimSettings,
    n: int,
    seed: int,
    out: Path,
    scratch: Path,
    files: OutputSet,
    progress: ProgressReporter | None,
    poses: Path | None = None,
) -> SimResult:
    """The body of :func:`simulate`: outputs go into `files` (published when `simulate` returns)."""
    kind = sim_loop(sc.loop_type)
    ss = np.random.SeedSequence(seed)
    rng_truth, rng_plan, rng_noise = (np.random.default_rng(c) for c in ss.spawn(3))
    # the environment of the newer loop types (plane, tracker pose, tracker noise): a fourth stream, so
    # the older scenarios' draws are unchanged
    rng_env = np.random.default_rng(ss.spawn(1)[0]) if kind.draws_environment else None

    nominal = _nominal(sc, scratch, files, out)  # 1
    readings, where = _read_poses(poses, nominal.joint_names) if poses is not None else (None, [])
    truth = _draw_truth(sc, settings, nominal, rng_truth)  # 2
    q0 = np.asarray(sc.q0, dtype=float)  # 3: the scene, closed at the true grasp configuration
    scene = build_scene(truth.urdf, sc, settings, nominal.joint_names, q0, rng=rng_env)
    files.add(out / "scene.xml", scene.to_xml())
    r0 = sensor_readings(q0, truth.offset, truth.scale, settings.noise, settings.quantization, rng_noise)
    planner, loop = _planner(sc, kind, settings, nominal.model, scene, r0, rng_plan)  # 4
    mark_running("simulate")  # a supervising process may now interrupt the work (`io.marker`)
    t_start = time.perf_counter()
    plan = None
    if readings is not None:  # the given readings, on the seed's robot and fixture, with noise of their own
        plan = poses_plan(readings, loop, r0, settings.step_rad)
        rng_noise = np.random.default_rng(_poses_noise_seed(seed, readings))
        n = len(readings)
    elif settings.select:  # pose selection on the nominal model (closedloop.sims.selection)
        from closedloop.sims.selection import plan_selected

        start = loop.full_q(r0) if loop is not None else r0
        plan = plan_selected(sc, settings, nominal.path, nominal.joint_names, planner, loop, start, n, nominal.model)
    t_plan = time.perf_counter() - t_start
    rec = track_and_record(
        sc,
        kind,
        settings,
        scene,
        truth.offset,
        truth.scale,
        planner,
        plan,
        n,
        rng_noise,
        rng_env,
        progress,
        t_start,
        POSE_STRAY if readings is not None else None,
    )  # 5-6
    log.info(
        "%s: %d samples, %d dropped, %d steps, %d QP solves, %.2f s (%.0f configs/s)",
        sc.name,
        rec.done,
        rec.dropped,
        rec.steps,
        planner.stats.qp_solves,
        rec.elapsed,
        rec.done / max(rec.elapsed, 1e-12),
    )

    if rec.done == 0:  # nothing to write: the dataset would be an empty log
        raise EmptySimulationError(
            f"{sc.name}: no configuration recorded of the {n} asked ({rec.dropped} dropped): "
            + (
                rec.shortfall(n, settings.max_steps)
                if poses is None
                else _poses_shortfall(rec, where, settings.max_steps)
            )
        )
    # outputs
    measured = {f"{sc.loop_name}:{a}": rec.meas[:, k] for k, a in enumerate("xyz")} if not kind.closed else {}
    write_log(
        files,
        out / "log.csv",
        nominal.joint_names,
        rec.readings,
        rec.tau,
        rec.viol_m,
        rec.viol_rad,
        rec.force,
        rec.door,
        measured,
    )
    truth_json = truth_record(
        sc,
        kind,
        scene,
        settings,
        seed,
        nominal.joint_names,
        q0,
        truth.values,
        list(measured),
        rec,
        planner.stats.qp_solves,
    )
    if plan is not None:
        truth_json["poses" if poses is not None else "selection"] = plan.info
    files.add(out / "truth.json", json.dumps(truth_json, indent=2))
    return SimResult(
        scenario=sc.name,
        seed=int(seed),
        out_dir=out,
        joint_names=nominal.joint_names,
        readings=rec.readings,
        q_true=rec.q_true,
        tau=rec.tau,
        violation_m=rec.viol_m,
        violation_rad=rec.viol_rad,
        constraint_force_n=rec.force,
        door_angle=rec.door,
        truth=truth_json,
        settings=settings,
        n_dropped=rec.dropped,
        n_asked=n,
        shortfall=rec.shortfall(n, settings.max_steps)
        if poses is None
        else _poses_shortfall(rec, where, settings.max_steps),
        n_steps=rec.steps,
        elapsed_s=rec.elapsed,
        extra={"select_s": t_plan} if plan is not None else {},
    )


def _read_poses(path: Path, joint_names: list[str]) -> tuple[np.ndarray, list[str]]:
    """(m, nj) readings of the driven joints from the CSV log at `path` (its columns in any order), and
    where each row was read (``next.csv line 3``)."""
    from closedloop.io.logs import read_log

    log_ = read_log(path, joint_names)
    missing = [j for j in joint_names if j not in log_.joints]
    if missing:
        raise ScenarioError(
            f"{path}: no column for driven joint(s) {', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''} "
            "(the poses need a reading of every joint the simulation drives)"
        )
    return log_.columns(joint_names), [log_.where(i) for i in range(len(log_))]


#: a given pose (``poses``) that comes to rest farther than this from its reading on some joint (rad, or m) is
#: not recorded: it is another configuration than the one asked for
POSE_STRAY = 0.05


def _poses_shortfall(rec, where: list[str], max_steps: int) -> str:
    """Why poses were not recorded: the rows, and what the robot did there ("" when all were)."""
    if not rec.dropped_at:
        return ""
    rows = ", ".join(where[i] for i in rec.dropped_at[:5]) + (", ..." if len(rec.dropped_at) > 5 else "")
    why = []
    if rec.strayed:
        why.append(
            f"{len(rec.strayed)} came to rest up to {max(rec.strayed):.2g} rad from the reading asked, elsewhere on "
            "the loop (the true robot reaches it by another branch of the loop, or it is far from the true loop)"
        )
    if rec.at_limit:
        why.append(f"it ended at a joint limit ({', '.join(sorted(rec.at_limit))}): at a stop the robot rests on it")
    if rec.unsettled:
        why.append(
            f"it did not come to rest within max_steps={max_steps} steps: a loop of many joints settles slowly "
            f"(try --set max_steps={4 * max_steps}), or a reading far from the true loop makes the servos fight "
            "it (the model that suggested it may be far off)"
        )
    return f"{rows} not recorded ({'; '.join(why)}); the log leaves them out, and its rows can be appended"


def _poses_noise_seed(seed: int, readings: np.ndarray) -> np.random.SeedSequence:
    """The noise stream of recorded poses: the seed's fifth child, keyed by the readings, so that the
    poses' noise is not the seed's own dataset's (the same draws on its first rows) nor another pose
    file's; the same seed and file give the same readings."""
    import zlib

    key = zlib.crc32(np.ascontiguousarray(readings, dtype=np.float64).tobytes())
    return np.random.SeedSequence(seed, spawn_key=(4, key))


def poses_plan(readings: np.ndarray, loop: NominalLoop | None, r0: np.ndarray, step_rad: float):
    """The path through given readings (a :class:`~closedloop.sims.selection.Plan`): each reading is
    recorded, in the order given, the robot led to it from the grasp ``r0`` (or the previous one) through
    intermediate waypoints on its nominal loop where a joint would move more than `step_rad`
    (:func:`closedloop.sims.selection.bridge`; none for a measured loop, which moves freely)."""
    from closedloop.sims.selection import Plan, bridge

    full = (lambda r: loop.full_q(r)) if loop is not None else (lambda r: np.asarray(r, dtype=float).copy())
    waypoints: list[np.ndarray] = []
    record: list[bool] = []
    here = full(r0)
    for r in readings:
        target = full(r)
        if loop is not None and loop.kind.env_joint:  # no reading of the door: it starts where it was
            target[-1] = here[-1]
        for w in bridge(loop, here, target, step_rad):
            waypoints.append(w)
            record.append(False)
        waypoints.append(target)
        record.append(True)
        here = target
    info = {"configurations": int(len(readings)), "bridge_waypoints": int(len(record) - int(np.sum(record)))}
    return Plan(np.array(waypoints), np.array(record, dtype=bool), info)


def _nominal(sc: Scenario, scratch: Path, files: OutputSet, out: Path) -> _Nominal:
    """Step 1: the cleaned nominal URDF (written to the scratch folder) and its model; the outputs' copy
    keeps the robot file's visuals (`outputs.with_visuals`: what a viewer shows, same kinematics)."""
    urdf_nom = nominal_urdf(sc.robot)
    nominal_path = scratch / "nominal.urdf"
    nominal_path.write_text(urdf_nom)
    files.add(out / "nominal.urdf", with_visuals(urdf_nom, ROBOTS[sc.robot].path))
    pmodel = pin.buildModelFromXML(urdf_nom)
    joint_names = [pmodel.names[j] for j in range(1, pmodel.njoints) if pmodel.joints[j].nq == 1]
    if len(joint_names) != pmodel.nq:
        raise ScenarioError(f"{sc.robot}: only 1-DOF joints are supported")
    return _Nominal(urdf_nom, nominal_path, pmodel, joint_names)


def _draw_truth(sc: Scenario, settings: SimSettings, nominal: _Nominal, rng: np.random.Generator) -> _Truth:
    """Step 2: errors drawn on the parameters the core identifies (every joint origin with the setting
    ``truth=all``); offsets and scales stay in the sensor model."""
    joint_names = nominal.joint_names
    if settings.truth == "all":
        names = all_parameters(joint_names, settings.scale > 0.0)
    else:
        names = identifiable_parameters(nominal.path, sc, joint_names, settings.scale > 0.0)
    values = draw_errors(
        names,
        rng,
        {
            "translation": settings.translation,
            "rotation": settings.rotation,
            "offset": settings.offset,
            "scale": settings.scale,
        },
    )
    offset = np.array([values.get(f"{j}.offset", 0.0) for j in joint_names])
    scale = np.array([values.get(f"{j}.scale", 1.0) for j in joint_names])
    return _Truth(values, offset, scale, true_urdf(nominal.path, values))


def _planner(
    sc: Scenario,
    kind: SimLoop,
    settings: SimSettings,
    pmodel: pin.Model,
    scene: Scene,
    r0: np.ndarray,
    rng: np.random.Generator,
) -> tuple[NominalLoopPlanner | RandomConfigurations, NominalLoop | None]:
    """Step 4: the robot's nominal loop and its planner (an open loop: random configurations)."""
    if not kind.closed:
        return RandomConfigurations(
            pmodel, r0, rng, margin=settings.limit_margin, target_span=settings.target_span
        ), None
    door_range = sc.door.angle_range if sc.door else (-0.6, 0.6)
    normal = scene.plane_pose.rotation[:, 2] if scene.plane_pose is not None else None
    loop = NominalLoop(
        pmodel,
        sc.tool_frame,
        sc.loop_type,
        r0,
        hinge=scene.hinge_pose,
        door_range=door_range,
        target_frame=sc.target_frame,
        normal=normal,
    )
    planner = NominalLoopPlanner(
        loop,
        loop.full_q(r0),
        rng,
        step_rad=settings.step_rad,
        margin=settings.limit_margin,
        target_span=settings.target_span,
        retarget_every=settings.retarget_every,
    )
    return planner, loop
