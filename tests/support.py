"""Test support: an independent closed 7R D-H chain built from axis lines, and rotation distances.

Independent of closedloop: standard D-H frames from lines (Fig. 3-2).  Frame
j-1 has z along axis j; x_j is the common normal of axes j and j+1 (axis 8 is
axis 1, so frame 7 is frame 0 and the chain closes, thesis Fig. 3-3).
"""

from __future__ import annotations

import numpy as np


def _common_normal(p1, d1, p2, d2):
    """Feet of the common normal on line 1 and line 2, and its unit direction."""
    n = np.cross(d1, d2)
    if np.linalg.norm(n) < 1e-9:
        raise ValueError("parallel axes")
    n /= np.linalg.norm(n)
    # p1 + t1 d1 + s n = p2 + t2 d2
    A = np.column_stack([d1, -d2, n])
    t1, t2, s = np.linalg.solve(A, p2 - p1)
    if s < 0:
        n, s = -n, -s
    return p1 + t1 * d1, p2 + t2 * d2, n


def closed_chain(rng: np.random.Generator, n: int = 7, spread: float = 0.4):
    """D-H rows (s, a, alpha) and the joint angles theta at which they close."""
    pts = [rng.normal(scale=spread, size=3) for _ in range(n)]
    dirs = [d / np.linalg.norm(d) for d in (rng.normal(size=3) for _ in range(n))]
    # frame j-1 (j = 1..n) has z along axis j; x_{j} = common normal (axis j -> axis j+1)
    feet = []
    for j in range(n):
        a_foot, b_foot, nrm = _common_normal(pts[j], dirs[j], pts[(j + 1) % n], dirs[(j + 1) % n])
        feet.append((a_foot, b_foot, nrm))
    # frame k (k = 0..n-1): z = dirs[k], x = normal between axis k and axis k+1?  D-H: x_k is the normal
    # from z_{k-1} to z_k, origin on z_k.  With z_k = axis k+1, x_k = normal(axis k -> axis k+1).
    frames = []
    for k in range(n):
        a_foot, b_foot, nrm = feet[(k - 1) % n]  # normal from axis k (index k-1) to axis k+1 (index k)
        z = dirs[k]
        x = nrm
        y = np.cross(z, x)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, y, z])
        T[:3, 3] = b_foot
        frames.append(T)
    rows, theta = [], []
    for j in range(1, n + 1):
        T0 = frames[j - 1]
        T1 = frames[j % n]
        rel = np.linalg.solve(T0, T1)  # A_j = Rot(z,th) Trans(z,s) Trans(x,a) Rot(x,alpha)
        th = np.arctan2(rel[1, 0], rel[0, 0])
        s = rel[2, 3]
        a = np.hypot(rel[0, 3], rel[1, 3]) * np.sign(rel[0, 3] * np.cos(th) + rel[1, 3] * np.sin(th))
        alpha = np.arctan2(rel[2, 1], rel[2, 2])
        rows.append((float(s), float(a), float(alpha)))
        theta.append(float(th))
    return rows, np.array(theta)


def dh_transform(th, s, a, alpha):
    c, sn = np.cos(th), np.sin(th)
    ca, sa = np.cos(alpha), np.sin(alpha)
    return np.array([[c, -sn * ca, sn * sa, a * c], [sn, c * ca, -c * sa, a * sn], [0, sa, ca, s], [0, 0, 0, 1]])


def geodesic(r1, r2) -> float:
    """Angle between two rotations given as rotation vectors."""
    import pinocchio as pin

    return float(np.linalg.norm(pin.log3(pin.exp3(np.asarray(r1, float)).T @ pin.exp3(np.asarray(r2, float)))))


def relative_fk_error(
    res,
    truth_values,
    frame_a: str,
    frame_b: str,
    n: int = 60,
    seed: int = 0,
    fit_scale: bool = True,
    tip: str | None = None,
) -> tuple[float, float, float]:
    """Gauge-free comparison of a calibration with a truth: what the robot does, not its parameters.

    The pose of frame A in frame B at `n` random readings (within the loop
    joints' ranges), from the calibrated parameters and from `truth_values`
    (a full parameter vector of the same problem).  Positions are compared
    after the best scale s (only the loop's length scale is a free gauge of a
    closed loop: base and tool are inside the relative pose), rotations as
    they are.  With `tip` (the loop's name of a point loop) only the point
    T_B^-1 T_A tip is compared, each model with its own tip (a ball joint
    leaves the orientation free).  Returns (max position error [m], max
    rotation error [rad], s).
    """
    import pinocchio as pin

    prob = res.problem
    rng = np.random.default_rng(seed)
    lo = np.array([max(prob.robot.joint(j).lower, -np.pi) for j in prob.joints])
    hi = np.array([min(prob.robot.joint(j).upper, np.pi) for j in prob.joints])
    readings = rng.uniform(lo, hi, (n, len(prob.joints)))

    def poses(values):
        state = prob.rp.apply(np.asarray(values)[: prob.n_robot])
        q = prob.robot.configurations(readings * state.scale + state.offset, prob.joints)
        fa, fb = prob.robot.frame_id(frame_a), prob.robot.frame_id(frame_b)
        out = []
        for qi in q:
            pin.forwardKinematics(state.model, state.data, qi)
            out.append(
                pin.updateFramePlacement(state.model, state.data, fb).actInv(
                    pin.updateFramePlacement(state.model, state.data, fa)
                )
            )
        return out

    cal, tru = poses(res.fit.values), poses(truth_values)
    if tip is not None:
        idx = [prob.index[f"{tip}.tip_{a}"] for a in "xyz"]
        tc, tt = np.asarray(res.fit.values)[idx], np.asarray(truth_values)[idx]
        P = np.array([m.act(tc) for m in cal])
        Q = np.array([m.act(tt) for m in tru])
        s = float(np.sum(P * Q) / np.sum(P * P)) if fit_scale else 1.0
        return float(np.abs(s * P - Q).max()), 0.0, s
    P = np.array([m.translation for m in cal])
    Q = np.array([m.translation for m in tru])
    s = float(np.sum(P * Q) / np.sum(P * P)) if fit_scale else 1.0
    pos = float(np.abs(s * P - Q).max())
    rot = max(float(np.linalg.norm(pin.log3(a.rotation.T @ b.rotation))) for a, b in zip(cal, tru))
    return pos, rot, s


def central_difference_jacobian(prob, x, h: float = 1e-6):
    """(analytic, numerical) d r / d parameters of `prob` at `x`: `evaluate`'s Jacobian and central
    differences of its residual, both (rows, P)."""
    import numpy as np

    J = prob.evaluate(x)[0].J.reshape(-1, x.size)
    Jn = np.zeros_like(J)
    for k in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (prob.evaluate(xp, False)[0].r.ravel() - prob.evaluate(xm, False)[0].r.ravel()) / (2 * h)
    return J, Jn


def calibrated_names(robot, loops, theta0, options=None, n: int = 30, seed: int = 0) -> list[str]:
    """The robot parameters `calibrate` estimates for `loops` on the nominal robot's exact self-motion
    through `theta0` (n configurations per loop, random walk `seed`): what a calibration actually does,
    against which the structural reading (`closedloop.studies.identifiable.identifiable_names`, same walk)
    is checked."""
    from closedloop.calibration.pipeline import calibrate
    from closedloop.io.logs import JointLog
    from closedloop.studies.identifiable import loop_joints, nominal_walks

    walks = nominal_walks(robot, loops, theta0, n, seed)
    rows = np.vstack(walks)
    loop_col = np.repeat([lp.name for lp in loops], [len(w) for w in walks]) if len(loops) > 1 else None
    res = calibrate(robot, JointLog(loop_joints(robot, loops), rows, None, loop_col), loops, options)
    own = tuple(f"{lp.name}." for lp in loops)
    return [m for m, s in zip(res.fit.names, res.fit.status) if s == "estimated" and not m.startswith(own)]
