"""A stack of loops over logged configurations: residuals and analytic Jacobians.

For loop l at configuration i with readings theta^i the model joint angles are
theta' = k * theta^i + theta_off - c * tau^i (eq. 4.4, plus joint compliance c
under the logged actuator torques tau, when present).  With Pinocchio's LOCAL
frame kinematic regressors K_A, K_B (block j: Ad(T_frame^-1 T_parent(j) M_j),
the frame's motion under a right twist of joint j's placement M_j), the
LOCAL frame Jacobians are J_A = K_A S, J_B = K_B S (S: each joint's motion
subspace in its own frame, placed in its block: joint j turning by dtheta is
M_j exp6(S_j dtheta)), and the chain rule gives the columns of C^i (eq. 4.9):

  placement / D-H geometry:  dA K_A G + dB K_B G          (G: right-twist generators)
  offset of joint j:         (dA J_A + dB J_B)[:, j]       (eq. 4.11, first column)
  scale of joint j:          theta_j^i * (dA J_A + dB J_B)[:, j]      (eq. 4.15)
  compliance of joint j:     -tau_j^i * (dA J_A + dB J_B)[:, j]
  loop parameters:           the loop's own dp
  joint readings (for the noise model): k_j * (dA J_A + dB J_B)[:, j]

Only the requested columns are formed (the solver asks for the estimated
parameters alone): with B holding each column's generator (a column of G, or
S_j for a sensor parameter of joint j, then scaled by theta_j or -tau_j per
configuration), one product d K B per frame gives them all.  The
per-configuration Pinocchio calls (forward kinematics, frame placement,
kinematic regressor) are in one loop; everything else is batched numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
import pinocchio as pin

from closedloop.errors import LogError
from closedloop.loops.base import Loop
from closedloop.model.parameters import Parameter, RobotParameters, RobotState
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import poses_from_adjoints
from closedloop.parallel.chunks import chunk_threads, for_each_chunk
from closedloop.problem.blocks import BlockEval, ChunkStack, Workspace, copy_eval, read_only
from closedloop.problem.shared import loop_columns

# What a parameter's Jacobian column is made of (`CalibrationProblem._role`).
_GEOMETRY, _OFFSET, _SCALE, _COMPLIANCE, _LOOP, _MIMIC = range(6)


@dataclass
class LoopBlock:
    """The configurations a loop is evaluated on, with its measurements there (the loop keeps none)."""

    loop: Loop
    theta: np.ndarray  # (N, n_joints) readings, columns in problem.joints order
    rows: np.ndarray  # row numbers in the log (1-based data rows), for messages
    tau: np.ndarray | None = None  # (N, n_joints) actuator torques, if logged
    #: (N, len(loop.columns())) the loop's measurements (`Loop.measurements`); None: it measures nothing
    meas: np.ndarray | None = None

    def subset(self, idx: np.ndarray) -> "LoopBlock":
        """The block on configurations `idx` (indices into its rows), measurements sliced alike."""
        return LoopBlock(
            self.loop,
            self.theta[idx],
            self.rows[idx],
            None if self.tau is None else self.tau[idx],
            None if self.meas is None else self.meas[idx],
        )


def even_sample(n: int, k: int) -> np.ndarray:
    """Indices of at most `k` of `n` rows, evenly spaced from the first to the last (all of them if n <= k)."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(int))


@dataclass
class BlockNoise:
    """A block's measurement noise as the weighting sees it: kept by the problem, never by the loop.

    measurement_cov = C + diag(task_var) on the loop's translation rows: C the loop's own covariance
    (`Loop.measurement_cov` without a task-space term: a tracker's sigma_t, a camera's sigma_px), task_var
    the loop's task-space variance, given (``sigma_task=0.2mm``) or estimated during a calibration
    (`variance.variance_components`, eq. 3.17 with a task term).  Estimating it changes this record,
    not the user's loop, so that two calibrations with the same loops are independent.
    """

    own: np.ndarray | None  # (m, m) the loop's own measurement covariance (None: it measures nothing)
    translation_rows: tuple[int, ...]
    dim: int
    task_var: np.ndarray | float | None = None  # task-space variance (m^2) on the translation rows
    estimated: bool = False  # task_var estimated (a variance component), not given
    pooled: bool = False  # estimated as one component with the other task loops (`variance.homogeneous`)
    measurement_cov: np.ndarray | None = field(default=None, init=False)  # own + task term (`set_task`)

    def __post_init__(self) -> None:
        self.set_task(self.task_var, self.estimated)

    @classmethod
    def of(cls, loop: Loop) -> "BlockNoise":
        """The noise a loop was configured with (`loops.settings.set_task_noise` keeps its own part apart)."""
        own = getattr(loop, "own_cov", loop.measurement_cov)
        return cls(own, tuple(loop.translation_rows), loop.dim, getattr(loop, "task_var", None))

    def set_task(self, var: np.ndarray | float | None, estimated: bool = False) -> None:
        """Task-space variance `var` (per translation row, or one for all; None: none)."""
        self.task_var, self.estimated = var, estimated
        if var is None:
            self.measurement_cov = self.own
            return
        T = np.zeros((self.dim, self.dim))
        rows = list(self.translation_rows)
        T[rows, rows] = np.broadcast_to(np.asarray(var, dtype=float), (len(rows),))
        self.measurement_cov = T if self.own is None else self.own + T


MEMO_ROWS = 20_000  # configurations up to which `CalibrationProblem.evaluate` keeps parameter Jacobians
#: bytes of a long log's parameter Jacobian up to which `CalibrationProblem.evaluate` keeps a copy (a fresh
#: evaluation of 100,000 configurations costs ~20 times the copy)
MEMO_BYTES = 1 << 28
#: configurations from which `frame_kinematics` computes frames on revolute and prismatic chains for all of them at
#: once (`model.stacked`): below, Pinocchio's loop costs less (a Panda's frame: 64 rows 0.24 ms against 0.96 ms
#: with regressors; 4,096 rows 15 ms against 13 ms, and 6.1 ms against 2.5 ms without)
STACKED_ROWS = 2048
#: configurations of a long log's block evaluated at a time (a block of up to twice this many, a long log's
#: even sample, at once): each chunk's temporaries stay in the heap (below glibc's mmap limit), and two
#: chunks' regressors (16 MB each) in a processor cache of 32 MB (100,000 rows with the Jacobian: 1.0-1.1 s
#: of CPU against 1.3 s in chunks of 8,192)
CHUNK = 4096


class CalibrationProblem:
    """Parameters of a robot and its loops, evaluated over logged configurations."""

    def __init__(
        self,
        robot: RobotModel,
        joints: list[str],
        blocks: list[LoopBlock],
        priors: dict | None = None,
        noise: list[BlockNoise] | None = None,
    ):
        self.robot = robot
        self.joints = list(joints)
        self.blocks = blocks
        self.priors = priors
        #: per block, its measurement noise (`BlockNoise`); the weighting reads it, not the loop
        self.noise = noise if noise is not None else [BlockNoise.of(b.loop) for b in blocks]
        self.rp = RobotParameters(robot, self.joints, priors)
        self.params: list[Parameter] = list(self.rp.params)
        # Each loop's parameters as an index map into the one vector (closedloop.problem.shared: a parameter
        # shared by several loops is one column); `loop_slices` the same as slices where contiguous
        # (always, unless loops share), else the index arrays.
        self.loop_columns, new = loop_columns([b.loop for b in blocks], len(self.params), [p.name for p in self.params])
        self.params.extend(new)
        self.loop_slices: list = [
            slice(int(c[0]), int(c[-1]) + 1)
            if c.size and np.array_equal(c, np.arange(c[0], c[-1] + 1))
            else (c if c.size else slice(len(self.params), len(self.params)))
            for c in self.loop_columns
        ]
        # position of each parameter in each loop's own vector (-1: not that loop's)
        self._local = np.full((len(blocks), len(self.params)), -1, dtype=int)
        for bi, c in enumerate(self.loop_columns):
            self._local[bi, c] = np.arange(c.size)
        self.names = [p.name for p in self.params]
        self.index = {n: i for i, n in enumerate(self.names)}
        self.n_robot = len(self.rp.params)
        # Per parameter: its role, and its joint (sensor parameters) or loop block (loop parameters).
        self._role = np.full(len(self.params), _GEOMETRY)
        self._owner = np.zeros(len(self.params), dtype=int)
        for role, idx in (
            (_OFFSET, self.rp.offset_index()),
            (_SCALE, self.rp.scale_index()),
            (_COMPLIANCE, self.rp.compliance_index()),
        ):
            self._role[idx] = role
            self._owner[idx] = np.arange(len(self.joints))
        for bi, c in enumerate(self.loop_columns):
            self._role[c] = _LOOP
            self._owner[c] = bi
        for name, followed, _, _ in robot.coupled(self.joints):  # a multiplier acts through the followed joint
            k = self.rp.index[f"{name}.mimic"]
            self._role[k] = _MIMIC
            self._owner[k] = self.joints.index(followed)
        # Motion subspaces S_j (LOCAL joint Jacobian column of joint j at the neutral configuration),
        # rows in the regressor's block of joint j, one column per problem joint.
        model = robot.model
        data = model.createData()
        pin.computeJointJacobians(model, data, pin.neutral(model))
        self._S = np.zeros((6 * (model.njoints - 1), len(self.joints)))
        for jc, name in enumerate(self.joints):
            j = robot.joint(name)
            self._S[6 * (j.jid - 1) : 6 * j.jid, jc] = pin.getJointJacobian(model, data, j.jid, pin.LOCAL)[:, j.idx_v]
        # a coupled joint (URDF <mimic>) moves with the joint it follows: its multiplier times its motion
        # subspace joins that joint's column (`_joint_columns`, at the state's multiplier)
        self._coupled = []
        for name, followed, _, _ in robot.coupled(self.joints):
            m = robot.joint(name)
            S_m = np.zeros(self._S.shape[0])
            S_m[6 * (m.jid - 1) : 6 * m.jid] = pin.getJointJacobian(model, data, m.jid, pin.LOCAL)[:, m.idx_v]
            self._coupled.append((name, self.joints.index(followed), S_m, self.rp.index[f"{name}.mimic"]))

    def _joint_columns(self, state: RobotState) -> np.ndarray:
        """The joints' motion subspaces in the regressor's rows, a coupled joint's in the followed joint's
        column times the state's multiplier (`_S` itself when there is no coupled joint)."""
        if not self._coupled:
            return self._S
        S = self._S.copy()
        for name, c, S_m, _ in self._coupled:
            S[:, c] += state.mimic[name] * S_m
        return S

    def without_rows(self, rows) -> "CalibrationProblem":
        """The same problem without the log rows `rows` (1-based, as in `LoopBlock.rows`) in any block.

        Each block keeps its other configurations with their measurements (`LoopBlock.subset`); a
        loop without configurations of its own (``parameter_only``, a known distance) is kept whole.
        The noise records are the same objects: a task-space variance estimated on one is the other's.
        """
        drop = np.asarray(sorted(rows), dtype=int)
        blocks = []
        for b in self.blocks:
            if getattr(b.loop, "parameter_only", False):
                blocks.append(b)
                continue
            keep = np.flatnonzero(~np.isin(b.rows, drop))
            if keep.size == 0:
                raise LogError(
                    f"no row is left for loop '{b.loop.name}' once rows {', '.join(map(str, drop[:5]))} are left out"
                )
            blocks.append(b.subset(keep))
        return CalibrationProblem(self.robot, self.joints, blocks, self.priors, self.noise)

    def __getstate__(self) -> dict:
        """Pickled (a result sent by a process pool or Ray) without the evaluation memo, the kept poses and the
        chunks' workspace: caches of up to ~100 MB on a long log, made again when needed."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_memo", "_work", "_poses", "_samples")}

    def sampled(self, per_block: int | Sequence[int], first: bool = False) -> "CalibrationProblem":
        """The problem on at most `per_block` configurations of each block (one count, or one per block),
        evenly spaced along the log (the first ones with `first`; self when no block has more): structural
        questions (redundancy, mobility) need generic configurations, not 100,000 of them.  The noise
        records are shared, as in `without_rows`."""
        counts = [per_block] * len(self.blocks) if isinstance(per_block, (int, np.integer)) else list(per_block)
        if all(b.theta.shape[0] <= n for b, n in zip(self.blocks, counts)):
            return self
        key = (tuple(int(n) for n in counts), first)
        kept = self.__dict__.setdefault("_samples", {}).get(key)
        if kept is not None and kept[0] is self.blocks and kept[1] is self.noise:
            return kept[2]  # one sample of a long log, with its memo, for the stages that read it
        blocks = [
            b if b.theta.shape[0] <= n else b.subset(np.arange(n) if first else even_sample(b.theta.shape[0], n))
            for b, n in zip(self.blocks, counts)
        ]
        sample = CalibrationProblem(self.robot, self.joints, blocks, self.priors, self.noise)
        self.__dict__["_samples"][key] = (self.blocks, self.noise, sample)
        return sample

    def on_robot(self, robot: RobotModel) -> "CalibrationProblem":
        """The same problem (joints, loops, log, noise records) on another model of the same joints and frames
        (its geometry may differ): the same parameters in the same order."""
        return CalibrationProblem(robot, self.joints, self.blocks, self.priors, self.noise)

    def normalized(self, x: np.ndarray, est: list[int] | None = None) -> np.ndarray:
        """A copy of x with the loops' parameters in their canonical form (`Loop.normalize`: a rotation vector
        within pi): the same model.  With `est`, only the loops whose parameters are all among `est`."""
        x = np.array(x, dtype=float)
        keep = None if est is None else set(est)
        for b, cols in zip(self.blocks, self.loop_columns):
            if keep is None or (cols.size and keep.issuperset(cols.tolist())):
                x[cols] = b.loop.normalize(x[cols])
        return x

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.params])

    # ------------------------------------------------------------- kinematics
    def model_angles(self, state: RobotState, theta: np.ndarray, tau: np.ndarray | None) -> np.ndarray:
        """theta' = k theta + theta_off - c tau (the sensor model)."""
        angles = theta * state.scale + state.offset
        if tau is not None:
            angles = angles - tau * state.compliance
        return angles

    def frame_kinematics(
        self,
        state: RobotState,
        theta: np.ndarray,
        frames: list[int],
        need_jac: bool,
        tau: np.ndarray | None = None,
        work: Workspace | None = None,
        stacked: bool | None = None,
    ) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
        """Poses (N, 4, 4) and, with `need_jac`, LOCAL kinematic regressors (N, 6, 6 (njoints - 1)) of frames.

        The base frame (id 0) has the identity pose and no regressor.  With `work` the regressors are
        formed in its buffers (valid until its next use).  Frames on chains of revolute and prismatic joints
        are computed for all configurations at once (`model.stacked`) where they are `STACKED_ROWS` or more;
        others by Pinocchio, a configuration
        at a time, where with the regressors the poses are read off them: the block of the chain's first
        joint r is Ad(T^-1 P_r), P_r its placement on the base (`se3.poses_from_adjoints`): one Pinocchio
        call per configuration fewer.
        """
        model = state.model
        q = self.robot.configurations(self.model_angles(state, theta, tau), self.joints, state.mimic)
        N = q.shape[0]
        live = [f for f in frames if f != 0]
        base = {0: (np.broadcast_to(np.eye(4), (N, 4, 4)), None)} if 0 in frames else {}
        stack = self.robot.stacked
        if (N >= STACKED_ROWS if stacked is None else stacked) and all(
            stack.covers(model, f) for f in live
        ):  # revolute and prismatic chains
            shape = (N, 6, 6 * (model.njoints - 1))
            K = {f: work.get(f"K{f}", shape) if work else np.empty(shape) for f in live} if need_jac else {}
            T = stack.frames(model, q, live, K if need_jac else None)
            return {f: (T[f], K.get(f)) for f in live} | base
        return self.pinocchio_kinematics(state, q, live, need_jac, work) | base

    def pinocchio_kinematics(
        self, state: RobotState, q: np.ndarray, live: list[int], need_jac: bool, work: Workspace | None = None
    ) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
        """`frame_kinematics` of frames other than the base at configurations `q` (N, nq), by Pinocchio, a
        configuration at a time (any joint type)."""
        model, data = state.model, state.data
        N = q.shape[0]
        roots = {f: model.supports[model.frames[f].parentJoint][1:2] for f in live}  # [] on the base
        from_K = [f for f in live if need_jac and roots[f]]
        placed = [f for f in live if f not in from_K]
        T = {f: [None] * N for f in placed}
        shape = (N, 6, 6 * (model.njoints - 1))
        K = {f: work.get(f"K{f}", shape) if work else np.empty(shape) for f in live} if need_jac else {}
        fk, place, regressor, local = (
            pin.forwardKinematics,
            pin.updateFramePlacement,
            pin.computeFrameKinematicRegressor,
            pin.LOCAL,
        )
        if len(live) == 1 and N:  # one frame (most loops): no inner loops; a list comprehension gathers fastest
            f = live[0]
            if need_jac:
                K[f][...] = [regressor(model, data, f, local) for qi in q if fk(model, data, qi) is None]
            if placed:
                T[f] = [place(model, data, f).homogeneous for qi in q if fk(model, data, qi) is None]
        else:
            for i, qi in enumerate(q):
                fk(model, data, qi)
                for f in placed:
                    T[f][i] = place(model, data, f).homogeneous
                if need_jac:
                    for f in live:
                        K[f][i] = regressor(model, data, f, local)
        out = {f: (np.array(T[f]).reshape(N, 4, 4), K.get(f)) for f in placed}
        for f in from_K:
            r = roots[f][0]
            out[f] = (poses_from_adjoints(K[f][:, :, 6 * (r - 1) : 6 * r], model.jointPlacements[r].homogeneous), K[f])
        return out

    def loop_poses(
        self, values: np.ndarray, block_index: int, theta: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """T_A, T_B of one loop at `values` (for initialisation and export checks)."""
        Ts = self.loop_frame_poses(values, block_index, theta)
        return Ts[0], Ts[1]

    def initialize_loop(self, values: np.ndarray, block_index: int) -> np.ndarray | None:
        """The loop's own start values from its configurations and measurements at `values` (`Loop.initialize`)."""
        b = self.blocks[block_index]
        return b.loop.initialize_frames(self.loop_frame_poses(values, block_index), b.meas)

    def forget_poses(self) -> None:
        """Drop the poses `loop_frame_poses` keeps (on a long log, two arrays of 128 bytes per configuration)."""
        self.__dict__.pop("_poses", None)

    def loop_frame_poses(
        self, values: np.ndarray, block_index: int, theta: np.ndarray | None = None
    ) -> list[np.ndarray]:
        """Poses (N, 4, 4) of every frame of one loop (`Loop.frames`) at `values`.

        At the problem's own readings the last block's poses are kept, keyed by the robot's parameters (the
        loop's own do not move its frames): the start's loop initialisation and its check of the data
        (`Loop.mismatch`) read the same poses, a pass over every row each on a long log."""
        b = self.blocks[block_index]
        key = (block_index, np.asarray(values[: self.n_robot], dtype=float).tobytes())
        kept = self.__dict__.get("_poses")
        if theta is None and kept is not None and kept[0] == key and kept[1] is self.blocks:
            return list(kept[2])
        state = self.rp.apply(values[: self.n_robot])
        fids = [self.robot.frame_id(f) for f in b.loop.frames]
        tau = b.tau if theta is None else None
        kin = self.frame_kinematics(state, b.theta if theta is None else theta, fids, False, tau)
        out = [kin[f][0] for f in fids]
        if theta is None:
            for T in out:
                T.flags.writeable = False  # shared with the next caller: read-only
            self.__dict__["_poses"] = (key, self.blocks, out)
        return list(out)

    # ------------------------------------------------------------- evaluation
    @property
    def keeps_jacobians(self) -> bool:
        """Whether `evaluate` keeps parameter Jacobians for reuse (up to MEMO_ROWS configurations)."""
        return sum(b.theta.shape[0] for b in self.blocks) <= MEMO_ROWS

    def evaluate(
        self,
        values: np.ndarray,
        jacobian: bool = True,
        thetas: list[np.ndarray] | None = None,
        columns: Sequence[int] | None = None,
    ) -> list[BlockEval]:
        """Residuals (and Jacobians) of every loop at parameter vector `values`.

        With `jacobian`, J holds the columns `columns` of d r / d parameters
        in that order (default: all P; an empty list gives Jq alone), and Jq
        the derivatives with respect to the readings.  The last two
        evaluations at the problem's own readings are kept (with the parameter
        Jacobian up to MEMO_ROWS configurations, and above while it takes at most MEMO_BYTES; residuals and Jq
        at any size) and given again, as copies, for the same parameter
        vector to the bit: the stages after a solve each ask for the
        solution's residual (outlier screen, closure level, standard errors,
        noise summary, residual statistics, the accuracy prediction's plain fit).
        Above MEMO_ROWS an evaluation with the parameter Jacobian within MEMO_BYTES
        is kept and given as it is, read-only (`blocks.read_only`): a caller that
        would write into it makes its own.
        """
        if thetas is not None:
            return self._evaluate(values, jacobian, thetas, columns)
        large = not self.keeps_jacobians
        key = np.asarray(values, dtype=float).tobytes()
        cols = None if columns is None else tuple(int(c) for c in columns)
        memo = self.__dict__.setdefault("_memo", [])
        if large and jacobian and (columns is None or len(columns) > 0):  # kept: J too, if within MEMO_BYTES
            for k, blocks, kind, evals in memo:
                if k == key and blocks is self.blocks and kind == cols:
                    return list(evals)
            out = self._evaluate(values, jacobian, None, columns)
            if sum(e.J.nbytes for e in out if e.J is not None) <= MEMO_BYTES:  # kept as it is, shared read-only
                out = [read_only(e) for e in out]
                memo.insert(0, (key, self.blocks, cols, out))
            else:  # its residual and Jq kept, copies: the caller whitens its J in place, no second J in memory
                memo.insert(0, (key, self.blocks, (), [copy_eval(e, True, True) for e in out]))
            del memo[2:]
            return out
        for k, blocks, kind, evals in memo:
            if k == key and blocks is self.blocks and (not jacobian or kind == cols or (kind != "r" and cols == ())):
                return [copy_eval(e, jacobian, cols == ()) for e in evals]
        out = self._evaluate(values, jacobian, None, columns)
        memo.insert(0, (key, self.blocks, cols if jacobian else "r", out))
        del memo[2:]
        return [copy_eval(e, jacobian, False) for e in out]

    def kept(self, values: np.ndarray, columns: Sequence[int]) -> list[BlockEval] | None:
        """A long log's evaluation with the Jacobian over `columns` at `values` where `evaluate` keeps one (shared,
        read-only; with `relinearized`, its Jacobian is that of a point within a chord step), else None:
        nothing is evaluated here."""
        if self.keeps_jacobians:
            return None
        key, cols = np.asarray(values, dtype=float).tobytes(), tuple(int(c) for c in columns)
        memo = self.__dict__.get("_memo", [])
        return next((list(e) for k, b, kind, e in memo if k == key and b is self.blocks and kind == cols), None)

    def relinearized(self, values: np.ndarray, at: np.ndarray) -> None:
        """Keep, as the evaluation with Jacobians at `values`, the kept one at `at` with the residual at
        `values` (both kept by `evaluate`): a solver's chord step from `at` to `values`
        (`lm.SolverOptions.chord`), which linearises its solution at `at`.  Nothing if either is not kept."""
        memo = self.__dict__.get("_memo", [])
        key, key_at = (np.asarray(v, dtype=float).tobytes() for v in (values, at))
        r = next((e for k, b, kind, e in memo if k == key and b is self.blocks and kind == "r"), None)
        lin = next(((kind, e) for k, b, kind, e in memo if k == key_at and b is self.blocks and kind != "r"), None)
        if r is None or lin is None or len(r) != len(lin[1]):
            return
        kind, evals = lin
        shared = not self.keeps_jacobians and kind != ()  # a long log's J, shared read-only (`evaluate`)
        out = [replace(e, r=a.r, valid=a.valid) for e, a in zip(evals, r)]
        memo.insert(0, (key, self.blocks, kind, [read_only(e) for e in out] if shared else out))
        del memo[2:]

    def _evaluate(
        self, values: np.ndarray, jacobian: bool, thetas: list[np.ndarray] | None, columns: Sequence[int] | None
    ) -> list[BlockEval]:
        """`evaluate` without the memo."""
        state = self.rp.apply(values[: self.n_robot])
        cols = np.arange(len(self.params)) if columns is None else np.asarray(columns, dtype=int)
        role, owner = self._role[cols], self._owner[cols]
        C, nj = cols.size, len(self.joints)
        # Each column's twist generator in the regressor's rows: G for geometry, S_j for the sensor
        # parameters of joint j (they move theta'_j), none for loop parameters; then S for Jq.
        S = self._joint_columns(state)
        B = np.zeros((S.shape[0], C + nj))
        geo = np.flatnonzero(role == _GEOMETRY)
        sensor = np.flatnonzero((role == _OFFSET) | (role == _SCALE) | (role == _COMPLIANCE))
        B[:, geo] = state.G[:, cols[geo]]
        B[:, sensor] = S[:, owner[sensor]]
        B[:, C:] = S
        for _, _, S_m, k in self._coupled:  # d q_m / d multiplier = theta'_f (the factor, in `_block`)
            B[:, np.flatnonzero(cols == k)] = S_m[:, None]
        rows = np.flatnonzero(np.any(B != 0, axis=1))  # the regressor blocks that matter
        span = slice(rows[0], rows[-1] + 1) if rows.size else slice(0, 0)
        B = B[span]
        ctx = (cols, role, owner, B, span, geo, state)
        out = []
        for bi, b in enumerate(self.blocks):
            theta = b.theta if thetas is None else thetas[bi]
            if theta.shape[0] <= 2 * CHUNK:
                out.append(self._block(bi, theta, b.tau, b.meas, b.rows, values, jacobian, ctx))
                continue
            out.append(self._chunked(bi, theta, values, jacobian, ctx))
        return out

    def _chunked(self, bi: int, theta: np.ndarray, values: np.ndarray, jacobian: bool, ctx: tuple) -> BlockEval:
        """Block `bi` on more than twice `CHUNK` configurations, a chunk at a time into one `ChunkStack`; on threads
        (`parallel.chunks`) where the kinematics are stacked (Pinocchio's loop shares one `Data`), each
        forming its chunks' temporaries in a `Workspace` of its own, kept for the next evaluation."""
        b, N = self.blocks[bi], theta.shape[0]
        starts = list(range(0, N, CHUNK))
        model = ctx[-1].model
        fids = [f for f in (self.robot.frame_id(name) for name in b.loop.frames) if f != 0]
        stacked = N >= STACKED_ROWS and all(self.robot.stacked.covers(model, f) for f in fids)
        works = self.__dict__.setdefault("_work", [Workspace()])
        n_threads = chunk_threads(len(starts) - 1) if stacked else 1
        works.extend(Workspace() for _ in range(n_threads - len(works)))
        stack = ChunkStack(N)

        def one(a: int, work: Workspace) -> None:
            e = slice(a, a + CHUNK)
            tau, meas = (None if v is None else v[e] for v in (b.tau, b.meas))
            stack.put(a, self._block(bi, theta[e], tau, meas, b.rows[e], values, jacobian, ctx, work, stacked))

        one(starts[0], works[0])  # the first chunk sets the fields' shapes
        for_each_chunk(one, starts[1:], works[:n_threads])
        return stack.result()

    def _block(
        self,
        bi: int,
        theta: np.ndarray,
        tau: np.ndarray | None,
        meas: np.ndarray | None,
        rows: np.ndarray,
        values: np.ndarray,
        jacobian: bool,
        ctx: tuple,
        work: Workspace | None = None,
        stacked: bool | None = None,
    ) -> BlockEval:
        """Block `bi` on configurations `theta` (its readings, or a chunk of them), `_evaluate`'s context `ctx`.

        With `work` (a chunk) its J is a view of the workspace, to be copied out before the next chunk.

        J = sum over the loop's frames f of d_f K_f B (eq. 3.8 chained: the loop's derivative w.r.t. the
        frame's right perturbation, Pinocchio's LOCAL kinematic regressor, each column's twist generator),
        plus the frames' own generators; Jq the same through the joints' motion subspaces.
        """
        cols, role, owner, B, span, geo, state = ctx
        b, sl = self.blocks[bi], self.loop_columns[bi]
        C, nj = cols.size, len(self.joints)
        only = getattr(b.loop, "parameter_only", False)  # a known length or distance: no reading moves it
        fids = [self.robot.frame_id(f) for f in b.loop.frames]
        kin = self.frame_kinematics(state, theta, fids, jacobian, tau, work, stacked)
        Ts = [kin[f][0] for f in fids]
        if not jacobian:
            return BlockEval(
                b.loop.residual_frames(Ts, values[sl], meas),
                None,
                None,
                b.loop.valid_frames(Ts, values[sl], meas),
                None,
                None if only else rows,
            )
        ev = b.loop.evaluate_frames(Ts, values[sl], meas)
        N, m = ev.r.shape
        shape = (N, m, C + nj)
        D = work.get("D", shape) if work else np.empty(shape)  # [J | d r / d theta']
        first = True
        for f, d in zip(fids, ev.frame_derivatives()):
            K = kin[f][1]
            if f == 0:
                continue
            assert K is not None  # frame_kinematics forms every non-base frame's regressor when asked (jacobian)
            # (N, m, 6 nj): small per-configuration products, then one GEMM with B, into D for the first frame
            dK = np.matmul(d, K[:, :, span], out=work.get("dK", (N, m, B.shape[0])) if work else None)
            into = D if first else work.get("dKB", shape) if work else np.empty(shape)
            np.matmul(dK.reshape(N * m, -1), B, out=into.reshape(N * m, -1))
            if not first:
                D += into
            first = False
            if f in state.G_frames:
                D[:, :, geo] += d @ state.G_frames[f][:, cols[geo]]
        if first:  # no frame but the base
            D[...] = 0.0
        J = D[:, :, :C]
        factors = [(_SCALE, theta), (_COMPLIANCE, np.zeros_like(theta) if tau is None else -tau)]
        if self._coupled:  # a multiplier's column: the coupled joint's motion times the followed joint's angle
            factors.append((_MIMIC, self.model_angles(state, theta, tau)))
        for kind, factor in factors:  # d theta' / d parameter: 1 (offset), theta (scale), -tau (compliance)
            k = np.flatnonzero(role == kind)
            J[:, :, k] *= factor[:, None, owner[k]]
        loc = self._local[bi, cols]  # the loop's own parameters among the columns (shared ones included)
        own = np.flatnonzero(loc >= 0)
        J[:, :, own] = ev.dp[:, :, loc[own]]
        Jq = np.zeros_like(D[:, :, C:]) if only else D[:, :, C:] * state.scale[None, None, :]
        return BlockEval(ev.r, J, Jq, ev.valid, ev.cov, None if only else rows)
