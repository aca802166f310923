"""Triangular factors R of tall matrices (A = Q R, Q never formed).

A^T A = R^T R, so every question least squares asks about A's columns
(singular values and right singular vectors, a column's residual on the
others, null combinations, rank) has the same answer on R, at n rows instead
of A's thousands: the solver, the structure analysis and the standard errors
reduce once and analyse the triangle.

The rows are taken a chunk of CHUNK_ROWS at a time (a few MB: the chunk stays
in cache, and a long log never needs a second copy of its Jacobian); each
chunk is reduced by LAPACK's blocked Householder QR (dgeqrf, level-3 BLAS) and
the chunks' triangles, stacked, are reduced again (tall-skinny QR).  numpy's
own `qr` takes LAPACK's unblocked path on tall matrices (2.5x slower on a
6,000 x 28 Jacobian), so dgeqrf is called directly, through the LAPACK numpy
links (`numpy.linalg.lapack_lite`; `np.linalg.qr` where a numpy lacks it).
"""

from __future__ import annotations

from typing import Any, Callable, Iterator, cast

import numpy as np

_dgeqrf: Callable[..., Any] | None = None
_LAPACK_ERRORS: tuple[type[Exception], ...] = (TypeError,)  # a numpy whose binding takes other arguments
try:  # numpy's own LAPACK binding: no scipy.linalg import (0.27 s) on the command line's path
    from numpy.linalg import lapack_lite as _lapack_lite
except ImportError:  # pragma: no cover - numpy builds without it
    pass
else:
    _dgeqrf = _lapack_lite.dgeqrf
    _LAPACK_ERRORS = (TypeError, _lapack_lite.LapackError)

CHUNK_ROWS = 1 << 14  # rows reduced at a time (~4 MB at 30 columns)


def _numpy_r(A: np.ndarray) -> np.ndarray:
    """R of A = Q R by numpy's own (unblocked) QR, Q not formed."""
    # numpy's stubs type every mode's result as QRResult; mode "r" returns the array R alone
    return cast(np.ndarray, np.linalg.qr(A, mode="r"))


def _triangle(At: np.ndarray) -> np.ndarray:
    """R (n, n) of A = Q R given At = A^T, C-contiguous (n, m), m >= n; At is overwritten.

    At is A in column-major order, as LAPACK wants it: dgeqrf factors it in
    place and R is its upper triangle (column-major), i.e. the lower one of At.
    """
    n, m = At.shape
    if _dgeqrf is None:
        return _numpy_r(At.T)
    lwork = 64 * n  # dgeqrf's block size (32) times n, with room: the blocked path
    try:
        out = _dgeqrf(m, n, At, m, np.empty(n), np.empty(lwork), lwork, 0)
    except _LAPACK_ERRORS:  # pragma: no cover - a numpy whose binding takes other arguments
        return _numpy_r(At.T)
    if out["info"] != 0:  # pragma: no cover - argument errors only
        raise np.linalg.LinAlgError(f"dgeqrf failed (info {out['info']})")
    return np.triu(At[:, :n].T)


def _triangles(J: np.ndarray, scale: np.ndarray, r: np.ndarray | None = None) -> Iterator[np.ndarray]:
    """The triangles of the rows of [J D | r] (D = diag(scale); without r: J D), a chunk of CHUNK_ROWS rows at a
    time; a chunk not taller than wide is given as it is."""
    m, n = J.shape
    w = n + (r is not None)
    for a in range(0, m, CHUNK_ROWS):
        b = min(a + CHUNK_ROWS, m)
        At = np.empty((w, b - a))
        np.multiply(J[a:b].T, scale[:, None], out=At[:n])
        if r is not None:
            At[n] = r[a:b]
        yield _triangle(At) if b - a >= w else At.T.copy()


def _reduce(parts: list[np.ndarray], n: int) -> np.ndarray:
    """R of the rows of `parts` stacked (each (k_i, n)), square (n, n) when the rows allow."""
    if not parts:
        return np.zeros((0, n))
    A = np.concatenate(parts) if len(parts) > 1 else parts[0]
    if len(parts) == 1 or A.shape[0] <= n:
        return A
    return _triangle(np.ascontiguousarray(A.T))


def r_factor(A: np.ndarray) -> np.ndarray:
    """The n x n triangular factor R of a tall A = Q R (row signs arbitrary); A itself if not taller than wide."""
    A = np.asarray(A, dtype=float)
    m, n = A.shape
    return A if m <= n else _reduce(list(_triangles(A, np.ones(n))), n)


def scaled_r_factor(J: np.ndarray, r: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """R of [J D | r] (D = diag(scale)), formed a chunk of rows at a time: never a whole copy of J."""
    return _reduce(list(_triangles(J, scale, r)), J.shape[1] + 1)


def scaled_r_factor_of_blocks(blocks: list[np.ndarray], scale: np.ndarray) -> np.ndarray:
    """The R factor of the rows of every block (N_i, m_i, n) stacked and column-scaled, [B_1; ...] D = Q R.

    A chunk of CHUNK_ROWS rows at a time: no stacked copy of the blocks; the same R as
    `r_factor(np.vstack(...) * scale)` up to the signs of its rows and round-off.
    """
    n = scale.size
    return _reduce([t for blk in blocks for t in _triangles(blk.reshape(-1, n), scale)], n)
