"""A run's predicted accuracy over the workspace: the options ``workspace``, ``accuracy``, ``regions``,
``suggest`` and ``suggest_n`` of `closedloop.run.options.CalibrateOptions` read and run
(`closedloop.analysis.accuracy` computes; `closedloop.cli.accuracy` prints the summary's lines)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from closedloop.errors import InputError


def workspace_readings(o, robot, joints: list[str]) -> tuple[np.ndarray | None, str | None]:
    """The readings (n, joints) ``--workspace`` asks the accuracy to be predicted at, and where they come
    from: its log file (its rows, columns by joint name) or its box ``joint=lo:hi,...`` (random readings
    in it); (None, None) without it (random readings within the joint ranges, seed 0: the readings
    `closedloop check` compares the robots at)."""
    from closedloop.analysis.accuracy import N_WORKSPACE, random_readings

    spec = o.workspace
    if not spec:
        return None, None
    if Path(spec).is_file():
        from closedloop.io.logs import read_log

        lg = read_log(spec, robot.joint_names, degrees=bool(o.degrees))
        missing = [j for j in joints if j not in lg.joints]
        if missing:
            raise InputError(
                f"--workspace {spec}: no column for joint {missing[0]} (the calibrated joints: {', '.join(joints)})"
            )
        if len(lg) == 0:
            raise InputError(f"--workspace {spec}: no row")
        return lg.columns(joints), f"the {len(lg)} readings of {spec}"
    box = check_workspace(spec)
    return random_readings(robot, joints, box=box), f"{N_WORKSPACE} random readings within {spec}"


def check_workspace(spec: str) -> dict[str, tuple[float, float]] | None:
    """``--workspace`` checked before any work: None for a log file, else its joint ranges (`parse_box`)."""
    if Path(spec).is_file():
        return None
    if "=" not in spec:
        raise InputError(f"--workspace {spec}: no such file (give a log file, or joint ranges joint=lo:hi,...)")
    return parse_box(spec)


def predicted_accuracy(res, readings: np.ndarray | None = None, source: str | None = None, prior=None):
    """The calibration's predicted accuracy over the workspace (`analysis.accuracy.predict_from_result`)
    at `readings` (`workspace_readings`; None: within the joint ranges), with the nominal tolerance `prior`
    (`parse_prior`; None: `PriorTolerance`'s defaults); None where no loop has a frame to follow, or the
    kinematics are not finite at a reading (a note says so)."""
    from closedloop.analysis.accuracy import predict_from_result

    try:
        return predict_from_result(res, readings, source=source, prior=prior)
    except np.linalg.LinAlgError as exc:  # the calibration stands; the prediction is said to be missing
        res.notes.append(f"accuracy over the workspace not predicted: {exc}")
        return None


def next_poses(o, res, accuracy, report: dict) -> str | None:
    """``--suggest FILE``: the ``--suggest-n`` configurations of the first followed loop that most reduce the
    predicted workspace error (`closedloop.design.next_poses.suggest_poses`), as the CSV to write (a header
    of joint names, one row per configuration, radians: a log the robot can play), recorded in the report
    (``accuracy.next_poses``); None without --suggest or when none can be suggested (a note says why)."""
    path = o.suggest
    if not path:
        return None
    from closedloop.design.next_poses import suggest_poses

    k = int(o.suggest_n or 10)
    followed = [
        i for i, b in enumerate(res.problem.blocks) if accuracy and b.loop.name in {f.loop for f in accuracy.frames}
    ]
    found = suggest_poses(res, accuracy, k, followed[0]) if followed else None
    if found is None or not found.readings.shape[0]:
        res.notes.append(f"--suggest {path}: no configuration to suggest (no followed loop closes at new readings)")
        return None
    report.setdefault("accuracy", {})["next_poses"] = {
        "file": str(path),
        "loop": found.loop,
        "configurations": int(found.readings.shape[0]),
        "candidates": found.candidates,
        "predicted_rms_before_m": found.rms_before_m,
        "predicted_rms_after_m": [float(v) for v in found.rms_after_m],
    }
    lines = [",".join(found.joints)] + [",".join(repr(float(v)) for v in row) for row in found.readings]
    return "\n".join(lines) + "\n"


def region_validation(robot, lg, loops, opts, o, res, prog) -> dict | None:
    """Held-out validation by region (`validation.regions.region_validate`, ``--regions K``), as the
    report's record; a region the refit cannot do without is a note, not an error."""
    from closedloop.errors import ClosedLoopError
    from closedloop.validation.regions import region_validate

    k = int(o.regions or 0)
    if k < 2 or not res.converged:
        return None
    if len(lg) < 4 * k:  # regions of a few rows each say nothing of extrapolation: not run, said in the report
        return {"k": k, "skipped": f"{len(lg)} rows: too few for {k} regions (at least {4 * k})"}
    prog("validating regions", 0, k)
    try:
        cv = region_validate(
            robot,
            lg,
            loops,
            res.problem.joints,
            opts,
            k=k,
            exclude=[rj.row - 1 for rj in res.outliers.rejected],
            progress=lambda task, done, total=None, note="": prog("validating regions", done, total, note),
        )
    except ClosedLoopError as exc:
        _close(prog)
        res.notes.append(f"region validation skipped: {str(exc).splitlines()[0]}")
        return {"k": k, "skipped": str(exc).splitlines()[0]}
    _close(prog)
    return {
        "k": cv["k"],
        "rows": [len(r) for r in cv["regions"]],
        "test": cv["test"],
        "train": cv["train"],
        "folds_converged": [f["converged"] for f in cv["folds"]],
    }


def _close(progress) -> None:
    close = getattr(progress, "close", None)
    if close is not None:
        close()


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
        if not (value > 0 and value < 1e3):
            raise InputError(f"--accuracy '{part}': the target must be > 0")
        if hit.group(2) in ("m", "mm", "um"):
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
