"""`closedloop.model.se3` by itself: the batched log3 / log6 / Jlog6 against Pinocchio's, pose by pose (moved
from test_se3_batched.py, assertions unchanged), the adjoints, inverses and charts against Pinocchio,
the rigid and hand-eye fits, and the parsing of user poses and vectors."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.errors import InputError, LoopError
from closedloop.model.se3 import (
    adjoint,
    as_se3,
    generators,
    hand_eye,
    kabsch,
    log3,
    log6,
    parse_pose,
    parse_vec,
    pose_of,
    project_so3,
    rigid_inverse,
    skew,
    vec3,
    vec_of,
)


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


def test_adjoint_and_inverse_match_pinocchio():
    T = np.array([pin.SE3.Random().homogeneous for _ in range(50)])
    Ad = adjoint(T)
    Ti = rigid_inverse(T)
    for k in range(T.shape[0]):
        X = pin.SE3(T[k])
        assert np.abs(Ad[k] - X.action).max() < 1e-14
        assert np.abs(Ti[k] - X.inverse().homogeneous).max() < 1e-14
    assert adjoint(T[0]).shape == (6, 6) and rigid_inverse(T[None])[0].shape == (50, 4, 4)


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(1)
    v, u = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    assert np.abs(np.einsum("nij,nj->ni", skew(v), u) - np.cross(v, u)).max() < 1e-15
    S = skew(v[0])
    assert S.shape == (3, 3) and np.array_equal(S, -S.T)


def test_pose_chart_and_its_generators():
    """vec_of inverts pose_of; generators(v) maps dv to the right perturbation: X(v + dv) ~ X(v) exp6(G dv)."""
    rng = np.random.default_rng(2)
    for _ in range(20):
        v = np.concatenate([rng.normal(size=3), rng.uniform(-1.0, 1.0, size=3) * 2.5 / np.sqrt(3)])
        X = pose_of(v)
        assert np.abs(vec_of(X) - v).max() < 1e-12
        G = generators(v)
        h = 1e-6
        for j in range(6):
            dv = np.zeros(6)
            dv[j] = h
            fd = (pin.log6(X.actInv(pose_of(v + dv))).vector - pin.log6(X.actInv(pose_of(v - dv))).vector) / (2 * h)
            assert np.abs(fd - G[:, j]).max() < 1e-8


def test_kabsch_recovers_a_rigid_motion_and_project_so3_a_rotation():
    rng = np.random.default_rng(3)
    X = pin.SE3.Random()
    m = rng.normal(size=(10, 3))
    y = m @ X.rotation.T + X.translation
    R, t = kabsch(m, y, np.eye(3))
    assert np.abs(R - X.rotation).max() < 1e-12 and np.abs(t - X.translation).max() < 1e-12
    R0 = pin.exp3(np.array([0.1, 0.2, 0.3]))
    R1, t1 = kabsch(m[:2], y[:2], R0)  # two points: the given rotation, the first point matched
    assert np.array_equal(R1, R0) and np.abs(R0 @ m[0] + t1 - y[0]).max() < 1e-12
    A = X.rotation + 1e-3 * rng.normal(size=(3, 3))
    Q = project_so3(A)
    assert np.abs(Q.T @ Q - np.eye(3)).max() < 1e-12 and abs(np.linalg.det(Q) - 1.0) < 1e-12
    assert np.abs(Q - X.rotation).max() < 1e-2
    assert np.abs(project_so3(X.rotation) - X.rotation).max() < 1e-12


def test_user_poses_and_vectors_parse_or_are_refused_by_name():
    X = pin.SE3.Random()
    assert as_se3(X, "base") is X
    assert np.abs(as_se3(X.homogeneous, "base").homogeneous - X.homogeneous).max() < 1e-15
    v = np.array([0.1, 0.2, 0.3, 0.0, 0.0, np.pi / 2])
    assert np.abs(as_se3(v, "base").homogeneous - pose_of(v).homogeneous).max() < 1e-15
    assert np.abs(parse_pose("0.1, 0.2 0.3 0 0 1.5707963267948966").homogeneous - pose_of(v).homogeneous).max() < 1e-15
    assert np.array_equal(parse_vec("1,2 3", 3, "tip"), [1.0, 2.0, 3.0])
    assert np.array_equal(vec3([1, 2, 3], "tip"), [1.0, 2.0, 3.0])
    for call, words in (
        (lambda: as_se3([1, 2, 3], "initial_base"), "initial_base"),
        (lambda: vec3([1, 2, np.nan], "tip"), "tip"),
        (lambda: parse_vec("1 2 x", 3, "point"), "point '1 2 x'"),
        (lambda: parse_vec("1 2", 3, "point"), "expected 3 finite numbers"),
        (lambda: parse_pose("0 0 0 0 0"), "closure '0 0 0 0 0'"),
    ):
        with pytest.raises(LoopError, match=words) as info:
            call()
        assert isinstance(info.value, InputError)


def test_hand_eye_recovers_both_unknown_poses():
    """W_i Y = X M_i: from six exact pairs the closed form gives X and Y; one rotation axis leaves it undetermined."""
    rng = np.random.default_rng(4)
    X, Y = pin.SE3.Random(), pin.SE3.Random()
    W = [pin.SE3.Random() for _ in range(6)]
    M = [X.inverse() * w * Y for w in W]
    Xe, Ye = hand_eye(W, M)
    assert np.abs(Xe.homogeneous - X.homogeneous).max() < 1e-9
    assert np.abs(Ye.homogeneous - Y.homogeneous).max() < 1e-9
    axis = rng.normal(size=3)
    W1 = [pin.SE3(pin.exp3(a * axis), rng.normal(size=3)) for a in (0.1, 0.7, 1.3)]
    assert hand_eye(W1, [X.inverse() * w * Y for w in W1]) is None
