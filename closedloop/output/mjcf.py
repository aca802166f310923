"""The calibrated MJCF of an MJCF robot, written with ``mujoco.MjSpec``.

Convention (the same as the calibrated URDF, :mod:`closedloop.output.urdf`).  Pinocchio reads an MJCF
joint of body b as the frame ``F_b = B_b Trans(p_b)``: the body frame moved to the joint anchor
``p_b`` (``jnt_pos``, body coordinates), the body's orientation.  Calibration moves it to
``F_b' = F_b exp6(v_b) Rot(a_b, theta_off_b)`` (placement twist ``v_b`` in the joint's own frame,
the offset folded about the joint axis ``a_b``; a translation ``a_b theta_off`` for a slide joint),
which is the body pose (in its parent's frame)

    P_b' = P_b Trans(p_b) exp6(v_b) Rot(a_b, theta_off_b) Trans(-p_b).

The anchor and the axis keep their body coordinates, the children keep their poses in the body
frame, so everything downstream moves with the joint frame exactly as in the Pinocchio model.
Joint ranges shift by ``-theta_off`` (the calibrated MJCF takes the readings directly).  Scale
factors and compliance cannot be expressed in MJCF: they are in the sensor file beside the model
(`closedloop.output.report.write_sensors`) and the report; a joint value for the model is
``scale * reading - compliance * tau``.

Only the pose of a body with a calibrated joint is rewritten (``pos`` and ``quat``, computed from
MuJoCo's compiled model, so ``euler``/``axisangle`` and ``angle="degree"`` inputs work); everything
else (geoms, meshes, actuators, defaults) stays as the input wrote it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import pinocchio as pin

from closedloop.errors import ModelError
from closedloop.model.robot import RobotModel

if TYPE_CHECKING:
    from closedloop.output.urdf import ModelFrame

log = logging.getLogger(__name__)

_FIELDS = ("x", "y", "z", "rx", "ry", "rz")


def body_correction(anchor: np.ndarray, axis: np.ndarray, twist: np.ndarray, offset: float, prismatic: bool) -> pin.SE3:
    """``Trans(p) exp6(v) Rot(a, theta_off) Trans(-p)`` (module doc)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    off = pin.SE3(np.eye(3), a * offset) if prismatic else pin.SE3(pin.exp3(a * offset), np.zeros(3))
    T = pin.SE3(np.eye(3), np.asarray(anchor, dtype=float))
    return T * pin.exp6(pin.Motion(np.asarray(twist, dtype=float))) * off * T.inverse()


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in np.atleast_1d(v))


def calibrated_mjcf(
    robot: RobotModel, values: dict[str, float], out_dir: str | Path | None = None, frames: Sequence[ModelFrame] = ()
) -> str:
    """The MJCF text of ``robot`` (an MJCF model) with the calibrated joint frames.

    MuJoCo (``MjSpec``) compiles the input and gives each calibrated body's pose, joint anchor
    and axis in its parent's frame; the new pose is written into the input's own XML element
    (``pos`` and ``quat``, 17 significant digits; ``MjSpec.to_xml`` keeps 6, a rounding of up to
    0.5 um on a 1 m arm, too coarse for a calibration), so the rest of the file stays as written.
    With ``out_dir`` other than the input's directory, relative asset paths are rewritten relative to
    ``out_dir`` (`_rebase_assets`).  `frames` (`closedloop.output.urdf.model_frames`: tool points,
    fixtures, sensors) are added as joint-less ``<body>`` elements: a frame on a body (or a site) as a
    child of that body, which both MuJoCo and Pinocchio read as a frame (Pinocchio places a site of a
    nested fixed body wrongly, a body rightly), a frame on the world as a body of the worldbody
    (MuJoCo's static frame; Pinocchio does not read joint-less world bodies: the sensor file and the
    report hold their values too).
    """
    import xml.etree.ElementTree as ET

    import mujoco

    if robot.kind != "mjcf" or robot.source is None:
        raise ModelError(
            f"{robot.source}: a calibrated MJCF can only be written for MJCF input (this model is {robot.kind})"
        )
    src = Path(robot.source)
    try:
        spec = mujoco.MjSpec.from_file(str(src))
        model = spec.compile()
        root = ET.parse(src).getroot()
    except Exception as exc:
        raise ModelError(f"{src}: MuJoCo cannot load this MJCF ({str(exc).splitlines()[0]})") from None
    bodies = {b.get("name"): b for b in root.iter("body") if b.get("name")}
    for name in robot.joint_names:
        twist = np.array([values.get(f"{name}.{f}", 0.0) for f in _FIELDS])
        offset = float(values.get(f"{name}.offset", 0.0))
        if not np.any(twist) and offset == 0.0:
            continue
        jid = model.joint(name).id
        bid = int(model.jnt_bodyid[jid])
        bname = model.body(bid).name
        if int(model.body_jntnum[bid]) != 1:
            raise ModelError(
                f"{src}: body '{bname}' has {model.body_jntnum[bid]} joints; a calibrated MJCF needs "
                "one joint per calibrated body"
            )
        el = bodies.get(bname)
        sb = spec.body(bname)
        if el is None or sb is None or sb.frame is not None:
            raise ModelError(
                f"{src}: joint '{name}': its body '{bname}' is not a named <body> of this file outside "
                "any <frame> (an included file?); a calibrated MJCF cannot be written"
            )
        prismatic = int(model.jnt_type[jid]) == int(mujoco.mjtJoint.mjJNT_SLIDE)
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.body_quat[bid])
        P = pin.SE3(R.reshape(3, 3), model.body_pos[bid].copy())
        P = P * body_correction(model.jnt_pos[jid], model.jnt_axis[jid], twist, offset, prismatic)
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(P.rotation).reshape(9))
        for attr in ("euler", "axisangle", "xyaxes", "zaxis"):
            el.attrib.pop(attr, None)
        el.set("pos", _fmt(P.translation))
        el.set("quat", _fmt(q))
        if offset and model.jnt_limited[jid]:
            jel = next((j for j in el.findall("joint") if j.get("name") == name), None)
            lo, hi = model.jnt_range[jid] - offset  # radians / metres
            if jel is None:
                raise ModelError(f"{src}: joint '{name}' is not a <joint> element of its body")
            deg = spec.compiler.degree and not prismatic
            jel.set("range", _fmt(np.degrees([lo, hi]) if deg else [lo, hi]))
        if model.qpos0[model.jnt_qposadr[jid]] != 0.0:
            log.warning(
                "%s: joint %s has ref=%g; its reading is taken relative to it",
                src,
                name,
                float(model.qpos0[model.jnt_qposadr[jid]]),
            )
    _add_sites(root, model, frames, src)
    _check_compiles(root, src)  # (asset paths still the input's)
    if out_dir is not None and Path(out_dir).resolve() != src.resolve().parent:
        _rebase_assets(root, src, Path(out_dir))
    return ET.tostring(root, encoding="unicode")


def _add_sites(root, model, frames, src: Path) -> None:
    """`frames` into the MJCF: child bodies of the bodies they hang on or of the worldbody (docstring above).

    A frame on a site hangs on the site's body with the site's pose composed in; a name already taken
    by a body or site gets a suffix; a parent that is neither a body nor a site of this file is left to
    the report.
    """
    import xml.etree.ElementTree as ET

    import mujoco

    bodies = {b.get("name"): b for b in root.iter("body") if b.get("name")}
    sites = {s_.get("name") for s_ in root.iter("site") if s_.get("name")}
    world = root.find("worldbody")
    for name, parent, pose in frames:
        M = pose if isinstance(pose, pin.SE3) else pin.SE3(np.eye(3), np.asarray(pose, dtype=float).reshape(3))
        if parent in ("universe", "world"):
            el, tag = world, "body"
        elif parent in bodies:
            el, tag = bodies[parent], "body"
        elif parent in sites:
            sid = model.site(parent).id
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, model.site_quat[sid])
            M = pin.SE3(R.reshape(3, 3), model.site_pos[sid].copy()) * M
            bname = model.body(int(model.site_bodyid[sid])).name
            el, tag = (bodies.get(bname), "body") if bname != "world" else (world, "body")
        else:
            continue
        if el is None:
            continue
        base, k = name, 1
        while name in bodies or name in sites:
            k += 1
            name = f"{base}{k}"
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(M.rotation).reshape(9))
        new = ET.SubElement(el, tag, name=name, pos=_fmt(M.translation), quat=_fmt(q))
        if tag == "body":
            bodies[name] = new
        else:
            sites.add(name)


def _rebase_assets(root, src: Path, out_dir: Path | None) -> None:
    """Relative asset directories and included files rewritten for a file written in `out_dir` (None: made
    absolute, for a copy compiled from memory).

    MuJoCo finds meshes and textures in ``meshdir``/``texturedir`` (else ``assetdir``, else the model's
    folder) relative to the model file, and included files relative to it too: each becomes the path
    from `out_dir` to the same place.  Absolute paths stay.
    """
    import os
    import xml.etree.ElementTree as ET

    src_dir = src.resolve().parent

    def rebased(rel: str) -> str:
        target = src_dir / rel
        return str(target.resolve()) if out_dir is None else Path(os.path.relpath(target, out_dir.resolve())).as_posix()

    comp = root.find("compiler")
    if comp is None:
        comp = ET.Element("compiler")
        root.insert(0, comp)
    for attr in ("meshdir", "texturedir"):
        d = comp.get(attr, comp.get("assetdir", ""))
        if not Path(d).is_absolute():
            comp.set(attr, rebased(d))
    for inc in root.iter("include"):
        f = inc.get("file")
        if f and not Path(f).is_absolute():
            inc.set("file", rebased(f))


def _check_compiles(root, src: Path) -> None:
    """The calibrated MJCF must load in MuJoCo (checked on a copy with absolute asset paths)."""
    import copy
    import xml.etree.ElementTree as ET

    import mujoco

    if root.find(".//include") is not None:
        return  # included files resolve relative to the written file only
    probe = copy.deepcopy(root)
    _rebase_assets(probe, src, None)
    try:
        mujoco.MjModel.from_xml_string(ET.tostring(probe, encoding="unicode"))
    except Exception as exc:
        raise ModelError(f"{src}: the calibrated MJCF does not load in MuJoCo ({str(exc).splitlines()[0]})") from None


def write_mjcf(
    robot: RobotModel, values: dict[str, float], out_path: str | Path, frames: Sequence[ModelFrame] = ()
) -> None:
    """Write `calibrated_mjcf` to `out_path` whole (assets found from wherever it is written; `frames` added)."""
    from closedloop.io.files import atomic_write_text, refuse_overwrite

    refuse_overwrite(out_path, robot.source)
    atomic_write_text(out_path, calibrated_mjcf(robot, values, Path(out_path).parent, frames))
