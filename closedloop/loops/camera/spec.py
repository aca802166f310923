"""The ``camera`` loop on the command line (``--loop camera:...``).

    camera:frame=marker_link                              one camera in the world, everything unknown
    camera:frame=tool0,cameras=2,to=head                  a stereo pair on one frame (a fixed head)
    camera:frame=tool0,to=cam_left_optical+cam_right_optical
                                                          camera c on frame c (a verging head: each
                                                          camera moves on its own sensed joint)
    camera:frame=tool0,to=left+right,closure=triangulation   the thesis's stereo closure (eq. 5.13)
    camera:frame=tool0,info1=left.yaml,dist=k1+k2         intrinsics from a camera_info file, k1, k2 identified

Frames in ``to`` are joined by ``+`` (no quotes needed).  Per camera c = 1, 2, ...:
``K<c>="fx fy cx cy"`` known intrinsics, ``K<c>_0=`` a guess of unknown ones, ``pose<c>="x y z rx ry rz"``
a guess of its pose in its frame, ``D<c>="k1 k2 p1 p2 k3"`` its distortion (fixed, or the start of the
coefficients named in ``dist``), ``info<c>=FILE`` a ROS camera_info / OpenCV YAML giving K<c> and D<c>.
"""

from __future__ import annotations

import numpy as np

from closedloop.errors import InputError, LoopError
from closedloop.loops.base import Loop
from closedloop.loops.camera.model import DIST_FIELDS
from closedloop.loops.spec import register
from closedloop.model.robot import RobotModel
from closedloop.model.se3 import parse_vec

MAX_CAMERAS = 4
_PER_CAMERA = ("K{}", "K{}_0", "pose{}", "D{}", "info{}")
KEYS = {"frame", "to", "cameras", "rig", "tip", "tip0", "sigma_px", "dist", "closure"} | {
    k.format(c) for k in _PER_CAMERA for c in range(1, MAX_CAMERAS + 1)
}


def _vec(kw: dict[str, str], key: str, n: int, name: str) -> np.ndarray | None:
    if kw.get(key, "unknown") == "unknown":
        return None
    try:
        return parse_vec(kw[key], n, key)
    except LoopError as exc:
        raise LoopError(f"camera loop '{name}': {exc}") from None


def _float(kw: dict[str, str], key: str, name: str) -> float | None:
    if key not in kw:
        return None
    try:
        return float(kw[key])
    except ValueError:
        raise LoopError(f"camera loop '{name}': {key}='{kw[key]}' is not a number") from None


@register("camera", KEYS)
def camera_loop_from_spec(kw: dict[str, str], robot: RobotModel) -> Loop:
    """camera:frame=A[,to=B|F1+F2+..][,cameras=1|2][,closure=reprojection|triangulation][,dist=k1+k2+p1+p2+k3]
    [,K<c>=|K<c>_0="fx fy cx cy"][,pose<c>="x y z rx ry rz"][,D<c>="k1 k2 p1 p2 k3"][,info<c>=FILE]
    [,rig="x y z rx ry rz"][,tip=|tip0="x y z"][,sigma_px=px] (module docstring)."""
    from closedloop.loops.camera.loop import CLOSURES, CameraLoop  # camera.py imports this module to register the type

    name = kw.get("name", "camera")
    if "frame" not in kw:
        raise LoopError(f"camera loop '{name}': needs frame=<tool frame>")
    to = [f.strip() for f in kw.get("to", "universe").split("+")]
    if any(not f for f in to):
        raise LoopError(f"camera loop '{name}': to='{kw['to']}': empty frame name (frames are joined by '+')")
    multi = len(to) > 1
    try:
        cameras = int(kw.get("cameras", str(len(to))))
    except ValueError:
        cameras = 0
    if multi and cameras != len(to):
        raise LoopError(f"camera loop '{name}': cameras={kw.get('cameras')} but to= names {len(to)} camera frames")
    if not multi and cameras not in (1, 2):
        raise LoopError(
            f"camera loop '{name}': cameras='{kw.get('cameras')}': expected 1 or 2 on one frame "
            "(more: one frame each, to=F1+F2+F3)"
        )
    if cameras > MAX_CAMERAS:
        raise LoopError(f"camera loop '{name}': {cameras} cameras; at most {MAX_CAMERAS}")
    extra = sorted(
        k for k in kw for c in range(cameras + 1, MAX_CAMERAS + 1) if k in {p.format(c) for p in _PER_CAMERA}
    )
    if "rig" in kw and cameras != 2:
        extra.insert(0, "rig")
    if extra:
        raise LoopError(f"camera loop '{name}': {extra[0]} given but the loop has {cameras} camera(s)")
    closure = kw.get("closure", "reprojection")
    if closure not in CLOSURES:
        raise LoopError(f"camera loop '{name}': closure='{closure}': expected {' or '.join(CLOSURES)}")
    dist = (
        []
        if kw.get("dist", "none") in ("none", "")
        else (list(DIST_FIELDS) if kw["dist"] == "all" else [f.strip() for f in kw["dist"].split("+")])
    )
    K, K0, poses, D = [], [], [], []
    for c in range(1, cameras + 1):
        for a, b in ((f"K{c}", f"K{c}_0"), (f"info{c}", f"K{c}"), (f"info{c}", f"K{c}_0"), (f"info{c}", f"D{c}")):
            if a in kw and b in kw:
                raise LoopError(f"camera loop '{name}': give {a} or {b}, not both")
        k, d = _vec(kw, f"K{c}", 4, name), _vec(kw, f"D{c}", 5, name)
        if f"info{c}" in kw:
            from closedloop.io.camera_info import read_camera_info

            try:
                info = read_camera_info(kw[f"info{c}"])
            except InputError as exc:
                raise LoopError(f"camera loop '{name}': info{c}: {exc}") from None
            k, d = info.K, info.D
        K.append(k)
        K0.append(_vec(kw, f"K{c}_0", 4, name))
        poses.append(_vec(kw, f"pose{c}", 6, name))
        D.append(d)
    if "tip" in kw and "tip0" in kw:
        raise LoopError(f"camera loop '{name}': give tip (known) or tip0 (a guess), not both")
    return CameraLoop(
        name,
        kw["frame"],
        to[0],
        cameras=cameras,
        K=K,
        initial_K=K0,
        initial_poses=poses,
        rig=_vec(kw, "rig", 6, name),
        tip=_vec(kw, "tip", 3, name),
        initial_tip=_vec(kw, "tip0", 3, name),
        sigma_px=_float(kw, "sigma_px", name),
        camera_frames=to if multi else None,
        dist=dist,
        D=D,
        closure=closure,
    )
