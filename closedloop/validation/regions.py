"""Held-out validation by region of joint space: the held-out figure of extrapolation.

Random folds (`closedloop.validation.kfold`) hold out rows drawn from the same region as the training
rows: they measure interpolation, and say little about configurations unlike those recorded.  Here the
held-out sets are whole regions: the log's configurations are grouped by k-means
(`scipy.cluster.vq.kmeans2`) on their readings, each joint scaled by its range over the joint limits
(`closedloop.analysis.accuracy.joint_ranges`) so that a radian of a short-range joint weighs as much
as its share of the workspace; each region is left out in turn, the calibration refitted on the others
with the same options and the held-out region's closure evaluated at the refit's values
(`kfold.cross_validate` with these sets).  A calibration that holds only where it was fitted shows a
held-out closure far above the random folds'.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from closedloop.analysis.accuracy import joint_ranges
from closedloop.calibration.pipeline import CalibrationOptions, CalibrationResult
from closedloop.errors import ParameterError
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import even_sample
from closedloop.progress import ProgressReporter
from closedloop.validation.kfold import cross_validate, subset

N_REGIONS = 4  # regions left out in turn (the default of `closedloop calibrate --regions`)


def regions(
    log_: JointLog, robot: RobotModel, joints: list[str], k: int = N_REGIONS, seed: int = 0
) -> list[np.ndarray]:
    """k disjoint sets of row indices (0-based) of the log, each a region of joint space (module docstring).

    Regions are k-means clusters of the readings of `joints` scaled by their ranges; an empty cluster is
    dropped (fewer regions than k on a log of few distinct configurations).  Where the rows belong to
    several loops (the log's 'loop' column: each loop recorded on its own), each loop's rows are clustered
    on their own and region c holds the c-th cluster of every loop, so that every refit keeps rows of every
    loop (a loop whose rows all lie in the left-out region could not be refitted).
    """
    if k < 2:
        raise ParameterError("region validation needs k >= 2 regions")
    groups = (
        [np.arange(len(log_))]
        if log_.loop is None
        else [np.flatnonzero(log_.loop == name) for name in dict.fromkeys(log_.loop.tolist())]
    )
    for g in groups:
        if g.size < 2 * k:
            which = "" if log_.loop is None else f" of loop '{log_.loop[g[0]]}'"
            raise ParameterError(
                f"region validation with {k} regions needs at least {2 * k} rows{which}; "
                f"{log_.source or 'the log'} has {g.size}"
            )
    X = log_.columns(joints)
    lo, hi = joint_ranges(robot, joints)
    Z = (X - lo) / (hi - lo)
    out: list[list[int]] = [[] for _ in range(k)]
    for g in groups:
        for c, part in enumerate(_clusters(Z[g], k, seed)):
            out[c].extend(g[part].tolist())
    return [np.sort(np.array(r, dtype=int)) for r in out if r]


#: rows above which the k-means centres are found on an even sample of this many (`_clusters`)
CLUSTER_SAMPLE = 8192


def _clusters(Z: np.ndarray, k: int, seed: int) -> list[np.ndarray]:
    """The k-means clusters (row indices of `Z`) of scaled readings, the joints that do not move left out;
    the empty ones dropped.  Above `CLUSTER_SAMPLE` rows the centres are those of an evenly spaced sample of
    that many (a few regions of joint space need no more to be placed) and every row joins its nearest
    centre: the cost stops growing with the log but for that last assignment."""
    from scipy.cluster.vq import kmeans2, vq

    moving = np.ptp(Z, axis=0) > 0
    Z = Z[:, moving] if moving.any() else Z
    if Z.shape[0] > CLUSTER_SAMPLE:
        centres, _ = kmeans2(Z[even_sample(Z.shape[0], CLUSTER_SAMPLE)], k, seed=seed, minit="++")
        labels = vq(Z, centres, check_finite=False)[0]
    else:
        _, labels = kmeans2(Z, k, seed=seed, minit="++")
    return [np.flatnonzero(labels == c) for c in range(k) if np.any(labels == c)]


def region_validate(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    joints: list[str],
    options: CalibrationOptions | None = None,
    k: int = N_REGIONS,
    seed: int = 0,
    exclude=None,
    executor=None,
    progress: ProgressReporter | None = None,
    result: CalibrationResult | None = None,
) -> dict[str, Any]:
    """Leave each region of `regions` out in turn (module docstring): `kfold.cross_validate`'s record
    over these held-out sets, with 'regions' (the rows of each, 0-based) and 'k' their number.  The rows
    `exclude` (the full calibration's rejected outliers) are neither judged, nor trained on, nor clustered:
    a refit leaves a region of the data out, and the rows that are no data are in no region.  The refits
    reuse the full calibration's outlier screen (`cross_validate`'s `train_without_excluded`); given that
    calibration (`result`), a refit on a long log's sample of training rows starts at its solution
    (`cross_validate`'s warm refit)."""
    # the regions of the data: a rejected row (a reading of 100 rad) would be a region of its own
    keep = np.setdiff1d(np.arange(len(log_)), np.asarray(exclude if exclude is not None else [], dtype=int))
    parts = [keep[p] for p in regions(subset(log_, keep), robot, joints, k, seed)]
    out = cross_validate(
        robot,
        log_,
        loops,
        options,
        k=len(parts),
        seed=seed,
        executor=executor,
        progress=progress,
        exclude=exclude,
        parts=parts,
        train_without_excluded=True,
        result=result,
    )
    out["regions"] = [p.tolist() for p in parts]
    return out
