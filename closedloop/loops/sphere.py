"""The sphere loop: two spheres in contact, or any known distance between two points (1 equation).

Two hands with spherical ends pressed together, a ball on the tool touching a ball in the world, or two
robot frames a known distance apart: the distance between a point of frame A and a point of frame B is
constant (5 passive task DOF: the point of A slides over a sphere about the point of B).
"""

from __future__ import annotations

import numpy as np

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.common import POINT_FIELDS, TIP_FIELDS, point_parameters, relative_point
from closedloop.loops.spec import register
from closedloop.model.parameters import DEFAULT_PRIORS, Parameter
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import parse_vec, vec3

#: below this distance (m) the residual's direction is undefined on noise: a point contact
MIN_DISTANCE = 1e-3


class SphereLoop(Loop):
    """One closure equation per configuration: a point of A stays at distance d from a point of B.

    The extension of thesis 3.4 to t = 5 passive task DOF (the contact of two spheres: the centre of one
    slides over a sphere of radius d = r_A + r_B about the other's); of the six closure equations only
    the distance survives the elimination of the unsensed DOF:

        u = T_B^-1 T_A t - p,     r = |u| - d                 (1 row, metres)

    t is the point in frame A (``<loop>.tip_x/y/z``, or known ``tip=``), p the point in frame B
    (``<loop>.px/py/pz``, or known ``point=``) and d the distance (``<loop>.d``, or known
    ``distance=``).  With n = u / |u| and y = T_B^-1 T_A t (see `common.relative_point`):

        dr/d(delta_A) = n^T R_BA [I  -[t]x],   dr/d(delta_B) = n^T [-I  [y]x],
        dr/dt = n^T R_BA,   dr/dp = -n^T,   dr/dd = -1.

    A known distance sets the robot's size (thesis 3.3: the loop is not scale-free); an unknown one
    does not.  ``tip=0 0 0,point=0 0 0,distance=D`` is a known distance between the origins of two
    frames.  Distances under 1 mm are refused: the direction n is then noise (use ``point``).
    """

    translation_rows = (0,)
    rotation_rows = ()

    def __init__(
        self,
        name: str,
        frame_a: str,
        frame_b: str = "universe",
        tip: np.ndarray | None = None,
        point: np.ndarray | None = None,
        distance: float | None = None,
        prior: float | None = None,
    ):
        super().__init__(name, frame_a, frame_b)
        self.prior = prior
        self.tip = None if tip is None else vec3(tip, "tip")
        self.point = None if point is None else vec3(point, "point")
        if distance is not None and not (np.isfinite(distance) and distance >= MIN_DISTANCE):
            raise LoopError(
                f"sphere loop '{name}': distance={distance} m: give at least {MIN_DISTANCE} m (a contact of two "
                "points is a point loop: --loop point:...)"
            )
        self.distance = None if distance is None else float(distance)
        self.scale_free = self.distance is None  # a known distance is a known length

    @property
    def dim(self) -> int:
        return 1

    @property
    def n_tip(self) -> int:
        return 0 if self.tip is not None else 3

    @property
    def n_point(self) -> int:
        return 0 if self.point is not None else 3

    def parameters(self) -> list[Parameter]:
        out = []
        if self.tip is None:
            out += point_parameters(self.name, TIP_FIELDS, np.zeros(3), prior=self.prior)
        if self.point is None:
            out += point_parameters(self.name, POINT_FIELDS, np.zeros(3), order0=3, prior=self.prior)
        if self.distance is None:
            prior = DEFAULT_PRIORS["loop_m"] if self.prior is None else self.prior
            out.append(
                Parameter(
                    f"{self.name}.d",
                    "loop",
                    self.name,
                    "d",
                    0.0,
                    "m",
                    prior,
                    scales_with_length=0.0,
                    priority=1,
                    order=6,
                )
            )
        return out

    def split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(tip, point, distance) from the loop's parameter vector."""
        k = self.n_tip
        tip = self.tip if self.tip is not None else p[:3]
        point = self.point if self.point is not None else p[k : k + 3]
        d = self.distance if self.distance is not None else float(p[k + self.n_point])
        return np.asarray(tip, dtype=float), np.asarray(point, dtype=float), float(d)

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """The unknown point and distance from the data at the nominal model: a sphere fitted to the points
        y_i = T_B^-1 T_A t (algebraic least squares, |y|^2 = 2 p.y + c with c = d^2 - |p|^2), the known
        ones kept; the tip starts at frame A's origin unless given."""
        tip = self.tip if self.tip is not None else np.zeros(3)
        y, *_ = relative_point(TA, TB, tip)
        p = self.point
        if p is None:
            m = y.mean(axis=0)
            p = m
            if y.shape[0] >= 4:
                A = np.c_[2 * y, np.ones(len(y))]
                S = np.linalg.svd(A, compute_uv=False)
                if S[-1] > 1e-6 * S[0]:
                    p = np.linalg.lstsq(A, np.sum(y * y, axis=1), rcond=None)[0][:3]
            v = p - m
            # no centre fitted (one point, or points that fix none): any direction will do, but one, so that the
            # closure has a derivative (at zero distance it has none)
            u = v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-9 else np.array([0.0, 0.0, 1.0])
            if self.distance is not None:  # the centre at the known distance from the points' mean
                p = m + self.distance * u
            elif np.linalg.norm(v) <= 1e-9:
                p = m + MIN_DISTANCE * u
        d = float(np.mean(np.linalg.norm(y - p, axis=1)))
        out = [] if self.tip is not None else [tip]
        if self.point is None:
            out.append(p)
        if self.distance is None:
            out.append(np.array([max(d, MIN_DISTANCE)]))
        return np.concatenate(out) if out else None

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        tip, point, d = self.split(p)
        y, RBA, dyA, dyB = relative_point(TA, TB, tip)
        u = y - point
        norm = np.linalg.norm(u, axis=1)
        n = u / np.maximum(norm, 1e-300)[:, None]
        N = TA.shape[0]
        r = (norm - d)[:, None]
        dA = np.einsum("ni,nij->nj", n, dyA)[:, None, :]
        dB = np.einsum("ni,nij->nj", n, dyB)[:, None, :]
        blocks = []
        if self.tip is None:
            blocks.append(np.einsum("ni,nij->nj", n, RBA)[:, None, :])
        if self.point is None:
            blocks.append(-n[:, None, :])
        if self.distance is None:
            blocks.append(np.full((N, 1, 1), -1.0))
        dp = np.concatenate(blocks, axis=2) if blocks else np.zeros((N, 1, 0))
        return LoopEval(r, dA, dB, dp)

    def describe(self) -> dict:
        return super().describe() | {
            "tip": "unknown" if self.tip is None else self.tip.tolist(),
            "point": "unknown" if self.point is None else self.point.tolist(),
            "distance": "unknown" if self.distance is None else self.distance,
        }


@register("sphere", {"frame", "to", "tip", "point", "distance"})
def _sphere(kw: dict[str, str], robot: RobotModel) -> Loop:
    """sphere:frame=A[,to=B][,tip="x y z"][,point="x y z"][,distance=D]  (each unknown if absent)."""
    if "frame" not in kw:
        raise LoopError("sphere loop needs frame=<frame A>")
    tip = parse_vec(kw["tip"], 3, "tip") if kw.get("tip", "unknown") != "unknown" else None
    point = parse_vec(kw["point"], 3, "point") if kw.get("point", "unknown") != "unknown" else None
    d = kw.get("distance", "unknown")
    distance = None if d == "unknown" else float(parse_vec(d, 1, "distance")[0])
    return SphereLoop(
        kw.get("name", "sphere"), kw["frame"], kw.get("to", "universe"), tip=tip, point=point, distance=distance
    )
