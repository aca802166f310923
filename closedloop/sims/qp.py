"""The planner's small linear algebra: a box-constrained QP solved exactly, and minimum-norm steps.

:func:`solve_box_qp` is a primal active-set method on bounds (Nocedal & Wright alg. 16.3), a few
microseconds for the 6-9 variables of one planning step (:mod:`closedloop.sims.driver`).
"""

from __future__ import annotations

import math
from operator import gt, le

import numpy as np
from scipy.linalg import lapack

__all__ = ["solve_box_qp", "min_norm_step", "svd_full", "solve_vec"]

# The planner's small systems (6-9 variables) call LAPACK's dgesv / dgesdd through scipy's public
# wrappers (scipy.linalg.lapack): the routines numpy.linalg.solve / svd call, with the same results to
# the bit on the planner's matrices (the datasets are unchanged), in ~1 / ~5 us where numpy's wrappers
# (their checks, type dispatch and `errstate`) take ~3.3 / ~8.3 us: ~10 us per waypoint.
_GESV = lapack.dgesv
_GESDD = lapack.dgesdd


def solve_vec(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(a, b)`` of a square float matrix and a vector (LAPACK ``dgesv``, LU with pivoting).

    Raises :class:`numpy.linalg.LinAlgError` if ``a`` is singular, as numpy does.
    """
    _lu, _piv, x, info = _GESV(a, b)
    if info:
        raise np.linalg.LinAlgError("Singular matrix" if info > 0 else f"dgesv: argument {-info} invalid")
    return x


def svd_full(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.linalg.svd(a)`` (full ``u`` and ``vt``) of a float matrix: LAPACK ``dgesdd``, ``(u, s, vt)``.

    ``vt`` is returned in row-major order, like numpy's: products with LAPACK's column-major
    result would go through other BLAS kernels and round differently (the datasets would change).
    ``u`` (the planner does not use it) stays column-major.  Raises
    :class:`numpy.linalg.LinAlgError` if it does not converge, as numpy does.
    """
    u, s, vt, info = _GESDD(a)
    if info:
        raise np.linalg.LinAlgError("SVD did not converge" if info > 0 else f"dgesdd: argument {-info} invalid")
    return u, s, np.ascontiguousarray(vt)


def solve_box_qp(
    P: np.ndarray, c: np.ndarray, lb: np.ndarray, ub: np.ndarray, max_iter: int | None = None
) -> np.ndarray | None:
    """Exact solution of ``min 1/2 x^T P x + c^T x  s.t.  lb <= x <= ub`` (``P`` symmetric positive definite).

    Primal active-set method (Nocedal & Wright, *Numerical Optimization*, alg. 16.3)
    specialised to bounds: from the feasible point ``clip(0, lb, ub)``, solve the
    equality-constrained problem on the free variables, step to the first blocking
    bound (added to the working set) or, at the working set's minimiser, release
    the bound with the most negative multiplier; stop when every multiplier is
    non-negative (KKT conditions hold to rounding).  Finite for a strictly convex
    QP; a few microseconds per iteration for the planner's 6-9 variables, and
    usually one iteration (no bound active).  Returns ``None`` if it has not
    converged after ``max_iter`` iterations (default ``10 n + 10``) or if ``lb > ub``.
    """
    n = c.shape[0]
    # lb <= ub, and x within them: on Python floats (6-9 values; numpy's comparisons cost more)
    lo, hi = lb.tolist(), ub.tolist()
    if any(map(gt, lo, hi)):
        return None
    x = solve_vec(P, -c)  # the unconstrained minimiser (P positive definite): the usual answer
    xl = x.tolist()
    if all(map(le, lo, xl)) and all(map(le, xl, hi)):  # lo <= x <= hi (a NaN fails, as in numpy)
        return x
    x = np.clip(np.zeros(n), lb, ub)
    # working set: -1 at the lower bound, +1 at the upper bound, 0 free
    w = np.where(lb > 0.0, -1, np.where(ub < 0.0, 1, 0)).astype(np.int8)
    fixed_eq = lb == ub
    w[fixed_eq] = -1
    scale = 1.0 + float(np.abs(c).max()) + float(np.abs(P).max())
    tol = 1e-13 * scale
    for _ in range(max_iter if max_iter is not None else 10 * n + 10):
        free = w == 0
        if free.any():
            act = ~free
            rhs = -c[free]
            if act.any():
                rhs = rhs - P[np.ix_(free, act)] @ x[act]
            xf = solve_vec(P[np.ix_(free, free)], rhs)
            xo = x[free]
            p = xf - xo
            # ratio test: the first bound the step from xo to xf crosses
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(p < 0.0, (lb[free] - xo) / p, np.where(p > 0.0, (ub[free] - xo) / p, np.inf))
            k = int(np.argmin(t))
            if t[k] < 1.0:
                alpha = max(float(t[k]), 0.0)
                x[free] = xo + alpha * p
                j = int(np.flatnonzero(free)[k])
                if p[k] < 0.0:
                    w[j], x[j] = -1, lb[j]
                else:
                    w[j], x[j] = 1, ub[j]
                continue
            x[free] = xf
        # minimiser on the working set: multipliers of the active bounds
        g = P @ x + c
        lam = np.where(w < 0, g, -g)
        lam[(w == 0) | fixed_eq] = np.inf
        j = int(np.argmin(lam))
        if lam[j] >= -tol:
            return x
        w[j] = 0
    return None


def min_norm_step(jac: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``J^+ e``: ``J^T (J J^T)^-1 e`` for a wide ``J`` of full row rank, else least squares (SVD)."""
    m, n = jac.shape
    if m <= n:
        try:
            dq = jac.T @ solve_vec(jac @ jac.T, e)
        except np.linalg.LinAlgError:  # J J^T singular (np.linalg.solve raises): least squares below
            dq = None
        if dq is not None and all(map(math.isfinite, dq.tolist())):  # np.isfinite(dq).all(), on floats
            return dq
    return np.linalg.lstsq(jac, e, rcond=None)[0]
