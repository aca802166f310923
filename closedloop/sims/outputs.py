"""A simulated dataset's files: the log, the truth record, and the refusal to overwrite another dataset.

``log.csv``: the joint readings (header = joint names), then ``tau:<joint>``, ``violation_m``,
``violation_rad``, ``constraint_force_n``, ``door_angle`` (hinge loops) and the loop's measurement
columns (open loops); ``truth.json``: the scenario, seed, settings, the loop (type, frames, name and its
type's record), ``q0``, the true parameters, the violation and sample counts (:func:`truth_record`).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np

from closedloop.errors import InputError
from closedloop.io.files import OutputSet
from closedloop.sims.loop_types import SIM_LOOPS, SimLoop
from closedloop.sims.scenarios import Scenario, SimSettings

__all__ = ["DATASET_FILES", "check_dataset_dir", "write_log", "truth_record"]

#: the files of a dataset, in the order they are published (truth.json, the manifest, last)
DATASET_FILES = ("nominal.urdf", "scene.xml", "log.csv", "truth.json")


def check_dataset_dir(out: Path, replace: bool = False) -> None:
    """Refuse to write a dataset into a directory that holds another one, unless `replace`.

    (A dataset is a set: a new ``log.csv`` beside an old ``truth.json`` would look complete.)
    """
    if replace or not out.is_dir():
        return
    present = [f for f in DATASET_FILES if (out / f).exists()]
    if present:
        raise InputError(
            f"--out {out}: holds another dataset ({', '.join(present)}); "
            "give a new directory or --replace to replace it"
        )


def truth_record(
    sc: Scenario,
    kind: SimLoop,
    scene,
    settings: SimSettings,
    seed: int,
    joint_names: list[str],
    q0: np.ndarray,
    values: dict[str, float],
    measured: list[str],
    rec,
    qp_solves: int,
) -> dict[str, Any]:
    """The contents of ``truth.json`` (module docstring); ``rec``: the `Recording` of the run."""
    params = dict(values)
    if settings.compliance > 0.0:
        params.update({f"{j}.compliance": float(settings.compliance) for j in joint_names})
    params.update(kind.truth_parameters(sc.loop_name, scene))
    loop_info: dict[str, Any] = {"type": sc.loop_type, "frame": sc.tool_frame, "name": sc.loop_name}
    if sc.target_frame is not None:
        loop_info["to"] = sc.target_frame
    loop_info.update(kind.truth_record(sc.loop_name, scene, settings, measured))
    rms = lambda a: float(np.sqrt(np.mean(a**2))) if a.size else 0.0  # noqa: E731
    foreign = {k for other in SIM_LOOPS.values() for k in other.own_settings} - set(kind.own_settings)
    return {
        "scenario": sc.name,
        "seed": int(seed),
        "robot": sc.robot,
        "joint_names": joint_names,
        "settings": settings.as_dict(drop=foreign),
        "loop": loop_info,
        "q0": [float(v) for v in q0],
        "parameters": params,
        "violation": {
            "rms_m": rms(rec.viol_m),
            "max_m": float(rec.viol_m.max(initial=0.0)),
            "rms_rad": rms(rec.viol_rad),
            "max_rad": float(rec.viol_rad.max(initial=0.0)),
        },
        "samples": {"recorded": rec.done, "dropped": rec.dropped, "steps": rec.steps, "qp_solves": qp_solves},
    }


def write_log(
    files: OutputSet,
    path: Path,
    joint_names: list[str],
    readings: np.ndarray,
    tau: np.ndarray,
    viol_m: np.ndarray,
    viol_rad: np.ndarray,
    force: np.ndarray,
    door: np.ndarray,
    measured: dict[str, np.ndarray] | None = None,
) -> None:
    """Write the calibration log: joint readings first, then diagnostic columns, then measurements."""
    measured = measured or {}
    header = (
        list(joint_names) + [f"tau:{j}" for j in joint_names] + ["violation_m", "violation_rad", "constraint_force_n"]
    )
    if door.size:
        header.append("door_angle")
    header += list(measured)
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(header)
    for i in range(len(readings)):
        row = [repr(float(v)) for v in readings[i]] + [repr(float(v)) for v in tau[i]]
        row += [repr(float(viol_m[i])), repr(float(viol_rad[i])), repr(float(force[i]))]
        if door.size:
            row.append(repr(float(door[i])))
        row += [repr(float(col[i])) for col in measured.values()]
        w.writerow(row)
    files.add(path, f.getvalue())
