"""Forward kinematics and kinematic regressors of many configurations at once, as stacked arrays.

Pinocchio computes one configuration per call; over a long log that is a Python loop of one call per row,
the largest part of an evaluation (100,000 rows: 0.56 s for `computeFrameKinematicRegressor` after
`forwardKinematics`, against 0.05 s for the same products over the stack).  A chain of revolute and
prismatic joints (every joint a URDF makes but floating and planar ones) needs only products of 3 x 3
matrices, which numpy forms for the whole stack at once:

* the pose of joint i, oM_i = oM_lambda(i) X_i exp(S_i q_i) (Featherstone's recursion; X_i the joint's
  placement in its parent, `model.jointPlacements`, read at each call, so that a calibrated model's
  placements are the ones used);
* the pose of a frame, oM_f = oM_parent(f) fMp;
* its LOCAL kinematic regressor (Pinocchio's `computeFrameKinematicRegressor`): the frame's twist
  d_f = sum_i Ad(oM_f^-1 oM_lambda(i) X_i) delta_i for right perturbations X_i exp(delta_i) of the placements
  of the joints supporting it (the thesis' eq. 3.8 differentiated, one 6 x 6 block per joint; zero blocks
  for the joints that do not support the frame).

`StackedKinematics.covers` says which frames it computes; the caller keeps Pinocchio's loop for the others
(spherical, floating and planar joints).  The results agree with Pinocchio's to rounding (1e-12).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.model.se3 import skew

# joint type -> (kind, axis); "R" revolute (q: angle), "U" unbounded revolute (q: cos, sin), "P" prismatic
_AXES = {"X": (1.0, 0.0, 0.0), "Y": (0.0, 1.0, 0.0), "Z": (0.0, 0.0, 1.0)}
_KINDS = {
    **{f"JointModelR{a}": ("R", a) for a in _AXES},
    **{f"JointModelRUB{a}": ("U", a) for a in _AXES},
    **{f"JointModelP{a}": ("P", a) for a in _AXES},
    "JointModelRevoluteUnaligned": ("R", None),
    "JointModelRevoluteUnboundedUnaligned": ("U", None),
    "JointModelPrismaticUnaligned": ("P", None),
}
_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2}
#: configurations per block of `StackedKinematics.gravity` (100,000 at once take three times as long)
GRAVITY_ROWS = 16384


class StackedKinematics:
    """Stacked forward kinematics of one model's joint tree (the module docstring).

    Built once from the model's structure (joint types, axes, configuration indices); the placements
    are read from the model passed to each call (a copy of it with other placements will do).
    """

    def __init__(self, model: pin.Model) -> None:
        self._kind: dict[int, tuple[str, str | None, np.ndarray, int]] = {}
        for j in range(1, model.njoints):
            jm = model.joints[j]
            kind = _KINDS.get(jm.shortname())
            if kind is None:
                continue
            name, aligned = kind
            axis = np.array(_AXES[aligned]) if aligned else np.asarray(jm.extract().axis, dtype=float).copy()
            self._kind[j] = (name, aligned, axis, jm.idx_q)
        self._parents = list(model.parents)
        self._supports = [list(s) for s in model.supports]

    def covers(self, model: pin.Model, frame: int) -> bool:
        """Whether every joint supporting `frame` is one this module computes."""
        return all(j in self._kind for j in self._supports[model.frames[frame].parentJoint][1:])

    def frames(
        self, model: pin.Model, q: np.ndarray, frames: list[int], regressors: dict[int, np.ndarray] | None = None
    ) -> dict[int, np.ndarray]:
        """Poses oM_f (N, 4, 4) of `frames` at configurations `q` (N, nq); with `regressors` (frame -> an array
        (N, 6, 6 (njoints - 1)) to fill), each frame's LOCAL kinematic regressor written into its array.

        Every frame must be `covers`ed.  Inside, a stack of rotations is (3, 3, N) and of vectors (3, N):
        each entry a contiguous row of N numbers, so that every product is a few vector operations or one
        BLAS call, not N small ones.
        """
        N = q.shape[0]
        qT = np.ascontiguousarray(q.T)
        parents = {f: model.frames[f].parentJoint for f in frames}
        joints = sorted({j for f in frames for j in self._supports[parents[f]][1:]})
        R: dict[int, np.ndarray] = {}
        p: dict[int, np.ndarray] = {}
        placed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # oM_lambda(i) X_i: the joint's frame at q_i = 0
        for j in joints:
            X = model.jointPlacements[j]
            placed[j] = _compose(R.get(self._parents[j]), p.get(self._parents[j]), X, N)
            R[j], p[j] = self._moved(*placed[j], qT, j)
        out: dict[int, np.ndarray] = {}
        for f in frames:
            TR, Tp = _compose(R.get(parents[f]), p.get(parents[f]), model.frames[f].placement, N)
            T = np.zeros((N, 4, 4))
            T[:, :3, :3] = np.moveaxis(TR, 2, 0)
            T[:, :3, 3] = Tp.T
            T[:, 3, 3] = 1.0
            out[f] = T
            if regressors is not None and f in regressors:
                support = self._supports[parents[f]][1:]
                K = self._regressor(TR, Tp, support, placed, model.njoints)
                regressors[f][...] = np.moveaxis(K, 2, 0)  # to the caller's layout (N, 6, 6 (njoints - 1))
        return out

    def gravity(self, model: pin.Model, q: np.ndarray) -> np.ndarray | None:
        """The generalized gravity g(q) (N, nv) of `model`'s inertials at configurations `q` (N, nq): what
        Pinocchio's ``computeGeneralizedGravity`` (RNEA at zero velocity and acceleration) gives one
        configuration per call, to rounding.  Joint i holds the weight of the bodies it carries (its
        subtree: mass m_i, mass-weighted centre c_i = sum of m_b times each body's centre in the world):
        tau_i = a_i . ((c_i - m_i o_i) x -g) for a revolute joint of axis a_i and origin o_i in the world,
        a_i . (-m_i g) for a prismatic one.  None where a joint is not one this module computes (the caller
        keeps Pinocchio's loop).
        """
        if len(self._kind) != model.njoints - 1:
            return None
        if q.shape[0] > GRAVITY_ROWS:  # in blocks whose stacks stay in the processor's cache
            return np.concatenate(
                [self.gravity(model, q[i : i + GRAVITY_ROWS]) for i in range(0, q.shape[0], GRAVITY_ROWS)]
            )
        N = q.shape[0]
        qT = np.ascontiguousarray(q.T)
        R: dict[int, np.ndarray] = {}
        p: dict[int, np.ndarray] = {}
        mass = np.zeros(model.njoints)
        centre = np.zeros((model.njoints, 3, N))
        for j in range(1, model.njoints):
            placed = _compose(R.get(self._parents[j]), p.get(self._parents[j]), model.jointPlacements[j], N)
            R[j], p[j] = self._moved(*placed, qT, j)
            body = model.inertias[j]
            mass[j] = body.mass
            centre[j] = body.mass * (p[j] + np.einsum("ikn,k->in", R[j], np.asarray(body.lever)))
        for j in range(model.njoints - 1, 1, -1):  # a child's index is above its parent's
            mass[self._parents[j]] += mass[j]
            centre[self._parents[j]] += centre[j]
        down = -np.asarray(model.gravity.linear, dtype=float)
        turn = skew(down)  # a . (arm x down) = arm . (down x a) = arm . ([down]x a)
        tau = np.zeros((N, model.nv))
        for j, (kind, _, axis, _) in self._kind.items():
            a = np.einsum("ikn,k->in", R[j], axis)  # the joint's axis in the world
            if kind == "P":
                tau[:, model.joints[j].idx_v] = mass[j] * (down @ a)
            else:
                arm = centre[j] - mass[j] * p[j]
                tau[:, model.joints[j].idx_v] = np.einsum("in,in->n", arm, turn @ a)
        return tau

    def _moved(self, AR: np.ndarray, Ap: np.ndarray, qT: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
        """oM_i = A exp(S_i q_i) for the joint's frame A = (AR, Ap) at q_i = 0 (stacks (3, 3, N), (3, N))."""
        kind, aligned, axis, iq = self._kind[j]
        if kind == "P":
            return AR, Ap + np.einsum("ikn,k->in", AR, axis) * qT[iq]
        if kind == "U":
            c, s = qT[iq], qT[iq + 1]
        else:
            c, s = np.cos(qT[iq]), np.sin(qT[iq])
        if aligned is not None:  # a rotation about a basis axis k: columns a, b turn in their plane
            k = _AXIS_INDEX[aligned]
            a, b = (k + 1) % 3, (k + 2) % 3
            Rm = np.empty_like(AR)
            Rm[:, k] = AR[:, k]
            Rm[:, a] = AR[:, a] * c + AR[:, b] * s
            Rm[:, b] = AR[:, b] * c - AR[:, a] * s
            return Rm, Ap
        # Rodrigues, as Pinocchio forms it: E = c I + s [a]x + (1 - c) a a^T, then A E
        E = np.multiply.outer(np.outer(axis, axis), 1.0 - c) + np.multiply.outer(skew(axis), s)
        E[[0, 1, 2], [0, 1, 2]] += c
        return _times(AR, E), Ap

    @staticmethod
    def _regressor(
        TR: np.ndarray,
        Tp: np.ndarray,
        support: list[int],
        placed: dict[int, tuple[np.ndarray, np.ndarray]],
        njoints: int,
    ) -> np.ndarray:
        """(6, 6 (njoints - 1), N): Ad(oM_f^-1 A_i) in the columns of each supporting joint i (A_i = oM_lambda(i)
        X_i), zero elsewhere; Ad(M) = [[R, [p]x R], [0, R]] (Pinocchio's motion order: linear, angular)."""
        N = TR.shape[2]
        K = np.zeros((6, 6 * (njoints - 1), N))
        for j in support:
            AR, Ap = placed[j]
            Rx = np.einsum("kin,kjn->ijn", TR, AR)  # oR_f^T AR
            x, y, z = np.einsum("kin,kn->in", TR, Ap - Tp)  # oR_f^T (Ap - op_f)
            c = 6 * (j - 1)
            K[:3, c : c + 3] = Rx
            K[3:, c + 3 : c + 6] = Rx
            K[0, c + 3 : c + 6] = y * Rx[2] - z * Rx[1]  # [p]x R, row by row
            K[1, c + 3 : c + 6] = z * Rx[0] - x * Rx[2]
            K[2, c + 3 : c + 6] = x * Rx[1] - y * Rx[0]
        return K


def _compose(R: np.ndarray | None, p: np.ndarray | None, X: pin.SE3, N: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) X for a stack (3, 3, N), (3, N), None for the identity, and one placement X."""
    if R is None or p is None:
        return (
            np.repeat(X.rotation[:, :, None], N, axis=2),
            np.repeat(np.asarray(X.translation)[:, None], N, axis=1),
        )
    # (R Xr)[i, j] = sum_k R[i, k] Xr[k, j]: per row i, Xr^T (3 x 3) times R[i] (3 x N), one BLAS call each
    return np.matmul(X.rotation.T, R), p + np.einsum("ikn,k->in", R, X.translation)


def _times(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A B for two stacks of 3 x 3 matrices (3, 3, N)."""
    return np.einsum("ikn,kjn->ijn", A, B)
