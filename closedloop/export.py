"""Writing calibrated models: URDF (yourdfpy) and D-H YAML, always atomically.

URDF convention.  A Pinocchio joint placement is F * O, with O the URDF joint
origin and F the fixed joints before it; the calibrated placement is
F * O * exp6(p) (right twist), so the new origin is exactly O * exp6(p).
Joint offsets are folded into the origin:  O <- O * Rot(axis, theta_off)
(a translation along the axis for prismatic joints), and the joint limits
shift by -theta_off, so the calibrated URDF takes the corrected readings
k * theta directly.  Scale factors k cannot be expressed in URDF: they are in
the report, and a joint value for the calibrated URDF is k * reading.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import pinocchio as pin

from .errors import InputError, ModelError
from .robot import RobotModel


def atomic_write(path: str | Path, writer: Callable[[str], None]) -> None:
    """Call `writer(tmp_path)` on a temporary file beside `path`, then os.replace it onto `path`.

    Readers see either the old file or the complete new one, never a partial write.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write `text` to `path` atomically."""
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def refuse_overwrite(out: str | Path, *inputs: str | Path | None) -> None:
    """An output must never replace one of the user's inputs."""
    o = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == o:
            raise InputError(f"{out}: refusing to overwrite an input file; choose another output path")


def write_urdf(robot: RobotModel, values: dict[str, float], out_path: str | Path, fold_offsets: bool = True) -> None:
    """Write the URDF of `robot` with joint origins moved by `values` (see module doc)."""
    import yourdfpy

    if robot.kind != "urdf" or robot.source is None:
        raise ModelError(f"{robot.source}: a calibrated URDF can only be written for URDF input "
                         f"(this model is {robot.kind}); the report holds the parameters")
    refuse_overwrite(out_path, robot.source)
    try:
        urdf = yourdfpy.URDF.load(str(robot.source), build_scene_graph=False, build_collision_scene_graph=False,
                                  load_meshes=False, load_collision_meshes=False)
    except Exception as exc:
        raise ModelError(f"{robot.source}: yourdfpy cannot read this URDF ({exc})") from None
    by_name = {j.name: j for j in urdf.robot.joints}
    for name in robot.joint_names:
        twist = np.array([values.get(f"{name}.{f}", 0.0) for f in ("x", "y", "z", "rx", "ry", "rz")])
        offset = values.get(f"{name}.offset", 0.0) if fold_offsets else 0.0
        if not np.any(twist) and offset == 0.0:
            continue
        j = by_name.get(name)
        if j is None:
            raise ModelError(f"{robot.source}: joint '{name}' not found by yourdfpy")
        O = np.eye(4) if j.origin is None else np.array(j.origin, dtype=float)
        O = O @ pin.exp6(twist).homogeneous
        if offset:
            axis = np.array(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=float)
            axis /= np.linalg.norm(axis)
            T = np.eye(4)
            if j.type == "prismatic":
                T[:3, 3] = axis * offset
            else:
                T[:3, :3] = pin.exp3(axis * offset)
            O = O @ T
            if j.limit is not None and j.type != "continuous":
                if j.limit.lower is not None:
                    j.limit.lower = float(j.limit.lower - offset)
                if j.limit.upper is not None:
                    j.limit.upper = float(j.limit.upper - offset)
        j.origin = O
    atomic_write(out_path, urdf.write_xml_file)


def write_dh(robot: RobotModel, values: dict[str, float], out_path: str | Path) -> None:
    """Write the calibrated D-H table (same units as the input)."""
    from .dh import dump_dh

    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, dump_dh(robot.dh, values))


def write_model(robot: RobotModel, values: dict[str, float], out_path: str | Path) -> None:
    """The calibrated model in the input's own format (URDF or D-H YAML)."""
    if robot.kind == "dh":
        write_dh(robot, values, out_path)
    else:
        write_urdf(robot, values, out_path)
