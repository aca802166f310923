"""Robot and scene models shipped with closedloop (or referenced from installed packages).

Robot URDFs from ``example-robot-data`` are *referenced*, never copied: the
installed package (pip ``example-robot-data`` 6.x, a cmeel package) ships its
robot files under ``<site-packages>/cmeel.prefix/share/example-robot-data/robots``
and :func:`example_robot_data_dir` finds that directory at run time.

:func:`nominal_urdf` returns a *cleaned* copy of a robot's URDF as a string,
suited to both Pinocchio and MuJoCo and used as the nominal model of a
simulated calibration experiment:

* visuals, collisions, ``<dynamics>`` (URDF friction/damping, which MuJoCo
  would import as dry friction), ``<transmission>`` and ``<gazebo>`` tags are
  removed;
* links and joints that are not part of the calibrated chain are removed
  (the Panda's fingers; the UR5's ``world`` link);
* massless links get a tiny, valid inertia so that MuJoCo accepts them;
* optional fixed "tool" links are appended (e.g. a stylus tip).

Files in this directory:

* ``door.xml`` -- MJCF door panel on a hinge with a handle site, attached to
  scenes by :mod:`closedloop.sims.scene`.
"""

from __future__ import annotations

import copy
import site
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

__all__ = [
    "RobotSource",
    "ROBOTS",
    "ToolLink",
    "example_robot_data_dir",
    "model_file",
    "nominal_urdf",
]

_ERD_SUBDIR = Path("cmeel.prefix") / "share" / "example-robot-data" / "robots"


def example_robot_data_dir() -> Path:
    """Return the ``robots`` directory of the installed ``example-robot-data`` package.

    Looks in every site-packages directory of the running interpreter
    (``site.getsitepackages()``, the user site, and ``sys.path``).

    Raises:
        FileNotFoundError: if the package is not installed.
    """
    candidates: list[str] = []
    try:
        candidates += list(site.getsitepackages())
    except AttributeError:  # virtualenv without getsitepackages
        pass
    user = site.getusersitepackages() if hasattr(site, "getusersitepackages") else None
    if user:
        candidates.append(user)
    candidates += [p for p in sys.path if p]
    candidates.append(str(Path(sys.prefix) / "lib"))
    for base in candidates:
        d = Path(base) / _ERD_SUBDIR
        if d.is_dir():
            return d
    raise FileNotFoundError(
        "example-robot-data robots not found; install it with `pip install example-robot-data`"
    )


def model_file(name: str) -> Path:
    """Path of a file shipped in ``closedloop.models`` (e.g. ``"door.xml"``)."""
    return Path(str(resources.files(__name__).joinpath(name)))


@dataclass(frozen=True)
class ToolLink:
    """A fixed link appended to the URDF (e.g. a stylus tip).

    Attributes:
        name: new link name (also the Pinocchio BODY frame name).
        parent: existing parent link.
        xyz: translation of the new link in the parent frame [m].
        rpy: roll-pitch-yaw of the new link in the parent frame [rad].
    """

    name: str
    parent: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class RobotSource:
    """Where a robot's URDF comes from and how it is cleaned.

    Attributes:
        name: short robot name.
        relpath: path relative to the example-robot-data ``robots`` directory.
        remove_links: links removed together with the joints attached to them.
        tools: fixed links appended to the chain.
    """

    name: str
    relpath: str
    remove_links: tuple[str, ...] = ()
    tools: tuple[ToolLink, ...] = field(default_factory=tuple)

    @property
    def path(self) -> Path:
        """Absolute path of the original URDF in the installed package."""
        return example_robot_data_dir() / self.relpath


ROBOTS: dict[str, RobotSource] = {
    "panda": RobotSource(
        name="panda",
        relpath="panda_description/urdf/panda.urdf",
        remove_links=("panda_leftfinger", "panda_rightfinger"),
    ),
    "ur5": RobotSource(
        name="ur5",
        relpath="ur_description/urdf/ur5_robot.urdf",
        remove_links=("world",),
        tools=(ToolLink("stylus_tip", "tool0", xyz=(0.0, 0.0, 0.10)),),
    ),
}

# Mass and inertia given to links that have none (MuJoCo rejects massless moving bodies).
_TINY_MASS = 1e-3
_TINY_INERTIA = 1e-6


def _fmt(v: float) -> str:
    return repr(float(v))


def clean_urdf_tree(root: ET.Element, remove_links: tuple[str, ...] = ()) -> ET.Element:
    """Clean a URDF element tree in place (see module docstring) and return it."""
    for tag in ("transmission", "gazebo", "material"):
        for el in list(root.findall(tag)):
            root.remove(el)
    # remove links and every joint touching them
    removed = set(remove_links)
    for link in list(root.findall("link")):
        if link.get("name") in removed:
            root.remove(link)
    for joint in list(root.findall("joint")):
        parent = joint.find("parent")
        child = joint.find("child")
        if (parent is not None and parent.get("link") in removed) or (
            child is not None and child.get("link") in removed
        ):
            root.remove(joint)
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for el in list(link.findall(tag)):
                link.remove(el)
        inertial = link.find("inertial")
        mass_el = inertial.find("mass") if inertial is not None else None
        mass = float(mass_el.get("value", "0")) if mass_el is not None else 0.0
        if inertial is None or mass <= 0.0:
            if inertial is not None:
                link.remove(inertial)
            inertial = ET.SubElement(link, "inertial")
            ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
            ET.SubElement(inertial, "mass", value=_fmt(_TINY_MASS))
            ET.SubElement(
                inertial,
                "inertia",
                ixx=_fmt(_TINY_INERTIA), ixy="0", ixz="0",
                iyy=_fmt(_TINY_INERTIA), iyz="0", izz=_fmt(_TINY_INERTIA),
            )
    for joint in root.findall("joint"):
        for el in list(joint.findall("dynamics")):
            joint.remove(el)
        for el in list(joint.findall("safety_controller")):
            joint.remove(el)
        for el in list(joint.findall("calibration")):
            joint.remove(el)
    return root


def nominal_urdf(robot: str) -> str:
    """Cleaned nominal URDF of a registered robot (see :data:`ROBOTS`), as a string."""
    try:
        src = ROBOTS[robot]
    except KeyError:
        raise KeyError(f"unknown robot {robot!r}; known: {sorted(ROBOTS)}") from None
    root = ET.parse(src.path).getroot()
    root = clean_urdf_tree(copy.deepcopy(root), src.remove_links)
    for tool in src.tools:
        link = ET.SubElement(root, "link", name=tool.name)
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(inertial, "mass", value=_fmt(_TINY_MASS))
        ET.SubElement(
            inertial, "inertia",
            ixx=_fmt(_TINY_INERTIA), ixy="0", ixz="0",
            iyy=_fmt(_TINY_INERTIA), iyz="0", izz=_fmt(_TINY_INERTIA),
        )
        joint = ET.SubElement(root, "joint", name=f"{tool.name}_joint", type="fixed")
        ET.SubElement(joint, "parent", link=tool.parent)
        ET.SubElement(joint, "child", link=tool.name)
        ET.SubElement(
            joint, "origin",
            xyz=" ".join(_fmt(v) for v in tool.xyz), rpy=" ".join(_fmt(v) for v in tool.rpy),
        )
    ET.indent(root)
    return ET.tostring(root, encoding="unicode")
