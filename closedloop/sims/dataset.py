"""Run a scenario: draw the true robot, simulate the closed loop, record and write a dataset.

Pipeline of :func:`simulate`:

1. nominal URDF (cleaned, :func:`closedloop.models.nominal_urdf`) and its
   Pinocchio model; arm joints = movable joints in Pinocchio order;
2. true parameters: :func:`~closedloop.sims.scenarios.perturbable_parameters`
   drawn by :func:`~closedloop.sims.scenarios.draw_errors`; the true URDF
   carries the placement errors (offsets/scales stay in the sensor model);
3. MuJoCo scene of the true robot with the loop closed at the true grasp
   configuration ``q0`` (:func:`~closedloop.sims.scene.build_scene`);
4. the robot reads ``r0 = sensor(q0)``, builds its nominal loop and plans
   waypoints along the nominal self-motion (:mod:`closedloop.sims.driver`);
   (with the setting ``select``: the waypoints are n configurations chosen from a
   pool of nominal self-motion configurations by pose selection, visited in a
   short path, :mod:`closedloop.sims.selection`);
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

import csv
import io
import json
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pinocchio as pin

from closedloop.errors import InputError
from closedloop.export import OutputSet
from closedloop.models import nominal_urdf

from .driver import NominalLoop, NominalLoopPlanner, RandomConfigurations
from .scenarios import SCENARIOS, Scenario, SimSettings, draw_errors, identifiable_parameters
from .scene import Scene, build_scene, site_pose, true_urdf

__all__ = ["SimResult", "simulate", "sensor_readings"]

log = logging.getLogger(__name__)

_COMPS = ("x", "y", "z", "rx", "ry", "rz")
#: the files of a dataset, in the order they are published (truth.json, the manifest, last)
DATASET_FILES = ("nominal.urdf", "scene.xml", "log.csv", "truth.json")


def check_dataset_dir(out: Path, replace: bool = False) -> None:
    """Refuse to write a dataset into a directory that holds another one, unless `replace`.

    (A dataset is a set: a new ``log.csv`` beside an old ``truth.json`` would look complete.)
    """
    if replace or not out.is_dir():
        return
    present = [f for f in DATASET_FILES if (out / f).exists()]
    if present:
        raise InputError(f"--out {out}: holds another dataset ({', '.join(present)}); "
                         "give a new directory or --replace to replace it")


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


def sensor_readings(
    q: np.ndarray,
    offset: np.ndarray,
    scale: np.ndarray,
    noise: float,
    quantum: float,
    rng: np.random.Generator | None,
) -> np.ndarray:
    """Sensor model: ``Q((q - offset) / scale + N(0, noise))``, see module docstring."""
    r = (np.asarray(q, dtype=float) - offset) / scale
    if noise > 0.0:
        if rng is None:
            raise ValueError("noise > 0 needs a random generator")
        r = r + rng.normal(0.0, noise, size=r.shape)
    if quantum > 0.0:
        r = quantum * np.round(r / quantum)
    return r


def _violation(scene: Scene, point: bool) -> tuple[float, float]:
    """Distance and rotation angle between the tool site and the target site (after ``mj_forward``)."""
    d, t, g = scene.data, scene.tool_site, scene.target_site
    dp = float(np.linalg.norm(d.site_xpos[t] - d.site_xpos[g]))
    if point:
        return dp, 0.0
    rel = d.site_xmat[g].reshape(3, 3).T @ d.site_xmat[t].reshape(3, 3)
    return dp, float(np.linalg.norm(pin.log3(rel)))


_EQUALITY = int(mujoco.mjtConstraint.mjCNSTR_EQUALITY)


def _constraint_force(scene: Scene) -> float:
    """Norm of the translational part of the loop constraint force (``efc_force``)."""
    d = scene.data
    nefc = d.nefc
    rows = np.flatnonzero((d.efc_type[:nefc] == _EQUALITY) & (d.efc_id[:nefc] == scene.eq_id))
    return float(np.linalg.norm(d.efc_force[rows[:3]])) if rows.size else 0.0


def _pose_params(prefix: str, pose: pin.SE3, rotation: bool = True) -> dict[str, float]:
    vals = list(pose.translation) + (list(pin.log3(pose.rotation)) if rotation else [])
    return {f"{prefix}.{c}": float(v) for c, v in zip(_COMPS, vals)}


def _plane_params(prefix: str, plane: pin.SE3) -> dict[str, float]:
    """``PlaneLoop`` parameters of a plane frame (z = normal, n_z > 0) with the reference normal e_z."""
    from closedloop.loops.plane import PlaneLoop

    n = plane.rotation[:, 2]
    w = PlaneLoop(prefix, "tool").angles(n)
    return {f"{prefix}.nrx": float(w[0]), f"{prefix}.nry": float(w[1]),
            f"{prefix}.d": float(n @ plane.translation)}


_CHUNK = 5  # simulation steps between two settle checks


def _settle(scene: Scene, ctrl_from: np.ndarray, ctrl_to: np.ndarray, s: SimSettings,
            vel_tol: float) -> tuple[bool, int]:
    """Ramp the servo commands over ``ramp_steps``, then step until ``max |qdot| < vel_tol``.

    Returns (settled, steps); at most ``max_steps`` steps, at least ``min_steps``
    (counting the ramp); the velocity is checked every 5 steps.
    """
    m, d = scene.model, scene.data
    ids = scene.actuator_ids
    ramp = max(1, s.ramp_steps)
    commands = ctrl_from + np.outer(np.arange(1, ramp + 1) / ramp, ctrl_to - ctrl_from)
    ctrl, step = _ctrl_view(d, ids), mujoco.mj_step  # per step: one copy into a view, one call
    for row in commands:
        ctrl[...] = row
        step(m, d)
    steps = ramp
    qvel = d.qvel  # a view of the simulation state
    lo, hi = -vel_tol, vel_tol
    if steps < s.min_steps:  # no check before min_steps: one call
        k = -(-(s.min_steps - steps) // _CHUNK)
        k = min(k, -(-(s.max_steps - steps) // _CHUNK))
        if k > 0:
            step(m, d, k * _CHUNK)
            steps += k * _CHUNK
    while steps < s.max_steps:
        # max |qdot| < vel_tol, on a Python list (a few joints: cheaper than numpy's reductions;
        # a NaN fails every comparison, as in numpy)
        if all(lo < v < hi for v in qvel.tolist()):
            return True, steps
        step(m, d, _CHUNK)
        steps += _CHUNK
    return False, steps


def _ctrl_view(d, ids: np.ndarray) -> np.ndarray:
    """``d.ctrl[ids]`` as a writable view when the ids are a contiguous range, else an index proxy."""
    ids = np.asarray(ids)
    if ids.size and np.array_equal(ids, np.arange(ids[0], ids[0] + ids.size)):
        return d.ctrl[int(ids[0]):int(ids[0]) + ids.size]
    return _Scatter(d.ctrl, ids)


class _Scatter:
    """``proxy[...] = row`` writes ``target[ids] = row`` (non-contiguous actuator ids)."""

    def __init__(self, target: np.ndarray, ids: np.ndarray):
        self.target, self.ids = target, ids

    def __setitem__(self, key, value) -> None:
        self.target[self.ids] = value


def _sample(scene: Scene, ctrl: np.ndarray, target: np.ndarray, s: SimSettings) -> tuple[bool, int, np.ndarray]:
    """Drive to one waypoint and come to rest there; returns (settled, steps, final servo command).

    Without ``relax`` the servos are commanded ``target`` and the robot settles to
    ``vel_tol``.  With it, the move only settles to ``move_vel_tol`` (the robot is
    near the waypoint and slow), then ``relax_passes`` times the servos are
    commanded the measured joint positions and the robot settles again, to
    ``move_vel_tol`` and, the last time, to ``vel_tol``.  Each pass releases most
    of the preload the previous one left (the servo, driven from the wrong nominal
    model, pushes against the closed chain; the loop springs back when released and
    the servo takes up a fraction of the deflection), so the recorded configuration
    loads the loop far less than one long settle would.
    """
    d = scene.data
    passes = max(0, int(s.relax_passes)) if s.relax else 0
    settled, steps = _settle(scene, ctrl, target, s, s.move_vel_tol if passes else s.vel_tol)
    ctrl = target
    for k in range(passes):
        relaxed = d.qpos[scene.qpos_adr].copy()
        ok, st = _settle(scene, ctrl, relaxed, s, s.vel_tol if k == passes - 1 else s.move_vel_tol)
        settled &= ok
        steps += st
        ctrl = relaxed
    return settled, steps, ctrl


def _targets(planner, plan, max_attempts: int):
    """(planning vector, record?) pairs: the planner's waypoints, or a selected plan's path."""
    if plan is None:
        for _ in range(max_attempts):
            yield planner.step(), True
    else:
        yield from zip(plan.waypoints, plan.record)


def simulate(
    scenario: str,
    n: int,
    seed: int,
    out_dir: Path | str,
    progress: Callable[[int, int], None] | None = None,
    **overrides: Any,
) -> SimResult:
    """Generate a closed-loop calibration dataset by simulation.

    Args:
        scenario: key of :data:`~closedloop.sims.scenarios.SCENARIOS`.
        n: number of recorded (settled, unflagged) configurations.
        seed: random seed (truth, targets, noise); the same seed gives an identical log.
        out_dir: output directory (created).
        progress: optional callback ``progress(done, n)`` called after each recorded sample.
        **overrides: :class:`~closedloop.sims.scenarios.SimSettings` fields, plus
            ``stiff=True`` for the stiff-loop preset (``SimSettings.stiff``).

    Returns:
        the :class:`SimResult`; files ``log.csv``, ``nominal.urdf``, ``truth.json``,
        ``scene.xml`` are written in ``out_dir``.
    """
    try:
        sc: Scenario = SCENARIOS[scenario]
    except KeyError:
        raise KeyError(f"unknown scenario {scenario!r}; known: {sorted(SCENARIOS)}") from None
    if n < 1:
        raise ValueError("n must be >= 1")
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
    # the dataset is computed beside a scratch nominal.urdf, then published whole into `out` (truth.json last)
    files = OutputSet(order=[out / f for f in DATASET_FILES])
    with tempfile.TemporaryDirectory(prefix="closedloop-sim-") as scratch:
        result = _simulate(sc, settings, n, seed, out, Path(scratch), files, progress)
    files.commit()
    return result


def _simulate(sc: Scenario, settings: SimSettings, n: int, seed: int, out: Path, scratch: Path, files: OutputSet,
              progress: Callable[[int, int], None] | None) -> SimResult:
    """The body of :func:`simulate`: outputs go into `files` (published when `simulate` returns)."""
    scenario = sc.name

    ss = np.random.SeedSequence(seed)
    rng_truth, rng_plan, rng_noise = (np.random.default_rng(c) for c in ss.spawn(3))
    # the environment of the new loop types (plane, tracker pose, tracker noise): a fourth stream, so
    # the older scenarios' draws are unchanged
    rng_env = np.random.default_rng(ss.spawn(1)[0]) if sc.loop_type in ("plane", "measured_point") else None

    # 1. nominal model
    urdf_nom = nominal_urdf(sc.robot)
    nominal_path = scratch / "nominal.urdf"
    nominal_path.write_text(urdf_nom)
    files.add(out / "nominal.urdf", urdf_nom)
    pmodel = pin.buildModelFromXML(urdf_nom)
    joint_names = [pmodel.names[j] for j in range(1, pmodel.njoints) if pmodel.joints[j].nq == 1]
    if len(joint_names) != pmodel.nq:
        raise ValueError(f"{sc.robot}: only 1-DOF joints are supported")
    nj = len(joint_names)

    # 2. truth
    names = identifiable_parameters(nominal_path, sc, joint_names, settings.scale > 0.0)
    values = draw_errors(
        names,
        rng_truth,
        {"translation": settings.translation, "rotation": settings.rotation,
         "offset": settings.offset, "scale": settings.scale},
    )
    offset = np.array([values.get(f"{j}.offset", 0.0) for j in joint_names])
    scale = np.array([values.get(f"{j}.scale", 1.0) for j in joint_names])
    urdf_true = true_urdf(nominal_path, values)

    # 3. scene, closed at the true grasp configuration
    q0 = np.asarray(sc.q0, dtype=float)
    scene = build_scene(urdf_true, sc, settings, joint_names, q0, rng=rng_env)
    files.add(out / "scene.xml", scene.to_xml())
    m, d = scene.model, scene.data

    # 4. the robot's nominal loop and planner
    r0 = sensor_readings(q0, offset, scale, settings.noise, settings.quantization, rng_noise)
    door_range = sc.door.angle_range if sc.door else (-0.6, 0.6)
    planner: NominalLoopPlanner | RandomConfigurations
    loop: NominalLoop | None = None
    if sc.loop_type == "measured_point":  # open loop: random configurations of the nominal model
        planner = RandomConfigurations(pmodel, r0, rng_plan, margin=settings.limit_margin,
                                       target_span=settings.target_span)
    else:
        normal = scene.plane_pose.rotation[:, 2] if scene.plane_pose is not None else None
        loop = NominalLoop(pmodel, sc.tool_frame, sc.loop_type, r0, hinge=scene.hinge_pose, door_range=door_range,
                           target_frame=sc.target_frame, normal=normal)
        planner = NominalLoopPlanner(
            loop, loop.full_q(r0), rng_plan, step_rad=settings.step_rad, margin=settings.limit_margin,
            target_span=settings.target_span, retarget_every=settings.retarget_every,
        )
    tracker = scene.target_pose if sc.loop_type == "measured_point" else None

    # 5-6. track and record
    readings = np.zeros((n, nj))
    q_true = np.zeros((n, nj))
    tau = np.zeros((n, nj))
    viol_m = np.zeros(n)
    viol_rad = np.zeros(n)
    force = np.zeros(n)
    door = np.zeros(n) if sc.loop_type == "hinge" else np.zeros(0)
    meas = np.zeros((n, 3)) if tracker is not None else np.zeros((0, 3))
    ctrl = d.ctrl[scene.actuator_ids].copy()
    lo, hi = scene.jnt_range[:, 0], scene.jnt_range[:, 1]
    limited = m.jnt_limited[[m.joint(j).id for j in joint_names]].astype(bool)
    done = dropped = total_steps = 0
    max_attempts = 3 * n + 20
    t_start = time.perf_counter()
    plan = None
    if settings.select:  # pose selection on the nominal model (closedloop.sims.selection)
        from .selection import plan_selected

        start = loop.full_q(r0) if loop is not None else r0
        plan = plan_selected(sc, settings, nominal_path, joint_names, planner, loop, start, n, pmodel)
    t_plan = time.perf_counter() - t_start
    targets = _targets(planner, plan, max_attempts)
    while done < n:
        wp, record = next(targets, (None, False))
        if wp is None:
            break
        target = scale * wp[:nj] + offset
        if not record:  # a waypoint on the way to the next selected configuration: move only
            _ok, steps = _settle(scene, ctrl, target, settings, settings.move_vel_tol)
            total_steps += steps
            ctrl = target
            continue
        settled, steps, ctrl = _sample(scene, ctrl, target, settings)
        total_steps += steps
        mujoco.mj_forward(m, d)
        q = d.qpos[scene.qpos_adr].copy()
        at_limit = bool(np.any(limited & ((q - lo < settings.limit_flag) | (hi - q < settings.limit_flag))))
        if not settled:
            log.debug("sample %d not settled after %d steps (max |qdot| = %.3g)", done, steps, np.max(np.abs(d.qvel)))
        if settings.drop_flagged and (at_limit or not settled):
            dropped += 1
            continue
        tau[done] = d.qfrc_actuator[scene.dof_adr]
        # joint compliance: the motor-side encoder leads the link by c * tau (tau = K (theta_m - q))
        readings[done] = sensor_readings(q + settings.compliance * tau[done], offset, scale, settings.noise,
                                         settings.quantization, rng_noise)
        q_true[done] = q
        if tracker is not None:
            # the tracker measures the true tool point in its frame; the "violation" of this
            # loop is the measurement error
            tip = site_pose(m, d, scene.tool_site).translation
            meas[done] = tracker.actInv(tip) + rng_env.normal(0.0, settings.tracker_noise, 3)
            viol_m[done] = float(np.linalg.norm(meas[done] - tracker.actInv(tip)))
        else:
            viol_m[done], viol_rad[done] = _violation(scene, sc.loop_type in ("point", "plane"))
        force[done] = _constraint_force(scene)
        if door.size:
            door[done] = d.qpos[scene.door_qpos_adr]
        done += 1
        if progress is not None:
            progress(done, n)
    elapsed = time.perf_counter() - t_start
    if done < n:
        log.warning("%s: only %d of %d samples recorded (%d dropped)", scenario, done, n, dropped)
        readings, q_true, tau = readings[:done], q_true[:done], tau[:done]
        viol_m, viol_rad, force = viol_m[:done], viol_rad[:done], force[:done]
        door, meas = door[:done], meas[:done]
    log.info(
        "%s: %d samples, %d dropped, %d steps, %d QP solves, %.2f s (%.0f configs/s)",
        scenario, done, dropped, total_steps, planner.stats.qp_solves, elapsed, done / max(elapsed, 1e-12),
    )

    # outputs
    measured = {f"{sc.loop_name}:{a}": meas[:, k] for k, a in enumerate("xyz")} if tracker is not None else {}
    _write_log(files, out / "log.csv", joint_names, readings, tau, viol_m, viol_rad, force, door, measured)
    params = dict(values)
    if settings.compliance > 0.0:
        params.update({f"{j}.compliance": float(settings.compliance) for j in joint_names})
    if sc.loop_type == "point":  # names of closedloop.loops.PointLoop: contact point, tool tip in the tool frame
        c = scene.target_pose.translation
        params.update({f"{sc.loop_name}.p{a}": float(v) for a, v in zip("xyz", c)})
        params.update({f"{sc.loop_name}.tip_{a}": 0.0 for a in "xyz"})
    elif sc.loop_type == "weld":  # the tool in the fixture (world) or in the robot's target frame
        params.update(_pose_params(sc.loop_name, scene.closure))
    elif sc.loop_type == "measured_point":  # MeasuredPointLoop: tracker frame in the base, tip in the tool
        params.update(_pose_params(sc.loop_name, tracker))
        params.update({f"{sc.loop_name}.tip_{a}": 0.0 for a in "xyz"})
    elif sc.loop_type == "plane":  # PlaneLoop with its default (fixed) reference normal e_z
        params.update(_plane_params(sc.loop_name, scene.plane_pose))
        params.update({f"{sc.loop_name}.tip_{a}": 0.0 for a in "xyz"})
    # hinge: the HingeLoop's chart is relative to a reference axis fitted from data, so its
    # parameters are not comparable with a fixed truth; truth.json gives the true axis instead
    # (loop.hinge_axis) and `closedloop check` compares the robot parameters.
    loop_info: dict[str, Any] = {"type": sc.loop_type, "frame": sc.tool_frame, "name": sc.loop_name}
    if sc.target_frame is not None:
        loop_info["to"] = sc.target_frame
    if scene.hinge_pose is not None:
        loop_info["hinge_axis"] = {
            "point": [float(v) for v in scene.hinge_pose.translation],
            "direction": [float(v) for v in scene.hinge_pose.rotation[:, 2]],
            "frame": _pose_params("hinge", scene.hinge_pose),
        }
    if scene.plane_pose is not None:
        loop_info["plane"] = {
            "point": [float(v) for v in scene.plane_pose.translation],
            "normal": [float(v) for v in scene.plane_pose.rotation[:, 2]],
            "frame": _pose_params("plane", scene.plane_pose),
        }
    if tracker is not None:
        loop_info["tracker"] = {"frame": _pose_params(sc.loop_name, tracker), "noise_m": float(settings.tracker_noise),
                                "columns": list(measured)}
    rms = lambda a: float(np.sqrt(np.mean(a**2))) if a.size else 0.0  # noqa: E731
    truth = {
        "scenario": sc.name,
        "seed": int(seed),
        "robot": sc.robot,
        "joint_names": joint_names,
        "settings": settings.as_dict(sc.loop_type),
        "loop": loop_info,
        "q0": [float(v) for v in q0],
        "parameters": params,
        "violation": {
            "rms_m": rms(viol_m), "max_m": float(viol_m.max(initial=0.0)),
            "rms_rad": rms(viol_rad), "max_rad": float(viol_rad.max(initial=0.0)),
        },
        "samples": {"recorded": done, "dropped": dropped, "steps": total_steps,
                    "qp_solves": planner.stats.qp_solves},
    }
    if plan is not None:
        truth["selection"] = plan.info
    files.add(out / "truth.json", json.dumps(truth, indent=2))
    return SimResult(
        scenario=sc.name, seed=int(seed), out_dir=out, joint_names=joint_names, readings=readings,
        q_true=q_true, tau=tau, violation_m=viol_m, violation_rad=viol_rad, constraint_force_n=force,
        door_angle=door, truth=truth, settings=settings, n_dropped=dropped, n_steps=total_steps,
        elapsed_s=elapsed, extra={"select_s": t_plan} if plan is not None else {},
    )


def _write_log(
    files: OutputSet,
    path: Path,
    joint_names: list[str],
    readings: np.ndarray,
    tau: np.ndarray,
    viol_m: np.ndarray,
    viol_rad: np.ndarray,
    force: np.ndarray,
    door: np.ndarray,
    measured: dict[str, np.ndarray] | None = None,
) -> None:
    """Write the calibration log: joint readings first, then diagnostic columns, then measurements."""
    measured = measured or {}
    header = list(joint_names) + [f"tau:{j}" for j in joint_names] + ["violation_m", "violation_rad", "constraint_force_n"]
    if door.size:
        header.append("door_angle")
    header += list(measured)
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(header)
    for i in range(len(readings)):
        row = [repr(float(v)) for v in readings[i]] + [repr(float(v)) for v in tau[i]]
        row += [repr(float(viol_m[i])), repr(float(viol_rad[i])), repr(float(force[i]))]
        if door.size:
            row.append(repr(float(door[i])))
        row += [repr(float(col[i])) for col in measured.values()]
        w.writerow(row)
    files.add(path, f.getvalue())
