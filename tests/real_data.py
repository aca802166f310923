"""Public recordings of real robots, read where they live: ``../shared/real-data/`` beside the repository.

The recordings are third-party data (each folder holds its source, commit and licence); the project carries
no copy.  A test that needs one calls :func:`real_folder`, which skips with a reason naming the folder when
it is absent (a checkout without ``shared/`` beside it); a benchmark calls :func:`real_folder` with
``skip=False`` and stops with the same sentence.

The FIGAROH recordings (TALOS, TIAGo) are CSV files with a header: marker coordinates ``x1, y1, z1, ...``
(m), then the joint readings, every joint column named ``*_joint`` (rad; the TIAGo torso lift in m).
:func:`figaroh_log` reads the first marker as a tracker reading ``m:x, m:y, m:z`` of a ``measured_point``
loop named ``m``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from closedloop.io.logs import JointLog

REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO.parent / "shared" / "real-data"


@dataclass(frozen=True)
class Recording:
    """One public recording: its folder in ``../shared/real-data/``, its CSV, the robot's URDF in
    example-robot-data and the link the measured marker is fixed to."""

    folder: str
    csv: str
    urdf: str
    frame: str


RECORDINGS = {
    # TALOS whole-body plane-constrained calibration (Nguyen et al. 2025): cross-validated RMS error
    # reduced by a factor 2.3 from the manufacturer's model
    "talos": Recording(
        folder="figaroh-talos-left-arm",
        csv="talos_left_arm_02_10_contact.csv",
        urdf="talos_data/robots/talos_full_v2.urdf",
        frame="gripper_left_base_link",
    ),
    # TIAGo geometric + non-geometric calibration (Nguyen et al. 2024): end-effector position RMSE 5.7 mm
    "tiago": Recording(
        folder="figaroh-tiago-mocap",
        csv="qualysis_base_hand_calibration.csv",
        urdf="tiago_description/robots/tiago.urdf",
        frame="arm_7_link",
    ),
}


def real_folder(folder: str, *, skip: bool = True) -> Path:
    """``../shared/real-data/<folder>``; where it is absent, the test is skipped (or, with ``skip=False``,
    the program stops) with a reason naming the folder."""
    path = REAL_DATA / folder
    if path.is_dir():
        return path
    why = f"public recording not found: {path} (the folder shared/real-data/{folder} beside the repository)"
    if skip:
        import pytest

        pytest.skip(why)
    raise SystemExit(why)


def figaroh_log(name: str, *, skip: bool = True) -> JointLog:
    """The recording's joint readings, and its first marker's position as the tracker loop 'm'."""
    rec = RECORDINGS[name]
    path = real_folder(rec.folder, skip=skip) / rec.csv
    d = np.genfromtxt(path, delimiter=",", names=True)
    joints = [n for n in d.dtype.names if n.endswith("_joint")]
    extra = {"m:x": d["x1"], "m:y": d["y1"], "m:z": d["z1"]}
    return JointLog(joints, np.column_stack([d[n] for n in joints]), None, None, extra)


def chain_urdf(src: Path, tip: str | tuple[str, ...], dst: Path) -> Path:
    """The URDF `src` cut to the chains from its root to link `tip` (or each of several tips; the other
    branches do not move the loops and cost time in every evaluation); the chains' kinematics unchanged."""
    tree = ET.parse(src)
    root = tree.getroot()
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    links: set[str] = set()
    joints: list = []
    for link in (tip,) if isinstance(tip, str) else tip:
        links.add(link)
        while link in by_child:
            joints.append(by_child[link])
            link = by_child[link].find("parent").get("link")
            links.add(link)
    for el in list(root):
        if (el.tag == "link" and el.get("name") not in links) or (el.tag == "joint" and el not in joints):
            root.remove(el)
        elif el.tag not in ("link", "joint", "material"):
            root.remove(el)
    tree.write(dst)
    return dst
