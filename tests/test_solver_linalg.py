"""The solver's reduced linear algebra (issue 17): TSQR triangle, SVD of the triangle, no U ever formed.

Checked against numpy's full SVD / lstsq on the same matrices, and the LM solution
against the closed-form least-squares one.
"""

from __future__ import annotations

import numpy as np

from closedloop.qr import r_factor
from closedloop.solver import SolverOptions, levenberg_marquardt, scaled_svd


def _tall(rng: np.random.Generator, m: int = 5000, n: int = 27, cond: float = 1e6) -> np.ndarray:
    Q, _ = np.linalg.qr(rng.normal(size=(m, n)))
    V, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Q * np.logspace(0, -np.log10(cond), n)) @ V.T


def test_scaled_svd_matches_full_svd():
    rng = np.random.default_rng(0)
    J = _tall(rng)
    r = rng.normal(size=J.shape[0])
    scale = np.exp(rng.normal(size=J.shape[1]))
    S, Vt, g = scaled_svd(J, r, scale)
    U0, S0, Vt0 = np.linalg.svd(J * scale, full_matrices=False)
    assert np.allclose(S, S0, rtol=1e-12, atol=1e-14 * S0[0])  # backward-stable: errors ~ eps s_max
    # singular vectors up to sign: compare the projections they define
    signs = np.sign(np.sum(Vt * Vt0, axis=1))
    assert np.max(np.abs(Vt * signs[:, None] - Vt0)[:20]) < 1e-9  # well-separated directions
    assert np.allclose(g * signs, U0.T @ r, rtol=1e-9, atol=1e-12 * np.linalg.norm(r))


def test_r_factor_keeps_every_column_relation():
    rng = np.random.default_rng(1)
    A = _tall(rng, 4000, 12, 1e4)
    A[:, 5] = A[:, 1] - 2.0 * A[:, 3]  # an exact dependency
    R = r_factor(A)
    assert R.shape == (12, 12)
    assert np.allclose(R.T @ R, A.T @ A, rtol=0, atol=1e-12 * np.abs(A.T @ A).max())
    x_a = np.linalg.lstsq(np.delete(A, 5, axis=1), A[:, 5], rcond=None)[0]
    x_r = np.linalg.lstsq(np.delete(R, 5, axis=1), R[:, 5], rcond=None)[0]
    assert np.allclose(x_r, x_a, atol=1e-9)
    assert np.allclose(x_a[[1, 3]], [1.0, -2.0], atol=1e-9)  # columns 1 and 3 (before column 5)


def test_levenberg_marquardt_on_linear_least_squares_is_exact():
    rng = np.random.default_rng(2)
    A = _tall(rng, 3000, 10, 1e3)
    b = rng.normal(size=3000)
    x_star = np.linalg.lstsq(A, b, rcond=None)[0]
    res = levenberg_marquardt(lambda x, jac: (A @ x - b, A if jac else None), np.zeros(10), np.ones(10),
                              SolverOptions(noise=1e-12))
    assert res.status == "converged"
    assert np.allclose(res.x, x_star, rtol=1e-10, atol=1e-10 * np.abs(x_star).max())
