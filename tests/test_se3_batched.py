"""The batched log3 / log6 / Jlog6 of `closedloop.loops.weld` against Pinocchio's, pose by pose."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.loops.weld import log3, log6


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _poses() -> np.ndarray:
    """Random poses, and rotations at and near 0 and pi (every branch of Pinocchio's formulas)."""
    rng = np.random.default_rng(0)
    poses = [pin.SE3.Random().homogeneous for _ in range(1000)]
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    for k, axis in enumerate(axes):
        eps = 10.0 ** -(k % 17)  # 1 ... 1e-16
        for angle in (np.pi - eps, np.pi, eps, 0.0, np.pi - 1e-3 * rng.random()):
            poses.append(_pose(pin.exp3(angle * axis), rng.normal(size=3)))
    for axis in np.eye(3):  # half turns about the frame axes: ties in the choice of the pivot
        for angle in (np.pi, -np.pi, np.pi - 1e-9):
            poses.append(_pose(pin.exp3(angle * axis), rng.normal(size=3)))
    for d in ([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]):
        poses.append(_pose(np.diag(d), rng.normal(size=3)))
    return np.array(poses)


def test_log6_and_jlog6_match_pinocchio():
    T = _poses()
    r, J = log6(T, jacobian=True)
    r_pin = np.array([pin.log6(pin.SE3(t)).vector for t in T])
    J_pin = np.array([pin.Jlog6(pin.SE3(t)) for t in T])
    assert np.abs(r - r_pin).max() < 1e-12
    assert np.abs(J - J_pin).max() < 1e-12
    assert np.array_equal(log6(T)[0], r)  # the residual alone is the same number
    w, theta = log3(T[:, :3, :3])
    assert np.abs(w - np.array([pin.log3(t[:3, :3]) for t in T])).max() < 1e-12
    assert np.all((theta >= 0.0) & (theta <= np.pi))
