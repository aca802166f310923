"""Joint-noise level beside a known measurement noise (closedloop.estimate.noise): synthetic residuals."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.estimate.noise import joint_variance_scale


def draw(rng, s, c, N=3000, m=3, nj=6):
    """Residuals r_i ~ N(0, s A_i + c I) with A_i = J_i J_i^T."""
    J = rng.normal(size=(N, m, nj))
    W = s * (J @ np.swapaxes(J, 1, 2)) + c * np.eye(m)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(W), rng.normal(size=(N, m)))
    return r, J


@pytest.mark.parametrize("s, c", [(1e-8, 1e-10), (1e-10, 1e-8), (1e-9, 1e-9)])
def test_recovers_joint_variance_beside_measurement_noise(s, c):
    r, J = draw(np.random.default_rng(1), s, c)
    est = joint_variance_scale([r], [J], [c * np.eye(3)], np.ones(6), 0)
    # 9,000 residual rows; where joint noise is 1 % of the measurement noise the estimate is poorer
    assert est == pytest.approx(s, rel=0.1 if s >= c else 0.25)


def test_noise_free_joints_give_zero_or_negligible():
    r, J = draw(np.random.default_rng(2), 0.0, 1e-10)
    est = joint_variance_scale([r], [J], [1e-10 * np.eye(3)], np.ones(6), 0)
    assert est < 1e-3 * 1e-10  # joint noise contributes less than 0.1 % of the measurement variance


def test_closed_loop_block_alone_is_the_usual_estimate():
    rng = np.random.default_rng(3)
    r, J = draw(rng, 4e-8, 0.0, N=2000, m=6, nj=7)
    est = joint_variance_scale([r], [J], [None], np.ones(7), 0)
    A = J @ np.swapaxes(J, 1, 2)
    direct = np.mean(np.einsum("ni,ni->n", r, np.linalg.solve(A, r[..., None])[..., 0])) / 6
    assert est == pytest.approx(direct, rel=1e-9) and est == pytest.approx(4e-8, rel=0.05)


def test_closed_and_measured_blocks_together_and_dof_correction():
    rng = np.random.default_rng(4)
    r1, J1 = draw(rng, 1e-8, 1e-10)
    r2, J2 = draw(rng, 1e-8, 0.0, m=6, nj=6)
    both = joint_variance_scale([r1, r2], [J1, J2], [1e-10 * np.eye(3), None], np.ones(6), 0)
    assert both == pytest.approx(1e-8, rel=0.05)
    # p fitted parameters: the fitted residual is smaller, so the estimate is scaled up by M / (M - p)
    fewer = joint_variance_scale([r2], [J2], [None], np.ones(6), 100)
    assert fewer == pytest.approx(
        joint_variance_scale([r2], [J2], [None], np.ones(6), 0) * r2.size / (r2.size - 100), rel=1e-9
    )
