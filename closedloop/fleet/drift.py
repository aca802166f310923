"""Drift of a robot's parameters between calibrations at several dates, in one gauge, with its uncertainty.

A closed loop does not fix every parameter: the overall size (thesis 3.3: a loop with no known
length closes at any scale), the base against the fixture, and groups of parameters that move the
closures alike (the reduction keeps one of each) are set by the calibration's gauge: the
parameters F it holds at given values (the length held for the scale, the dropped and unselected
ones), the others E estimated.  Two calibrations of the same robot in different gauges (another
length held, another reduction) give different values for the same kinematics: their parameter
differences mean nothing until both are in one gauge.

Common gauge (first order, the earlier calibration A's): the later calibration's closures are
kept while A's held values are imposed on it, i.e. B is re-solved in A's gauge on its own
linearised system.  With G = J^T W J the information (Gram) matrix of B's whitened closure
Jacobian over all P parameters at B's solution (eq. 3.17),

    p_B'[F_A] = p_A[F_A],   p_B'[E_A] = p_B[E_A] - G[E_A,E_A]^-1 G[E_A,F_A] (p_A[F_A] - p_B[F_A]),

the least-squares change of A's estimated parameters that keeps B's closures when A's held ones
move to A's values (exact along gauge directions, where the closures do not change at all).  It
is linear, p_B' = M p_B + c, so B's covariance becomes M Cov_B M^T.  The change of every robot
parameter A estimated, d = p_B'[k] - p_A[k], has the variance Cov_A[k,k] + (M Cov_B M^T)[k,k],
z = d / sqrt of it, flagged when |z| > z_max (default 3): larger than the two calibrations' noise
can explain.  The move's cost (the increase of B's whitened closure sum of squares) is ~0 for a
gauge change; when it exceeds what chi^2 with k degrees of freedom allows (k: parameters B
estimated and A holds; mean + z_max standard deviations) A holds a value B's data contradict, a
real change hidden in a held parameter: the pair gets a flagged row '*' with a note.  Loop
parameters (the fixture) are not reported: they are not the robot.  When both calibrations
estimated the same parameters and held the same values this is the plain difference
z = (v2 - v1) / sqrt(se1^2 + se2^2).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Drift:
    """The change of one robot parameter between two consecutive calibrations of a robot."""

    robot: str
    before: str  # job names
    after: str
    parameter: str
    change: float  # in the earlier calibration's gauge
    se: float  # its standard error
    z: float
    flagged: bool
    note: str = ""  # why a pair could not be compared


def gauge_record(res) -> dict[str, Any]:
    """What drift needs of a calibration: every parameter (name, kind, value, estimated or not), the
    covariance of the estimated ones, and the information matrix G = J^T W J of the whitened closure
    Jacobian over all parameters at the solution (prior-scaled columns; P x P, whatever the log's size)."""
    from closedloop.analysis.observability import resolve, whitened_blocks

    P = len(res.problem.params)
    problem, vals, idx, sigma_q = resolve(res, None, list(range(P)))
    C = np.vstack([J.reshape(-1, P) for _, J in whitened_blocks(problem, vals, idx, sigma_q, res.noise.weighting)])
    return {
        "names": list(problem.names),
        "kinds": [p.kind for p in problem.params],
        "values": [float(v) for v in res.fit.values],
        "estimated": [int(k) for k in res.fit.estimated],
        "prior": [float(p.prior) for p in problem.params],
        "covariance": np.asarray(res.fit.covariance, float).tolist(),
        "information": (C.T @ C).tolist(),
    }


def in_gauge_of(a: dict, b: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """B's parameter vector and covariance (P x P) in A's gauge (module docstring), and the move's
    cost: the increase of B's whitened closure sum of squares (chi^2 units; ~0 for a gauge change)."""
    P = len(b["values"])
    pa, pb = np.asarray(a["values"], float), np.asarray(b["values"], float)
    s = np.asarray(b["prior"], float)
    G = np.asarray(b["information"], float).reshape(P, P) / np.outer(s, s)  # physical units
    Eb = np.asarray(b["estimated"], int)
    cov_b = np.zeros((P, P))
    cov_b[np.ix_(Eb, Eb)] = np.asarray(b["covariance"], float).reshape(len(Eb), len(Eb))
    Ea = np.asarray(a["estimated"], int)
    Fa = np.setdiff1d(np.arange(P), Ea)
    if Fa.size == 0:
        return pb, cov_b, 0.0
    K = -np.linalg.lstsq(G[np.ix_(Ea, Ea)], G[np.ix_(Ea, Fa)], rcond=None)[0]  # d p[E_A] / d p[F_A]
    M = np.zeros((P, P))
    M[Ea, Ea] = 1.0
    M[np.ix_(Ea, Fa)] = -K  # p'[E_A] = p_B[E_A] + K (p_A[F_A] - p_B[F_A])
    out = pb.copy()
    out[Fa] = pa[Fa]
    out[Ea] = pb[Ea] + K @ (pa[Fa] - pb[Fa])
    d = out - pb
    return out, M @ cov_b @ M.T, float(d @ G @ d)


def compare(robot: str, name_a: str, name_b: str, a: dict, b: dict, z_max: float) -> list[Drift]:
    """The drift rows of one pair (A earlier, B later): robot parameters A estimated, in A's gauge."""
    if a["names"] != b["names"]:
        return [
            Drift(
                robot,
                name_a,
                name_b,
                "*",
                np.nan,
                np.nan,
                np.nan,
                False,
                "not comparable: not the same model and loops (different parameter lists)",
            )
        ]
    pb, cov_b, cost = in_gauge_of(a, b)
    log.debug("%s %s -> %s: closure cost of the gauge move %.3g", robot, name_a, name_b, cost)
    Ea = np.asarray(a["estimated"], int)
    moved = sorted(set(b["estimated"]) - set(a["estimated"]))  # B's estimates that A's gauge holds
    out = []
    if moved and cost > len(moved) + z_max * np.sqrt(2.0 * len(moved)):  # chi^2_k: mean + z_max sd
        names = ", ".join(a["names"][k] for k in moved[:4])
        out.append(
            Drift(
                robot,
                name_a,
                name_b,
                "*",
                np.nan,
                np.nan,
                float(np.sqrt(cost)),
                True,
                f"changed where the earlier calibration holds values ({names}): the later log's "
                f"closures worsen by chi^2 {cost:.3g} in that gauge",
            )
        )
    cov_a = np.asarray(a["covariance"], float).reshape(len(Ea), len(Ea))
    pa = np.asarray(a["values"], float)
    for i, k in enumerate(Ea):
        if a["kinds"][k] == "loop":
            continue
        var = float(cov_a[i, i] + cov_b[k, k])
        if not var > 0:
            continue
        se = float(np.sqrt(var))
        change = float(pb[k] - pa[k])
        z = change / se
        out.append(Drift(robot, name_a, name_b, a["names"][k], change, se, z, bool(abs(z) > z_max)))
    return out


def compare_parameters(robot: str, name_a: str, name_b: str, pa: dict, pb: dict, z_max: float) -> list[Drift]:
    """Fallback for results without a gauge record (written by an older closedloop): plain differences,
    only when both calibrations estimated the same parameters."""
    if set(pa) != set(pb):
        diff = sorted(set(pa) ^ set(pb))
        return [
            Drift(
                robot,
                name_a,
                name_b,
                "*",
                np.nan,
                np.nan,
                np.nan,
                False,
                f"not comparable: not the same parameters estimated ({', '.join(diff[:4])}) and no gauge "
                "record (calibrated by an older closedloop: run these jobs again)",
            )
        ]
    out = []
    for name in pa:
        (v1, s1, kind), (v2, s2, _) = pa[name], pb[name]
        if kind == "loop" or s1 is None or s2 is None:
            continue
        se = float(np.hypot(s1, s2))
        if se > 0:
            z = (v2 - v1) / se
            out.append(Drift(robot, name_a, name_b, name, v2 - v1, se, z, bool(abs(z) > z_max)))
    return out


def drift(
    jobs: list, results: Mapping[str, dict], z_max: float = 3.0, rows: Mapping[str, dict] | None = None
) -> list[Drift]:
    """Parameter changes between consecutive dates of each robot, with their uncertainty (module docstring).

    Only calibrations that converged with a verdict other than 'failed' are compared.  `results`: each
    job's record (its ``row``, ``parameters``, ``gauge``) by name; with `rows` (each job's summary row by
    name) the records are looked up only for the pairs compared, robot by robot and in date order, so a
    mapping that loads them from disk on demand holds two at a time.
    """
    out: list[Drift] = []
    by_robot: dict[str, list] = {}
    for j in jobs:
        if rows is not None:
            row = rows.get(j.name)
        else:
            r = results.get(j.name)
            row = r["row"] if r else None
        if j.robot and row and row["status"] == "ok" and row.get("verdict") != "failed":
            by_robot.setdefault(j.robot, []).append(j)
    for robot, js in by_robot.items():
        js.sort(key=lambda j: j.date)
        for a, b in zip(js, js[1:]):
            ra, rb = results[a.name], results[b.name]
            if ra.get("gauge") and rb.get("gauge"):
                out.extend(compare(robot, a.name, b.name, ra["gauge"], rb["gauge"], z_max))
            else:
                out.extend(compare_parameters(robot, a.name, b.name, ra["parameters"], rb["parameters"], z_max))
    return out


def drift_columns(rows: dict[str, dict], drifts: list[Drift]) -> None:
    """Fill the summary's drift columns (drift_from, drift_max_z, drift_flagged) of each later job."""
    for d in drifts:
        row = rows[d.after]
        row["drift_from"] = d.before
        if d.note:
            row["drift_flagged"] = d.note
            continue
        row["drift_max_z"] = max(abs(d.z), row.get("drift_max_z") or 0.0)
        if d.flagged:
            row["drift_flagged"] = "; ".join(filter(None, [row.get("drift_flagged"), f"{d.parameter} z={d.z:+.1f}"]))
