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

import errno
import os
import shutil
import tempfile
from contextvars import ContextVar
from pathlib import Path
from typing import Callable

import numpy as np
import pinocchio as pin

from closedloop.errors import InputError, ModelError
from closedloop.model.robot import RobotModel


#: the model file suffixes `write_model` writes for each input kind
MODEL_SUFFIXES = {"urdf": (".urdf",), "dh": (".yaml", ".yml"), "mjcf": (".xml", ".mjcf")}
_STAGE = ".closedloop-"  # prefix of every temporary name beside an output
_active: ContextVar["OutputSet | None"] = ContextVar("closedloop_output_set", default=None)


class OutputSet:
    """The files of one command, published together: the old set or the new one, never a temporary file.

    Used as a context manager, every `atomic_write_text` inside the block is staged in memory and the
    whole set is published when the block exits without an exception (nothing is written otherwise):

    1. each file's bytes go into an unnamed file (``O_TMPFILE``) in its target's directory and are
       fsynced, so a process killed at any moment of this step leaves no name behind (where the file
       system has no ``O_TMPFILE``: a hidden staging directory ``.closedloop-<pid>-*`` beside the target,
       removed on any exit, including SIGTERM/SIGINT turned into exceptions by the CLI);
    2. then, in `order` (model first, report or manifest last), each is linked under a temporary name
       and renamed onto its target (two system calls: the only moment a kill can leave a name, or
       leave a new model beside an old report, is a few microseconds wide);
    3. the directories are fsynced.
    """

    def __init__(self, order: list | tuple = ()):
        self.order = [Path(p).absolute() for p in order if p is not None]
        self.files: dict[Path, bytes] = {}
        self._token = None

    def add(self, target: str | Path, data: str | bytes) -> None:
        self.files[Path(target).absolute()] = data.encode() if isinstance(data, str) else bytes(data)

    def __enter__(self) -> "OutputSet":
        self._token = _active.set(self)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        _active.reset(self._token)
        if exc_type is None:
            self.commit()

    def commit(self) -> None:
        rank = {p: k for k, p in enumerate(self.order)}
        targets = sorted(self.files, key=lambda p: rank.get(p, len(rank)))
        staged: list[tuple[Path, int | None, Path | None]] = []  # (target, fd of an unnamed file, staged path)
        stage_dirs: list[Path] = []
        try:
            for t in targets:
                t.parent.mkdir(parents=True, exist_ok=True)
                fd = _unnamed(t.parent)
                if fd is None:  # no O_TMPFILE: a hidden staging directory beside the target
                    d = Path(tempfile.mkdtemp(dir=t.parent, prefix=f"{_STAGE}{os.getpid()}-"))
                    stage_dirs.append(d)
                    tmp = d / t.name
                    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                    staged.append((t, None, tmp))
                else:
                    staged.append((t, fd, None))
                try:
                    _write_all(fd, self.files[t])
                    os.fsync(fd)
                finally:
                    if staged[-1][1] is None:
                        os.close(fd)
            held = _hold_open(targets)  # freeing a replaced file's blocks waits for close()
            try:
                named = []  # every name first, then the renames back to back: the moment of a mix is minimal
                for t, fd, tmp in staged:
                    if fd is not None:
                        tmp = t.parent / f"{_STAGE}{os.getpid()}-{t.name}.tmp"
                        _link_unnamed(fd, tmp)
                    named.append((tmp, t))
                for tmp, t in named:
                    os.replace(tmp, t)
            finally:
                for h in held:
                    os.close(h)
            for d in {t.parent for t in targets}:
                _fsync_dir(d)
        finally:
            for t, fd, _ in staged:
                if fd is not None:
                    os.close(fd)
                    leftover = t.parent / f"{_STAGE}{os.getpid()}-{t.name}.tmp"
                    if leftover.exists():
                        leftover.unlink()
            for d in stage_dirs:
                shutil.rmtree(d, ignore_errors=True)


def _hold_open(paths: list[Path]) -> list[int]:
    """Read descriptors of the existing `paths`: a rename over a file whose inode is still open is a
    metadata update (~0.05 ms), over a closed one it frees the old blocks first (~4 ms on ext4 with
    discard), which would widen the moment at which a kill leaves a mixed set 100-fold."""
    fds = []
    for p in paths:
        try:
            fds.append(os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0)))
        except OSError:
            pass
    return fds


def _unnamed(directory: Path) -> int | None:
    """An unnamed file in `directory` (Linux ``O_TMPFILE``), or None where the file system has none."""
    flag = getattr(os, "O_TMPFILE", None)
    if flag is None:
        return None
    try:
        return os.open(directory, flag | os.O_WRONLY, 0o666)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL, errno.ENOENT):
            return None
        raise


def _link_unnamed(fd: int, path: Path) -> None:
    """Give the unnamed file `fd` the name `path`: linkat(AT_SYMLINK_FOLLOW) on /proc/self/fd/N.

    (A `dir_fd` makes CPython call linkat rather than link, which would not follow the magic link.)
    """
    root = os.open("/", os.O_RDONLY)
    try:
        os.link(f"/proc/self/fd/{fd}", path, src_dir_fd=root, follow_symlinks=True)
    finally:
        os.close(root)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_text(path: str | Path, text: str | bytes) -> None:
    """Write `text` to `path` whole: into the active `OutputSet` if there is one, else as a set of one."""
    active = _active.get()
    if active is not None:
        active.add(path, text)
        return
    one = OutputSet()
    one.add(path, text)
    one.commit()


def atomic_write(path: str | Path, writer: Callable[[str], None]) -> None:
    """Call `writer(tmp_path)` on a temporary file beside `path`, then publish it like `atomic_write_text`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = tempfile.mkdtemp(dir=path.parent, prefix=f"{_STAGE}{os.getpid()}-")
    try:
        tmp = os.path.join(d, path.name)
        writer(tmp)
        data = Path(tmp).read_bytes()
    finally:
        shutil.rmtree(d, ignore_errors=True)
    atomic_write_text(path, data)


def refuse_overwrite(out: str | Path, *inputs: str | Path | None) -> None:
    """An output must never replace one of the user's inputs."""
    o = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == o:
            raise InputError(f"{out}: refusing to overwrite an input file; choose another output path")


def check_outputs(outputs: dict[str, str | Path | None], inputs: list = (), directory: bool = False) -> None:
    """Refuse, before any work, output paths that cannot be written (one line naming the option and path).

    `outputs` maps an option (``--out``) to its path.  Refused: two options naming one file, an input
    file, an existing directory (`directory=False`) or an existing file (`directory=True`), a path below
    a file, a directory where no file can be created (read-only, no permission: probed).
    """
    seen: dict[Path, str] = {}
    for opt, out in outputs.items():
        if out is None:
            continue
        p = Path(out)
        r = p.resolve()
        if r in seen:
            raise InputError(f"{opt} {out}: the same file as {seen[r]}; give each output its own path")
        seen[r] = f"{opt} {out}"
        refuse_overwrite(out, *inputs)
        if not directory and p.is_dir():
            raise InputError(f"{opt} {out}: is a directory; give a file name")
        if directory and p.exists() and not p.is_dir():
            raise InputError(f"{opt} {out}: is a file; give a directory")
        anc = p if directory else p.parent
        while not anc.exists() and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            raise InputError(f"{opt} {out}: '{anc}' is a file, not a directory")
        _probe(anc, f"{opt} {out}")


def _probe(directory: Path, what: str) -> None:
    """Create (and drop) an unnamed file in `directory`: does the file system let us write there?"""
    try:
        fd = _unnamed(directory)
        if fd is None:
            fd, tmp = tempfile.mkstemp(dir=directory, prefix=_STAGE)
            os.unlink(tmp)
        os.close(fd)
    except OSError as exc:
        raise InputError(f"{what}: cannot write in {directory} ({exc.strerror})") from None


def check_model_output(kind: str, out: str | Path | None, model: str | Path | None = None) -> None:
    """The calibrated model is written in the input's own format: its suffix must say so."""
    if out is None:
        return
    suffixes = MODEL_SUFFIXES.get(kind)
    if not suffixes:
        raise InputError(f"--out {out}: no calibrated model can be written for {kind} input {model or ''} "
                         "(the report holds the parameters); drop --out")
    if Path(out).suffix.lower() not in suffixes:
        raise InputError(f"--out {out}: a {kind} input gives a calibrated {kind} model; name it "
                         f"*{' or *'.join(suffixes)}")


def write_urdf(robot: RobotModel, values: dict[str, float], out_path: str | Path, fold_offsets: bool = True,
               frames: list[tuple[str, str, np.ndarray]] = ()) -> None:
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
        raise ModelError(f"{robot.source}: a calibrated URDF can only be written for URDF input "
                         f"(this model is {robot.kind}); the report holds the parameters")
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
    T[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
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


def write_model(robot: RobotModel, values: dict[str, float], out_path: str | Path,
                frames: list[tuple[str, str, np.ndarray]] = ()) -> None:
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
        if owner in seen or any(result.status[i] not in ("estimated", "fixed") for i in idx):
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
