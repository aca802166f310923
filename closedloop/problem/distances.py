"""Known geometry as measurements: distances between loop points.

A closed loop closes at any overall size (thesis 3.3): without a length the
robot's scale is held by an arbitrary one (`gauge`).  A rig usually has one
true length, e.g. two sockets of a block 50 mm apart.  `DistanceLoop` adds it
as a measurement,

    r = |p_a - p_b| - d,        W = sigma^2,

one row whose parameters are the two loops' points (shared columns,
`closedloop.problem.shared`): ``front_a.point`` is the contact point of loop front_a
(px, py, pz), ``front_a.tip`` its tool point.  Both points must be in the same
frame (the world for two sockets).  Jacobian: dr/dp_a = u^T, dr/dp_b = -u^T,
u = (p_a - p_b) / |p_a - p_b|.  The row is weighted by 1/sigma like a tracker's
reading (`noise.whiten`), so the joint noise level is estimated beside it.

The loop is not scale-free, so the structural analysis holds no length
(`identifiability.analyse_structure`): the distance sets the scale, and
`scale_note` says so ("the distance front_a-front_b (50 mm)"); without one
the note says the scale is not set by the data.

Command line: ``--distance front_a.point front_b.point 0.050 [sigma]``
(metres; sigma default 10 micrometres); in a ``--config`` file a list of
``front_a.point front_b.point 0.050`` lines; the words are read by `closedloop.problem.rig`, the loops
made by `distance_loops`.

A block of n sockets at known positions s_i in the block's own frame, moved as
one rigid body (`parse_blocks`, ``--block NAME A.point=X,Y,Z B.point=X,Y,Z
... [sigma=S]``): the loops' points p_i are one rigid body of known shape,
given as the n(n-1)/2 pairwise distances |p_i - p_j| = |s_i - s_j|.  A point
set is fixed up to a rigid motion and a reflection by its pairwise distances
(n >= 3, not collinear); the reflection does not matter for the closure, since
the block's pose at each place is free anyway.  Each distance is weighted by
sigma (for n > 3 the distances are not independent, so sigma is that of one
distance, slightly optimistic for the block).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.settings import key_fields
from closedloop.problem.rig import KnownDistance, block_distances, known_distances
from closedloop.problem.shared import parameter_name

if TYPE_CHECKING:
    from closedloop.model.parameters import Parameter
    from closedloop.problem.problem import CalibrationProblem

DEFAULT_SIGMA = 1e-5  # m: a machined or printed block's distance
FIELDS = ("a_x", "a_y", "a_z", "b_x", "b_y", "b_z")


def _point_of(loops: list[Loop], ref: str) -> tuple[Loop, list[Parameter], str]:
    """The loop, its three point parameters and their frame for 'LOOP.point' or 'LOOP.tip'."""
    name, _, key = ref.rpartition(".")
    by_name = {lp.name: lp for lp in loops}
    if name not in by_name or key not in ("point", "tip"):
        raise LoopError(
            f"--distance {ref}: expected LOOP.point or LOOP.tip of a loop (loops: {', '.join(by_name) or 'none'})"
        )
    lp = by_name[name]
    try:
        fields = key_fields(lp, key)
    except LoopError:
        fields = []
    params = [p for p in lp.parameters() if p.field in fields]
    if len(params) != 3:
        raise LoopError(f"--distance {ref}: loop '{name}' has no unknown 3-D {key}")
    return lp, params, lp.frame_b if key == "point" else lp.frame_a


class DistanceLoop(Loop):
    """One residual row: the distance between two loop points minus its known value (module docstring)."""

    translation_rows = (0,)
    scale_free = False
    parameter_only = True  # no configuration of its own: `calibration.pipeline.build_problem` gives it one row

    def __init__(self, loops: list[Loop], a: str, b: str, distance: float, sigma: float | None = None):
        d = float(distance)
        sig = DEFAULT_SIGMA if sigma is None else float(sigma)
        if not np.isfinite(d) or d <= 0.0:
            raise LoopError(f"--distance {a} {b} {distance}: the distance must be a positive length (m)")
        if not np.isfinite(sig) or sig <= 0.0:
            raise LoopError(f"--distance {a} {b}: sigma {sigma} must be a positive length (m)")
        (la, pa, fa), (lb, pb, fb) = (_point_of(loops, ref) for ref in (a, b))
        if fa != fb:
            raise LoopError(f"--distance {a} {b}: the points are in different frames ({fa}, {fb})")
        if la is lb and a == b:
            raise LoopError(f"--distance {a} {b}: a point's distance to itself")
        super().__init__(f"{a}-{b}", "universe", "universe")
        self.a, self.b, self.distance, self.sigma = a, b, d, sig
        self.refers_to = (la.name, lb.name)  # the loops whose points it joins (one rigid fixture)
        self.block: str | None = None  # the block (`parse_blocks`) this distance belongs to
        self.measurement_cov = np.array([[sig * sig]])
        self._params = [
            replace(p, name=parameter_name(lp, p), field=f)
            for (lp, p), f in zip([(la, p) for p in pa] + [(lb, p) for p in pb], FIELDS)
        ]
        self.shared = {p.field: p.name for p in self._params}

    @property
    def dim(self) -> int:
        return 1

    def parameters(self) -> list[Parameter]:
        return list(self._params)

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        N = TA.shape[0]
        diff = p[:3] - p[3:6]
        n = float(np.linalg.norm(diff))
        u = diff / n if n > 0 else np.zeros(3)
        dp = np.broadcast_to(np.concatenate([u, -u]), (N, 1, 6)).copy()
        z = np.zeros((N, 1, 6))
        return LoopEval(np.full((N, 1), n - self.distance), z, z.copy(), dp)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "type": "distance",
            "a": self.a,
            "b": self.b,
            "distance_m": self.distance,
            "sigma_m": self.sigma,
        } | ({"block": self.block} if self.block else {})

    def label(self) -> str:
        """'the distance front_a-front_b (50 mm)'."""
        return f"the distance {self.a.rsplit('.', 1)[0]}-{self.b.rsplit('.', 1)[0]} ({self.distance * 1e3:.4g} mm)"


def distance_loops(known: Sequence[KnownDistance], loops: list[Loop]) -> list[DistanceLoop]:
    """The DistanceLoops of a rig's known distances (`closedloop.problem.rig`: ``--distance`` and each
    ``--block``'s pairwise ones) between the points of `loops`."""
    out = []
    for k in known:
        dl = DistanceLoop(loops, k.a, k.b, k.distance, k.sigma)
        dl.block = k.block
        out.append(dl)
    return out


def parse_distances(items: list[list[str]], loops: list[Loop]) -> list[DistanceLoop]:
    """``--distance A B D [SIGMA]`` occurrences (lists of strings) -> DistanceLoops over `loops`."""
    return distance_loops(known_distances(items), loops)


def parse_blocks(items: list[list[str]], loops: list[Loop]) -> list[DistanceLoop]:
    """``--block NAME A.point=X,Y,Z B.point=X,Y,Z ... [sigma=S]`` -> the block's pairwise DistanceLoops.

    The positions are in the block's own frame (metres); module docstring for the model.
    """
    return distance_loops(block_distances(items), loops)


def distance_blocks(problem: CalibrationProblem) -> list[DistanceLoop]:
    return [b.loop for b in problem.blocks if isinstance(b.loop, DistanceLoop)]
