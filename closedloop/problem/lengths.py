"""A known length between two frames of the robot: a link measured with calipers.

Closed loops close at any overall size (thesis 3.3).  A length between two
frames A and B, measured with every joint at a reading of 0 (the robot's
home), is a measurement of the robot itself:

    r = |p_B - p_A| - L,        W = sigma^2,

one row at that configuration (`LengthLoop.measured_at`).  With right
perturbations T <- T exp6((v, w)) of the frames' world poses,
dr/d(delta_A) = (-u^T R_A, 0) and dr/d(delta_B) = (u^T R_B, 0),
u = (p_B - p_A) / |p_B - p_A|; the problem chains them with Pinocchio's
frame Jacobians, so every joint origin on the way between A and B enters.
Being a length, it is what sets the scale, never an arbitrarily held one
(`scale_free` is False: no gauge is chosen).

Whether such a length sets the robot's size is a question of the data, not
of the length: the loops fix the ratios of the robot's lengths only as well
as they excite them, and a length that also moves with a parameter the loops
cannot see (a frame's position along a joint axis) says nothing of the size
through it.  Two checks at the solution, both in the report:

* `size_response`: the robot's size change (`gauge.scale_content`) of the
  least-squares step that a 0.1 % change of L makes, on the fit's own
  truncated system.  1 means that the length sets the size; outside
  [0.9, 1.1] the result is `suspect` ("sets the robot's size only in part").
* `held_leak`: the null space N of the loops alone (closure-projected
  Jacobian, `identifiability.closure_jacobian`) holds the uniform scaling s
  and what the loops cannot see at all (a frame's position along its joint
  axis).  The length's gradient g on N should be a multiple of the scale
  content c: the part g_perp of N^T g orthogonal to N^T c, per step of
  HELD_ERROR (1 mm or 1 mrad) along N, divided by L, is the relative size
  error such an error of those held values makes.  Over LEAK_TOL (0.1 %)
  the result is `suspect`, naming the parameter; the size's standard error
  (`analysis.scale.scale_std`) is quoted with it added in quadrature.

Command line: ``--length FRAME_A FRAME_B METRES [SIGMA]`` (sigma default
20 micrometres, a caliper's), read by `closedloop.problem.rig`, made loops by `length_loops_on`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.problem.rig import KnownLength, known_lengths

if TYPE_CHECKING:
    from closedloop.model.robot import RobotModel
    from closedloop.problem.problem import CalibrationProblem

DEFAULT_SIGMA = 2e-5  # m: a caliper's reading


class LengthLoop(Loop):
    """One residual row: the distance between two robot frames minus its known value (module docstring)."""

    translation_rows = (0,)
    scale_free = False
    parameter_only = True  # no configuration of its own: `calibration.pipeline.build_problem` gives it one row

    def __init__(self, frame_a: str, frame_b: str, length: float, sigma: float | None = None):
        L = float(length)
        sig = DEFAULT_SIGMA if sigma is None else float(sigma)
        where = f"--length {frame_a} {frame_b} {length}"
        if not np.isfinite(L) or L <= 0.0:
            raise LoopError(f"{where}: the length must be a positive distance (m)")
        if not np.isfinite(sig) or sig <= 0.0:
            raise LoopError(f"{where}: sigma {sigma} must be a positive length (m)")
        if frame_a == frame_b:
            raise LoopError(f"{where}: a frame's distance to itself")
        super().__init__(f"{frame_a}-{frame_b}", frame_a, frame_b)
        self.length, self.sigma = L, sig
        self.measurement_cov = np.array([[sig * sig]])

    @property
    def dim(self) -> int:
        return 1

    def parameters(self) -> list:
        return []

    def measured_at(self, joints: list[str]) -> np.ndarray:
        """The readings the length is measured at (1, len(joints)): every joint at a reading of 0."""
        return np.zeros((1, len(joints)))

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        d = TB[:, :3, 3] - TA[:, :3, 3]
        n = np.linalg.norm(d, axis=1)
        u = d / np.maximum(n, 1e-300)[:, None]
        N = TA.shape[0]
        dA = np.zeros((N, 1, 6))
        dB = np.zeros((N, 1, 6))
        dA[:, 0, :3] = -np.einsum("ni,nij->nj", u, TA[:, :3, :3])
        dB[:, 0, :3] = np.einsum("ni,nij->nj", u, TB[:, :3, :3])
        return LoopEval((n - self.length)[:, None], dA, dB, np.zeros((N, 1, 0)))

    def describe(self) -> dict:
        return {
            "name": self.name,
            "type": "length",
            "frame_a": self.frame_a,
            "frame_b": self.frame_b,
            "length_m": self.length,
            "sigma_m": self.sigma,
        }

    def label(self) -> str:
        """'the length panda_link3-panda_link4 (82.5 mm)'."""
        return f"the length {self.frame_a}-{self.frame_b} ({self.length * 1e3:.4g} mm)"


def parse_lengths(items: list, robot: RobotModel) -> list[LengthLoop]:
    """``--length A B L [SIGMA]`` occurrences (lists of strings, or 'A B L' lines of a --config) -> loops."""
    return length_loops_on(robot, known_lengths(items))


def length_loops_on(robot: RobotModel, known: Sequence[KnownLength]) -> list[LengthLoop]:
    """The LengthLoops of a rig's known lengths (`closedloop.problem.rig`) between frames of `robot`: each
    frame one of the model's, and the length near the model's own (a calibration corrects millimetres; a
    length metres off is a slip of unit)."""
    out = []
    for k in known:
        lp = LengthLoop(k.frame_a, k.frame_b, k.length, k.sigma)
        nominal = _nominal_distance(robot, k)
        if abs(k.length - nominal) > max(0.5 * nominal, 0.05):
            raise LoopError(
                f"{k.given}: the model puts these frames {nominal:.4g} m apart; a measured length differs from it "
                f"by a calibration's correction (millimetres), not {abs(k.length - nominal):.4g} m (metres expected)"
            )
        out.append(lp)
    return out


def _nominal_distance(robot: RobotModel, k: KnownLength) -> float:
    """Distance between the frames of `k` in the nominal model at its neutral configuration; a frame the
    model does not have is a LoopError naming the option."""
    import numpy as np
    import pinocchio as pin

    try:
        fa, fb = robot.frame_id(k.frame_a), robot.frame_id(k.frame_b)
    except Exception as exc:
        raise LoopError(f"{k.given}: {exc}") from None
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, pin.neutral(robot.model))
    return float(np.linalg.norm(data.oMf[fa].translation - data.oMf[fb].translation))


def length_blocks(problem: CalibrationProblem) -> list[int]:
    """Indices of the problem's blocks that are known lengths."""
    return list(length_loops(problem))


def length_loops(problem: CalibrationProblem) -> dict[int, LengthLoop]:
    """The problem's known lengths by block index (in block order)."""
    return {bi: b.loop for bi, b in enumerate(problem.blocks) if isinstance(b.loop, LengthLoop)}
