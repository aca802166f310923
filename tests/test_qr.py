"""`closedloop.estimate.qr`: the triangular factors against numpy's QR, chunked and not, with and without LAPACK's dgeqrf."""

from __future__ import annotations

import numpy as np
import pytest

import closedloop.estimate.qr as qr


def _same_triangle(R, R_ref):
    """Equal up to the signs of the rows (a QR factor's only freedom), to round-off; a matrix not taller than
    wide is its own factor (the same R^T R)."""
    if R.shape[0] > R.shape[1] or np.allclose(np.tril(R, -1), 0.0):
        assert R.shape == R_ref.shape
        np.testing.assert_allclose(np.abs(R), np.abs(R_ref), rtol=0, atol=1e-12 * np.abs(R_ref).max())
    np.testing.assert_allclose(R.T @ R, R_ref.T @ R_ref, rtol=0, atol=1e-11 * np.abs(R_ref).max() ** 2)


@pytest.mark.parametrize("lapack", [True, False])
@pytest.mark.parametrize("rows", [40, 29, 1000, 3 * qr.CHUNK_ROWS + 17])
def test_scaled_factors_match_numpy(monkeypatch, lapack, rows):
    if not lapack:
        monkeypatch.setattr(qr, "_dgeqrf", None)
    rng = np.random.default_rng(rows)
    J = rng.normal(size=(rows, 28)) * np.logspace(0, -6, 28)  # columns of very different sizes
    r = rng.normal(size=rows)
    scale = rng.uniform(0.1, 10.0, 28)
    A = np.column_stack([J * scale, r])
    ref = np.linalg.qr(A, mode="r")
    _same_triangle(qr.scaled_r_factor(J, r, scale), ref)
    _same_triangle(qr.r_factor(A), ref)
    blocks = [J[: rows // 2 // 6 * 6].reshape(-1, 6, 28), J[rows // 2 // 6 * 6 :].reshape(-1, 1, 28)]
    _same_triangle(qr.scaled_r_factor_of_blocks(blocks, scale), np.linalg.qr(J * scale, mode="r"))


def test_short_matrices_are_returned_as_they_are():
    A = np.arange(12.0).reshape(3, 4)
    assert np.array_equal(qr.r_factor(A), A)
    assert qr.scaled_r_factor_of_blocks([], np.ones(4)).shape == (0, 4)
