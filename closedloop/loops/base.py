"""The loop interface: a residual and its Jacobians, nothing else.

A loop joins frame A and frame B of the robot model.  Given their poses
T_A, T_B (world, per configuration) it returns

* r      (N, m): the closure error,
* dA, dB (N, m, 6): derivatives w.r.t. right perturbations of T_A and T_B
  (T <- T exp6(delta), delta in the frame's LOCAL coordinates),
* dp     (N, m, P): derivatives w.r.t. the loop's own parameters.

The problem chains dA, dB with Pinocchio's frame Jacobians and kinematic
regressors, so a loop knows nothing about the robot and the solver knows
nothing about loops.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from closedloop.model.parameters import Parameter


@dataclass
class LoopEval:
    r: np.ndarray
    dA: np.ndarray | None
    dB: np.ndarray | None
    dp: np.ndarray
    #: derivatives w.r.t. each frame of `Loop.frames` (N, m, 6), for loops on more than two frames
    dF: list[np.ndarray] | None = None
    #: (N, m) False for rows without an observation (a marker out of view): their r, dF, dp rows are 0 and
    #: they carry no degree of freedom; None when every row is observed
    valid: np.ndarray | None = None
    #: (N, m, m) per-configuration measurement covariance, for loops whose measurement noise depends on the
    #: configuration (stereo triangulation); it adds to `Loop.measurement_cov`
    cov: np.ndarray | None = None
    #: largest inner Gauss-Newton count (loops that eliminate passive joints), for diagnostics
    iterations: int = 0

    def frame_derivatives(self) -> list[np.ndarray]:
        """d r / d (right perturbation) of each frame, in the order of `Loop.frames`."""
        if self.dF is not None:
            return self.dF
        if self.dA is None or self.dB is None:
            raise ValueError("a loop evaluation without Jacobians has no frame derivatives")
        return [self.dA, self.dB]


class Loop(ABC):
    """A kinematic loop closure between two frames of one model."""

    #: residual rows that are lengths (m); the others are angles (rad)
    translation_rows: tuple[int, ...] = ()
    rotation_rows: tuple[int, ...] = ()
    #: residual rows that are image coordinates (px), in (u, v) pairs, one pair per image point
    pixel_rows: tuple[int, ...] = ()
    #: True when the loop cannot tell the overall size of the robot (thesis 3.3)
    scale_free: bool = True

    # Configuration a loop spec may set on the loop (declared, not defaulted: `hasattr` tells whether set):
    #: own parameter field -> its shared group's parameter name (`loops.settings.share`)
    shared: dict[str, str]
    #: the loop's measurement covariance without the task-space term, the task noise given ('estimate' or
    #: per-axis std) and its variance (`loops.settings.set_task_noise`)
    own_cov: np.ndarray | None
    task_noise: str | np.ndarray | None
    task_var: np.ndarray | float | None
    #: the fixture the loop's configurations were recorded at, and the log file they came from (`loops.spec`)
    fixture: str
    log_path: str

    def __init__(self, name: str, frame_a: str, frame_b: str = "universe"):
        self.name = name
        self.frame_a = frame_a
        self.frame_b = frame_b

    @property
    @abstractmethod
    def dim(self) -> int:
        """Residual rows per configuration."""

    @abstractmethod
    def parameters(self) -> list[Parameter]:
        """The loop's own parameters, nominal values included."""

    def prepare(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> "Loop":
        """The loop with what it reads off the data once fixed (the hinge's chart reference): a new
        object, or `self` when there is nothing to fix.  Called once per problem, at the nominal robot
        (`calibration.pipeline.build_problem`); loops keep no per-dataset state beyond what this returns."""
        return self

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """Initial values of the loop's parameters from the data (None: keep nominal)."""
        return None

    def initialize_frames(self, Ts: list[np.ndarray], meas: np.ndarray | None = None) -> np.ndarray | None:
        """`initialize` at the poses of every frame of `frames` (loops on more frames override it)."""
        return self.initialize(Ts[0], Ts[1]) if meas is None else self.initialize(Ts[0], Ts[1], meas)

    @abstractmethod
    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        """Residuals and Jacobians at poses TA, TB (N, 4, 4), own parameters p and measurements meas.

        `meas` (N, len(columns())) holds the loop's measurements per configuration (`measurements`);
        a loop that measures nothing need not take the argument (it is passed only when not None).
        """

    #: (m, m) covariance of an external measurement in the residual, added to the
    #: covariance propagated from joint noise (None: the loop measures nothing)
    measurement_cov: np.ndarray | None = None

    def columns(self) -> list[str]:
        """The log's extra columns the loop measures (none for a pure closure)."""
        return []

    def measurements(self, extra: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray | None:
        """The loop's measurements (len(rows), len(columns())) from the log's extra columns at `rows`.

        A pure function of its arguments (the loop keeps nothing): the problem stores the result in
        `LoopBlock.meas` and passes it to `evaluate` and `initialize`.  None: the loop measures nothing.
        """
        return None

    @property
    def frames(self) -> tuple[str, ...]:
        """Every frame the closure involves (A, B; a loop on more frames overrides this)."""
        return (self.frame_a, self.frame_b)

    def evaluate_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        """Residuals and Jacobians at the poses of `frames` (a list of (N, 4, 4)).

        Two-frame loops need not override it; a loop on more frames (a stereo
        head whose cameras move on their own joints) overrides it and fills
        `LoopEval.dF` with one derivative per frame.
        """
        return self.evaluate(Ts[0], Ts[1], p) if meas is None else self.evaluate(Ts[0], Ts[1], p, meas)

    def residual_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        """The residual alone at the poses of `frames`."""
        return self.residual(Ts[0], Ts[1], p) if meas is None else self.residual(Ts[0], Ts[1], p, meas)

    def valid_frames(self, Ts: list[np.ndarray], p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """`LoopEval.valid` without the Jacobians (None: every row observed)."""
        return None

    def normalize(self, p: np.ndarray) -> np.ndarray:
        """A canonical form of the loop's parameters (e.g. rotation vectors within pi)."""
        return p

    def normalize_jacobian(self, p: np.ndarray) -> np.ndarray | None:
        """d p / d p' at p' = normalize(p) (the same model in the canonical coordinates): a Jacobian J in p is
        J (d p / d p') in p'.  None: not known (the caller evaluates again at p')."""
        return None

    def recentred(self, p: np.ndarray) -> tuple["Loop", np.ndarray] | None:
        """A copy of the loop whose parameter chart is centred at `p`, and `p` in it; None: nothing to move.

        For loops whose parameters are coordinates in a chart around a reference
        (the hinge's line): the solver re-centres the chart as it goes, so that its
        steps are taken where the chart is nearly flat (a retraction, as on a Lie
        group).  The model is unchanged: `express(p', self)` gives `p` back.
        """
        return None

    def express(self, p: np.ndarray, other: "Loop") -> np.ndarray:
        """`p` (this loop's chart) in the chart of `other`, a re-centred copy of this loop."""
        return p

    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        """The residual alone (N, m); loops override it when that is cheaper than `evaluate`."""
        return (self.evaluate(TA, TB, p) if meas is None else self.evaluate(TA, TB, p, meas)).r

    def mismatch(self, Ts: list[np.ndarray], meas: np.ndarray | None = None) -> str | None:
        """Why the data cannot be this loop's, read off the poses of `frames` at the nominal model before any
        fit: what the loop holds fixed varies across the rows by far more than a rough model explains, while
        what another loop type holds fixed does not.  One line naming the likely type; None when nothing
        contradicts the loop (the default)."""
        return None

    def spec(self, kind: str) -> str:
        """This loop's frames and name as a ``--loop`` spec of type `kind` (for messages)."""
        to = "" if self.frame_b == "universe" else f",to={self.frame_b}"
        return f"{kind}:frame={self.frame_a}{to},name={self.name}"

    def describe(self) -> dict:
        return {"name": self.name, "type": type(self).__name__, "frame_a": self.frame_a, "frame_b": self.frame_b}
