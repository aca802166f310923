"""The planar calibration example of thesis 2.5 (Figure 2-2), solved twice.

A 3-DOF planar arm (``assets/planar3.urdf``: revolute joints about z, links
along x) holds its tip at a fixed point of the ground.  The ground is the
fourth link, of length a4: the tip is pinned at (-a4, 0), so with
phi_j = theta_1 + ... + theta_j the closure equations are (2.1)-(2.2)

    a1 cos(phi1) + a2 cos(phi2) + a3 cos(phi3) + a4 = 0
    a1 sin(phi1) + a2 sin(phi2) + a3 sin(phi3)      = 0

They are LINEAR in the link lengths.  Fixing a4 = 1 (the length scale, 3.3)
and stacking configurations gives 0 = C phi + y (2.4), phi = (a1, a2, a3),
y = (a4, 0, a4, 0, ...), C as in (2.5), solved by least squares (2.5).

1. ``linear_solution``: that linear system, written out here, independent of
   the library.
2. ``general_solution``: the library's nonlinear calibration of the same
   problem, a ``PointLoop`` from frame ``link3`` (tip unknown: its x is a3)
   to the known ground point (-a4, 0, 0), identifying a1 - a1_nom =
   ``joint2.x``, a2 - a2_nom = ``joint3.x`` and a3 = ``ground.tip_x`` (the
   lateral tip offsets ``tip_y``, ``tip_z`` are held at 0 as in the thesis's
   model, and the joint readings are exact: no offsets).

On noise-free data the two agree to round-off.  ``parallelogram_data``
produces the mechanism of Singularity 4 (3.3.1): a1 = a3 and a2 = a4, so the
four-bar is a parallelogram and opposite sides stay parallel (x1 + x3 = 0,
the analogue of eq. 3.23 for this labelling); the columns of C for a1 and a3
are then opposite, only a1 - a3 is determined, and the library reports the
combination of ``joint2.x`` and ``ground.tip_x`` it cannot separate.

Run:  python examples/planar_ground_contact.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.io.logs import JointLog
from closedloop.loops.point import PointLoop
from closedloop.model.robot import RobotModel

URDF = Path(__file__).resolve().parents[1] / "closedloop" / "assets" / "planar3.urdf"
NOMINAL = np.array([1.0, 0.8, 0.6])  # a1, a2, a3 of the URDF
JOINTS = ["joint1", "joint2", "joint3"]


def phis(theta: np.ndarray) -> np.ndarray:
    """phi_j = theta_1 + ... + theta_j (N, 3)."""
    return np.cumsum(theta, axis=1)


def closure_data(a: np.ndarray, a4: float, theta1: np.ndarray, elbow: float = 1.0) -> np.ndarray:
    """Joint angles (N, 3) that pin the tip at (-a4, 0): two-link inverse kinematics from joint 2."""
    a1, a2, a3 = a
    out = []
    for t1 in theta1:
        P1 = a1 * np.array([np.cos(t1), np.sin(t1)])
        d = np.array([-a4, 0.0]) - P1
        D = np.linalg.norm(d)
        c = (a2**2 + D**2 - a3**2) / (2 * a2 * D)
        if abs(c) > 1:
            raise ValueError(f"theta1 = {t1}: the ground point is out of reach")
        phi2 = np.arctan2(d[1], d[0]) - elbow * np.arccos(c)
        P2 = P1 + a2 * np.array([np.cos(phi2), np.sin(phi2)])
        e3 = np.array([-a4, 0.0]) - P2
        phi3 = np.arctan2(e3[1], e3[0])
        th = np.array([t1, phi2 - t1, phi3 - phi2])
        out.append(np.arctan2(np.sin(th), np.cos(th)))
    return np.array(out)


def parallelogram_data(a1: float, a4: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Truth (a1, a4, a1) and joint angles of the parallelogram: phi1 = t, phi2 = pi, phi3 = t + pi."""
    theta = np.column_stack([t, np.pi - t, t])
    return np.array([a1, a4, a1]), theta


def linear_system(theta: np.ndarray, a4: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """C (2N, 3) and y (2N,) of eqs. (2.4)-(2.5)."""
    ph = phis(theta)
    C = np.empty((2 * len(theta), 3))
    C[0::2] = np.cos(ph)
    C[1::2] = np.sin(ph)
    y = np.zeros(2 * len(theta))
    y[0::2] = a4
    return C, y


def linear_solution(theta: np.ndarray, a4: float = 1.0) -> np.ndarray:
    """phi = (C^T C)^-1 C^T (-y), the least-squares solution of 2.5."""
    C, y = linear_system(theta, a4)
    return np.linalg.solve(C.T @ C, C.T @ (-y))


def general_solution(theta: np.ndarray, a4: float = 1.0, **options):
    """The library's calibration of the same problem; returns ((a1, a2, a3), result)."""
    robot = RobotModel.from_file(URDF)
    loop = PointLoop(
        "ground", "link3", point=[-a4, 0.0, 0.0], initial_tip=[NOMINAL[2], 0.0, 0.0], prior=0.01
    )  # a3 is a link length like a1, a2: same prior
    opt = CalibrationOptions(
        identify=["joint2.x", "joint3.x", "loop"],
        fix={"ground.tip_y": 0.0, "ground.tip_z": 0.0},
        weighting="none",
        **options,
    )
    res = calibrate(robot, JointLog(JOINTS, theta), [loop], opt)
    a = np.array([NOMINAL[0] + res.value("joint2.x"), NOMINAL[1] + res.value("joint3.x"), res.value("ground.tip_x")])
    return a, res


def main() -> None:
    truth = np.array([1.05, 0.75, 0.65])
    theta = closure_data(truth, 1.0, np.linspace(1.8, 2.9, 25))
    a_lin = linear_solution(theta)
    a_gen, res = general_solution(theta)
    print("truth          a1 a2 a3 =", truth)
    print("linear (2.5)   a1 a2 a3 =", a_lin, " |err| =", np.abs(a_lin - truth).max())
    print("general solver a1 a2 a3 =", a_gen, " |lin - gen| =", np.abs(a_lin - a_gen).max())
    print(
        "  status:", ", ".join(f"{n} {s.value}" for n, s in zip(res.fit.names, res.fit.status) if s != "not selected")
    )

    a_par, th_par = parallelogram_data(0.7, 1.0, np.linspace(0.3, 1.3, 25))
    C, _ = linear_system(th_par)
    print("\nparallelogram (Singularity 4): singular values of C =", np.linalg.svd(C, compute_uv=False))
    a_p, res = general_solution(th_par)
    chosen = ", ".join(f"{n} {s.value}" for n, s in zip(res.fit.names, res.fit.status) if s != "not selected")
    print("  truth", a_par, "estimate", a_p, "status:", chosen)
    for d in res.identifiability.dropped:
        print("  dropped:", d.describe())
    for c in res.identifiability.weak:
        print("  weak:", c.describe())


if __name__ == "__main__":
    main()
