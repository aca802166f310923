"""`se3.relative`: T_B^-1 T_A, with the base's broadcast identity taken as it is (no product)."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.model.se3 import relative, rigid_inverse


def test_relative_is_the_product_and_skips_the_bases_identity():
    rng = np.random.default_rng(0)

    def pose() -> np.ndarray:
        return pin.SE3(pin.exp3(rng.normal(0.0, 1.0, 3)), rng.normal(0.0, 0.5, 3)).homogeneous

    TA = np.stack([pose() for _ in range(5)])
    TB = np.stack([pose() for _ in range(5)])
    assert np.allclose(relative(TA, TB), rigid_inverse(TB) @ TA, rtol=0, atol=1e-14)
    base = np.broadcast_to(np.eye(4), TA.shape)  # frame 0's poses (`CalibrationProblem.frame_kinematics`)
    assert relative(TA, base) is TA
    eye = np.tile(np.eye(4), (5, 1, 1))  # an identity that is no broadcast: the product, the same value
    assert relative(TA, eye) is not TA and np.array_equal(relative(TA, eye), TA)
    other = np.broadcast_to(pose(), TA.shape)  # one pose broadcast, not the identity
    assert np.allclose(relative(TA, other), rigid_inverse(other) @ TA, rtol=0, atol=1e-14)
