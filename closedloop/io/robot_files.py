"""Robot files (URDF, MJCF) checked before Pinocchio parses them: one line naming the file and element.

Pinocchio's parsers trust their input: a link with two parents, a cycle or a chain thousands of links
deep crash the process (a recursion in C++ per link: a 5,000-link chain is a segmentation fault), and
their refusals reach the user as several lines of urdfdom log.  `check_urdf` and `check_mjcf` read the
file with the standard XML parser (no recursion) and refuse, naming the element:

* not XML, or not a ``<robot>`` (URDF) / ``<mujoco>`` (MJCF) document;
* xacro syntax (``${...}``, ``<xacro:...>``, ``$(find ...)``): "this is a xacro file: run xacro first";
* two links or two joints of one name; a joint without a parent or child, or naming a link not defined;
* a link that is the child of two joints (a closed chain written into the tree), a cycle, several roots;
* a tree deeper than `MAX_DEPTH` links;
* an ``<origin>``, ``<axis>`` or ``<limit>`` whose values are not finite numbers, a zero axis on a
  moving joint, an unknown joint type;
* a misspelt attribute of a joint's ``<origin>``, ``<axis>`` or ``<limit>`` (``<origin xzy=...>``) or a
  joint's element spelt close to one of the URDF's (``<orgin>``): urdfdom skips what it does not know,
  and the joint would silently keep its default (a zero origin, the x axis, no limits).

`read_model_file` is the one read of a robot model file, whichever its format: it checks it, reads what
Pinocchio does not (a URDF's `UrdfJoints`, a D-H table's document against its schema) and notes the file
as an input of the running command; `closedloop.model.robot.RobotModel.from_file` builds the model from it.
"""

from __future__ import annotations

import difflib
import math
import os
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from closedloop.errors import ModelError

#: the element ``closedloop simulate --robot`` puts in a joint it held fixed at zero (not driven: the log
#: has no readings of it), ``<closedloop_held type="revolute"/>`` (the joint's own type); URDF readers
#: (urdfdom, MuJoCo) skip elements they do not know
HELD = "closedloop_held"

#: deepest kinematic tree accepted (links from the root): Pinocchio recurses once per link
MAX_DEPTH = 1000
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "floating", "planar", "spherical")
#: the attributes URDF reads of a joint's elements (a link's <origin> the same as a joint's)
JOINT_ATTRIBUTES = {
    "origin": ("xyz", "rpy"),
    "axis": ("xyz",),
    "limit": ("lower", "upper", "effort", "velocity"),
}
#: the elements URDF reads in a <joint> (`HELD` is closedloop's own mark)
JOINT_ELEMENTS = ("origin", "parent", "child", "axis", "calibration", "dynamics", "limit", "mimic", "safety_controller")
_XACRO = re.compile(r"\$\{|\$\(")


_PARSED: dict[tuple[str, str], ET.Element] = {}  # (path, digest of its bytes) -> root; a few kept


def parse_xml(path: str | Path) -> ET.Element:
    """The root of the XML file at `path`, parsed once per process for the same bytes: a worker that
    calibrates many robots of one model (a fleet) parses it once, not once per job and per check.  The
    tree is shared: read it, never change it.  Raises as ``ET.parse`` does (``ET.ParseError``, ``OSError``)."""
    import hashlib

    data = Path(path).read_bytes()
    key = (os.path.abspath(path), hashlib.blake2b(data, digest_size=16).hexdigest())
    root = _PARSED.get(key)
    if root is None:
        parser = ET.XMLParser()
        parser.feed(data)
        root = parser.close()
        if len(_PARSED) >= 8:
            _PARSED.pop(next(iter(_PARSED)))
        _PARSED[key] = root
    return root


def _parse(path: Path, kind: str) -> ET.Element:
    try:
        return parse_xml(path)
    except ET.ParseError as exc:
        line, col = getattr(exc, "position", (0, 0))
        raise ModelError(f"{path}: not valid XML (line {line}, column {col}: {str(exc).split(':')[0]})") from None
    except OSError as exc:
        raise ModelError(f"{path}: cannot read {kind} ({exc.strerror})") from None


def _xacro(path: Path, root: ET.Element) -> None:
    """Refuse unexpanded xacro: the ``xacro`` namespace, ``${expr}`` or ``$(arg ...)`` in a value."""
    for el in root.iter():
        tag = el.tag if isinstance(el.tag, str) else ""
        if "xacro" in tag or tag.startswith("{http://www.ros.org/wiki/xacro}"):
            raise ModelError(
                f"{path}: this is a xacro file (element <{tag.split('}')[-1]}>): run xacro first "
                "(xacro FILE.urdf.xacro > FILE.urdf)"
            )
        for name, value in el.attrib.items():
            if _XACRO.search(value):
                raise ModelError(
                    f'{path}: this is a xacro file (<{tag} {name}="{value[:40]}">): run xacro first '
                    "(xacro FILE.urdf.xacro > FILE.urdf)"
                )


def _numbers(path: Path, where: str, text: str | None, n: int) -> list[float] | None:
    """`n` finite numbers separated by spaces (None when the attribute is absent)."""
    if text is None:
        return None
    parts = text.split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise ModelError(f'{path}: {where}="{text.strip()[:60]}": expected {n} finite number(s)')
    return values


def _attributes(path: Path, where: str, el: ET.Element) -> None:
    """Refuse an attribute of `el` (an <origin>, <axis> or <limit>) spelt close to one URDF reads and `el` lacks
    (``<origin xzy=...>``: the origin would be zero); others (a vendor's ``command_effort``) are left."""
    absent = [a for a in JOINT_ATTRIBUTES[str(el.tag)] if a not in el.attrib]
    for attr in el.attrib:
        near = difflib.get_close_matches(attr, absent, n=1, cutoff=0.6)
        if near:
            raise ModelError(
                f'{path}: {where}: <{el.tag} {attr}="{el.attrib[attr][:40]}">: no such attribute (did you mean '
                f"{near[0]}?); URDF readers skip it and keep the default"
            )


def _misspelt(path: Path, joint: str, el: ET.Element) -> None:
    """Refuse a joint's element spelt close to one URDF reads and the joint lacks (``<orgin>``), and a misspelt attribute of its
    <origin>, <axis> or <limit>: each would be skipped, the joint keeping its default (module doc)."""
    for child in el:
        tag = child.tag if isinstance(child.tag, str) else ""
        if tag in JOINT_ATTRIBUTES:
            _attributes(path, f"joint '{joint}'", child)
        elif tag not in JOINT_ELEMENTS and tag != HELD:
            absent = [e for e in JOINT_ELEMENTS if el.find(e) is None]
            near = difflib.get_close_matches(tag, absent, n=1, cutoff=0.75)
            if near:
                raise ModelError(
                    f"{path}: joint '{joint}': <{tag}> is not a URDF element (did you mean <{near[0]}>?); URDF "
                    "readers skip it and keep the default"
                )


def check_urdf(path: str | Path, one_root: bool = True) -> None:
    """Refuse a URDF Pinocchio would crash on or refuse in several lines (module doc).  `one_root` False
    accepts several root links (the simulator keeps the tree of the loop's links and notes the others)."""
    path = Path(path)
    root = _parse(path, "URDF")
    _xacro(path, root)
    if root.tag != "robot":
        raise ModelError(f"{path}: not a URDF (the root element is <{root.tag}>, not <robot>)")
    links: set[str] = set()
    for el in root.findall("link"):
        name = el.get("name")
        if not name:
            raise ModelError(f"{path}: a <link> without a name")
        if name in links:
            raise ModelError(f"{path}: two links named '{name}'")
        links.add(name)
        for org in el.iter("origin"):
            _attributes(path, f"link '{name}'", org)
            _numbers(path, f"link '{name}': <origin> xyz", org.get("xyz"), 3)
            _numbers(path, f"link '{name}': <origin> rpy", org.get("rpy"), 3)
    if not links:
        raise ModelError(f"{path}: no <link> in this URDF")
    parent_of: dict[str, tuple[str, str]] = {}  # child link -> (parent link, joint)
    children: dict[str, list[str]] = {}
    joints: set[str] = set()
    for el in root.findall("joint"):
        name = el.get("name")
        if not name:
            raise ModelError(f"{path}: a <joint> without a name")
        if name in joints:
            raise ModelError(f"{path}: two joints named '{name}'")
        joints.add(name)
        jtype = el.get("type")
        if jtype not in JOINT_TYPES:
            raise ModelError(f"{path}: joint '{name}': type '{jtype}' is not one of {', '.join(JOINT_TYPES)}")
        ends = {}
        for end in ("parent", "child"):
            e = el.find(end)
            link = e.get("link") if e is not None else None
            if not link:
                raise ModelError(f"{path}: joint '{name}': no <{end} link=...>")
            if link not in links:
                raise ModelError(
                    f"{path}: joint '{name}': {end} link '{link}' is not defined (no <link name=\"{link}\">)"
                )
            ends[end] = link
        parent, child = ends["parent"], ends["child"]
        if child in parent_of:
            raise ModelError(
                f"{path}: link '{child}' is the child of two joints ('{parent_of[child][1]}' and '{name}'); a URDF "
                "is a tree: write a closed chain as a loop (--loop) instead"
            )
        parent_of[child] = (parent, name)
        children.setdefault(parent, []).append(child)
        _misspelt(path, name, el)
        origin = el.find("origin")
        if origin is not None:
            _numbers(path, f"joint '{name}': <origin> xyz", origin.get("xyz"), 3)
            _numbers(path, f"joint '{name}': <origin> rpy", origin.get("rpy"), 3)
        axis = el.find("axis")
        if axis is not None:
            xyz = _numbers(path, f"joint '{name}': <axis> xyz", axis.get("xyz"), 3)
            if xyz is not None and jtype in ("revolute", "continuous", "prismatic") and not any(xyz):
                raise ModelError(
                    f"{path}: joint '{name}': <axis xyz=\"{axis.get('xyz')}\"> is zero; give a nonzero axis"
                )
        lim = el.find("limit")
        if lim is not None:
            for attr in ("lower", "upper", "effort", "velocity"):
                _numbers(path, f"joint '{name}': <limit> {attr}", lim.get(attr), 1)
    roots = sorted(links - set(parent_of))
    if not roots:
        raise ModelError(f"{path}: the joints form a cycle (every link has a parent, e.g. '{sorted(links)[0]}')")
    if len(roots) > 1 and one_root:
        raise ModelError(
            f"{path}: {len(roots)} root links ({', '.join(repr(r) for r in roots[:4])}): a URDF has one root; "
            "join them with a fixed joint"
        )
    depth = dict.fromkeys(roots, 0)
    root_of = {r: r for r in roots}
    todo = list(roots)
    while todo:  # breadth first, no recursion
        link = todo.pop()
        for c in children.get(link, []):
            depth[c], root_of[c] = depth[link] + 1, root_of[link]
            if depth[c] > MAX_DEPTH:
                raise ModelError(
                    f"{path}: link '{c}' lies {depth[c]} links below the root '{root_of[c]}'; trees deeper than "
                    f"{MAX_DEPTH} links are refused"
                )
            todo.append(c)
    lost = sorted(links - set(depth))
    if lost:
        raise ModelError(f"{path}: the joints form a cycle through link '{lost[0]}' (not reachable from the root)")


@dataclass(frozen=True)
class UrdfJoints:
    """What a URDF's joints say beyond the kinematics Pinocchio builds: the tree by links (joint -> (parent
    link, child link)), the joints ``closedloop simulate --robot`` held fixed (marked `HELD`), and the
    coupled joints (``<mimic joint=f multiplier=m offset=o>``: joint -> (f, m, o))."""

    tree: dict[str, tuple[str, str]] = field(default_factory=dict)
    held: frozenset[str] = frozenset()
    mimics: dict[str, tuple[str, float, float]] = field(default_factory=dict)
    # a calibrated URDF's joints (those carrying `NOMINAL_ORIGIN`): O^-1 O_nominal (4x4), the change that takes
    # the joint's origin O back to the one of the model it was calibrated from
    calibrated_from: dict[str, np.ndarray] = field(default_factory=dict)


def read_urdf_joints(path: str | Path) -> UrdfJoints:
    """The `UrdfJoints` of the URDF at `path` (read once, when the model is loaded); empty where it cannot
    be read (`check_urdf` has refused it before)."""
    try:
        root = parse_xml(path)
    except (ET.ParseError, OSError):
        return UrdfJoints()
    tree: dict[str, tuple[str, str]] = {}
    held: set[str] = set()
    mimics: dict[str, tuple[str, float, float]] = {}
    calibrated_from: dict[str, np.ndarray] = {}
    for j in root.iter("joint"):
        name = j.get("name")
        if not name:
            continue
        parent, child = j.find("parent"), j.find("child")
        tree[name] = (
            parent.get("link", "") if parent is not None else "",
            child.get("link", "") if child is not None else "",
        )
        if j.find(HELD) is not None:
            held.add(name)
        m = j.find("mimic")
        if m is not None:
            try:
                mult, off = float(m.get("multiplier", 1.0)), float(m.get("offset", 0.0))
            except ValueError:
                raise ModelError(f"{path}: joint '{name}': <mimic> multiplier and offset must be numbers") from None
            mimics[name] = (m.get("joint", "?"), mult, off)
        nominal = j.find(NOMINAL_ORIGIN)
        if nominal is not None:
            calibrated_from[name] = np.linalg.inv(urdf_origin(j.find("origin"), path, name)) @ urdf_origin(
                nominal, path, name
            )
    return UrdfJoints(tree, frozenset(held), mimics, calibrated_from)


#: the element a calibrated URDF's joint carries: its origin in the model it was calibrated from
#: (`closedloop.output.urdf.write_urdf`), read back as `UrdfJoints.calibrated_from`
NOMINAL_ORIGIN = "closedloop_nominal_origin"


def urdf_floats(text: str, n: int, source, joint: str) -> np.ndarray:
    """n numbers of a URDF attribute of `joint`, or a ModelError naming the file, the joint and the text."""
    try:
        v = np.array([float(t) for t in text.split()])
    except ValueError:
        v = np.zeros(0)
    if v.size != n:
        raise ModelError(f"{source}: joint '{joint}': expected {n} numbers, got '{text}'")
    return v


def urdf_origin(origin, source, joint: str) -> np.ndarray:
    """The 4x4 transform of a URDF ``<origin xyz rpy>`` (identity when absent): R = Rz(y) Ry(p) Rx(r)."""
    T = np.eye(4)
    if origin is None:
        return T
    r, p, y = urdf_floats(origin.get("rpy", "0 0 0"), 3, source, joint)
    T[:3, 3] = urdf_floats(origin.get("xyz", "0 0 0"), 3, source, joint)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    return T


def check_mjcf(path: str | Path) -> None:
    """Refuse an MJCF that is not XML, not ``<mujoco>``, xacro, or nests bodies deeper than `MAX_DEPTH`."""
    path = Path(path)
    root = _parse(path, "MJCF")
    _xacro(path, root)
    if root.tag != "mujoco":
        raise ModelError(f"{path}: not an MJCF model (the root element is <{root.tag}>, not <mujoco>)")
    todo = [(root, 0)]
    while todo:
        el, d = todo.pop()
        for c in el:
            dc = d + (c.tag == "body")
            if dc > MAX_DEPTH:
                raise ModelError(
                    f"{path}: body '{c.get('name', '?')}' is nested {dc} bodies deep; trees deeper than "
                    f"{MAX_DEPTH} bodies are refused"
                )
            todo.append((c, dc))


#: the robot model files read, by suffix: their kind (`read_model_file`)
MODEL_KINDS = {".urdf": "urdf", ".xml": "mjcf", ".mjcf": "mjcf", ".yaml": "dh", ".yml": "dh"}


@dataclass(frozen=True)
class ModelFile:
    """A robot model file read and checked before a model is built from it: its path, its kind ('urdf',
    'mjcf' or 'dh'), and what it holds beyond what Pinocchio reads: a URDF's joints (`UrdfJoints`), a D-H
    table's document (checked against `closedloop.io.schemas.DH_SCHEMA`)."""

    path: Path
    kind: str
    urdf: UrdfJoints | None = None
    dh: dict | None = None


def read_model_file(path: str | Path) -> ModelFile:
    """The model file at `path`, read once (`ModelFile`): a URDF or an MJCF checked (`check_urdf`,
    `check_mjcf`: what would crash Pinocchio or reach the user as urdfdom's log lines), a URDF's joints
    read, a D-H table's YAML read against its schema; noted as an input (`closedloop.io.files.note_input`).
    A missing file or an unknown suffix is a ModelError."""
    from closedloop.io.files import note_input
    from closedloop.io.schemas import DH_SCHEMA, load_yaml

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: no such model file")
    suffix = path.suffix.lower()
    kind = MODEL_KINDS.get(suffix)
    if kind is None:
        raise ModelError(f"{path}: unknown model type '{suffix}' (use .urdf, .xml/.mjcf or .yaml)")
    urdf = doc = None
    if kind == "urdf":
        check_urdf(path)
        urdf = read_urdf_joints(path)
    elif kind == "mjcf":
        check_mjcf(path)
    else:
        doc = load_yaml(path, "D-H table", ModelError, schema=DH_SCHEMA, rows="joints")
    note_input(path)
    return ModelFile(path, kind, urdf, doc)
