"""Writing calibrated models: URDF (the input's XML, edited) and D-H YAML, always atomically.

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

from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.errors import InputError, ModelError
from closedloop.io.files import atomic_write_text, refuse_overwrite
from closedloop.model.robot import RobotModel
from closedloop.records import ParamStatus

#: the model file suffixes `write_model` writes for each input kind
MODEL_SUFFIXES = {"urdf": (".urdf",), "dh": (".yaml", ".yml"), "mjcf": (".xml", ".mjcf")}


def check_model_output(kind: str, out: str | Path | None, model: str | Path | None = None) -> None:
    """The calibrated model is written in the input's own format: its suffix must say so."""
    if out is None:
        return
    suffixes = MODEL_SUFFIXES.get(kind)
    if not suffixes:
        raise InputError(
            f"--out {out}: no calibrated model can be written for {kind} input {model or ''} "
            "(the report holds the parameters); drop --out"
        )
    if Path(out).suffix.lower() not in suffixes:
        raise InputError(
            f"--out {out}: a {kind} input gives a calibrated {kind} model; name it *{' or *'.join(suffixes)}"
        )


def write_urdf(
    robot: RobotModel,
    values: dict[str, float],
    out_path: str | Path,
    fold_offsets: bool = True,
    frames: list[tuple[str, str, np.ndarray]] = (),
) -> None:
    """Write the URDF of `robot` with joint origins moved by `values` (see module doc).

    `frames` (name, parent link, xyz): estimated tool points added as links on fixed joints
    (`tool_frames`), so the calibrated URDF carries the tool point it estimated.

    The input's XML is edited in place (ElementTree): only the ``<origin>`` (and,
    with folded offsets, the ``<limit>``) of the calibrated joints change; links,
    meshes (never loaded), comments and every other element are copied as they
    are.  Origins are written as URDF's ``xyz`` and ``rpy`` (R = Rz(y) Ry(p) Rx(r))
    at full precision.
    """
    import xml.etree.ElementTree as ET

    if robot.kind != "urdf" or robot.source is None:
        raise ModelError(
            f"{robot.source}: a calibrated URDF can only be written for URDF input "
            f"(this model is {robot.kind}); the report holds the parameters"
        )
    refuse_overwrite(out_path, robot.source)
    try:
        tree = ET.parse(str(robot.source), parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    except (ET.ParseError, OSError) as exc:
        raise ModelError(f"{robot.source}: cannot read this URDF ({exc})") from None
    by_name = {j.get("name"): j for j in tree.getroot().findall("joint")}
    for name in robot.joint_names:
        twist = np.array([values.get(f"{name}.{f}", 0.0) for f in ("x", "y", "z", "rx", "ry", "rz")])
        offset = values.get(f"{name}.offset", 0.0) if fold_offsets else 0.0
        if not np.any(twist) and offset == 0.0:
            continue
        j = by_name.get(name)
        if j is None:
            raise ModelError(f"{robot.source}: joint '{name}' not found in the URDF")
        origin = j.find("origin")
        O = _urdf_origin(origin, robot.source, name) @ pin.exp6(twist).homogeneous
        if offset:
            axis_el = j.find("axis")
            axis = _floats(axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0", 3, robot.source, name)
            axis /= np.linalg.norm(axis)
            T = np.eye(4)
            if j.get("type") == "prismatic":
                T[:3, 3] = axis * offset
            else:
                T[:3, :3] = pin.exp3(axis * offset)
            O = O @ T
            limit = j.find("limit")
            if limit is not None and j.get("type") != "continuous":
                for key in ("lower", "upper"):
                    if limit.get(key) is not None:
                        limit.set(key, str(float(limit.get(key)) - offset))
        if origin is None:
            origin = ET.Element("origin")
            j.insert(0, origin)
        origin.set("xyz", " ".join(repr(float(v)) for v in O[:3, 3]))
        origin.set("rpy", " ".join(repr(float(v)) for v in _rpy(O[:3, :3])))
    _add_frames(tree.getroot(), frames)
    atomic_write_text(out_path, ET.tostring(tree.getroot(), encoding="UTF-8", xml_declaration=True) + b"\n")


def _floats(text: str, n: int, source, joint: str) -> np.ndarray:
    try:
        v = np.array([float(t) for t in text.split()])
    except ValueError:
        v = np.zeros(0)
    if v.size != n:
        raise ModelError(f"{source}: joint '{joint}': expected {n} numbers, got '{text}'")
    return v


def _urdf_origin(origin, source, joint: str) -> np.ndarray:
    """The 4x4 transform of a URDF ``<origin xyz rpy>`` (identity when absent): R = Rz(y) Ry(p) Rx(r)."""
    T = np.eye(4)
    if origin is None:
        return T
    r, p, y = _floats(origin.get("rpy", "0 0 0"), 3, source, joint)
    T[:3, 3] = _floats(origin.get("xyz", "0 0 0"), 3, source, joint)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    return T


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw of a rotation (static x-y-z Euler angles; yaw 0 at pitch +-pi/2)."""
    cy = np.hypot(R[0, 0], R[1, 0])
    if cy > 4.0 * np.finfo(float).eps:
        return np.array([np.arctan2(R[2, 1], R[2, 2]), np.arctan2(-R[2, 0], cy), np.arctan2(R[1, 0], R[0, 0])])
    return np.array([np.arctan2(-R[1, 2], R[1, 1]), np.arctan2(-R[2, 0], cy), 0.0])


def write_dh(robot: RobotModel, values: dict[str, float], out_path: str | Path) -> None:
    """Write the calibrated D-H table (same units as the input)."""
    from closedloop.model.dh import dump_dh

    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, dump_dh(robot.dh, values))


def write_model(
    robot: RobotModel, values: dict[str, float], out_path: str | Path, frames: list[tuple[str, str, np.ndarray]] = ()
) -> None:
    """The calibrated model in the input's own format (URDF, MJCF or D-H YAML); `frames`: tool points (URDF)."""
    if robot.kind == "dh":
        write_dh(robot, values, out_path)
    elif robot.kind == "mjcf":
        from closedloop.output.mjcf import write_mjcf

        write_mjcf(robot, values, out_path)
    else:
        write_urdf(robot, values, out_path, frames=frames)


def tool_frames(result) -> list[tuple[str, str, np.ndarray]]:
    """The estimated tool points of a calibration as URDF frames: (name, parent link, xyz).

    One per tool point (a shared group once): ``<group or loop>_tip`` on the
    loop's frame A, at the calibrated ``tip_x, tip_y, tip_z``.
    """
    prob = result.problem
    out, seen = [], set()
    for b, cols in zip(prob.blocks, prob.loop_columns):
        names = [prob.names[k] for k in cols]
        idx = [next((k for k, n in zip(cols, names) if n.endswith(f".tip_{a}")), None) for a in "xyz"]
        if any(i is None for i in idx):
            continue
        owner = prob.names[idx[0]].rsplit(".", 1)[0]
        if owner in seen or any(result.status[i] not in (ParamStatus.ESTIMATED, ParamStatus.FIXED) for i in idx):
            continue
        seen.add(owner)
        out.append((f"{owner}_tip", b.loop.frame_a, np.array([result.values[i] for i in idx], dtype=float)))
    return out


def _add_frames(root, frames) -> None:
    """Links on fixed joints under existing links (a name already taken gets a suffix)."""
    import xml.etree.ElementTree as ET

    links = {el.get("name") for el in root.findall("link")}
    joints = {el.get("name") for el in root.findall("joint")}
    for name, parent, xyz in frames:
        if parent not in links:
            continue  # a joint frame or a frame of another format: the report has the point
        base, k = name, 1
        while name in links or f"{name}_joint" in joints:
            k += 1
            name = f"{base}{k}"
        link = ET.SubElement(root, "link", name=name)
        link.tail = "\n"
        j = ET.SubElement(root, "joint", name=f"{name}_joint", type="fixed")
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=name)
        ET.SubElement(j, "origin", xyz=" ".join(repr(float(v)) for v in xyz), rpy="0 0 0")
        j.tail = "\n"
        links.add(name)
        joints.add(f"{name}_joint")
