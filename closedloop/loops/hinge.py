"""The door loop: the tool grasps a handle that turns about an unknown hinge (thesis 3.4.2).

Passive degrees of freedom are eliminated by VARIABLE PROJECTION, shared
with `passive.PassiveChainLoop` (thesis 3.4.3):

The closure pose of frame A in frame B depends on the loop parameters p and
on k unmeasured task joint values phi,  X = X(phi, p).  Per configuration i

    r_i(phi) = log6( X(phi, p)^-1  T_B^-1  T_A ),     E := X^-1 T_B^-1 T_A   (eq. 3.18, exact)

and the passive values are eliminated exactly,  phi_i* = argmin |r_i(phi)|^2,
by Gauss-Newton on phi (with step halving) from a closed-form or warm start,
converged to |dphi| < 1e-13, for all configurations at once (`projection`:
batched SE(3) algebra, per-configuration step halving by masks).  The residual handed to the core is r_i(phi_i*):
still the 6-D exact SE(3) log, in which the k directions J_phi = dr/dphi are
used up (the thesis drops one equation for the door; here the 6 rows stay and
r* is orthogonal to J_phi).  Its Jacobian w.r.t. everything else x (frames A, B,
loop parameters) is the reduced one

    dr*/dx = (I - J_phi J_phi^+) dr/dx.

Justification (envelope theorem): the cost f(x) = 1/2 |r(phi*(x), x)|^2 has,
because J_phi^T r = 0 at phi*, the gradient df/dx = r^T dr/dx = r^T (I - J_phi J_phi^+) dr/dx,
so the reduced Jacobian gives the EXACT gradient of the eliminated problem
everywhere; it equals the exact derivative of r* where the loop closes
(r* = 0; away from closure the neglected terms are O(|r*|), Kaufman's
approximation), so Gauss-Newton keeps its quadratic convergence on consistent
data.  It also keeps the rows along J_phi exactly zero, which the core's noise
weighting W = J_theta Sigma J_theta^T (rank 6 - k) needs: an exact derivative
would put O(|r*|) entries in the direction that the whitening's regulariser
amplifies by 1e5.

Derivatives, with right perturbations (as in `weld.WeldLoop`):

    dr/d(delta_A) = Jlog6(E),  dr/d(delta_B) = -Jlog6(E) Ad(T_A^-1 T_B),
    dr/d(delta_X) = -Jlog6(E) Ad(E^-1),   J_phi = dr/d(delta_X) dX/dphi.

Hinge geometry (this module).  The door frame D is the hinge frame turned by
the hinge angle,  X(phi) = H Rz(phi) G,  with

* H, the hinge line (4 parameters), in a chart around a reference frame H0
  (z = reference axis): H = H0 (exp3(rx, ry, 0), (x, y, 0)).  The line passes
  through (x, y, 0) of H0 with direction H0.R exp3(rx, ry, 0) e_z.  Rotations
  about and translations along the axis are not parameters: they are the
  line's own symmetries (absorbed by phi and the grasp height).  The chart is
  regular while the axis is tilted less than 90 deg from the reference (the
  line meets H0's xy-plane once); near 90 deg it degenerates.  H0 is the data's
  circle fit (or the user's `axis=`), so the tilt stays small.
* G, the grasp (5 parameters): the handle frame (frame A at closure) in the
  door frame, G = (exp3(rx, ry, rz), (radius, 0, height)).  The door frame's x
  axis points at the handle origin, which removes the sixth, redundant
  parameter (a rotation of G about the hinge axis is a shift of every phi_i).
  The chart needs the handle off the axis (radius != 0): a handle on the axis
  traces no circle and leaves phi's zero to the grasp rotation alone.

Parameters: ``<loop>.hinge_x hinge_y`` (m), ``hinge_rx hinge_ry`` (rad),
``<loop>.radius height`` (m), ``grasp_rx grasp_ry grasp_rz`` (rad).
Thesis 3.4.2 extracts phi with atan2 and keeps 5 equations under a small-error
assumption; the projection above needs no small errors (atan2 only gives the
starting point of the Gauss-Newton iteration).
"""

from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin

from closedloop.errors import LoopError
from closedloop.loops.base import Loop, LoopEval
from closedloop.loops.projection import BatchPoseFn, Elimination, eliminate, projector
from closedloop.loops.spec import register
from closedloop.model.parameters import DEFAULT_PRIORS, Parameter
from closedloop.model.se3 import adjoint, log3, relative, rigid_inverse

HINGE_FIELDS = ("hinge_x", "hinge_y", "hinge_rx", "hinge_ry", "radius", "height", "grasp_rx", "grasp_ry", "grasp_rz")
HELD_STILL = 0.05  # rad: a door whose handle turns less than this RMS is held still (weld data)
RECENTRE = 0.1  # m or rad: how far the hinge may move in its chart before the chart follows it
_EZ = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # rotation about z (pin.Motion order: v, w)


# --------------------------------------------------------------- elimination
def _rz_stack(phi: np.ndarray) -> np.ndarray:
    """Rz(phi_i) as homogeneous transforms (n, 4, 4)."""
    c, s = np.cos(phi), np.sin(phi)
    T = np.zeros((phi.size, 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = T[:, 3, 3] = 1.0
    return T


def hinge_pose_fn(H: pin.SE3, G: pin.SE3) -> BatchPoseFn:
    """X(phi) = H Rz(phi) G for a batch of angles (n, 1), with its right twist Ad(G^-1) e_rz per dphi."""
    Hh, Gh = H.homogeneous, G.homogeneous
    XdG = G.inverse().action @ _EZ

    def pose(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = phi.shape[0]
        return Hh @ _rz_stack(phi[:, 0]) @ Gh, np.broadcast_to(XdG[None, :, None], (n, 6, 1))

    return pose


def hinge_starts(M: np.ndarray, H: pin.SE3, G: pin.SE3) -> list[np.ndarray]:
    """Starting angles (N, 1): the thesis's atan2 extraction from C = H^-1 M G^-1 ~ Rz(phi), and the
    angle of the handle position q = (H^-1 M).t ~ Rz(phi) g (NaN where q or g is on the axis)."""
    HM = rigid_inverse(H.homogeneous[None]) @ M
    R = HM[:, :3, :3] @ G.rotation.T
    starts = [np.arctan2(R[:, 1, 0] - R[:, 0, 1], R[:, 0, 0] + R[:, 1, 1])[:, None]]
    q, g = HM[:, :3, 3], G.translation
    ok = np.hypot(q[:, 0], q[:, 1]) > 1e-9
    if np.hypot(g[0], g[1]) > 1e-9 and ok.any():
        a = np.where(ok, np.arctan2(q[:, 1], q[:, 0]) - np.arctan2(g[1], g[0]), np.nan)
        starts.append(a[:, None])
    return starts


def _rz(phi: float) -> pin.SE3:
    return pin.SE3(pin.exp3(np.array([0.0, 0.0, phi])), np.zeros(3))


def _frame_from_axis(point: np.ndarray, direction: np.ndarray, toward: np.ndarray | None = None) -> pin.SE3:
    """A frame with origin `point`, z along `direction`, x toward `toward` (or B's x / y)."""
    z = np.asarray(direction, dtype=float)
    nz = np.linalg.norm(z)
    if not np.isfinite(nz) or nz < 1e-12:
        raise LoopError("hinge axis direction must be a non-zero vector")
    z = z / nz
    cands = ([np.asarray(toward, dtype=float)] if toward is not None else []) + [np.eye(3)[0], np.eye(3)[1]]
    for e in cands:
        x = e - (e @ z) * z
        if np.linalg.norm(x) > 1e-6 * max(float(np.linalg.norm(e)), 1e-300):
            break
    x = x / np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return pin.SE3(R, np.asarray(point, dtype=float).copy())


#: a tool position further from the fitted arc than this many times the positions' median distance is
#: left out of the hinge's start (a corrupted reading); a start only: every row stays in the fit
ARC_OUTLIER = 8.0


def _arc(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plane and circle through positions P (n, 3): (centre, unit normal, in-plane axes (2, 3), the
    singular values of the centred positions).  Plane: the smallest singular vector; circle: the algebraic
    (Kasa) fit in that plane."""
    c = P.mean(axis=0)
    _, S, Vt = np.linalg.svd(P - c, full_matrices=len(P) < 3)  # (not U: n x n, 13 GB at 40,000 positions)
    e1, e2 = Vt[0], np.cross(Vt[2], Vt[0])
    uv = np.column_stack([(P - c) @ e1, (P - c) @ e2])
    A = np.column_stack([2 * uv, np.ones(len(P))])
    sol = np.linalg.lstsq(A, (uv**2).sum(axis=1), rcond=None)[0]
    return c + sol[0] * e1 + sol[1] * e2, Vt[2], np.array([e1, e2]), S


#: a position this near the arc (times its radius) is on it, however close the others lie
ARC_NEAR = 0.01
#: circles through three positions tried by `arc_inliers` (fixed draws: the same start every run)
ARC_TRIALS = 64


def _deviation(P: np.ndarray, centre: np.ndarray, n: np.ndarray, radius: float) -> np.ndarray:
    """Distance of each position from the circle (centre, unit normal, radius): off its plane and off its radius."""
    d = P - centre
    off = d @ n
    return np.hypot(off, np.linalg.norm(d - np.outer(off, n), axis=1) - radius)


def arc_inliers(P: np.ndarray) -> np.ndarray:
    """Which tool positions lie on one circle, by least median of distances: of `ARC_TRIALS` circles
    through three positions, the one whose median distance to all positions is least; the positions
    within `ARC_OUTLIER` times that median of it (or `ARC_NEAR` times its radius) are on the arc.  A corrupted reading (one in ten, or
    more) draws a least-squares circle toward it far enough to hide; the median circle is that of the
    others; the circle fitted to its nearer half then sets the distances."""
    n = len(P)
    if n < 5:
        return np.ones(n, dtype=bool)
    rng = np.random.default_rng(0)
    best, dev_best = np.inf, None
    for _ in range(ARC_TRIALS):
        i, j, k = rng.choice(n, 3, replace=False)
        a, b = P[i] - P[k], P[j] - P[k]
        axb = np.cross(a, b)
        nn = float(axb @ axb)
        if nn <= 1e-24 * max(float(a @ a) * float(b @ b), 1e-300):
            continue  # three positions on a line
        centre = P[k] + np.cross(float(a @ a) * b - float(b @ b) * a, axb) / (2.0 * nn)
        dev = _deviation(P, centre, axb / np.sqrt(nn), float(np.linalg.norm(P[k] - centre)))
        med = float(np.median(dev))
        if med < best:
            best, dev_best = med, dev
    if dev_best is None:
        return np.ones(n, dtype=bool)
    keep = dev_best <= np.median(dev_best)  # the median circle's nearer half; then the circle fitted to them
    for _ in range(2):
        centre, normal, _, _ = _arc(P[keep])
        radius = float(
            np.median(np.linalg.norm((P[keep] - centre) - np.outer((P[keep] - centre) @ normal, normal), axis=1))
        )
        dev = _deviation(P, centre, normal, radius)
        keep = dev <= max(ARC_OUTLIER * float(np.median(dev[keep])), ARC_NEAR * radius)
    return keep if keep.sum() >= 3 else np.ones(n, dtype=bool)


def fit_hinge_axis(M: list[pin.SE3] | np.ndarray) -> pin.SE3:
    """Hinge frame from tool poses in B (SE3s, or a stack (N, 4, 4)): the circle traced by the tool origin.

    Axis direction: normal of the best-fit plane of the positions (smallest
    singular vector), oriented like the rotation the tool turns through
    (log3 of R_i R_0^T, which is about the hinge axis); centre: algebraic
    (Kasa) circle fit in that plane.  Positions off the arc of the others (a corrupted reading:
    `arc_inliers`) take no part; x points at the first position on the arc.
    """
    T = np.array([m.homogeneous for m in M]) if isinstance(M, list) else np.asarray(M, dtype=float)
    P = T[:, :3, 3]
    keep = arc_inliers(P)
    on = np.flatnonzero(keep)
    centre, n, _, S = _arc(P[keep])
    if S.size < 2 or S[1] < 1e-4:
        raise LoopError(
            "hinge: the tool positions do not trace an arc (the door hardly moves); "
            'give the axis (axis="px py pz dx dy dz")'
        )
    w = log3(T[on, :3, :3] @ T[on[0], :3, :3].T)[0]
    big = int(np.argmax(np.linalg.norm(w, axis=1)))
    if np.linalg.norm(w[big]) > 1e-6 and n @ w[big] < 0:
        n = -n
    return _frame_from_axis(centre, n, P[on[0]] - centre)


# --------------------------------------------------------------------- loop
class HingeLoop(Loop):
    """Tool on a door handle turning about an unknown hinge: 6 rows, 1 DOF projected out.

    `axis` (point, direction) in frame B, if given, is the reference line H0
    of the chart and the initial hinge; otherwise `prepare` returns a copy
    whose H0 is fitted to the data (needs >= 3 configurations spread along the
    arc).  The loop object is never changed.
    """

    translation_rows = (0, 1, 2)
    rotation_rows = (3, 4, 5)

    def __init__(
        self, name: str, frame_a: str, frame_b: str = "universe", axis: tuple[np.ndarray, np.ndarray] | None = None
    ):
        super().__init__(name, frame_a, frame_b)
        self.axis = axis
        self.H0 = _frame_from_axis(axis[0], axis[1]) if axis is not None else pin.SE3.Identity()
        self.fitted = False  # H0 read off the data by `prepare` (a prepared copy)

    @property
    def dim(self) -> int:
        return 6

    # ------------------------------------------------------------ parameters
    def parameters(self) -> list[Parameter]:
        out = []
        for k, f in enumerate(HINGE_FIELDS):
            unit = "rad" if f in ("hinge_rx", "hinge_ry", "grasp_rx", "grasp_ry", "grasp_rz") else "m"
            val = 0.0
            swl = 0.0
            if f in ("hinge_x", "hinge_y"):
                u = self.H0.rotation.T @ self.H0.translation  # H0's origin, in H0 axes
                swl = float(u[k])  # exact at zero tilt: the point scales with the world
            out.append(
                Parameter(
                    f"{self.name}.{f}",
                    "loop",
                    self.name,
                    f,
                    val,
                    unit,
                    DEFAULT_PRIORS["loop_m" if unit == "m" else "loop_rad"],
                    scales_with_length=swl,
                    priority=1,
                    order=k,
                )
            )
        return out

    def hinge(self, p: np.ndarray) -> pin.SE3:
        """The hinge frame H (z = hinge axis) in B."""
        R = pin.exp3(np.array([p[2], p[3], 0.0]))
        return self.H0 * pin.SE3(R, R @ np.array([p[0], p[1], 0.0]))

    @staticmethod
    def grasp(p: np.ndarray) -> pin.SE3:
        """The handle frame in the door frame."""
        return pin.SE3(pin.exp3(p[6:9]), np.array([p[4], 0.0, p[5]]))

    def line(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hinge axis in B: (point nearest B's origin, unit direction)."""
        H = self.hinge(p)
        d = H.rotation[:, 2]
        o = H.translation
        return o - (o @ d) * d, d

    def closing_parameters(self, line: np.ndarray, M: pin.SE3) -> np.ndarray:
        """Parameters with hinge `line` (4) whose orbit passes through pose M = T_B^-1 T_A."""
        p = np.zeros(9)
        p[:4] = line
        Gf = self.hinge(p).actInv(M)  # handle in the hinge frame at phi = 0
        t = Gf.translation
        G = _rz(-np.arctan2(t[1], t[0])) * Gf  # turn so that the handle lies on x
        p[4], p[5] = G.translation[0], G.translation[2]
        p[6:9] = pin.log3(G.rotation)
        return p

    def prepare(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> "HingeLoop":
        """A copy whose chart reference H0 is the hinge fitted to the tool's circle (`fit_hinge_axis`).

        With `axis=` given, or already prepared: `self`.  The parameters'
        length content (`parameters`, scales_with_length) is H0's, so a problem
        is built on the prepared loop.
        """
        if self.axis is not None or self.fitted:
            return self
        M = relative(TA, TB)
        if len(M) < 3:
            raise LoopError(
                f"hinge loop '{self.name}': cannot fit the hinge axis from {len(M)} "
                'configuration(s); give axis="px py pz dx dy dz" or log at least 3 along the arc'
            )
        other = copy.copy(self)
        try:
            other.H0, other.fitted = fit_hinge_axis(M), True
        except LoopError as exc:  # the door does not move: a weld, if the orientation does not either
            w = log3(M[:, :3, :3] @ M[0, :3, :3].T)[0]
            if float(np.sqrt(np.mean(np.sum(w**2, axis=1)))) < HELD_STILL:
                raise LoopError(
                    f"loop '{self.name}' (hinge on {self.frame_a}): neither the position nor the orientation of "
                    f"the frame moves across the rows at the nominal model: is this a weld? --loop {self.spec('weld')}"
                ) from None
            raise LoopError(f"loop '{self.name}' ({exc})") from None
        return other

    def initialize(self, TA: np.ndarray, TB: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray | None:
        """Hinge and grasp closing a typical configuration: the hinge is H0 once prepared (or given);
        an unprepared loop fits it here and gives its coordinates in its own chart.

        The configuration closed is the one whose handle lies nearest the median radius and height about
        H0's axis: never a corrupted reading that puts the handle elsewhere (the first one may be)."""
        if self.axis is None and not self.fitted:
            prepared = self.prepare(TA, TB)
            return prepared.express(prepared._closing_typical(TA, TB), self)
        return self._closing_typical(TA, TB)

    def _closing_typical(self, TA: np.ndarray, TB: np.ndarray) -> np.ndarray:
        """`initialize` about H0: the parameters closing the typical configuration."""
        M = np.linalg.solve(TB, TA)
        q = rigid_inverse(self.H0.homogeneous[None]) @ M
        radius, height = np.hypot(q[:, 0, 3], q[:, 1, 3]), q[:, 2, 3]
        typical = int(np.argmin(np.abs(radius - np.median(radius)) + np.abs(height - np.median(height))))
        return self.closing_parameters(np.zeros(4), pin.SE3(M[typical]))

    def normalize(self, p: np.ndarray) -> np.ndarray:
        """Grasp rotation within pi; a negative radius becomes positive (phi shifted by pi)."""
        q = np.array(p, dtype=float)
        G = self.grasp(q)
        if q[4] < 0:
            G = _rz(np.pi) * G
        q[4], q[5] = G.translation[0], G.translation[2]
        q[6:9] = pin.log3(G.rotation)
        return q

    def recentred(self, p: np.ndarray) -> tuple["HingeLoop", np.ndarray] | None:
        """The chart re-centred on the current hinge frame once it is RECENTRE m or rad off H0 (`Loop.recentred`)."""
        if np.abs(p[:4]).max() <= RECENTRE:
            return None
        other = copy.copy(self)
        other.H0, other.fitted = self.hinge(p), True
        q = np.array(p, dtype=float)
        q[:4] = 0.0
        return other, q

    def express(self, p: np.ndarray, other: Loop) -> np.ndarray:
        """The same line and grasp in the chart of `other` (`Loop.express`).

        With L = H0'^-1 H, the chart's rotation is the one about an axis normal
        to z taking z to L's axis d; the line's point nearest H0' gives (x, y);
        what is left of L is Rz(a) Tz(h): a shifts the eliminated angle, h
        the handle's height.
        """
        assert isinstance(other, HingeLoop)  # expressed in another hinge loop's chart
        L = other.H0.actInv(self.hinge(p))
        d = L.rotation[:, 2]
        w = np.array([-d[1], d[0], 0.0])  # z x d
        s = float(np.linalg.norm(w))
        rv = w * (np.arctan2(s, d[2]) / s) if s > 1e-12 else np.zeros(3)
        u = pin.exp3(rv).T @ L.translation
        q = np.array(p, dtype=float)
        q[:4] = u[0], u[1], rv[0], rv[1]
        q[5] += u[2]
        return q

    def describe(self) -> dict:
        return super().describe() | {
            "reference_axis": {"point": self.H0.translation.tolist(), "direction": self.H0.rotation[:, 2].tolist()}
        }

    # ------------------------------------------------------------ evaluation
    def solve_angles(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The eliminated hinge angles phi_i* (N,)."""
        return self._eliminate(relative(TA, TB), p).phi[:, 0]

    def _eliminate(self, M: np.ndarray, p: np.ndarray) -> Elimination:
        """phi_i* for M_i = T_B^-1 T_A (N, 4, 4), all configurations at once (`projection.eliminate`)."""
        H, G = self.hinge(p), self.grasp(p)
        return eliminate(M, hinge_pose_fn(H, G), hinge_starts(M, H, G))

    def residual(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> np.ndarray:
        """`evaluate`'s residual P r(phi*) alone."""
        el = self._eliminate(relative(TA, TB), p)
        return np.einsum("nij,nj->ni", projector(el.Jphi), el.r)

    def evaluate(self, TA: np.ndarray, TB: np.ndarray, p: np.ndarray, meas: np.ndarray | None = None) -> LoopEval:
        G = self.grasp(p)
        # right twists of X = H Rz(phi) G per parameter
        gen_h = np.zeros((6, 4))
        Jr = pin.Jexp3(np.array([p[2], p[3], 0.0]))[:, :2]
        gen_h[0, 0] = gen_h[1, 1] = 1.0
        gen_h[:3, 2:] = -pin.skew(np.array([p[0], p[1], 0.0])) @ Jr
        gen_h[3:, 2:] = Jr
        gen_g = np.zeros((6, 5))
        gen_g[:3, 0] = G.rotation.T[:, 0]
        gen_g[:3, 1] = G.rotation.T[:, 2]
        gen_g[3:, 2:] = pin.Jexp3(p[6:9])
        el = self._eliminate(relative(TA, TB), p)
        Pp = projector(el.Jphi)
        dA = Pp @ el.Jl
        dX = -dA @ adjoint(rigid_inverse(el.E))
        r = np.einsum("nij,nj->ni", Pp, el.r)  # exactly orthogonal to J_phi (a last linearised step, O(|dphi|))
        dB = -dA @ adjoint(rigid_inverse(TA) @ TB)
        Ginv_rz = adjoint(rigid_inverse(_rz_stack(el.phi[:, 0]) @ G.homogeneous))  # H's twist seen from X
        dp = np.concatenate([dX @ (Ginv_rz @ gen_h), dX @ gen_g], axis=2)
        return LoopEval(r, dA, dB, dp, iterations=int(el.iterations.max(initial=0)))


def parse_axis(text: str) -> tuple[np.ndarray, np.ndarray]:
    """'px py pz dx dy dz' -> (point, direction)."""
    try:
        v = np.array([float(t) for t in text.replace(",", " ").split()])
    except ValueError:
        raise LoopError(f"axis '{text}': expected six numbers 'px py pz dx dy dz'") from None
    if v.size != 6 or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-12:
        raise LoopError(f"axis '{text}': expected six finite numbers 'px py pz dx dy dz', direction non-zero")
    return v[:3], v[3:]


@register("hinge", {"frame", "to", "axis"})
def _hinge(kw: dict[str, str], robot) -> Loop:
    """hinge:frame=<tool>[,to=<frame>][,axis="px py pz dx dy dz"][,name=door]"""
    if "frame" not in kw:
        raise LoopError("hinge loop needs frame=<tool frame>")
    axis = parse_axis(kw["axis"]) if "axis" in kw else None
    return HingeLoop(kw.get("name", "hinge"), kw["frame"], kw.get("to", "universe"), axis=axis)
