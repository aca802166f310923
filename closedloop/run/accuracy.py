"""A run's predicted accuracy over the workspace: the options ``workspace``, ``accuracy``, ``suggest`` and
``suggest_n`` of `closedloop.run.options.CalibrateOptions` read and run (`closedloop.analysis.accuracy`
computes; `closedloop.calibration.verdict.judge_accuracy` judges the target; `closedloop.cli.accuracy`
prints the summary's lines)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from closedloop.errors import InputError


@dataclass(frozen=True)
class AccuracyRequest:
    """What the options ask of the accuracy, checked before any work: ``--workspace``'s joint ranges
    (`check_workspace`: None for a log file, or without it), ``--accuracy``'s target (metres or None,
    radians or None; `parse_accuracy`; None without it) and ``--prior-tolerance``'s nominal tolerance
    (`parse_prior`; None: `analysis.accuracy.PriorTolerance`'s defaults)."""

    box: dict[str, tuple[float, float]] | None = None
    target: tuple[float | None, float | None] | None = None
    prior: Any = None  # closedloop.analysis.accuracy.PriorTolerance


def workspace_request(o) -> AccuracyRequest:
    """The `AccuracyRequest` of the options `o`; one line naming the option at fault otherwise."""
    return AccuracyRequest(
        box=check_workspace(o.workspace) if o.workspace else None,
        target=parse_accuracy(o.accuracy) if o.accuracy else None,
        prior=parse_prior(o.prior_tolerance) if o.prior_tolerance else None,
    )


@dataclass(frozen=True)
class WorkspacePrediction:
    """A calibration's predicted accuracy over the workspace (`closedloop.analysis.accuracy`; None where
    it could not be predicted) and the configurations ``--suggest`` asks to record next: the CSV to write
    and the report's record of them (``accuracy.next_poses``), or the note saying why there are none."""

    accuracy: Any = None  # closedloop.analysis.accuracy.WorkspaceAccuracy
    suggested: str | None = None
    next_poses: dict | None = None
    note: str | None = None


def predict_workspace(o, robot, res, request: AccuracyRequest | None = None) -> WorkspacePrediction:
    """The calibrated robot's predicted accuracy (`analysis.accuracy.predict_from_result`) at the readings
    ``--workspace`` names: its log file (its rows, columns by joint name), its box (`request.box`: random readings
    in it), or without it random readings within the joint ranges (seed 0: the readings ``closedloop
    check`` compares the robots at); where no loop has a frame to follow, or the kinematics are not finite
    at a reading, no prediction (a note says so).  Then, with ``--suggest FILE``, the ``--suggest-n``
    configurations that most reduce the predicted error (`closedloop.design.next_poses.suggest_next`), as
    the CSV log to write and the report's record."""
    from closedloop.analysis.accuracy import N_WORKSPACE, predict_from_result, random_readings

    request = request or AccuracyRequest()
    box = request.box
    joints = res.problem.joints
    spec = o.workspace
    readings, source = None, None
    if spec and box is None:  # a log file
        from closedloop.io.logs import read_log

        lg = read_log(spec, robot.joint_names, degrees=bool(o.degrees))
        missing = [j for j in joints if j not in lg.joints]
        if missing:
            raise InputError(
                f"--workspace {spec}: no column for joint {missing[0]} (the calibrated joints: {', '.join(joints)})"
            )
        if len(lg) == 0:
            raise InputError(f"--workspace {spec}: no row")
        readings, source = lg.columns(joints), f"the {len(lg)} readings of {spec}"
    elif spec:
        readings, source = random_readings(robot, joints, box=box), f"{N_WORKSPACE} random readings within {spec}"
    try:
        accuracy = predict_from_result(res, readings, source=source, prior=request.prior)
    except np.linalg.LinAlgError as exc:  # the calibration stands; the prediction is said to be missing
        res.notes.append(f"accuracy over the workspace not predicted: {exc}")
        accuracy = None
    if not o.suggest:
        return WorkspacePrediction(accuracy)
    from closedloop.design.next_poses import suggest_next

    found = suggest_next(res, accuracy, int(o.suggest_n or 10))
    if found is None:
        note = f"--suggest {o.suggest}: no configuration to suggest (no followed loop closes at new readings)"
        return WorkspacePrediction(accuracy, note=note)
    record = found.record(o.suggest)
    return WorkspacePrediction(accuracy, suggested=found.csv(), next_poses=record)


def check_workspace(spec: str) -> dict[str, tuple[float, float]] | None:
    """``--workspace`` checked before any work: None for a log file, else its joint ranges (`parse_box`)."""
    if Path(spec).is_file():
        return None
    if "=" not in spec:
        raise InputError(f"--workspace {spec}: no such file (give a log file, or joint ranges joint=lo:hi,...)")
    return parse_box(spec)


def parse_box(text: str) -> dict[str, tuple[float, float]]:
    """A joint-space box ``joint=lo:hi,joint=lo:hi`` (rad, or m for a prismatic joint)."""
    out: dict[str, tuple[float, float]] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        name, eq, rng = part.partition("=")
        a, colon, b = rng.partition(":")
        try:
            if not eq or not colon:
                raise ValueError
            lo, hi = float(a), float(b)
        except ValueError:
            raise InputError(
                f"--workspace '{part}': expected joint=lo:hi (rad), e.g. panda_joint1=-1:1, or a log file"
            ) from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError(f"--workspace '{part}': the bounds must be finite numbers")
        out[name.strip()] = (lo, hi)
    if not out:
        raise InputError("--workspace: give joint=lo:hi ranges or a log file")
    return out


UNITS = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "rad": 1.0, "mrad": 1e-3, "urad": 1e-6, "deg": 0.017453292519943295}


def parse_accuracy(text: str) -> tuple[float | None, float | None]:
    """An accuracy target ``0.2mm``, ``1mrad`` or both (``0.2mm,1mrad``): (metres or None, radians or None)."""
    m: float | None = None
    rad: float | None = None
    for part in (p.strip() for p in text.split(",") if p.strip()):
        hit = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(m|mm|um|rad|mrad|urad|deg)", part)
        if not hit:
            raise InputError(
                f"--accuracy '{part}': expected a number and a unit, e.g. 0.2mm or 1mrad (m, mm, um, rad, mrad, urad, deg)"
            )
        value = float(hit.group(1)) * UNITS[hit.group(2)]
        if not value > 0:
            raise InputError(f"--accuracy '{part}': the target must be > 0")
        if not value < 1e3:
            raise InputError(f"--accuracy '{part}': the target must be below 1000 m or rad")
        position = hit.group(2) in ("m", "mm", "um")
        if (m if position else rad) is not None:
            kind = "position" if position else "angle"
            raise InputError(f"--accuracy '{text}': two {kind} targets; give one {kind} and at most one of the other")
        if position:
            m = value
        else:
            rad = value
    if m is None and rad is None:
        raise InputError("--accuracy: give a position target, an angle target or both, e.g. 0.2mm,1mrad")
    return m, rad


#: ``--prior-tolerance`` keys: the `PriorTolerance` field each sets and the units it takes (none: a ratio)
PRIOR_KEYS = {
    "length": ("length_m", ("m", "mm", "um")),
    "angle": ("angle_rad", ("rad", "mrad", "urad", "deg")),
    "offset": ("offset_rad", ("rad", "mrad", "urad", "deg")),
    "scale": ("scale", ()),
}


def parse_prior(text: str, label: str = "--prior-tolerance"):
    """The nominal model's tolerance ``length=1mm,angle=1mrad,offset=10mrad,scale=0.001`` (any of the keys,
    the others at `analysis.accuracy.PriorTolerance`'s defaults; a number without a unit is in m, rad or a
    ratio) as a `PriorTolerance`; one line naming the item at fault otherwise."""
    from dataclasses import replace

    from closedloop.analysis.accuracy import PriorTolerance

    values: dict[str, float] = {}
    for part in (p.strip() for p in text.split(",") if p.strip()):
        key, eq, rest = (t.strip() for t in part.partition("="))
        if not eq or key not in PRIOR_KEYS:
            raise InputError(
                f"{label} '{part}': expected key=value with the keys {', '.join(PRIOR_KEYS)}, "
                "e.g. length=1mm,angle=1mrad,offset=10mrad,scale=0.001"
            )
        name, units = PRIOR_KEYS[key]
        hit = re.fullmatch(r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-z]*)", rest)
        if not hit or (hit.group(2) and hit.group(2) not in units):
            said = f"a unit of {', '.join(units)}" if units else "no unit (a ratio)"
            raise InputError(f"{label} '{part}': expected a number >= 0 with {said}")
        value = float(hit.group(1)) * (UNITS[hit.group(2)] if hit.group(2) else 1.0)
        if not value < 1.0:  # a tolerance of a metre, a radian or 100 % is no nominal model
            raise InputError(f"{label} '{part}': a tolerance must be below 1 (m, rad or a ratio)")
        values[name] = value
    if not values:
        raise InputError(f"{label}: give key=value items, e.g. length=1mm,angle=1mrad,offset=10mrad,scale=0.001")
    return replace(PriorTolerance(), **values)
