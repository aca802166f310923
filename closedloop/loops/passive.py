"""A passive task chain closes the loop: door with handle, drawer, crank (thesis 3.4.3).

The task is a small Pinocchio model (URDF or MJCF) whose joints are
unsensed.  The robot's tool frame A holds the task's frame F:

    X(q, p) = P  T_F(q)            (pose of F in frame B)
    r       = log6( X^-1 T_B^-1 T_A )      (exact SE(3) log, eq. 3.18)

* P, the task's pose in B: 6 parameters ``<loop>.x y z rx ry rz``, a right
  twist on a reference pose P0, P = P0 exp6(p), generators Jexp6(p).  P0 is
  the user's `pose` or, by `prepare`, the pose that puts the task frame on
  the tool at the first configuration with the task at `q0` (so start the log
  with the task at q0, e.g. door closed, handle at rest).  The twist chart
  keeps the redundancy "turn the task about its first joint axis" a single
  component (rz for a z axis) however the task is oriented; a rotation-vector
  chart would make it a curve near |r| = pi, along which the reduced problem
  has spurious distant solutions.
* the task's joint placements, ``<loop>.<taskjoint>.x..rz``, with the right-
  twist convention of `closedloop.model.parameters`: M_j = M0_j exp6(p_j),
  generators Jexp6(p_j); the columns are Pinocchio's
  ``computeFrameKinematicRegressor`` (LOCAL) of the task model times them.
* the grasp, the placement of F on its parent joint, ``<loop>.grasp.x..rz``:
  F = F0 exp6(p), right twist of T_F by Jexp6(p).

Many of these are redundant (the rotation of a revolute joint's placement
about its own axis is its eliminated angle; consecutive placements absorb
each other along the axes); the core's structural reduction drops them,
keeping the base pose first, then joints from the task's base to its tip.

The task joint values q_i (up to 5 DOF: each uses up one of the 6 closure
equations) are eliminated per configuration and anew at each evaluation
with the current parameters (thesis 3.4.3, steps a-c), by Gauss-Newton on
|r_i(q)|^2 from the best of: the previous evaluation's solution for the same
row (warm start), the previous row's solution, and `q0`; all rows at once
(`projection.eliminate_along`), with the task's kinematics batched
(`ChainKinematics`) when every task joint is a 1-DOF revolute or prismatic
one, else Pinocchio's (frame Jacobian, `pin.integrate`) row by row.  The
residual and the reduced Jacobians (I - J_q J_q^+) d r / d x are those of
`projection` (variable projection; see the module docstring of `hinge` for
the envelope theorem).
Task joint limits are not enforced.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError, ModelError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.projection import eliminate_along, projector
from closedloop.loops.spec import register
from closedloop.loops.weld import CLOSURE_FIELDS
from closedloop.model.parameters import DEFAULT_PRIORS, PLACEMENT_FIELDS, Parameter
from closedloop.model.robot import find_frame
from closedloop.model.se3 import adjoint, relative, rigid_inverse, skew

MAX_PASSIVE_DOF = 5


def load_task_model(path: str | Path) -> pin.Model:
    path = Path(path)
    if not path.is_file():
        raise LoopError(f"task model {path}: no such file")
    suffix = path.suffix.lower()
    from closedloop.io.files import note_input
    from closedloop.io.robot_files import check_mjcf, check_urdf

    note_input(path)
    try:
        if suffix == ".urdf":
            check_urdf(path)  # what would crash Pinocchio (two parents, a cycle, a very deep tree, xacro)
            return pin.buildModelFromUrdf(str(path))
        if suffix in (".xml", ".mjcf"):
            check_mjcf(path)
            return pin.buildModelFromMJCF(str(path))
    except ModelError as exc:
        raise LoopError(f"task model {exc}") from None
    except Exception as exc:  # Pinocchio raises plain ValueError/RuntimeError
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise LoopError(f"task model {path}: Pinocchio cannot parse it ({first})") from None
    raise LoopError(f"task model {path}: unknown type '{suffix}' (use .urdf or .xml/.mjcf)")


class ChainKinematics:
    """Batched forward kinematics of a task model whose joints are all 1-DOF: revolute, prismatic or
    continuous (URDF "continuous": Pinocchio's unbounded revolute, q_j = (cos a, sin a)).

    oMi_j(q) = oMi_parent(j) M_j exp(S_j q_j) (M_j the joint placement, S_j its constant motion
    subspace in the joint frame: a rotation about, or translation along, a unit axis: Rodrigues'
    formula R = I + sin(a) [w]x + (1 - cos(a)) [w]x^2), oMf = oMi_parent(f) F.  With right (LOCAL) twists, the frame Jacobian column of a joint
    j supporting f is Ad(oMf^-1 oMi_j) S_j, and the kinematic regressor block of joint j's placement
    (M_j -> M_j exp6(delta)) is Ad(oMf^-1 oMi_parent(j) M_j) (Pinocchio's
    `computeFrameJacobian`, `computeFrameKinematicRegressor` (LOCAL), for a whole stack of q).
    """

    def __init__(self, model: pin.Model, fid: int):
        data = model.createData()
        pin.computeJointJacobians(model, data, pin.neutral(model))
        self.nj, self.nv = model.njoints - 1, model.nv
        self.parents = [int(model.parents[j]) for j in range(model.njoints)]
        self.M = np.array([model.jointPlacements[j].homogeneous for j in range(model.njoints)])
        self.S = np.zeros((model.njoints, 6))
        self.iv, self.iq = [0] * model.njoints, [0] * model.njoints
        for j in range(1, model.njoints):
            self.iv[j], self.iq[j] = model.joints[j].idx_v, model.joints[j].idx_q
            self.S[j] = pin.getJointJacobian(model, data, j, pin.LOCAL).reshape(6, -1)[:, self.iv[j]]
        fr = model.frames[fid]
        self.fj, self.F = int(fr.parentJoint), fr.placement.homogeneous
        self.support = [j for j in model.supports[self.fj] if j > 0]
        self.unbounded = [j for j in range(1, model.njoints) if model.joints[j].nq == 2]

    @staticmethod
    def of(model: pin.Model, fid: int) -> "ChainKinematics | None":
        """The batched kinematics, or None when a joint is not 1-DOF revolute / prismatic / continuous."""

        def simple(j) -> bool:
            name = j.shortname()
            if j.nv != 1:
                return False
            if j.nq == 2:
                return name.startswith(("JointModelRUB", "JointModelRevoluteUnboundedUnaligned"))
            return j.nq == 1 and name.startswith(("JointModelR", "JointModelP"))

        return ChainKinematics(model, fid) if all(simple(j) for j in model.joints[1:]) else None

    def integrate(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """q (+) dq (Pinocchio's `integrate`): q_j + dq_j, or (cos, sin) turned by dq_j and renormalised
        to first order, (c, s) * (3 - c^2 - s^2) / 2, for a continuous joint."""
        out = np.array(q, dtype=float)
        for j in range(1, self.nj + 1):
            iq, d = self.iq[j], dq[:, self.iv[j]]
            if j in self.unbounded:
                c, s, cd, sd = q[:, iq], q[:, iq + 1], np.cos(d), np.sin(d)
                c1, s1 = cd * c - sd * s, sd * c + cd * s
                k = (3.0 - (c1 * c1 + s1 * s1)) / 2.0
                out[:, iq], out[:, iq + 1] = c1 * k, s1 * k
            else:
                out[:, iq] += d
        return out

    def normalize(self, q: np.ndarray) -> np.ndarray:
        """Each continuous joint's (cos, sin) scaled to unit length (Pinocchio's `normalize`)."""
        out = np.array(q, dtype=float)
        for j in self.unbounded:
            iq = self.iq[j]
            out[:, iq : iq + 2] /= np.linalg.norm(out[:, iq : iq + 2], axis=1)[:, None]
        return out

    def forward(self, q: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """Joint poses oMi (njoints entries, (n, 4, 4)) and the frame pose oMf (n, 4, 4)."""
        n = q.shape[0]
        oMi = [np.broadcast_to(np.eye(4), (n, 4, 4))]
        for j in range(1, self.nj + 1):
            v, w = self.S[j, :3], self.S[j, 3:]
            qj = q[:, self.iq[j]]
            J = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
            if np.any(w):
                c, s = (qj, q[:, self.iq[j] + 1]) if j in self.unbounded else (np.cos(qj), np.sin(qj))
                K = skew(w)
                J[:, :3, :3] += s[:, None, None] * K + (1.0 - c)[:, None, None] * (K @ K)
            else:
                J[:, :3, 3] = qj[:, None] * v
            oMi.append(oMi[self.parents[j]] @ self.M[j] @ J)
        return oMi, oMi[self.fj] @ self.F

    def jacobian(self, oMi: list[np.ndarray], oMf: np.ndarray) -> np.ndarray:
        """The LOCAL frame Jacobian (n, 6, nv)."""
        fMo = rigid_inverse(oMf)
        Jf = np.zeros((oMf.shape[0], 6, self.nv))
        for j in self.support:
            Jf[:, :, self.iv[j]] = adjoint(fMo @ oMi[j]) @ self.S[j]
        return Jf

    def regressor(self, oMi: list[np.ndarray], oMf: np.ndarray) -> np.ndarray:
        """d(frame right twist) / d(right twists of the joint placements) (n, 6, 6 nj)."""
        fMo = rigid_inverse(oMf)
        R = np.zeros((oMf.shape[0], 6, 6 * self.nj))
        for j in self.support:
            R[:, :, 6 * (j - 1) : 6 * j] = adjoint(fMo @ oMi[self.parents[j]] @ self.M[j])
        return R


class PassiveChainLoop(Loop):
    """Tool frame A holds frame `task_frame` of a passive task chain placed in frame B."""

    translation_rows = (0, 1, 2)
    rotation_rows = (3, 4, 5)

    def __init__(
        self,
        name: str,
        frame_a: str,
        task_model_path: str | Path,
        task_frame: str,
        base_frame: str = "universe",
        q0: np.ndarray | None = None,
        pose: pin.SE3 | None = None,
    ):
        super().__init__(name, frame_a, base_frame)
        self.path = Path(task_model_path)
        self.model = load_task_model(self.path)
        if self.model.nv > MAX_PASSIVE_DOF:
            raise LoopError(
                f"passive loop '{name}': task model {self.path} has {self.model.nv} passive DOF; "
                f"at most {MAX_PASSIVE_DOF} can be eliminated from the 6 closure equations "
                "(thesis 3.4)"
            )
        if not self.model.existFrame(task_frame):
            names = [f.name for f in self.model.frames if f.name != "universe"]
            raise LoopError(
                f"passive loop '{name}': task model {self.path} has no frame '{task_frame}' "
                f"(frames: {', '.join(names)})"
            )
        self.task_frame = task_frame
        self.fid = find_frame(self.model, task_frame)
        self.task_joints = [self.model.names[j] for j in range(1, self.model.njoints)]
        if "grasp" in self.task_joints:
            raise LoopError(f"passive loop '{name}': a task joint named 'grasp' clashes with the grasp parameters")
        if q0 is None:
            self.q0 = pin.neutral(self.model)
        else:
            q0 = np.asarray(q0, dtype=float).ravel()
            if q0.size == self.model.nv and self.model.nq != self.model.nv:
                q0 = pin.integrate(self.model, pin.neutral(self.model), q0)
            if q0.size != self.model.nq:
                raise LoopError(
                    f"passive loop '{name}': q0 has {q0.size} values, the task model "
                    f"{self.path} has {self.model.nv} DOF"
                )
            self.q0 = q0
        self.known_pose = pose is not None
        self.P0 = pose.copy() if pose is not None else pin.SE3.Identity()
        self.fitted = False  # P0 read off the data by `prepare` (a prepared copy)
        self.nj = self.model.njoints - 1

    @property
    def dim(self) -> int:
        return 6

    @property
    def dof(self) -> int:
        return self.model.nv

    # ------------------------------------------------------------ parameters
    def parameters(self) -> list[Parameter]:
        out = []
        order = 0
        t0 = self.P0.rotation.T @ self.P0.translation
        for k, f in enumerate(CLOSURE_FIELDS):
            m = k < 3
            out.append(
                Parameter(
                    f"{self.name}.{f}",
                    "loop",
                    self.name,
                    f,
                    0.0,
                    "m" if m else "rad",
                    DEFAULT_PRIORS["loop_m" if m else "loop_rad"],
                    scales_with_length=float(t0[k]) if m else 0.0,
                    priority=1,
                    order=order,
                )
            )
            order += 1
        places = [(jn, self.model.jointPlacements[j + 1]) for j, jn in enumerate(self.task_joints)]
        places.append(("grasp", self.model.frames[self.fid].placement))
        for owner, M0 in places:
            t_local = M0.rotation.T @ M0.translation
            for k, f in enumerate(PLACEMENT_FIELDS):
                m = k < 3
                out.append(
                    Parameter(
                        f"{self.name}.{owner}.{f}",
                        "loop",
                        self.name,
                        f"{owner}.{f}",
                        0.0,
                        "m" if m else "rad",
                        DEFAULT_PRIORS["loop_m" if m else "loop_rad"],
                        scales_with_length=float(t_local[k]) if m else 0.0,
                        priority=1,
                        order=order,
                    )
                )
                order += 1
        return out

    def _split(self, p: np.ndarray):
        base = self.P0 * pin.exp6(p[0:6])
        joints = p[6 : 6 + 6 * self.nj].reshape(self.nj, 6)
        grasp = p[6 + 6 * self.nj : 12 + 6 * self.nj]
        return base, joints, grasp

    def task_model(self, p: np.ndarray) -> pin.Model:
        """The task model with the placements of `p`."""
        _, joints, grasp = self._split(p)
        model = self.model.copy()
        for j in range(self.nj):
            model.jointPlacements[j + 1] = self.model.jointPlacements[j + 1] * pin.exp6(joints[j])
        fr = model.frames[self.fid]
        fr.placement = self.model.frames[self.fid].placement * pin.exp6(grasp)
        model.frames[self.fid] = fr  # the Python binding hands out copies
        return model

    def _reference(self, TA: np.ndarray, TB: np.ndarray) -> pin.SE3:
        """The pose that puts the task frame on the tool at the first configuration with the task at q0."""
        data = self.model.createData()
        pin.forwardKinematics(self.model, data, self.q0)
        TF = pin.updateFramePlacement(self.model, data, self.fid)
        return pin.SE3(np.linalg.solve(TB[0], TA[0])) * TF.inverse()

    def prepare(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> "PassiveChainLoop":
        """A copy whose reference pose P0 is read off the first configuration (`Loop.prepare`); `self`
        when the pose was given or already read."""
        if self.known_pose or self.fitted:
            return self
        other = copy.copy(self)
        other.P0, other.fitted = self._reference(TA, TB), True
        return other

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """Zero twists on P0 once prepared (None with a given pose); unprepared, the reference pose's
        twist on this object's P0."""
        if self.known_pose:
            return None
        p = np.zeros(12 + 6 * self.nj)
        if not self.fitted:
            p[:6] = pin.log6(self.P0.actInv(self._reference(TA, TB))).vector
        return p

    def pose(self, p: np.ndarray) -> pin.SE3:
        """The task's pose in B."""
        return self._split(p)[0]

    def describe(self) -> dict:
        return super().describe() | {
            "reference_pose": np.concatenate([self.P0.translation, pin.log3(self.P0.rotation)]).tolist(),
            "task_model": str(self.path),
            "task_frame": self.task_frame,
            "task_joints": self.task_joints,
            "passive_dof": self.dof,
        }

    # ------------------------------------------------------------ evaluation
    def _solver(self, p: np.ndarray):
        """The task model at `p` and batched pose / integrate / snap functions over rows of q (n, nq)."""
        base, _, _ = self._split(p)
        model = self.task_model(p)
        data = model.createData()
        fid, nv, Bh = self.fid, model.nv, base.homogeneous
        chain = ChainKinematics.of(model, fid)

        def pose(q):
            if chain is not None:
                oMi, oMf = chain.forward(q)
                return Bh @ oMf, chain.jacobian(oMi, oMf)
            X, Xd = np.empty((q.shape[0], 4, 4)), np.empty((q.shape[0], 6, nv))
            for i in range(q.shape[0]):  # other joint types: Pinocchio's kinematics, one call per row
                pin.computeJointJacobians(model, data, q[i])
                X[i] = pin.updateFramePlacement(model, data, fid).homogeneous
                Xd[i] = pin.getFrameJacobian(model, data, fid, pin.LOCAL).reshape(6, nv)
            return Bh @ X, Xd

        def integrate(q, dq):
            if chain is not None:
                return chain.integrate(q, dq)
            return np.array([pin.integrate(model, a, d) for a, d in zip(q, dq)])

        def snap(q):  # warm starts give bit-identical results: restart from q rounded to 1e-8
            q = np.round(q, 8)
            return chain.normalize(q) if chain is not None else np.array([pin.normalize(model, a) for a in q])

        return model, data, base, chain, pose, integrate, snap

    def solve_angles(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The eliminated task configurations q_i* (N, nq)."""
        return self._evaluate(TA, TB, p, False)[1]

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        return self._evaluate(TA, TB, p, True)[0]

    def _evaluate(self, TA, TB, p, jac):
        N = TA.shape[0]
        model, data, base, chain, pose, integrate, snap = self._solver(p)
        el = eliminate_along(relative(TA, TB), pose, None, self.q0, integrate, snap)
        qs = el.phi
        Pp = projector(el.Jphi)
        r = np.einsum("nij,nj->ni", Pp, el.r)  # exactly orthogonal to J_q (a last linearised step, O(|dq|))
        if not jac:
            return None, qs
        _, joints, grasp = self._split(p)
        G = np.zeros((6 * self.nj, 6 * self.nj))
        for j in range(self.nj):
            G[6 * j : 6 * j + 6, 6 * j : 6 * j + 6] = pin.Jexp6(joints[j])
        if chain is not None:
            oMi, oMf = chain.forward(qs)
            Reg = chain.regressor(oMi, oMf)
        else:
            oMf, Reg = np.empty((N, 4, 4)), np.empty((N, 6, 6 * self.nj))
            for i in range(N):  # the task's kinematics at the solutions
                pin.forwardKinematics(model, data, qs[i])
                oMf[i] = pin.updateFramePlacement(model, data, self.fid).homogeneous
                Reg[i] = pin.computeFrameKinematicRegressor(model, data, self.fid, pin.LOCAL).reshape(6, -1)
        dA = Pp @ el.Jl
        dX = -dA @ adjoint(rigid_inverse(el.E))
        dB = -dA @ adjoint(rigid_inverse(TA) @ TB)
        dp = np.concatenate(
            [dX @ (adjoint(rigid_inverse(oMf)) @ pin.Jexp6(p[0:6])), dX @ (Reg @ G), dX @ pin.Jexp6(grasp)], axis=2
        )
        return LoopEval(r, dA, dB, dp, iterations=int(el.iterations.max(initial=0))), qs


@register("passive", {"frame", "to", "task", "task_frame", "q0"})
def _passive(kw: dict[str, str], robot) -> Loop:
    """passive:frame=<tool>,task=<task.urdf>,task_frame=<frame>[,to=<frame>][,q0="..."][,name=task]"""
    for key in ("frame", "task", "task_frame"):
        if key not in kw:
            raise LoopError(
                f"passive loop needs {key}=... (frame=<tool frame>, task=<task model file>, "
                "task_frame=<frame of the task model the tool holds>)"
            )
    q0 = None
    if "q0" in kw:
        try:
            q0 = np.array([float(t) for t in kw["q0"].replace(",", " ").split()])
        except ValueError:
            raise LoopError(f"q0 '{kw['q0']}': expected numbers (task joint values)") from None
    return PassiveChainLoop(
        kw.get("name", "task"), kw["frame"], kw["task"], kw["task_frame"], kw.get("to", "universe"), q0=q0
    )
