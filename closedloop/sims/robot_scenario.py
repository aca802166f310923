"""Simulate any robot: a user's URDF (or MJCF) made into a simulator scenario, with automatic choices.

``closedloop simulate --robot ROBOT.urdf --loop weld:frame=tool`` (or a scenario YAML whose
``robot:`` is a file) goes through :func:`prepare_robot`:

1. the robot file is read (an MJCF is converted to an equivalent URDF: one link per body, the
   joint's anchor as the link origin, sites as fixed links; :func:`mjcf_to_urdf`);
2. a ``tool: {xyz: [...]}`` adds a stylus link on the loop frame (a point, plane or tracker loop
   needs a tip off the flange axis);
3. the **driven joints** are the movable joints between the base and the loop frame(s) (for two
   chains, below their common ancestor); ``joints:`` chooses a subset; every other joint becomes
   fixed at its zero (fingers, a torso, a head), a continuous joint (or a revolute one without a
   range, as a wheel is written) gets limits of +-pi; a floating or planar base joint is fixed (the
   base stands still during a calibration); a joint held fixed is marked
   ``<closedloop_held type="revolute"/>`` in the written ``nominal.urdf``
   (:data:`closedloop.io.robot_files.HELD`: the log has no readings of it, and ``calibrate``
   refuses a loop through it, naming it);
4. the loop must leave the closed chain a self-motion (thesis Lemma 4): with n driven joints and
   m independent constraints (weld 6, hinge 6 minus the door's own joint, point 3, plane 1),
   ``n - m >= 1``; otherwise a plain-words error says what to change;
5. the **grasp pose** ``q0``, unless given, is the best of 400 random configurations in the middle
   70 % of the joint ranges (seed 0): the largest smallest singular value of the constraint
   Jacobian (rotation rows times the arm's reach), i.e. the pose farthest from a singularity of
   the loop.  The **fixture placement** follows: the fixture, socket, door, plane or partner frame
   is put where the true tool is at ``q0`` (:mod:`closedloop.sims.scene`), so a different ``q0``
   moves it.

A point contact (point, plane, tracker) on the axis of the last driven joint is refused
(:func:`closedloop.model.axes.blind_joints`): that joint could not move it.

The prepared URDF is registered in :data:`closedloop.assets.catalog.ROBOTS` under the file's stem (a
temporary file kept for the process), so :func:`closedloop.sims.simulate` runs it like a built-in.
"""

from __future__ import annotations

import atexit
import difflib
import logging
import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.errors import InputError
from closedloop.io.robot_files import HELD, check_mjcf, check_urdf
from closedloop.model.axes import blind_joints, point_on_axis_message
from closedloop.model.robot import find_frame
from closedloop.sims.loop_types import sim_loop

log = logging.getLogger(__name__)

MOVABLE = ("revolute", "continuous", "prismatic")
BASES = ("floating", "planar")  # joints of a base that moves in the world: held still
_TMP: list[str] = []


@dataclass(frozen=True)
class PreparedRobot:
    """A robot ready for the simulator: registry key, loop frame, driven joints and grasp pose."""

    key: str
    path: Path
    frame: str
    joints: tuple[str, ...]
    q0: tuple[float, ...]


def _tmpdir() -> Path:
    if not _TMP:
        _TMP.append(tempfile.mkdtemp(prefix="closedloop-robots-"))
        atexit.register(shutil.rmtree, _TMP[0], True)
    return Path(_TMP[0])


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in np.atleast_1d(v))


# --------------------------------------------------------------------------- MJCF -> URDF
def mjcf_to_urdf(path: Path) -> str:
    """An equivalent URDF of an MJCF robot (kinematics and inertias; one hinge/slide joint per body).

    Link frame = body frame moved to the joint anchor (``jnt_pos``, same orientation), so a URDF
    joint turns about its origin; sites become fixed links of the same name.
    """
    import mujoco

    try:
        m = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:
        raise InputError(f"{path}: MuJoCo cannot load this MJCF ({str(exc).splitlines()[0]})") from None
    root = ET.Element("robot", name=Path(path).stem)

    def name(t, i: int) -> str:
        return mujoco.mj_id2name(m, t, i) or f"{'body' if t == mujoco.mjtObj.mjOBJ_BODY else 'site'}{i}"

    anchor = np.zeros((m.nbody, 3))  # link frame = body frame + anchor
    ET.SubElement(root, "link", name=name(mujoco.mjtObj.mjOBJ_BODY, 0))
    for b in range(1, m.nbody):
        bn = name(mujoco.mjtObj.mjOBJ_BODY, b)
        joints = [j for j in range(m.njnt) if m.jnt_bodyid[j] == b]
        kinds = [int(m.jnt_type[j]) for j in joints]
        if len(joints) > 1 or any(k in (int(mujoco.mjtJoint.mjJNT_BALL),) for k in kinds):
            raise InputError(
                f"{path}: body '{bn}' has {len(joints)} joints or a ball joint; the simulator "
                "handles one hinge or slide joint per body"
            )
        free = bool(kinds) and kinds[0] == int(mujoco.mjtJoint.mjJNT_FREE)
        if joints and not free:
            anchor[b] = m.jnt_pos[joints[0]]
        link = ET.SubElement(root, "link", name=bn)
        inert = ET.SubElement(link, "inertial")
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, m.body_iquat[b])
        ET.SubElement(
            inert, "origin", xyz=_fmt(m.body_ipos[b] - anchor[b]), rpy=_fmt(pin.rpy.matrixToRpy(R.reshape(3, 3)))
        )
        ET.SubElement(inert, "mass", value=repr(float(m.body_mass[b])))
        ixx, iyy, izz = (float(v) for v in m.body_inertia[b])
        ET.SubElement(inert, "inertia", ixx=repr(ixx), iyy=repr(iyy), izz=repr(izz), ixy="0", ixz="0", iyz="0")
        p = int(m.body_parentid[b])
        mujoco.mju_quat2Mat(R, m.body_quat[b])
        xyz = m.body_pos[b] - anchor[p] + R.reshape(3, 3) @ anchor[b]
        kind = (
            "fixed"
            if not joints or free
            else ("prismatic" if kinds[0] == int(mujoco.mjtJoint.mjJNT_SLIDE) else "revolute")
        )
        jn = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, joints[0]) if joints and not free else f"{bn}_fixed"
        j = ET.SubElement(root, "joint", name=jn, type=kind)
        ET.SubElement(j, "parent", link=name(mujoco.mjtObj.mjOBJ_BODY, p))
        ET.SubElement(j, "child", link=bn)
        ET.SubElement(j, "origin", xyz=_fmt(xyz), rpy=_fmt(pin.rpy.matrixToRpy(R.reshape(3, 3))))
        if kind != "fixed":
            ET.SubElement(j, "axis", xyz=_fmt(m.jnt_axis[joints[0]]))
            lo, hi = m.jnt_range[joints[0]] if m.jnt_limited[joints[0]] else (-np.pi, np.pi)
            ET.SubElement(j, "limit", lower=repr(float(lo)), upper=repr(float(hi)), effort="100", velocity="10")
    for s in range(m.nsite):
        sn, b = name(mujoco.mjtObj.mjOBJ_SITE, s), int(m.site_bodyid[s])
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, m.site_quat[s])
        ET.SubElement(root, "link", name=sn)
        j = ET.SubElement(root, "joint", name=f"{sn}_site", type="fixed")
        ET.SubElement(j, "parent", link=name(mujoco.mjtObj.mjOBJ_BODY, b))
        ET.SubElement(j, "child", link=sn)
        ET.SubElement(j, "origin", xyz=_fmt(m.site_pos[s] - anchor[b]), rpy=_fmt(pin.rpy.matrixToRpy(R.reshape(3, 3))))
    return ET.tostring(root, encoding="unicode")


# --------------------------------------------------------------------------- URDF preparation
def _read(path: Path, where: str) -> ET.Element:
    """The robot file as a URDF tree, checked first as `calibrate` and `inspect` check it
    (`closedloop.io.robot_files.check_urdf`, `check_mjcf`): a typo is named in one line (the joint, the
    element) before Pinocchio or MuJoCo would reject the prepared file in their own words."""
    if not path.is_file():
        raise InputError(f"{where}: no such robot file {path}")
    if path.suffix.lower() in (".yaml", ".yml"):
        raise InputError(
            f"{where}: {path} is a D-H table: the simulator takes a URDF or MJCF file (links, joints and their "
            "inertias); a D-H table is calibrated from a log of the robot (closedloop calibrate TABLE LOG ...)"
        )
    if path.suffix.lower() in (".xml", ".mjcf"):
        check_mjcf(path)
        return ET.fromstring(mjcf_to_urdf(path))
    check_urdf(path, one_root=False)  # a second root (a table beside the robot) is noted when prepared
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"{path}: not valid XML ({exc})") from None


def _joint_link(joint: ET.Element, tag: str, path: Path) -> str:
    """The link a URDF joint's ``<parent>`` or ``<child>`` (`tag`) names."""
    el = joint.find(tag)
    link = None if el is None else el.get("link")
    if link is None:
        raise InputError(f"{path}: joint '{joint.get('name')}' has no <{tag} link=...>")
    return link


def _path_joints(root: ET.Element, link: str, path: Path) -> list[ET.Element]:
    """Joints from the root down to `link`."""
    by_child = {_joint_link(j, "child", path): j for j in root.findall("joint")}
    out = []
    while link in by_child:
        j = by_child[link]
        out.append(j)
        link = _joint_link(j, "parent", path)
    return out[::-1]


def _check_link(root: ET.Element, name: str, path: Path, what: str) -> None:
    links = [lk.get("name", "") for lk in root.findall("link")]
    if name not in links:
        close = difflib.get_close_matches(name, links, n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else f" (links: {', '.join(links[:12])} ...)"
        raise InputError(f"{path}: no link '{name}' for the loop's {what}{hint}; the simulator closes loops on links")


def _no_range(joint: ET.Element) -> bool:
    """A joint whose ``<limit>`` gives no range (``lower`` and ``upper`` absent or equal)."""
    lim = joint.find("limit")
    if lim is None:
        return True
    try:
        return float(lim.get("lower", "0")) >= float(lim.get("upper", "0"))
    except ValueError:
        return False


def _keep_tree(root: ET.Element, frame: str, path: Path) -> list[ET.Element]:
    """Drop, from a URDF with several root links, the trees that do not hold `frame` (one note naming
    their roots); return the remaining root link."""
    parent = {_joint_link(j, "child", path): _joint_link(j, "parent", path) for j in root.findall("joint")}
    top = frame
    while top in parent:
        top = parent[top]
    kept = {top}
    changed = True
    while changed:  # the links below the kept root (no recursion: deep trees are legal)
        changed = False
        for child, par in parent.items():
            if par in kept and child not in kept:
                kept.add(child)
                changed = True
    dropped_roots = [
        lk.get("name") for lk in root.findall("link") if lk.get("name") not in parent and lk.get("name") != top
    ]
    for lk in [lk for lk in root.findall("link") if lk.get("name") not in kept]:
        root.remove(lk)
    for j in [j for j in root.findall("joint") if _joint_link(j, "child", path) not in kept]:
        root.remove(j)
    log.warning(
        "note: %s: %d root links; the tree of %s (root %s) is simulated, the one(s) rooted at %s dropped "
        "(join them with a fixed joint to keep them)",
        path.name,
        len(dropped_roots) + 1,
        frame,
        top,
        ", ".join(str(r) for r in dropped_roots),
    )
    return [lk for lk in root.findall("link") if lk.get("name") == top]


def _prepare_tree(root: ET.Element, path: Path, loop_type: str, frame: str, to: str | None, tool, joints):
    """Tool link, driven joints (others fixed), continuous -> revolute; returns (frame, driven names)."""
    if tool:
        tool = dict(tool)
        _check_link(root, frame, path, "frame")
        new = str(tool.get("name", f"{frame}_tip"))
        ET.SubElement(root, "link", name=new)  # massless: closedloop.assets.catalog.clean_urdf_tree gives it an inertia
        j = ET.SubElement(root, "joint", name=f"{new}_joint", type="fixed")
        ET.SubElement(j, "parent", link=frame)
        ET.SubElement(j, "child", link=new)
        ET.SubElement(j, "origin", xyz=_fmt(tool.get("xyz", [0, 0, 0])), rpy=_fmt(tool.get("rpy", [0, 0, 0])))
        frame = new
    _check_link(root, frame, path, "frame")
    chain = _path_joints(root, frame, path)
    if to is not None:
        _check_link(root, to, path, "'to' frame")
        other = _path_joints(root, to, path)
        common = {id(j) for j in chain} & {id(j) for j in other}
        chain = [j for j in chain + other if id(j) not in common]
    for j in root.findall("joint"):  # a floating or planar base stands still while a loop is calibrated
        if j.get("type") in BASES:
            log.info("%s: %s joint %s held fixed (the base stands still)", path, j.get("type"), j.get("name"))
            j.set("type", "fixed")
    movable = [j.get("name", "") for j in chain if j.get("type") in MOVABLE]
    bad = [f"{j.get('name')} ({j.get('type')})" for j in chain if j.get("type") not in MOVABLE + ("fixed",)]
    if bad:
        raise InputError(
            f"{path}: joint(s) {', '.join(bad)} on the way to {frame}: the simulator drives revolute, "
            "continuous and prismatic joints only; write a ball joint as three revolute joints"
        )
    if joints:
        unknown = [j for j in joints if j not in movable]
        if unknown:
            raise InputError(
                f"{path}: joint(s) {', '.join(unknown)} do not move {frame} "
                f"(the movable joints on its chain: {', '.join(movable)})"
            )
        movable = [j for j in movable if j in joints]
    for j in root.findall("joint"):
        if j.get("name", "") not in movable:
            if j.get("type") != "fixed" and all(j is not c for c in chain):
                log.info("%s: joint %s held fixed at 0 (not on the loop's chain)", path, j.get("name"))
                # marked, so that calibrate refuses a loop through it before any work (io.robot_files.HELD);
                # a joint of the loop's own chain left out by `joints` is rigid in the truth as in the model
                ET.SubElement(j, HELD, type=j.get("type", ""))
            j.set("type", "fixed")
            for tag in ("mimic", "axis", "limit"):
                for el in j.findall(tag):
                    j.remove(el)
        elif j.get("type") == "continuous" or (j.get("type") == "revolute" and _no_range(j)):
            # a revolute joint written without a range (lower = upper, URDF's default 0) turns freely
            j.set("type", "revolute")
            lim = j.find("limit")
            if lim is None:
                lim = ET.SubElement(j, "limit", effort="100", velocity="10")
            lim.set("lower", repr(-np.pi))
            lim.set("upper", repr(np.pi))
        elif j.find("mimic") is not None:
            plain = [m.get("name", "") for m in chain if m.get("name") in movable and m.find("mimic") is None]
            raise InputError(
                f"{path}: joint {j.get('name')} mimics another joint (<mimic>), which the simulator does not "
                f"drive; leave it out: --joints {','.join(plain)} (joints: in a scenario file), or close the "
                "loop on a link before it"
            )
    children = {_joint_link(j, "child", path) for j in root.findall("joint")}
    roots = [lk for lk in root.findall("link") if lk.get("name") not in children]
    if len(roots) > 1:  # several trees in one file: the loop's is simulated, the others dropped
        roots = _keep_tree(root, frame, path)
    # a root link named 'world' clashes with MuJoCo's world body: drop it (its child becomes the root)
    if len(roots) == 1 and roots[0].get("name") == "world":
        for j in [j for j in root.findall("joint") if _joint_link(j, "parent", path) == "world"]:
            root.remove(j)
        root.remove(roots[0])
    return frame, movable


def _jacobian(model, data, q, loop_type: str, fa: int, fb: int | None, reach: float) -> np.ndarray:
    """Constraint Jacobian rows of the loop at q (rotation rows scaled by the reach)."""
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    Ja = pin.getFrameJacobian(model, data, fa, pin.LOCAL_WORLD_ALIGNED)
    if fb is not None:
        Jb = pin.getFrameJacobian(model, data, fb, pin.LOCAL_WORLD_ALIGNED)
        d = data.oMf[fa].translation - data.oMf[fb].translation
        Jb_at_a = Jb.copy()
        Jb_at_a[:3] += -pin.skew(d) @ Jb[3:]  # motion of the point of B that coincides with A
        Ja = Ja - Jb_at_a
    if sim_loop(loop_type).pose_rows:
        return np.vstack([Ja[:3], reach * Ja[3:]])
    return Ja[:3]


def choose_q0(model, loop_type: str, frame: str, to: str | None, n_samples: int = 400, seed: int = 0):
    """Best-conditioned grasp pose (module doc, step 5) and the self-motion dimension there."""
    data = model.createData()
    lo, hi = np.maximum(model.lowerPositionLimit, -np.pi), np.minimum(model.upperPositionLimit, np.pi)
    mid, half = 0.5 * (lo + hi), 0.35 * (hi - lo)
    fa = find_frame(model, frame)
    fb = find_frame(model, to) if to is not None else None
    pin.framesForwardKinematics(model, data, mid)
    reach = max(float(np.linalg.norm(data.oMf[fa].translation)), 0.1)
    rng = np.random.default_rng(seed)
    best, best_q, rank = -1.0, mid, 0
    for q in np.vstack([mid, rng.uniform(mid - half, mid + half, size=(n_samples, model.nq))]):
        J = _jacobian(model, data, q, loop_type, fa, fb, reach)
        S = np.linalg.svd(J, compute_uv=False)
        rank = max(rank, int(np.sum(S > 1e-8 * max(S[0], 1e-300))))
        if S[-1] > best:
            best, best_q = float(S[-1]), q
    return best_q, rank, best


def _fewer_constraints(rank: int, to: str | None) -> str:
    """The way out of a loop that leaves a chain no motion: the simulated loop types with fewer than `rank`
    constraints (a loop between two frames: on one of them, since only a weld closes two chains), or more
    joints."""
    kinds = ("point", "plane", "measured_point")
    fewer = [f"{t}: {sim_loop(t).constraints}" for t in kinds if sim_loop(t).constraints < rank]
    if not fewer:
        return "use a robot with more joints"
    where = "a loop with fewer constraints"
    if to is not None:
        where = "a loop on one of the two frames with fewer constraints (only a weld closes two chains)"
    return f"use {where} ({', '.join(fewer)}), or a robot with more joints"


def prepare_robot(
    path: str | Path,
    loop_type: str,
    frame: str,
    to: str | None = None,
    tool=None,
    joints=None,
    q0=None,
    where: str = "--robot",
) -> PreparedRobot:
    """Prepare a user's robot for the simulator and register it (module doc)."""
    from closedloop.assets.catalog import ROBOTS, RobotSource, nominal_urdf, repair_inertias
    from closedloop.sims.outputs import absolute_mesh_paths

    path = Path(path)
    root = absolute_mesh_paths(_read(path, where), path)  # the prepared file lives elsewhere: meshes by absolute path
    repaired = repair_inertias(root)
    if repaired:
        log.warning(
            "note: %s: %d link(s) have an inertia the simulator refuses (zero or not positive definite: %s); "
            "simulated with each principal moment at least that of a 1 cm sphere of the link's mass (the "
            "kinematics, all a calibration uses, unchanged)",
            path.name,
            len(repaired),
            ", ".join(repaired[:6]) + (", ..." if len(repaired) > 6 else ""),
        )
    frame, driven = _prepare_tree(root, path, loop_type, frame, to, tool, joints)
    key = path.stem  # a built-in robot's name is not taken over
    if key in ROBOTS and not str(ROBOTS[key].relpath).startswith(str(_tmpdir())):
        key = f"{key}_file"
    out = _tmpdir() / f"{key}.urdf"
    out.write_text(ET.tostring(root, encoding="unicode"))
    ROBOTS[key] = RobotSource(name=key, relpath=str(out), shipped=True)
    try:
        model = pin.buildModelFromXML(nominal_urdf(key))
    except Exception as exc:
        raise InputError(f"{path}: Pinocchio cannot read the prepared robot ({str(exc).splitlines()[0]})") from None
    n = model.nq
    what = f"a {loop_type} loop on {frame}" + (f" and {to}" if to else "")
    if n == 0:
        raise InputError(f"{path}: no movable joint between the base and {frame}")
    q_best, rank, _ = choose_q0(model, loop_type, frame, to)
    # independent constraints: the Jacobian's rank, at most the loop type's count (hinge: the door's own
    # angle takes one of the weld's six; plane: the unknown normal leaves one; a tracker none)
    rank = sim_loop(loop_type).independent(rank)
    if n - rank < 1:
        raise InputError(
            f"{path}: {what} leaves the closed chain no motion: its {n} driven joint(s) "
            f"({', '.join(driven)}) are all taken by the loop's {rank} independent constraints "
            f"(thesis Lemma 4: no self-motion, nothing to calibrate from); {_fewer_constraints(rank, to)}"
        )
    if q0 is None:
        q0 = q_best
        log.info("%s: grasp pose chosen automatically: %s", path, np.round(q0, 3))
    q0 = np.asarray(q0, dtype=float)
    if q0.shape != (n,):
        raise InputError(f"{where}: q0 has {q0.size} values; {frame} is driven by {n} joints ({', '.join(driven)})")
    lo, hi = model.lowerPositionLimit, model.upperPositionLimit
    outside = [model.names[k + 1] for k in range(n) if not lo[k] <= q0[k] <= hi[k]]
    if outside:
        raise InputError(f"{where}: q0 puts joint(s) {', '.join(outside)} outside their limits")
    if sim_loop(loop_type).point_contact and to is None:  # the point must move with the last joint
        blind = blind_joints(model, find_frame(model, frame), np.zeros(3), q0)
        if blind:
            raise InputError(
                point_on_axis_message(
                    f"{path}: {what}",
                    frame,
                    blind,
                    bool(tool),
                    'put the contact on a stylus off the axis: --tool "0.05 0 0" (a tool: {xyz: [...]} in a '
                    "scenario file), in the frame's axes",
                )
            )
    names = tuple(model.names[k] for k in range(1, model.njoints))
    return PreparedRobot(key, out, frame, names, tuple(float(v) for v in q0))
