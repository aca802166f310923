"""Validation across fixtures: leave one fixture out.

k-fold validation splits each loop's configurations; it cannot see a
calibration that fits the places it was recorded at and extrapolates badly
to others.  With several fixtures (the places of a block, recording days)
each fixture is held out in turn: the calibration is refitted on the others
with the same options, and the held-out fixture's closure is evaluated with
the refitted robot and with the nominal one (`evaluate.evaluate_model`).  With
the refit the figure is a prediction: what the refit estimated once for all
data (a shared ball, a tracker's base, cameras) is held at its values and
only the held-out fixture's own unknowns (its sockets, its pose) are fitted;
the nominal model, which has no calibration, has every loop unknown fitted.  A calibration that makes a held-out
fixture worse than the nominal model does not generalise: the verdict is
`suspect`, naming the fixture.

Given the full calibration, each refit starts at its solution and shares what does not depend on the
fixture left out (`validation.refit`: its noise, its outlier rejections, its loops' charts): a few
iterations each instead of a calibration from the nominal model, the same held-out figures within the
noise.  The rows it rejected are left out of every refit's data (they are judged as before).

Fixtures: a loop's ``fixture`` (spec key ``fixture=NAME``), else its name;
loops joined by a known distance (`problem.distances.DistanceLoop`) are one rigid
block, so one fixture.  A distance is trained on only when both its loops are.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from closedloop.errors import ClosedLoopError
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel
from closedloop.records import CalibrationResult

WORSE = 1.0  # held-out closure with the calibration above WORSE x the nominal model's (+ margin): suspect
MARGIN = 0.10  # at least 10 % worse, and beyond two standard deviations of an RMS over the fixture's rows:
# a nominal model already at the noise is not 'beaten' by a few percent of sampling scatter


def fixture_groups(loops: list[Loop]) -> dict[str, list[str]]:
    """Fixture name -> its loops' names (module docstring)."""
    real = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    parent = {lp.name: lp.name for lp in real}

    def root(n: str) -> str:
        while parent[n] != n:
            n = parent[n]
        return n

    label = {lp.name: str(getattr(lp, "fixture", None) or "") for lp in real}  # "": on no fixture
    by_label: dict[str, str] = {}
    for lp in real:
        if label[lp.name]:
            first = by_label.setdefault(label[lp.name], lp.name)
            parent[root(lp.name)] = root(first)
    for lp in loops:
        refs = getattr(lp, "refers_to", None)
        if refs and all(r in parent for r in refs):
            parent[root(refs[1])] = root(refs[0])
    groups: dict[str, list[str]] = {}
    for lp in real:
        groups.setdefault(root(lp.name), []).append(lp.name)
    out = {}
    for r, members in groups.items():
        named = sorted({label[m] for m in members if label[m]})
        out["+".join(named) if named else (r if len(members) == 1 else "+".join(members))] = members
    return out


def _subset(log_: JointLog, names: list[str]) -> JointLog:
    from closedloop.validation.kfold import subset

    rows = np.flatnonzero(np.isin(log_.loop, names)) if log_.loop is not None else np.zeros(0, dtype=int)
    return subset(log_, rows)


def _without(log_: JointLog, rows: list[int]) -> JointLog:
    """`log_` without its rows `rows` (0-based)."""
    from closedloop.validation.kfold import subset

    return subset(log_, np.setdiff1d(np.arange(len(log_)), np.asarray(rows, dtype=int))) if rows else log_


def leave_one_fixture_out(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    options=None,
    worse: float = WORSE,
    result: CalibrationResult | None = None,
) -> dict[str, Any] | None:
    """Refit without each fixture, evaluate it with the refit and with the nominal model; None if < 2 fixtures.

    `result`: the calibration of `log_` with `loops` and `options`; each refit then starts at its solution
    (`validation.refit`; None: each is a calibration from the nominal model).

    Returns {'fixtures': [{'fixture', 'loops', 'n_test', 'calibrated_rms_m', 'calibrated_mean_m',
    'nominal_rms_m', 'nominal_mean_m', 'converged', 'iterations', 'warm', 'worse'}], 'suspect': [reasons]};
    a fixture whose refit fails (the others alone do not determine the robot) has 'error' instead of the
    closures.
    """
    from closedloop.calibration.pipeline import CalibrationOptions
    from closedloop.validation.evaluate import evaluate_fitted, evaluate_model
    from closedloop.validation.refit import refit

    groups = fixture_groups(loops)
    if len(groups) < 2 or log_.loop is None:
        return None
    opt = options or CalibrationOptions()
    rows, reasons = [], []
    # the rows the calibration rejected are no data: no refit trains on them
    data = log_ if result is None else _without(log_, [rj.row - 1 for rj in result.outliers.rejected])
    for fx, members in groups.items():
        train = [
            lp
            for lp in loops
            if (lp.name not in members and not getattr(lp, "parameter_only", False))
            or (getattr(lp, "parameter_only", False) and not set(getattr(lp, "refers_to", ())) & set(members))
        ]
        test = [lp for lp in loops if lp.name in members]
        train_names = [lp.name for lp in train if not getattr(lp, "parameter_only", False)]
        test_log = _subset(log_, members)
        try:
            fitted = refit(result, robot, _subset(data, train_names), train, opt)
        except ClosedLoopError as exc:  # the other fixtures alone cannot calibrate: nothing to judge
            rows.append(
                {
                    "fixture": fx,
                    "loops": members,
                    "n_test": len(test_log),
                    "converged": False,
                    "error": str(exc),
                    "worse": False,
                }
            )
            continue
        cal = evaluate_fitted(fitted.problem, fitted.values, test_log, test)
        nom = evaluate_model(robot, test_log, test, None, "nominal")
        key = "rms_m" if cal.rms_m is not None else "rms_rad"
        c, n = getattr(cal, key), getattr(nom, key)
        rows_m = len(test_log) * max(lp.dim for lp in test)  # the RMS's own sampling spread: ~1/sqrt(2 M)
        bad = bool(c is not None and n is not None and c > worse * n * (1.0 + max(MARGIN, 2.0 / np.sqrt(2.0 * rows_m))))
        rows.append(
            {
                "fixture": fx,
                "loops": members,
                "n_test": len(test_log),
                "converged": fitted.converged,
                "iterations": fitted.iterations,
                "warm": fitted.warm,
                "calibrated_rms_m": cal.rms_m,
                "calibrated_mean_m": cal.mean_m,
                "nominal_rms_m": nom.rms_m,
                "nominal_mean_m": nom.mean_m,
                "calibrated_rms_rad": cal.rms_rad,
                "nominal_rms_rad": nom.rms_rad,
                "worse": bad,
            }
        )
        if bad:
            unit, f = ("mm", 1e3) if key == "rms_m" else ("mrad", 1e3)
            reasons.append(
                f"held-out fixture {fx} (loops {', '.join(members)}): closure RMS {c * f:.3g} {unit} "
                f"with the calibration refitted without it, worse than the nominal model's "
                f"{n * f:.3g} {unit}: the calibration does not extrapolate to it"
            )
    return {"fixtures": rows, "suspect": reasons}
