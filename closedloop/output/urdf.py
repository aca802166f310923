"""Writing calibrated models: URDF (the input's XML, edited) and D-H YAML, always atomically.

URDF convention.  A Pinocchio joint placement is F * O, with O the URDF joint
origin and F the fixed joints before it; the calibrated placement is
F * O * exp6(p) (right twist), so the new origin is exactly O * exp6(p).
Joint offsets are folded into the origin:  O <- O * Rot(axis, theta_off)
(a translation along the axis for prismatic joints), and the joint limits
shift by -theta_off, so the calibrated URDF takes the corrected readings
k * theta directly.  Scale factors k and compliances c cannot be expressed in
URDF: they are in the sensor file beside the model (`closedloop.output.report.write_sensors`) and
the report, and a joint value for the calibrated URDF is k * reading - c * tau.  What the loops
estimated (tool points, fixtures, sensors, planes) is added as links on fixed joints
(`model_frames`).

Each calibrated joint also keeps its input origin as ``<closedloop_nominal_origin xyz rpy>`` (the first
calibration's, through recalibrations; URDF readers ignore it): a recalibration from this file reads
its structure (what is redundant, which length holds the size) at that nominal geometry
(`closedloop.model.robot.RobotModel.calibrated_from`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import pinocchio as pin

from closedloop.errors import ModelError
from closedloop.io.files import atomic_write_text, refuse_overwrite
from closedloop.io.robot_files import NOMINAL_ORIGIN, urdf_floats, urdf_origin
from closedloop.model.robot import RobotModel


def write_urdf(
    robot: RobotModel,
    values: dict[str, float],
    out_path: str | Path,
    fold_offsets: bool = True,
    frames: Sequence[ModelFrame] = (),
) -> None:
    """Write `urdf_text` to `out_path` whole (never over the input)."""
    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, urdf_text(robot, values, out_path, fold_offsets, frames))


def urdf_text(
    robot: RobotModel,
    values: dict[str, float],
    out_path: str | Path,
    fold_offsets: bool = True,
    frames: Sequence[ModelFrame] = (),
) -> bytes:
    """The URDF of `robot` with joint origins moved by `values` (see module doc), to be written at
    `out_path` (relative mesh paths are rewritten for its folder).

    `frames` (name, parent frame, pose or xyz): what the calibration estimated about its loops (tool
    points, fixtures, sensors, planes; `model_frames`) added as links on fixed joints, so the
    calibrated URDF carries them.

    The input's XML is edited in place (ElementTree): only the ``<origin>`` (and,
    with folded offsets, the ``<limit>``) of the calibrated joints change, and relative
    mesh paths are rewritten for the output's folder (`relocate_meshes`); links,
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
        O = urdf_origin(origin, robot.source, name) @ pin.exp6(twist).homogeneous
        if offset:
            axis_el = j.find("axis")
            axis = urdf_floats(axis_el.get("xyz", "1 0 0") if axis_el is not None else "1 0 0", 3, robot.source, name)
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
                    bound = limit.get(key)
                    if bound is not None:
                        limit.set(key, str(float(bound) - offset))
        if j.find(NOMINAL_ORIGIN) is None:  # the first calibration's input: kept through recalibrations
            nominal = ET.SubElement(j, NOMINAL_ORIGIN)
            nominal.set("xyz", origin.get("xyz", "0 0 0") if origin is not None else "0 0 0")
            nominal.set("rpy", origin.get("rpy", "0 0 0") if origin is not None else "0 0 0")
        if origin is None:
            origin = ET.Element("origin")
            j.insert(0, origin)
        origin.set("xyz", " ".join(repr(float(v)) for v in O[:3, 3]))
        origin.set("rpy", " ".join(repr(float(v)) for v in _rpy(O[:3, :3])))
    _shift_mimics(by_name, values, fold_offsets)
    _add_frames(tree.getroot(), frames)
    relocate_meshes(tree.getroot(), Path(robot.source), Path(out_path))
    return ET.tostring(tree.getroot(), encoding="UTF-8", xml_declaration=True) + b"\n"


def _shift_mimics(by_name: dict, values: dict[str, float], fold_offsets: bool = True) -> None:
    """A coupled joint (``<mimic joint=f multiplier=m offset=o>``) follows f's joint value: m becomes the
    calibrated multiplier (``<joint>.mimic``) where there is one; with f's offset folded into its origin
    that value no longer contains it, so o becomes o + m * theta_off_f: the coupled joint stays where the
    fit put it (at m (k theta + theta_off_f) + o)."""
    for j in by_name.values():
        mimic = j.find("mimic")
        if mimic is None or not mimic.get("joint"):
            continue
        mult = float(mimic.get("multiplier", 1.0))
        if f"{j.get('name')}.mimic" in values and values[f"{j.get('name')}.mimic"] != mult:  # a calibrated coupling
            mult = float(values[f"{j.get('name')}.mimic"])
            mimic.set("multiplier", repr(mult))
        off = values.get(f"{mimic.get('joint')}.offset", 0.0) if fold_offsets else 0.0
        if off:
            mimic.set("offset", repr(float(mimic.get("offset", 0.0)) + mult * off))


def relocate_meshes(root, source: Path, out_path: Path) -> int:
    """Relative mesh and texture paths rewritten relative to the folder the URDF is written to.

    A relative ``filename`` is relative to the input's folder; written elsewhere it would point
    nowhere, so it becomes the path from the output's folder to the same file.  ``package://`` and
    other URIs and absolute paths are left as they are.  Returns the number of paths rewritten.
    """
    import os

    src_dir = source.resolve().parent
    out_dir = Path(out_path).resolve().parent
    if src_dir == out_dir:
        return 0
    n = 0
    for el in root.iter():
        if el.tag not in ("mesh", "texture") or not el.get("filename"):
            continue
        name = el.get("filename")
        if "://" in name or os.path.isabs(name):
            continue
        el.set("filename", Path(os.path.relpath(src_dir / name, out_dir)).as_posix())
        n += 1
    return n


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw of a rotation (static x-y-z Euler angles; yaw 0 at pitch +-pi/2)."""
    cy = np.hypot(R[0, 0], R[1, 0])
    if cy > 4.0 * np.finfo(float).eps:
        return np.array([np.arctan2(R[2, 1], R[2, 2]), np.arctan2(-R[2, 0], cy), np.arctan2(R[1, 0], R[0, 0])])
    return np.array([np.arctan2(-R[1, 2], R[1, 1]), np.arctan2(-R[2, 0], cy), 0.0])


def write_dh(robot: RobotModel, values: dict[str, float], out_path: str | Path) -> None:
    """Write the calibrated D-H table (`dh_text`) to `out_path` whole (never over the input)."""
    text = dh_text(robot, values)
    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, text)


def dh_text(robot: RobotModel, values: dict[str, float]) -> str:
    """The calibrated D-H table as YAML (same units as the input)."""
    from closedloop.model.dh import dump_dh

    if robot.dh is None:
        raise ModelError(f"{robot.source}: a {robot.kind} model, not a D-H table; write it as {robot.kind}")
    return dump_dh(robot.dh, values)


def write_model(
    robot: RobotModel, values: dict[str, float], out_path: str | Path, frames: Sequence[ModelFrame] = ()
) -> None:
    """Write the calibrated model (`model_text`) to `out_path` whole (never over the input)."""
    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, model_text(robot, values, out_path, frames))


def model_text(
    robot: RobotModel, values: dict[str, float], out_path: str | Path, frames: Sequence[ModelFrame] = ()
) -> str | bytes:
    """The calibrated model in the input's own format (URDF, MJCF or D-H YAML), to be written at
    `out_path`; `frames` (`model_frames`: tool points, fixtures) become links (URDF) or sites and bodies
    (MJCF); a D-H table cannot hold them (the report does)."""
    if robot.kind == "urdf":
        return urdf_text(robot, values, out_path, frames=frames)
    if robot.kind == "dh":
        return dh_text(robot, values)
    from closedloop.output.mjcf import calibrated_mjcf

    return calibrated_mjcf(robot, values, Path(out_path).parent, frames)


#: a written frame: (name, the model frame it hangs on, its pose in that frame; a bare xyz is a point)
ModelFrame = tuple[str, str, "pin.SE3 | np.ndarray"]


def model_frames(result) -> list[ModelFrame]:
    """What a calibration estimated about its loops, as frames of the written model.

    One frame per estimated (or given) quantity of a loop that has a place on the robot or in its
    world, a shared group once, named by its group or loop:

    * ``<owner>_tip``: a tool point (``tip_x, tip_y, tip_z``) on the loop's frame A;
    * ``<owner>_tool``: a measured loop's tool frame (``tool_x .. tool_rz``) on frame A;
    * ``<owner>_point``: a point loop's contact point (socket, ``px, py, pz``) in frame B;
    * ``<owner>_fixture``: a weld's closure X, the pose of frame A in frame B when closed (``x .. rz``);
    * ``<owner>_sensor``: a measured loop's sensor base X (tracker, ``x .. rz``) in frame B;
    * ``<owner>_plane``: a plane loop's plane in frame B, z along its normal n, origin at n d.

    Poses are ``X = (exp3(r), t)`` as the loops define them.  Hinges, passive chains and cameras are
    described in the report only.
    """
    prob = result.problem
    vals = dict(zip(prob.names, map(float, result.fit.values)))
    out: list[ModelFrame] = []
    seen: set[str] = set()

    def add(name: str, parent: str, pose) -> None:
        if name not in seen:
            seen.add(name)
            out.append((name, parent, pose))

    for b, cols in zip(prob.blocks, prob.loop_columns):
        lp = b.loop
        if getattr(lp, "parameter_only", False):
            continue
        names = [prob.names[k] for k in cols]
        by_field = {n.rsplit(".", 1)[1]: n for n in names}
        kind = getattr(lp, "kind", None) or type(lp).__name__

        def owner(fields: tuple[str, ...]) -> str:
            return by_field[fields[0]].rsplit(".", 1)[0]

        tip = ("tip_x", "tip_y", "tip_z")
        if all(f in by_field for f in tip):
            add(f"{owner(tip)}_tip", lp.frame_a, np.array([vals[by_field[f]] for f in tip]))
        elif getattr(lp, "tip", None) is not None and np.shape(lp.tip) == (3,):
            add(f"{lp.name}_tip", lp.frame_a, np.asarray(lp.tip, dtype=float))
        tool = tuple(f"tool_{f}" for f in ("x", "y", "z", "rx", "ry", "rz"))
        if all(f in by_field for f in tool):
            add(f"{owner(tool)}_tool", lp.frame_a, _pose([vals[by_field[f]] for f in tool]))
        point = ("px", "py", "pz")
        if all(f in by_field for f in point):
            add(f"{owner(point)}_point", lp.frame_b, np.array([vals[by_field[f]] for f in point]))
        pose = ("x", "y", "z", "rx", "ry", "rz")
        if all(f in by_field for f in pose):
            what = "fixture" if "Weld" in kind else "sensor"
            add(f"{owner(pose)}_{what}", lp.frame_b, _pose([vals[by_field[f]] for f in pose]))
        plane = ("nrx", "nry", "d")
        if all(f in by_field for f in plane) and hasattr(lp, "R0"):
            w = np.array([vals[by_field["nrx"]], vals[by_field["nry"]], 0.0])
            R = lp.R0 @ pin.exp3(w)
            add(f"{owner(plane)}_plane", lp.frame_b, pin.SE3(R, R[:, 2] * vals[by_field["d"]]))
    return out


def tool_frames(result) -> list[ModelFrame]:
    """The frames of `model_frames` (tool points, fixtures, sensors, planes): the name calibrate used first."""
    return model_frames(result)


def _pose(v) -> pin.SE3:
    """A loop pose from its six parameters: (exp3(r), t)."""
    v = np.asarray(v, dtype=float)
    return pin.SE3(pin.exp3(v[3:6]), v[:3].copy())


def as_se3(pose) -> pin.SE3:
    """A frame's pose: a pin.SE3 as it is, a bare xyz as a translation."""
    if isinstance(pose, pin.SE3):
        return pose
    return pin.SE3(np.eye(3), np.asarray(pose, dtype=float).reshape(3))


def _link_parents(root) -> tuple[set[str], dict[str, str], str | None]:
    """The URDF's links, each joint's child link, and its root link (never a child)."""
    links = [el.get("name") for el in root.findall("link")]
    child_of = {}
    children = set()
    for j in root.findall("joint"):
        c = j.find("child")
        if c is not None and j.get("name"):
            child_of[j.get("name")] = c.get("link")
            children.add(c.get("link"))
    roots = [n for n in links if n not in children]
    return set(links), child_of, roots[0] if roots else None


def _add_frames(root, frames) -> None:
    """Links on fixed joints under existing links (a name already taken gets a suffix).

    A frame on a joint's frame hangs on the joint's child link (URDF puts the link frame there), a
    frame on the world (``universe``, ``world``) on the root link; any other parent is not a link of
    this file and its frame is left to the report.
    """
    import xml.etree.ElementTree as ET

    links, child_of, root_link = _link_parents(root)
    joints = {el.get("name") for el in root.findall("joint")}
    for name, parent, pose in frames:
        M = as_se3(pose)
        if parent in ("universe", "world") and parent not in links:
            parent = root_link
        elif parent not in links and parent in child_of:
            parent = child_of[parent]
        if parent is None or parent not in links:
            continue  # not a link of this file: the report has the frame
        base, k = name, 1
        while name in links or f"{name}_joint" in joints:
            k += 1
            name = f"{base}{k}"
        link = ET.SubElement(root, "link", name=name)
        link.tail = "\n"
        j = ET.SubElement(root, "joint", name=f"{name}_joint", type="fixed")
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=name)
        ET.SubElement(
            j,
            "origin",
            xyz=" ".join(repr(float(v)) for v in M.translation),
            rpy=" ".join(repr(float(v)) for v in _rpy(M.rotation)),
        )
        j.tail = "\n"
        links.add(name)
        joints.add(f"{name}_joint")
