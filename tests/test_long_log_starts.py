"""A loop's start read off a long log's poses (the hinge's arc, a contact's pivot and plane, a tracker's
hand-eye) in memory that grows with the rows, not their square: each once took the SVD of all the rows with
its full U (n x n: 13 GB at 40,000 configurations of a door, where the kernel killed the calibration)."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pinocchio as pin

from closedloop.loops.common import contact_fits
from closedloop.loops.hinge import fit_hinge_axis
from closedloop.model.se3 import hand_eye

ROWS = 20_000  # full U: 3.2 GB (the arc, the plane)
HAND_EYE_ROWS = 2_000  # full U: 2.6 GB (9 rows a pose)
LIMIT = 64 << 20  # bytes numpy may hold at once: the rows' own arrays, not their square


def _peak(fn, *args):
    tracemalloc.start()
    try:
        out = fn(*args)
        return out, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _door(rng: np.random.Generator) -> tuple[list[pin.SE3], np.ndarray, np.ndarray]:
    """A handle turning about a hinge through `centre` along `axis`, 0.7 m out, with 0.1 mm of noise."""
    axis = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    centre = np.array([0.5, 0.2, 0.3])
    start = pin.SE3(
        np.eye(3), centre + 0.7 * np.cross(axis, [1.0, 0.0, 0.0]) / np.linalg.norm(np.cross(axis, [1.0, 0.0, 0.0]))
    )
    poses = []
    for a in rng.uniform(0.0, 1.2, ROWS):
        turn = pin.SE3(pin.exp3(a * axis), np.zeros(3))
        about = pin.SE3(np.eye(3), centre) * turn * pin.SE3(np.eye(3), -centre)
        m = about * start
        poses.append(pin.SE3(m.rotation, m.translation + rng.normal(0.0, 1e-4, 3)))
    return poses, axis, centre


def test_hinge_start_on_a_long_log_in_memory_linear_in_its_rows():
    poses, axis, centre = _door(np.random.default_rng(0))
    H, peak = _peak(fit_hinge_axis, poses)
    assert peak < LIMIT, peak
    assert abs(abs(float(H.rotation[:, 2] @ axis)) - 1.0) < 1e-6  # the hinge's axis, found
    along = H.translation - centre
    assert np.linalg.norm(along - (along @ axis) * axis) < 1e-4  # on the hinge's line


def test_contact_and_hand_eye_starts_on_a_long_log_in_memory_linear_in_its_rows():
    rng = np.random.default_rng(1)
    M = np.stack([pin.SE3(pin.exp3(rng.normal(0.0, 0.5, 3)), rng.normal(0.0, 0.3, 3)).homogeneous for _ in range(ROWS)])
    fits, peak = _peak(contact_fits, M)
    assert peak < 4 * LIMIT and all(np.isfinite(fits)), peak  # (its own stacks: 6 x 6 per row)
    X, Y = pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.3])), np.array([0.4, 0.0, 0.2])), pin.SE3.Random()
    W = [pin.SE3(pin.exp3(rng.normal(0.0, 1.0, 3)), rng.normal(0.0, 0.5, 3)) for _ in range(HAND_EYE_ROWS)]
    Ms = [X.inverse() * w * Y for w in W]  # W_i Y = X M_i
    XY, peak = _peak(hand_eye, W, Ms)
    assert XY is not None and peak < 4 * LIMIT, peak
    assert np.allclose(XY[0].homogeneous, X.homogeneous, atol=1e-9) and np.allclose(
        XY[1].homogeneous, Y.homogeneous, atol=1e-9
    )
