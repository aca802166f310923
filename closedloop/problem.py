"""A stack of loops over logged configurations: residuals and analytic Jacobians.

For loop l at configuration i with readings theta^i the model joint angles are
theta' = k * theta^i + theta_off - c * tau^i (eq. 4.4, plus joint compliance c
under the logged actuator torques tau, when present).  With Pinocchio LOCAL frame
Jacobians J_A, J_B and LOCAL frame kinematic regressors K_A, K_B, the chain
rule gives the columns of C^i (eq. 4.9):

  placement / D-H geometry:  dA K_A G + dB K_B G          (G: right-twist generators)
  offset of joint j:         (dA J_A + dB J_B)[:, j]       (eq. 4.11, first column)
  scale of joint j:          theta_j^i * (dA J_A + dB J_B)[:, j]      (eq. 4.15)
  compliance of joint j:     -tau_j^i * (dA J_A + dB J_B)[:, j]
  loop parameters:           the loop's own dp
  joint readings (for the noise model): k_j * (dA J_A + dB J_B)[:, j]

The per-configuration Pinocchio calls are in one loop; everything else is
batched numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .loops.base import Loop
from .parameters import Parameter, RobotParameters
from .robot import RobotModel


@dataclass
class LoopBlock:
    """The configurations a loop is evaluated on."""

    loop: Loop
    theta: np.ndarray  # (N, n_joints) readings, columns in problem.joints order
    rows: np.ndarray  # row numbers in the log (1-based data rows), for messages
    tau: np.ndarray | None = None  # (N, n_joints) actuator torques, if logged


@dataclass
class BlockEval:
    r: np.ndarray  # (N, m)
    J: np.ndarray | None  # (N, m, P)
    Jq: np.ndarray | None  # (N, m, n_joints) d r / d reading


class CalibrationProblem:
    """Parameters of a robot and its loops, evaluated over logged configurations."""

    def __init__(self, robot: RobotModel, joints: list[str], blocks: list[LoopBlock], priors: dict | None = None):
        self.robot = robot
        self.joints = list(joints)
        self.blocks = blocks
        self.rp = RobotParameters(robot, self.joints, priors)
        self.params: list[Parameter] = list(self.rp.params)
        self.loop_slices: list[slice] = []
        for b in blocks:
            own = b.loop.parameters()
            self.loop_slices.append(slice(len(self.params), len(self.params) + len(own)))
            self.params.extend(own)
        self.names = [p.name for p in self.params]
        self.index = {n: i for i, n in enumerate(self.names)}
        self.n_robot = len(self.rp.params)
        self._idx_v = np.array([robot.joint(n).idx_v for n in self.joints], dtype=int)

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.params])

    # ------------------------------------------------------------- kinematics
    def model_angles(self, state, theta: np.ndarray, tau: np.ndarray | None) -> np.ndarray:
        """theta' = k theta + theta_off - c tau (the sensor model)."""
        angles = theta * state.scale + state.offset
        if tau is not None:
            angles = angles - tau * state.compliance
        return angles

    def frame_kinematics(self, state, theta: np.ndarray, frames: list[int], need_jac: bool,
                         tau: np.ndarray | None = None):
        """Poses (N,4,4), LOCAL Jacobians (N,6,nv) and regressors (N,6,6(nj-1)) of frames."""
        model, data = state.model, state.data
        q = self.robot.configurations(self.model_angles(state, theta, tau), self.joints)
        N = q.shape[0]
        out = {}
        for f in frames:
            if f == 0:
                out[f] = (np.broadcast_to(np.eye(4), (N, 4, 4)), None, None)
            else:
                out[f] = (np.empty((N, 4, 4)),
                          np.empty((N, 6, model.nv)) if need_jac else None,
                          np.empty((N, 6, 6 * (model.njoints - 1))) if need_jac else None)
        live = [f for f in frames if f != 0]
        for i in range(N):
            if need_jac:
                pin.computeJointJacobians(model, data, q[i])
            else:
                pin.forwardKinematics(model, data, q[i])
            for f in live:
                T, J, R = out[f]
                T[i] = pin.updateFramePlacement(model, data, f).homogeneous
                if need_jac:
                    J[i] = pin.getFrameJacobian(model, data, f, pin.LOCAL)
                    R[i] = pin.computeFrameKinematicRegressor(model, data, f, pin.LOCAL)
        return out

    def loop_poses(self, values: np.ndarray, block_index: int, theta: np.ndarray | None = None):
        """T_A, T_B of one loop at `values` (for initialisation and export checks)."""
        b = self.blocks[block_index]
        state = self.rp.apply(values[:self.n_robot])
        fa, fb = self.robot.frame_id(b.loop.frame_a), self.robot.frame_id(b.loop.frame_b)
        tau = b.tau if theta is None else None
        kin = self.frame_kinematics(state, b.theta if theta is None else theta, [fa, fb], False, tau)
        return kin[fa][0], kin[fb][0]

    # ------------------------------------------------------------- evaluation
    def evaluate(self, values: np.ndarray, jacobian: bool = True,
                 thetas: list[np.ndarray] | None = None) -> list[BlockEval]:
        """Residuals (and Jacobians) of every loop at parameter vector `values`."""
        state = self.rp.apply(values[:self.n_robot])
        P = len(self.params)
        used = np.any(state.G != 0, axis=0)
        for Gf in state.G_frames.values():
            used |= np.any(Gf != 0, axis=0)
        geo = np.flatnonzero(used)
        Ggeo = state.G[:, geo]
        off_idx, sc_idx, c_idx = self.rp.offset_index(), self.rp.scale_index(), self.rp.compliance_index()
        out = []
        for bi, (b, sl) in enumerate(zip(self.blocks, self.loop_slices)):
            theta = b.theta if thetas is None else thetas[bi]
            fa, fb = self.robot.frame_id(b.loop.frame_a), self.robot.frame_id(b.loop.frame_b)
            kin = self.frame_kinematics(state, theta, [fa, fb], jacobian, b.tau)
            TA, JA, RA = kin[fa]
            TB, JB, RB = kin[fb]
            if not jacobian:
                out.append(BlockEval(b.loop.residual(TA, TB, values[sl]), None, None))
                continue
            ev = b.loop.evaluate(TA, TB, values[sl])
            N, m = ev.r.shape
            Jv = np.zeros((N, m, state.model.nv))
            Jg = np.zeros((N, m, geo.size))
            for f, d, Jf, Rf in ((fa, ev.dA, JA, RA), (fb, ev.dB, JB, RB)):
                if f == 0:
                    continue
                Jv += d @ Jf
                Jg += d @ (Rf @ Ggeo)
                if f in state.G_frames:
                    Jg += d @ state.G_frames[f][:, geo]
            J = np.zeros((N, m, P))
            J[:, :, geo] = Jg
            Jj = Jv[:, :, self._idx_v]  # d r / d theta'_j
            J[:, :, off_idx] += Jj
            J[:, :, sc_idx] += Jj * theta[:, None, :]
            if b.tau is not None:
                J[:, :, c_idx] -= Jj * b.tau[:, None, :]
            J[:, :, sl] = ev.dp
            out.append(BlockEval(ev.r, J, Jj * state.scale[None, None, :]))
        return out
