"""A simulated dataset's files: the log, the truth record, and the refusal to overwrite another dataset.

``log.csv``: the joint readings (header = joint names), then ``tau:<joint>``, ``violation_m``,
``violation_rad``, ``constraint_force_n``, ``door_angle`` (hinge loops) and the loop's measurement
columns (open loops); ``truth.json``: the scenario, seed, settings, the loop (type, frames, name, the
``--loop`` spec that calibrates it and its type's record), ``q0``, the true parameters, the violation and
sample counts (:func:`truth_record`); ``nominal.urdf``: the nominal robot the simulator plans with,
its links' visuals kept (:func:`with_visuals`, mesh paths made absolute) so that a viewer shows it.
:func:`next_commands`: the ``calibrate`` and ``check`` command lines for a dataset, as ``simulate``
prints them.
"""

from __future__ import annotations

import copy
import shlex
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from closedloop.errors import InputError
from closedloop.io.files import OutputSet
from closedloop.io.logs import write_log_csv
from closedloop.sims.loop_types import SIM_LOOPS, SimLoop
from closedloop.sims.scenarios import Scenario, SimSettings

__all__ = [
    "DATASET_FILES",
    "check_dataset_dir",
    "write_log",
    "truth_record",
    "loop_spec",
    "next_commands",
    "absolute_mesh_paths",
    "with_visuals",
]

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


def _mesh_file(name: str, source: Path) -> str:
    """A mesh reference of the URDF file `source` as an absolute path where the file is found.

    A relative path is taken from the URDF's folder; ``package://PKG/rest`` from the nearest folder
    named PKG above the URDF (the layout of a ROS package or of example-robot-data); anything else,
    or a file not found, is kept as written.
    """
    if name.startswith("package://"):
        pkg, _, rest = name[len("package://") :].partition("/")
        for folder in source.resolve().parents:
            if folder.name == pkg and (folder / rest).is_file():
                return str(folder / rest)
        return name
    if "://" in name or Path(name).is_absolute():
        return name
    path = (source.resolve().parent / name).resolve()
    return str(path) if path.is_file() else name


def absolute_mesh_paths(root: ET.Element, source: Path) -> ET.Element:
    """Every ``<mesh filename=...>`` of the URDF tree `root` (read from `source`) made absolute where found
    (so that the URDF written elsewhere still shows its meshes); edits and returns `root`."""
    for mesh in root.iter("mesh"):
        if mesh.get("filename"):
            mesh.set("filename", _mesh_file(mesh.get("filename", ""), Path(source)))
    return root


def with_visuals(cleaned: str, source: Path) -> str:
    """The cleaned nominal URDF text with the ``<visual>`` elements of the robot file `source` put back.

    Each link of `cleaned` gets its visuals from the link of the same name in `source`, and the
    file's top-level materials come along; mesh paths are made absolute (:func:`absolute_mesh_paths`).
    The kinematics, inertias and everything else are the cleaned file's.  `cleaned` as it is when
    `source` cannot be read.
    """
    try:
        original = ET.parse(source).getroot()
    except (OSError, ET.ParseError):
        return cleaned
    absolute_mesh_paths(original, Path(source))
    visuals = {link.get("name"): link.findall("visual") for link in original.findall("link")}
    root = ET.fromstring(cleaned)
    for link in root.findall("link"):
        for k, visual in enumerate(visuals.get(link.get("name"), [])):
            link.insert(k, copy.deepcopy(visual))
    for k, material in enumerate(original.findall("material")):
        root.insert(k, copy.deepcopy(material))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")


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
    loop_info["calibrate"] = loop_spec(sc, kind, settings)
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


def loop_spec(sc: Scenario, kind: SimLoop, settings: SimSettings) -> str:
    """The ``--loop`` spec ``calibrate`` takes for the scenario's loop: its registry type, the frames of
    the dataset's ``nominal.urdf`` (a ``tool`` link included), the loop name and the type's own keys."""
    keys = {"frame": sc.tool_frame, **({"to": sc.target_frame} if sc.target_frame else {}), "name": sc.loop_name}
    keys.update(kind.calibrate_keys(settings))
    return f"{sc.loop_type}:" + ",".join(f"{k}={v}" for k, v in keys.items())


def next_commands(out: str | Path, truth: dict[str, Any]) -> list[str]:
    """``closedloop calibrate`` and ``closedloop check`` command lines for the dataset in `out` (its truth).

    The loop is the one ``truth.json`` records (``loop.calibrate``, or a head-camera dataset's
    ``calibrate_loop``); a known joint noise is given (``--noise``); a head-camera dataset is checked
    at its documented tolerances (``check_tolerances``).  Empty when the truth names no loop.
    """
    loop = truth.get("loop")
    if not isinstance(loop, dict):
        loop = {}
    spec = loop.get("calibrate") or truth.get("calibrate_loop")
    if not spec:
        return []
    d = Path(out)
    q = lambda p: shlex.quote(str(p))  # noqa: E731
    calib = [
        "closedloop calibrate",
        q(d / "nominal.urdf"),
        q(d / "log.csv"),
        "--loop",
        q(spec),
        "--out",
        q(d / "calibrated.urdf"),
        "--report",
        q(d / "report.json"),
    ]
    settings = truth.get("settings")
    if not isinstance(settings, dict):
        settings = {}
    noise = truth.get("noise", {}).get("sigma_q") if isinstance(truth.get("noise"), dict) else settings.get("noise")
    if isinstance(noise, (int, float)) and noise > 0:
        calib += ["--noise", f"{noise:g}"]
    tols = truth.get("check_tolerances") or {}
    check = ["closedloop check", q(d / "truth.json"), q(d / "report.json")]
    check += [f"--{k.replace('_', '-')} {v:g}" for k, v in tols.items()]
    return [" ".join(calib), " ".join(check)]


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
    """Stage the calibration log in `files` (`io.logs.write_log_csv`): joint readings first, then
    diagnostic columns, then measurements."""
    columns = {j: readings[:, k] for k, j in enumerate(joint_names)}
    columns |= {f"tau:{j}": tau[:, k] for k, j in enumerate(joint_names)}
    columns |= {"violation_m": viol_m, "violation_rad": viol_rad, "constraint_force_n": force}
    if door.size:
        columns["door_angle"] = door
    write_log_csv(path, columns | dict(measured or {}), files)
