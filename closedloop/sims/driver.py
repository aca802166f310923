"""Driving the robot along its *nominal* loop self-motion (QP differential IK).

The robot only knows its nominal model (Pinocchio, built from the nominal
URDF) and its joint readings.  At the grasp it believes the loop closure is
where its nominal model puts the tool:

* ``weld``: fixture pose ``X = FK_nom(r0)`` (frame ``loop_target`` on the universe);
  welded to another robot frame ``B`` (``target_frame``), ``loop_target`` is a
  frame on B's parent joint at the nominal tool pose relative to B at ``r0``;
* ``point``: socket centre ``p = FK_nom(r0).translation``;
* ``hinge``: the door hinge ``H`` is known (the door's pose in the world) and a
  revolute joint ``door_hinge`` about ``H``'s z axis is appended to the nominal
  model; the handle frame sits at ``G = H^-1 FK_nom(r0)`` on the door (door
  angle 0 at the grasp).  The door angle is an unmeasured planning variable.

The nominal loop constraint is ``e(q) = 0`` with

* weld/hinge: ``e = log6(oMh^-1 oMt)`` (6 rows), ``de/dq = Jlog6(hMt) (J_t - Ad(tMh) J_h)``
  with ``J_t, J_h`` the LOCAL frame Jacobians of tool and handle;
* point: ``e = p_t - p`` (3 rows), ``de/dq = R_t J_t[:3]``;
* plane: ``e = n . p_t - d`` (1 row), ``de/dq = n^T R_t J_t[:3]``: the tip on the
  plane of unit normal ``n`` through the nominal tip at the grasp (``d = n . p_0``);
  the robot is given the plane's normal (the planned motion is a 5-DOF self-motion).

(each is its loop type's :meth:`~closedloop.sims.loop_types.SimLoop.nominal_target` and
:meth:`~closedloop.sims.loop_types.SimLoop.nominal_residual`).  A measured (open) loop has no
constraint: :class:`RandomConfigurations` draws random targets in the nominal joint space instead.

One planning step (:meth:`NominalLoopPlanner.step`) solves the QP

    min_dq  1/2 |dq - d|^2 + w/2 |J dq + e|^2
    s.t.    q_lo + margin <= q + dq <= q_hi - margin

exactly, by a primal active-set method on its bounds (:func:`solve_box_qp`: a
few microseconds for 6-9 variables, where setting up OSQP through qpsolvers
took ~2 ms per waypoint; OSQP remains the fallback should the active set not
converge), where ``d`` is the direction to a random target (or, for a 1-D self-motion,
along the null vector, sweeping back and forth) projected onto the null space
of ``J`` (the self-motion) and scaled so that no joint moves more than
``step_rad``; ``w`` is large so the step stays on the nominal loop.  Up to
three Gauss-Newton corrections ``dq = -J^+ e`` then put ``q`` back on the
nominal loop (to ``|e| < 1e-6``).  The result is a path of nominal waypoints; the simulation
tracks them with position servos and the compliant loop absorbs the mismatch
between nominal and true robot.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from closedloop.errors import ScenarioError
from closedloop.model.robot import find_frame, limit_margins
from closedloop.sims.loop_types import sim_loop
from closedloop.sims.qp import min_norm_step, solve_box_qp, svd_full
from closedloop.sims.scenarios import LoopType

__all__ = ["NominalLoop", "NominalLoopPlanner", "RandomConfigurations", "solve_box_qp"]

log = logging.getLogger(__name__)

_W_LOOP = 1e4  # weight of the loop-constraint task in the QP


class NominalLoop:
    """The nominal loop constraint ``e(q) = 0`` on a Pinocchio model.

    Args:
        model: nominal robot model (it is copied; a door joint may be appended).
        tool_frame: frame closing the loop.
        loop_type: a key of :data:`closedloop.sims.loop_types.SIM_LOOPS` (not ``measured_point``).
        r0: joint readings at the grasp (arm joints, model order).
        hinge: world pose of the door hinge frame (hinge loops).
        door_range: door joint limits (hinge loops).
        target_frame: weld loops: robot frame the tool is welded to (``None``: the world).
        normal: plane loops: unit normal of the plane (world frame).
    """

    def __init__(
        self,
        model: pin.Model,
        tool_frame: str,
        loop_type: LoopType,
        r0: np.ndarray,
        hinge: pin.SE3 | None = None,
        door_range: tuple[float, float] = (-0.6, 0.6),
        target_frame: str | None = None,
        normal: np.ndarray | None = None,
    ) -> None:
        self.model = pin.Model(model)
        self.loop_type = loop_type
        self.kind = sim_loop(loop_type)  # its target frame and residual (closedloop.sims.loop_types)
        self.n_arm = model.nq
        if not self.model.existFrame(tool_frame):
            raise ScenarioError(f"frame {tool_frame!r} not in the nominal model")
        self.tool = find_frame(self.model, tool_frame)
        data = self.model.createData()
        pin.framesForwardKinematics(self.model, data, np.asarray(r0, dtype=float))
        oMt0 = data.oMf[self.tool].copy()
        self.normal = None if normal is None else np.asarray(normal, dtype=float) / np.linalg.norm(normal)
        self.d = 0.0
        self.target = self.kind.nominal_target(self, data, oMt0, hinge, door_range, target_frame)
        #: the target frame is fixed in the world (its Jacobian is zero)
        self.target_fixed = self.model.frames[self.target].parentJoint == 0
        self.point = oMt0.translation.copy()
        self.data = self.model.createData()
        #: the tool's and the loop target's placements in ``data``: references, updated by every evaluation
        #: (looked up once: an ``oMf[i]`` lookup through the bindings costs as much as a frame update)
        self.tool_placement = self.data.oMf[self.tool]
        self.target_placement = self.data.oMf[self.target]
        self._last: tuple[bytes, np.ndarray, np.ndarray] | None = None  # (q bytes, e, de/dq)
        self.nq = self.model.nq
        self.lower = self.model.lowerPositionLimit.copy()
        self.upper = self.model.upperPositionLimit.copy()

    @property
    def n_constraints(self) -> int:
        """Number of rows of ``e``."""
        return self.kind.residual_rows

    def full_q(self, r: np.ndarray, door: float = 0.0) -> np.ndarray:
        """Planning vector from arm readings (and door angle for hinge loops)."""
        return np.concatenate([r, [door]]) if self.kind.env_joint else np.asarray(r, dtype=float).copy()

    def residual(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Loop error ``e(q)`` and its Jacobian ``de/dq`` (see module docstring; read-only arrays).

        The last evaluation is kept: the planner asks again at the point it has just
        projected onto the loop.
        """
        key = np.asarray(q, dtype=float).tobytes()
        if self._last is not None and key == self._last[0]:
            return self._last[1], self._last[2]
        e, jac = self._residual(q)
        e.setflags(write=False)  # (half the cost of `flags.writeable = False`)
        jac.setflags(write=False)
        self._last = (key, e, jac)
        return e, jac

    def _residual(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m, d = self.model, self.data
        pin.computeJointJacobians(m, d, q)
        pin.updateFramePlacements(m, d)
        jt = pin.getFrameJacobian(m, d, self.tool, pin.ReferenceFrame.LOCAL)
        return self.kind.nominal_residual(self, d, self.tool_placement, jt)

    def project(self, q: np.ndarray, iters: int = 3, tol: float = 1e-12) -> np.ndarray:
        """Gauss-Newton projection of ``q`` onto the nominal loop (minimum-norm steps ``dq = -J^+ e``)."""
        return self._project(np.array(q, dtype=float), iters, tol)

    def _project(self, q: np.ndarray, iters: int = 3, tol: float = 1e-12) -> np.ndarray:
        """:meth:`project` of a new array ``q`` (changed in place)."""
        for _ in range(iters):
            e, jac = self.residual(q)
            if float(e @ e) < tol:
                break
            q -= min_norm_step(jac, e)
        return q


@dataclass
class PlannerStats:
    """Counters of a planning run."""

    qp_solves: int = 0
    qp_failures: int = 0
    retargets: int = 0


class NominalLoopPlanner:
    """Random-target self-motion planner on a :class:`NominalLoop`.

    Args:
        loop: the nominal loop.
        q_start: start (planning vector, on the loop).
        rng: random generator for targets.
        step_rad: largest joint change per step.
        margin: distance kept from joint limits.
        target_span: targets are drawn within ``q_start +/- target_span``.
        retarget_every: steps after which a new target is drawn.
    """

    def __init__(
        self,
        loop: NominalLoop,
        q_start: np.ndarray,
        rng: np.random.Generator,
        step_rad: float = 0.15,
        margin: float = 0.1,
        target_span: float = 1.5,
        retarget_every: int = 10,
    ) -> None:
        self.loop = loop
        self.q = np.asarray(q_start, dtype=float).copy()
        self.rng = rng
        self.step_rad = step_rad
        self.retarget_every = retarget_every
        m = limit_margins(loop.lower, loop.upper, margin)  # in each joint's unit, scaled to its range
        self.lo = np.maximum(loop.lower + m, self.q - target_span)
        self.hi = np.minimum(loop.upper - m, self.q + target_span)
        self.lo = np.minimum(self.lo, self.q)  # a start inside the margin must stay feasible
        self.hi = np.maximum(self.hi, self.q)
        self.q_lo = np.minimum(loop.lower + m, self.q)
        self.q_hi = np.maximum(loop.upper - m, self.q)
        self.stats = PlannerStats()
        self._eye = np.eye(loop.nq)
        self._rank_tol = float(max(loop.n_constraints, loop.nq) * np.finfo(float).eps)  # numpy's matrix_rank tolerance
        _e, jac = loop.residual(self.q)
        self.one_dimensional = jac.shape[1] - np.linalg.matrix_rank(jac) == 1
        self._sweep_ref = np.linalg.svd(jac)[2][-1]
        self._sweep_sign = 1.0 if rng.uniform() < 0.5 else -1.0
        self._since_target = 0
        self._target = self._new_target()

    def _clip(self, q: np.ndarray) -> np.ndarray:
        """``np.clip(q, lower, upper)`` (the same values, without its wrapper)."""
        return np.minimum(np.maximum(q, self.loop.lower), self.loop.upper)

    def _new_target(self) -> np.ndarray:
        self.stats.retargets += 1
        self._since_target = 0
        return self.rng.uniform(self.lo, self.hi)

    def _linearize(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Loop error and Jacobian at ``self.q``, the Jacobian's right singular vectors and its rank."""
        e, jac = self.loop.residual(self.q)
        _u, sv, vt = svd_full(jac)
        # sv_max * max(m, n) * eps: the product by eps (a power of two) is exact, so the factor is precomputed;
        # the rank counted on Python floats (a NaN is not counted, as in numpy)
        sv = sv.tolist()
        tol = (sv[0] if sv else 0.0) * self._rank_tol
        return e, jac, vt, sum(map(tol.__lt__, sv))

    def _qp_step(
        self,
        direction: np.ndarray,
        step: float | None = None,
        lin: tuple[np.ndarray, np.ndarray, np.ndarray, int] | None = None,
    ) -> np.ndarray | None:
        """Solve the QP of the module docstring (``lin``: :meth:`_linearize` at ``self.q``); ``None`` if it fails."""
        step = self.step_rad if step is None else step
        e, jac, vt, rank = self._linearize() if lin is None else lin
        n = self.loop.nq
        # null-space direction of the nominal loop (direction - J^+ J direction), scaled to the step size
        vr = vt[:rank]
        dn = direction - vr.T @ (vr @ direction)
        amax = _abs_max(dn)
        if amax < 1e-9:
            return np.zeros(n)
        dn *= min(1.0, step / amax)
        wjt = _W_LOOP * jac.T  # P = I + w J^T J, c = -d + w J^T e (the products as written, (w J^T) first)
        P = self._eye + wjt @ jac
        c = wjt @ e - dn  # = -dn + w J^T e exactly (x - y is x + (-y))
        lb, ub = self.q_lo - self.q, self.q_hi - self.q
        self.stats.qp_solves += 1
        dq = solve_box_qp(P, c, lb, ub)
        if dq is None:  # not expected (strictly convex, feasible): the general solver
            log.debug("box QP did not converge; falling back to OSQP")
            with warnings.catch_warnings():
                # osqp >= 1.0 announces API changes on every call
                warnings.simplefilter("ignore", (DeprecationWarning, PendingDeprecationWarning))
                import scipy.sparse as sp  # only here: the fallback is not expected to run
                from qpsolvers import solve_qp

                dq = solve_qp(
                    sp.csc_matrix(P), c, lb=lb, ub=ub, solver="osqp", eps_abs=1e-8, eps_rel=1e-8, verbose=False
                )
        if dq is None:
            self.stats.qp_failures += 1
            return None
        return np.asarray(dq)

    def _sweep_direction(self, vt: np.ndarray) -> np.ndarray:
        """Direction along a 1-D self-motion: the null vector, oriented like the previous motion."""
        v = vt[-1]
        if float(v @ self._sweep_ref) < 0.0:
            v = -v
        self._sweep_ref = v
        # longer than any step: _qp_step scales it down to the step length
        # v * (sign * 10) = (v * sign) * 10 exactly (sign = +-1: rounding is symmetric)
        return v * (self._sweep_sign * 10.0) * self.step_rad / max(_abs_max(v), 1e-12)

    def step(self) -> np.ndarray:
        """Advance one waypoint along the nominal self-motion and return it (planning vector).

        With a 1-D self-motion the planner sweeps back and forth across the whole
        range (the direction flips when a joint limit stops it); the step length is
        drawn in ``[0.5, 1] * step_rad`` so that sweeps visit different points.
        Otherwise it moves towards random targets.
        """
        if self.one_dimensional:
            lin = self._linearize()
            for _attempt in range(2):
                step = self.step_rad * float(self.rng.uniform(0.5, 1.0))
                dq = self._qp_step(self._sweep_direction(lin[2]), step, lin)
                if dq is not None and _abs_max(dq) > 0.2 * step:
                    self.q = self._clip(self.loop._project(self.q + dq))
                    return self.q.copy()
                self._sweep_sign = -self._sweep_sign
                self.stats.retargets += 1
            return self.q.copy()
        for _attempt in range(5):
            if self._since_target >= self.retarget_every:
                self._target = self._new_target()
            self._since_target += 1
            dq = self._qp_step(self._target - self.q)
            size = _abs_max(dq) if dq is not None else 0.0
            if dq is None or size < 0.2 * self.step_rad:
                # stalled (joint limit or target reached): new target
                self._target = self._new_target()
                if dq is None:
                    continue
                if size < 1e-3:
                    continue
            self.q = self._clip(self.loop._project(self.q + dq))
            return self.q.copy()
        log.debug("planner stalled; repeating waypoint")
        return self.q.copy()


def _abs_max(x: np.ndarray) -> float:
    """``max |x_i|`` (``float(np.abs(x).max())`` for finite ``x``) of a short vector, without numpy's reductions."""
    v = x.tolist()
    return max(max(v), -min(v))


class RandomConfigurations:
    """Waypoints of a robot without a loop (measured loops): random configurations.

    Each :meth:`step` returns a target drawn uniformly in the NOMINAL joint space:
    within the nominal limits less ``margin`` and within ``q_start +/- target_span``.

    Args:
        model: nominal robot model.
        q_start: start configuration (readings at the start).
        rng: random generator.
        margin: distance kept from joint limits.
        target_span: targets are drawn within ``q_start +/- target_span``.
    """

    def __init__(
        self,
        model: pin.Model,
        q_start: np.ndarray,
        rng: np.random.Generator,
        margin: float = 0.1,
        target_span: float = 1.5,
    ) -> None:
        q = np.asarray(q_start, dtype=float)
        self.rng = rng
        m = limit_margins(model.lowerPositionLimit, model.upperPositionLimit, margin)
        self.lo = np.minimum(np.maximum(model.lowerPositionLimit + m, q - target_span), q)
        self.hi = np.maximum(np.minimum(model.upperPositionLimit - m, q + target_span), q)
        self.stats = PlannerStats()

    def step(self) -> np.ndarray:
        """A new random configuration (arm joints)."""
        self.stats.retargets += 1
        return self.rng.uniform(self.lo, self.hi)
