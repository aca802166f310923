"""Rotation vectors compared across fits: the same rotation, the 2*pi branch nearest to a reference.

A weld's closure rotation (``<loop>.rx, ry, rz``) is a rotation vector: two fits (Monte Carlo draws,
validation folds) can land on branches 2*pi apart for the same rotation.  Before their values are
compared or averaged, each is unwrapped towards a reference.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from closedloop.problem.problem import CalibrationProblem


# --------------------------------------------------------------------------- unwrap
def unwrap_rotation_vector(r: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The rotation vector of the same rotation as `r` nearest to `ref`."""
    r = np.asarray(r, float)
    a = np.linalg.norm(r)
    if a < 1e-12:
        u = ref / np.linalg.norm(ref) if np.linalg.norm(ref) > 1e-12 else np.array([1.0, 0.0, 0.0])
        cands = [np.zeros(3)] + [u * 2 * np.pi * k for k in (-1, 1)]
    else:
        u = r / a
        cands = [u * (a + 2 * np.pi * k) for k in (-2, -1, 0, 1, 2)]
    return min(cands, key=lambda c: float(np.linalg.norm(c - ref)))


def rotation_triples(problem: CalibrationProblem) -> list[tuple[int, int, int]]:
    """Index triples of rotation-vector parameters (weld closures: <loop>.rx, ry, rz)."""
    out = []
    for cols in problem.loop_columns:  # index maps (loops may share parameters)
        names = [problem.names[i] for i in cols]
        for k, n in enumerate(names):
            if (
                n.endswith(".rx")
                and k + 2 < len(names)
                and names[k + 1].endswith(".ry")
                and names[k + 2].endswith(".rz")
            ):
                out.append((int(cols[k]), int(cols[k + 1]), int(cols[k + 2])))
    return out


def unwrap(problem: CalibrationProblem, values: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """`values` with every closure rotation vector unwrapped towards `ref`."""
    v = np.array(values, float)
    for t in rotation_triples(problem):
        v[list(t)] = unwrap_rotation_vector(v[list(t)], ref[list(t)])
    return v
