"""Steps 5-6 of `simulate`: the true robot driven through the waypoints in MuJoCo, its samples recorded.

:func:`track_and_record` commands every waypoint (``ctrl = scale * reading + offset``: the servo acts
on the encoder reading) and records the settled ones: the readings through the sensor model
(:func:`sensor_readings`), torques, the closure violation, the loop force (and a tracker's
measurement, open loops).  :func:`sample` ramps the servo commands to the waypoint, steps until the
robot is at rest and, with ``relax``, commands the measured joint positions ``relax_passes`` times so
that the servos stop pushing against the closed chain (:class:`~closedloop.sims.scenarios.SimSettings`).
:func:`violation` and :func:`constraint_force` read the true closure error and the loop's force.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np
import pinocchio as pin

from closedloop.errors import ScenarioError
from closedloop.model.robot import limit_margins
from closedloop.progress import ProgressReporter
from closedloop.sims.loop_types import SimLoop
from closedloop.sims.scenarios import Scenario, SimSettings
from closedloop.sims.scene import Scene, site_pose

__all__ = [
    "Recording",
    "Settler",
    "SiteViews",
    "track_and_record",
    "sensor_readings",
    "settle",
    "sample",
    "violation",
    "constraint_force",
]

log = logging.getLogger(__name__)


def _norm(x: np.ndarray) -> float:
    """``np.linalg.norm(x)`` of a 1-D float vector: ``sqrt(x . x)``, as numpy computes it, without its wrapper."""
    return math.sqrt(x.dot(x))


def violation(scene: Scene, point: bool) -> tuple[float, float]:
    """Distance and rotation angle between the tool site and the target site (after ``mj_forward``)."""
    return SiteViews(scene).violation(point)


class SiteViews:
    """Views of the tool and target sites' positions and orientations in ``scene.data`` (made once).

    :meth:`violation` reads them after ``mj_forward``: the same arithmetic as indexing the site
    arrays at every configuration, without its lookups.
    """

    def __init__(self, scene: Scene) -> None:
        d, t, g = scene.data, scene.tool_site, scene.target_site
        self.p_tool, self.p_target = d.site_xpos[t], d.site_xpos[g]
        self.r_tool, self.r_target_t = d.site_xmat[t].reshape(3, 3), d.site_xmat[g].reshape(3, 3).T

    def violation(self, point: bool) -> tuple[float, float]:
        """:func:`violation` (see there)."""
        dp = _norm(self.p_tool - self.p_target)
        if point:
            return dp, 0.0
        return dp, _norm(pin.log3(self.r_target_t @ self.r_tool))


def constraint_force(scene: Scene) -> float:
    """Norm of the translational part of the loop constraint force (``efc_force``)."""
    d = scene.data
    # MuJoCo puts the equality rows first (d.ne of them), then friction, limits and contacts
    # (its first three rows, found on a Python list: a few rows, cheaper than numpy's flatnonzero)
    eq = scene.eq_id
    rows = [i for i, k in enumerate(d.efc_id[: d.ne].tolist()) if k == eq][:3]
    return _norm(d.efc_force[rows]) if rows else 0.0


_CHUNK = 5  # simulation steps between two settle checks


def settle(
    scene: Scene, ctrl_from: np.ndarray, ctrl_to: np.ndarray, s: SimSettings, vel_tol: float
) -> tuple[bool, int]:
    """Ramp the servo commands over ``ramp_steps``, then step until ``max |qdot| < vel_tol``.

    Returns (settled, steps); at most ``max_steps`` steps, at least ``min_steps``
    (counting the ramp); the velocity is checked every 5 steps.
    """
    return Settler(scene, s).settle(ctrl_from, ctrl_to, vel_tol)


class Settler:
    """:func:`settle` and :func:`sample` on one scene with one set of settings, their set-up done once.

    The servo-command and joint views, the ramp's fractions and buffers, the steps before the first
    velocity check are kept, so that a sample costs its MuJoCo calls and little else (the same steps
    and the same arithmetic as before: the ramp's rows are ``from + frac * (to - from)`` as before,
    computed into buffers).  ``mujoco.mj_step`` is looked up at every settle (benchmarks time it).
    """

    def __init__(self, scene: Scene, s: SimSettings) -> None:
        self.scene, self.s = scene, s
        self.m, self.d = scene.model, scene.data
        ramp = max(1, s.ramp_steps)
        self.ctrl, frac, self.qpos = _ramp_state(scene, ramp)  # servo-command view, (ramp, 1) fractions, qpos
        self.frac, self.ramp, self.max_steps = frac, ramp, s.max_steps
        # steps after the ramp before the first check (no check before min_steps): one call
        k = -(-(s.min_steps - ramp) // _CHUNK) if ramp < s.min_steps else 0
        self.first = max(0, min(k, -(-(s.max_steps - ramp) // _CHUNK))) * _CHUNK
        nu = len(scene.actuator_ids)
        self.delta = np.empty(nu)
        self.rows = np.empty((ramp, nu))
        self.row_views = list(self.rows)  # one view per ramp step, made once
        self.qvel = self.d.qvel  # a view of the simulation state
        passes = max(0, int(s.relax_passes)) if s.relax else 0
        # the tolerance of each settle of a sample: the move, then the relax passes (the last to vel_tol)
        self.tols = [s.move_vel_tol] * passes + [s.vel_tol] if passes else [s.vel_tol]

    def settle(self, ctrl_from: np.ndarray, ctrl_to: np.ndarray, vel_tol: float) -> tuple[bool, int]:
        """:func:`settle` (see there)."""
        m, d, ctrl, rows = self.m, self.d, self.ctrl, self.rows
        step = mujoco.mj_step
        np.subtract(ctrl_to, ctrl_from, out=self.delta)
        np.multiply(self.frac, self.delta, out=rows)
        np.add(ctrl_from, rows, out=rows)  # = np.outer(frac, delta) + from, bit for bit
        for row in self.row_views:
            ctrl[...] = row  # per step: one copy into a view, one call
            step(m, d)
        steps = self.ramp
        if self.first:
            step(m, d, self.first)
            steps += self.first
        qvel, max_steps = self.qvel, self.max_steps
        lo, hi = -vel_tol, vel_tol
        while steps < max_steps:
            # max |qdot| < vel_tol on a Python list (a few joints: cheaper than numpy's reductions): min and
            # max (two C calls; a NaN in first place fails them), then no NaN elsewhere (their sum is a
            # number: the other values are within the tolerance), as numpy's test would find
            v = qvel.tolist()
            if lo < min(v) and max(v) < hi:
                t = sum(v)
                if t == t:
                    return True, steps
            step(m, d, _CHUNK)
            steps += _CHUNK
        return False, steps

    def sample(self, ctrl: np.ndarray, target: np.ndarray) -> tuple[bool, int, np.ndarray]:
        """:func:`sample` (see there)."""
        tols = self.tols
        settled, steps = self.settle(ctrl, target, tols[0])
        ctrl = target
        qpos = self.qpos
        for tol in tols[1:]:
            relaxed = qpos.copy()
            ok, st = self.settle(ctrl, relaxed, tol)
            settled &= ok
            steps += st
            ctrl = relaxed
        return settled, steps, ctrl


_RAMP: dict[int, tuple] = {}  # id(MjData) -> (MjData, ramp, ctrl view, fractions, qpos view): one scene at a time


def _ramp_state(scene: Scene, ramp: int) -> tuple:
    """The servo-command view of ``scene``, the ramp fractions (1..ramp)/ramp as a column and the arm's
    ``qpos`` (a view, or ``qpos[adr]``: copy it), cached."""
    d = scene.data
    hit = _RAMP.get(id(d))
    if hit is None or hit[0] is not d or hit[1] != ramp:
        _RAMP.clear()
        hit = _RAMP[id(d)] = (
            d,
            ramp,
            _view(d.ctrl, scene.actuator_ids),
            (np.arange(1, ramp + 1) / ramp)[:, None],
            _view(d.qpos, scene.qpos_adr),
        )
    return hit[2], hit[3], hit[4]


def _view(x: np.ndarray, ids: np.ndarray):
    """``x[ids]`` as a writable view when the ids are a contiguous range, else an index proxy."""
    ids = np.asarray(ids)
    if ids.size and np.array_equal(ids, np.arange(ids[0], ids[0] + ids.size)):
        return x[int(ids[0]) : int(ids[0]) + ids.size]
    return _Scatter(x, ids)


class _Scatter:
    """``proxy[...] = row`` writes ``target[ids] = row`` (non-contiguous actuator ids)."""

    def __init__(self, target: np.ndarray, ids: np.ndarray):
        self.target, self.ids = target, ids

    def __setitem__(self, key, value) -> None:
        self.target[self.ids] = value

    def copy(self) -> np.ndarray:
        return self.target[self.ids]


def sample(scene: Scene, ctrl: np.ndarray, target: np.ndarray, s: SimSettings) -> tuple[bool, int, np.ndarray]:
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
    return Settler(scene, s).sample(ctrl, target)


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
            raise ScenarioError("sensor_readings: noise > 0 needs a random generator")
        r = r + rng.normal(0.0, noise, size=r.shape)
    if quantum > 0.0:
        r = quantum * np.round(r / quantum)
    return r


@dataclass
class Recording:
    """Steps 5-6: what was recorded at the ``done`` settled samples."""

    readings: np.ndarray
    q_true: np.ndarray
    tau: np.ndarray
    viol_m: np.ndarray
    viol_rad: np.ndarray
    force: np.ndarray
    door: np.ndarray
    meas: np.ndarray
    done: int = 0
    dropped: int = 0
    steps: int = 0
    elapsed: float = 0.0
    unsettled: int = 0  # of the dropped: not settled within max_steps
    at_limit: dict[str, int] = field(default_factory=dict)  # of the dropped: how often each joint was at a limit
    dropped_at: list[int] = field(default_factory=list)  # the dropped: their places among the waypoints to record
    strayed: list[float] = field(default_factory=list)  # of the dropped: how far from its waypoint each came to rest

    def shortfall(self, n: int, max_steps: int) -> str:
        """Why fewer than `n` configurations were recorded, and what to change ("" when all were);
        `max_steps`: the setting a sample had to settle within."""
        if self.done >= n:
            return ""
        why = []
        if self.at_limit:
            worst = sorted(self.at_limit.items(), key=lambda kv: -kv[1])[:3]
            why.append(
                "the robot reached a joint limit ("
                + ", ".join(f"{j} {c} time(s)" for j, c in worst)
                + "): the self-motion runs into it; try another --q0 away from the limits, --joints without "
                "that joint, or a loop with more self-motion"
            )
        if self.unsettled:
            why.append(
                f"{self.unsettled} waypoint(s) did not come to rest within max_steps={max_steps} steps (heavy "
                f"links on soft servos, or a stiff loop, settle slowly); try --set max_steps={5 * max_steps}"
            )
        if not why:
            why.append(
                "the planner found no motion the closed loop allows from the grasp pose (the loop cannot "
                "move: a singular grasp or joints at their limits); try another --q0, or a loop with fewer "
                "constraints (point: 3, plane: 1)"
            )
        return "; ".join(why)

    @classmethod
    def empty(cls, n: int, nj: int, env_joint: bool, measures: bool) -> "Recording":
        return cls(
            np.zeros((n, nj)),
            np.zeros((n, nj)),
            np.zeros((n, nj)),
            np.zeros(n),
            np.zeros(n),
            np.zeros(n),
            np.zeros(n) if env_joint else np.zeros(0),
            np.zeros((n, 3)) if measures else np.zeros((0, 3)),
        )

    def truncate(self) -> None:
        k = self.done
        self.readings, self.q_true, self.tau = self.readings[:k], self.q_true[:k], self.tau[:k]
        self.viol_m, self.viol_rad, self.force = self.viol_m[:k], self.viol_rad[:k], self.force[:k]
        self.door, self.meas = self.door[:k], self.meas[:k]


_AHEAD = 256  # waypoints planned in one go, before they are driven


def _targets(planner, plan, max_attempts: int, missing: Callable[[], int]):
    """(planning vector, record?) pairs: the planner's waypoints, or a selected plan's path.

    The planner works on the nominal model and its own random stream only, so its waypoints are
    planned ahead of the stepping, up to ``_AHEAD`` at a time: the planner's and MuJoCo's working
    sets then stay in the caches through a block instead of evicting each other at every waypoint
    (the same waypoints; the planner's CPU per waypoint 0.12 -> 0.05 ms on the hand, the Panda's
    loop 3-4 % faster).  A block is never longer than the samples still ``missing()`` (each waypoint
    gives at most one sample), so every planned waypoint is driven and the planner's counters
    (``stats``) are those of the driven waypoints.
    """
    if plan is not None:
        yield from zip(plan.waypoints, plan.record)
        return
    left = max_attempts
    while left > 0:
        k = max(1, min(_AHEAD, missing(), left))
        left -= k
        for wp in [planner.step() for _ in range(k)]:
            yield wp, True


def track_and_record(
    sc: Scenario,
    kind: SimLoop,
    settings: SimSettings,
    scene: Scene,
    offset: np.ndarray,
    scale: np.ndarray,
    planner,
    plan,
    n: int,
    rng_noise: np.random.Generator,
    rng_env: np.random.Generator | None,
    progress: ProgressReporter | None,
    t_start: float,
    stray: float | None = None,
) -> Recording:
    """Steps 5-6: drive the true robot through the waypoints in MuJoCo and record the settled samples.

    With `stray` (given readings, not planned ones: `dataset.poses_plan`) a sample that comes to rest farther
    than that from its waypoint on some joint (rad, or m) is dropped: it is not the configuration asked for."""
    m, d = scene.model, scene.data
    joint_names = scene.joint_names
    nj = len(joint_names)
    tracker = scene.target_pose if not kind.closed else None
    rec = Recording.empty(n, nj, kind.env_joint is not None, tracker is not None)
    ctrl = d.ctrl[scene.actuator_ids].copy()
    limited = m.jnt_limited[[m.joint(j).id for j in joint_names]].astype(bool)
    # (joint, lower, upper) of the limited joints: the at-limit test on Python floats (the same arithmetic)
    ranges = zip(scene.jnt_range[:, 0].tolist(), scene.jnt_range[:, 1].tolist(), limited.tolist())
    # flagged within limit_flag of a limit, in each joint's own unit: at most 5 % of a short range
    flags = limit_margins(scene.jnt_range[:, 0], scene.jnt_range[:, 1], settings.limit_flag, 0.05).tolist()
    limits = [(i, lo, hi, flags[i]) for i, (lo, hi, lim) in enumerate(ranges) if lim]
    settler = Settler(scene, settings)
    qpos = settler.qpos
    sites, point = SiteViews(scene), kind.point_contact
    tau = _view(d.qfrc_actuator, scene.dof_adr)  # the arm's actuator torques (read after mj_forward)
    targets = _targets(planner, plan, 3 * n + 20, lambda: n - rec.done)
    asked = -1  # the place of the waypoint among those to record
    while rec.done < n:
        wp, record = next(targets, (None, False))
        if wp is None:
            break
        asked += record
        target = scale * wp[:nj] + offset
        if not record:  # a waypoint on the way to the next selected configuration: move only
            _ok, steps = settler.settle(ctrl, target, settings.move_vel_tol)
            rec.steps += steps
            ctrl = target
            continue
        settled, steps, ctrl = settler.sample(ctrl, target)
        rec.steps += steps
        mujoco.mj_forward(m, d)
        q = qpos.copy()
        ql = q.tolist()
        at_limit = [i for i, lo, hi, f in limits if ql[i] - lo < f or hi - ql[i] < f]
        off = float(np.max(np.abs(q - target))) if stray is not None and nj else 0.0
        if stray is not None and off > stray:  # at rest elsewhere on the loop: not the reading asked for
            rec.dropped += 1
            rec.dropped_at.append(asked)
            rec.strayed.append(off)
            continue
        if not settled:
            log.debug(
                "sample %d not settled after %d steps (max |qdot| = %.3g)", rec.done, steps, np.max(np.abs(d.qvel))
            )
        if settings.drop_flagged and (at_limit or not settled):
            rec.dropped += 1
            rec.dropped_at.append(asked)
            rec.unsettled += not settled
            for k in at_limit:
                rec.at_limit[joint_names[k]] = rec.at_limit.get(joint_names[k], 0) + 1
            continue
        i = rec.done
        rec.tau[i] = tau.copy()
        # joint compliance: the motor-side encoder leads the link by c * tau (tau = K (theta_m - q))
        if settings.compliance:
            q_enc = q + settings.compliance * rec.tau[i]
        else:  # q + 0 * tau is q
            q_enc = q
        rec.readings[i] = sensor_readings(q_enc, offset, scale, settings.noise, settings.quantization, rng_noise)
        rec.q_true[i] = q
        if tracker is not None:
            # the tracker measures the true tool point in its frame; the "violation" of this
            # loop is the measurement error
            tip = site_pose(m, d, scene.tool_site).translation
            assert rng_env is not None  # an open (tracked) loop draws its environment (SimLoop.draws_environment)
            rec.meas[i] = tracker.actInv(tip) + rng_env.normal(0.0, settings.tracker_noise, 3)
            rec.viol_m[i] = float(np.linalg.norm(rec.meas[i] - tracker.actInv(tip)))
        else:
            rec.viol_m[i], rec.viol_rad[i] = sites.violation(point)
        rec.force[i] = constraint_force(scene)
        if rec.door.size:
            rec.door[i] = d.qpos[scene.door_qpos_adr]
        rec.done += 1
        if progress is not None:
            progress("simulating", rec.done, n)
    rec.elapsed = time.perf_counter() - t_start
    if rec.done < n:
        log.info("%s: only %d of %d samples recorded (%d dropped)", sc.name, rec.done, n, rec.dropped)
        rec.truncate()
    return rec
