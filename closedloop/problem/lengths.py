"""A known length between two frames of the robot (issue 18 item 2): a link measured with calipers.

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
  (`constraints.scale_std`) is quoted with it added in quadrature.

Command line: ``--length FRAME_A FRAME_B METRES [SIGMA]`` (sigma default
20 micrometres, a caliper's).
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.model.parameters import DEFAULT_PRIORS

if TYPE_CHECKING:
    from closedloop.model.robot import RobotModel
    from closedloop.problem.problem import CalibrationProblem

DEFAULT_SIGMA = 2e-5  # m: a caliper's reading
LEAK_TOL = 1e-3  # relative size error from a 1 mm (1 mrad) error of what the loops cannot see
HELD_ERROR = 1e-3  # m or rad: the error `held_leak` is quoted for
STEP = 1e-3  # relative change of L in `size_response`
SETS_SIZE = (0.9, 1.1)  # the size response that counts as setting the scale


class LengthLoop(Loop):
    """One residual row: the distance between two robot frames minus its known value (module docstring)."""

    translation_rows = (0,)
    scale_free = False
    parameter_only = True  # no configuration of its own: `calibration.build_problem` gives it one row

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

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> LoopEval:
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
    import re

    from closedloop.io.schemas import parse_number

    out = []
    for it in items:
        if isinstance(it, str):
            it = [t for t in re.split(r"[\s,\[\]'\"]+", it) if t]
        it = [str(t) for t in it]
        where = f"--length {' '.join(it)}"
        if len(it) not in (3, 4):
            raise LoopError(f"{where}: expected FRAME_A FRAME_B METRES [SIGMA] (e.g. panda_link3 panda_link4 0.0825)")
        for f in it[:2]:
            try:
                robot.frame_id(f)
            except Exception as exc:
                raise LoopError(f"{where}: {exc}") from None
        nums = [parse_number(t, where, LoopError) for t in it[2:]]
        out.append(LengthLoop(it[0], it[1], nums[0], nums[1] if len(nums) > 1 else None))
    return out


def length_blocks(problem: CalibrationProblem) -> list[int]:
    """Indices of the problem's blocks that are known lengths."""
    return [bi for bi, b in enumerate(problem.blocks) if isinstance(b.loop, LengthLoop)]


def size_response(
    problem: CalibrationProblem, x: np.ndarray, est: list[int], sigma_q: np.ndarray, weighting: str, snr: float
) -> float:
    """The robot's relative size change per relative change of the known lengths, at the solution x.

    The step is the least-squares answer of the fit's own system (whitened
    Jacobian J over `est`, prior-scaled, truncated below `snr` times the
    residual RMS as at the solution, eq. 4.17) to the residual change that
    scaling every known length by 1 + STEP makes; its size change is
    c^T dx with c the size change per parameter (`gauge.size_per_parameter`).
    """
    from closedloop.analysis.gauge import size_per_parameter
    from closedloop.estimate.stages import ResidualFunction
    from closedloop.problem.problem import CalibrationProblem as Problem

    idx = length_blocks(problem)
    if not idx or not any(k < problem.n_robot for k in est):
        return 0.0
    blocks = [
        replace(b, loop=replace_length(b.loop, 1.0 + STEP)) if bi in idx else b for bi, b in enumerate(problem.blocks)
    ]
    moved = Problem(problem.robot, problem.joints, blocks, problem.priors, problem.noise)
    r, J = ResidualFunction(problem, x, est, sigma_q, weighting)(x[est], True)
    r1, _ = ResidualFunction(moved, x, est, sigma_q, weighting)(x[est], False)
    scale = np.array([problem.params[k].prior for k in est])
    U, S, Vt = np.linalg.svd(J * scale, full_matrices=False)
    dof = max(r.size - len(est), 1)
    keep = S > max(1e-10 * (S[0] if S.size else 0.0), snr * float(np.sqrt(r @ r / dof)))
    dx = -(Vt[keep].T @ ((U[:, keep].T @ (r1 - r)) / S[keep])) * scale
    return float(size_per_parameter(problem, x, est) @ dx) / STEP


def replace_length(loop: LengthLoop, factor: float) -> LengthLoop:
    """A copy of `loop` with its length times `factor`."""
    out = LengthLoop(loop.frame_a, loop.frame_b, loop.length * factor, loop.sigma)
    out.name = loop.name
    return out


def length_findings(res, sigma_q: np.ndarray, snr: float) -> tuple[str, list[str]]:
    """(the sentence on what sets the scale, the warnings that make the result suspect) for a result whose
    problem has known lengths; sets `res.length_response` and `res.length_leak` (module docstring)."""
    problem = res.problem
    labels = " and ".join(problem.blocks[bi].loop.label() for bi in length_blocks(problem))
    res.length_response = size_response(problem, res.values, res.estimated, sigma_q, res.weighting, snr)
    free = [k for k, s in enumerate(res.status) if s in ("estimated", "dropped", "unidentifiable")]
    res.length_leak, held = held_leak(problem, res.values, free)
    warnings = []
    if not SETS_SIZE[0] <= res.length_response <= SETS_SIZE[1]:
        warnings.append(
            f"{labels} sets the robot's size only in part (a change of it by 1 % scales the robot by "
            f"{res.length_response:.3g} %): the loops tie it to the rest of the robot too loosely; the "
            "scale is not set by the data"
        )
    if not res.length_leak <= LEAK_TOL:
        warnings.append(
            f"{labels} also changes with {held}, which the loops cannot see (held at its value): an "
            f"error of 1 mm or 1 mrad there changes the identified size by {res.length_leak:.2%}"
            if held
            else f"{labels}: whether it sets the size could not be checked at the solution"
        )
    if warnings:
        return warnings[0], warnings
    return (f"the scale is set by {labels} (a change of it by 1 % scales the robot by {res.length_response:.3g} %)", [])


def held_leak(problem: CalibrationProblem, x: np.ndarray, free: list[int]) -> tuple[float, str | None]:
    """The relative size error a HELD_ERROR (1 mm, 1 mrad) error of what the loops cannot see makes through
    the known lengths, and the parameter that carries most of it (module docstring); (0, None) without."""
    from closedloop.analysis.gauge import kinematic_changes, random_configurations, scale_content
    from closedloop.analysis.identifiability import closure_jacobian
    from closedloop.problem.problem import CalibrationProblem as Problem

    idx = length_blocks(problem)
    if not idx or not free:
        return 0.0, None
    loops = Problem(
        problem.robot,
        problem.joints,
        [b for bi, b in enumerate(problem.blocks) if bi not in idx],
        problem.priors,
        problem.noise,
    )
    R = closure_jacobian(loops, x, free)
    if R is None:
        return float("nan"), None
    _, S, Vt = np.linalg.svd(R)
    null = np.concatenate([Vt[S.size :], Vt[: S.size][S <= 1e-8 * S[0]]]) if S.size else Vt
    if null.shape[0] == 0:
        return 0.0, None
    prior = np.array([problem.params[k].prior for k in free])
    V = np.zeros((len(problem.params), null.shape[0]))
    V[free] = null.T * prior[:, None]  # one prior-sized step along each null direction (an orthonormal basis)
    c, _ = scale_content(*kinematic_changes(loops, x, V, random_configurations(loops, 48)))
    evals = problem.evaluate(x, True, columns=free)
    worst, name = 0.0, None
    prior_m = float((problem.priors or {}).get("m", DEFAULT_PRIORS["m"]))  # the prior-sized step, in metres
    for bi in idx:
        g = evals[bi].J[0, 0]  # metres per unit of each free parameter
        gN = g @ V[free]
        perp = gN - (gN @ c) / max(c @ c, 1e-300) * c if c @ c > 0 else gN
        leak = HELD_ERROR / prior_m * float(np.linalg.norm(perp)) / problem.blocks[bi].loop.length
        if leak > worst:
            d = V[free] @ perp  # the held change that moves the length without the size
            worst, name = leak, problem.names[free[int(np.argmax(np.abs(d) / prior))]]
    return worst, name
