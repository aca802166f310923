"""Camera intrinsics as users have them: ROS ``camera_info`` YAML and OpenCV FileStorage YAML.

Read (``read_camera_info``) and write (``write_camera_info``) the pinhole
intrinsics k = (fx, fy, cx, cy) and the plumb-bob distortion
d = (k1, k2, p1, p2, k3) (OpenCV's order) of one camera.  Formats read:

* ROS 1 ``camera_calibration`` / ``camera_info_manager`` YAML: ``image_width``,
  ``image_height``, ``camera_name``, ``camera_matrix: {rows, cols, data}``,
  ``distortion_model``, ``distortion_coefficients: {rows, cols, data}``;
* a ROS 2 ``sensor_msgs/CameraInfo`` dump: ``width``, ``height``, ``k`` (9), ``d``;
* OpenCV ``cv::FileStorage`` YAML (``%YAML:1.0``, ``!!opencv-matrix``):
  ``camera_matrix`` (or ``K``), ``distortion_coefficients`` (or
  ``dist_coeffs``, ``D``), optional ``image_width``/``image_height``.

Fewer than five distortion coefficients are padded with zeros; a camera
matrix with skew, or a distortion model other than plumb_bob / radtan, is an
error (the loop's model has neither).  ``write_camera_info`` writes the ROS 1
form, which OpenCV-based tools and ``camera_info_manager`` read back.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from closedloop.errors import InputError

__all__ = ["CameraInfo", "read_camera_info", "write_camera_info", "camera_info_text", "camera_infos_from_result"]


class CameraInfoError(InputError):
    """A camera_info / OpenCV calibration file that cannot be read."""


@dataclass
class CameraInfo:
    K: np.ndarray  # fx, fy, cx, cy (px)
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))  # k1, k2, p1, p2, k3
    width: int | None = None
    height: int | None = None
    name: str = "camera"

    def matrix(self) -> np.ndarray:
        fx, fy, cx, cy = self.K
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _matrix(node, what: str, path) -> np.ndarray:
    if isinstance(node, dict):
        if "data" not in node:
            raise CameraInfoError(f"{path}: '{what}' has no 'data'")
        node = node["data"]
    try:
        a = np.asarray(node, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise CameraInfoError(f"{path}: '{what}' is not a list of numbers") from None
    if not np.all(np.isfinite(a)):
        raise CameraInfoError(f"{path}: '{what}' has a value that is not a finite number")
    return a


def _first(doc: dict, keys: tuple[str, ...]):
    for k in keys:
        if k in doc:
            return k, doc[k]
    return None, None


def read_camera_info(path: str | Path) -> CameraInfo:
    """Intrinsics and distortion of one camera from a ROS camera_info or OpenCV YAML file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CameraInfoError(f"{path}: cannot read ({exc.strerror})") from None
    text = re.sub(r"^%YAML:?[0-9.]*\s*\n", "", text)  # OpenCV's header
    text = text.replace("!!opencv-matrix", "")
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CameraInfoError(f"{path}: not YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise CameraInfoError(f"{path}: expected a YAML mapping with a camera matrix")
    key, node = _first(doc, ("camera_matrix", "K", "k", "cameraMatrix"))
    if key is None:
        raise CameraInfoError(f"{path}: no camera matrix (camera_matrix, K or k)")
    M = _matrix(node, key, path)
    if M.size != 9:
        raise CameraInfoError(f"{path}: '{key}' has {M.size} numbers, expected 9 (3 x 3)")
    M = M.reshape(3, 3)
    if abs(M[0, 1]) > 1e-9 * abs(M[0, 0]) or not np.allclose(M[2], [0, 0, 1]) or M[1, 0] != 0:
        raise CameraInfoError(f"{path}: '{key}' has skew or is not [[fx 0 cx] [0 fy cy] [0 0 1]]")
    if not (M[0, 0] > 0 and M[1, 1] > 0):
        raise CameraInfoError(f"{path}: '{key}': fx and fy must be positive")
    model = str(doc.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "radtan", "rational_polynomial"):
        raise CameraInfoError(f"{path}: distortion_model '{model}' is not supported (plumb_bob)")
    dkey, dnode = _first(doc, ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "d"))
    D = np.zeros(5)
    if dkey is not None:
        d = _matrix(dnode, dkey, path)
        if d.size > 5 and np.any(d[5:] != 0):
            raise CameraInfoError(f"{path}: '{dkey}' has {d.size} coefficients; only k1 k2 p1 p2 k3 are supported")
        D[: min(d.size, 5)] = d[:5]
    w = doc.get("image_width", doc.get("width"))
    h = doc.get("image_height", doc.get("height"))
    return CameraInfo(
        np.array([M[0, 0], M[1, 1], M[0, 2], M[1, 2]]),
        D,
        None if w is None else int(w),
        None if h is None else int(h),
        str(doc.get("camera_name", path.stem)),
    )


def _row(a) -> str:
    return "[" + ", ".join(repr(float(x)) for x in np.asarray(a).reshape(-1)) + "]"


def write_camera_info(path: str | Path, info: CameraInfo) -> None:
    """Write `info` as a ROS 1 camera_info YAML, whole (`io.files.atomic_write_text`)."""
    from closedloop.io.files import atomic_write_text

    atomic_write_text(path, camera_info_text(info))


def camera_info_text(info: CameraInfo) -> str:
    """`info` as the text of a ROS 1 camera_info YAML."""
    fx, fy, cx, cy = map(float, info.K)
    P = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0]])
    lines = [
        f"image_width: {info.width if info.width is not None else 0}",
        f"image_height: {info.height if info.height is not None else 0}",
        f"camera_name: {info.name}",
        "camera_matrix:",
        "  rows: 3",
        "  cols: 3",
        f"  data: {_row(info.matrix())}",
        "distortion_model: plumb_bob",
        "distortion_coefficients:",
        "  rows: 1",
        "  cols: 5",
        f"  data: {_row(info.D)}",
        "rectification_matrix:",
        "  rows: 3",
        "  cols: 3",
        f"  data: {_row(np.eye(3))}",
        "projection_matrix:",
        "  rows: 3",
        "  cols: 4",
        f"  data: {_row(P)}",
    ]
    return "\n".join(lines) + "\n"


def camera_infos_from_result(result, loop) -> list[CameraInfo]:
    """The calibrated intrinsics and distortion of every camera of a camera loop in a CalibrationResult."""
    values = dict(zip(result.fit.names, result.fit.values))
    shared = getattr(loop, "shared", None) or {}  # a field shared with a group (cam1=@head) has the group's name
    out = []
    for c in range(loop.cameras):

        def name(f: str, c: int = c) -> str:
            return shared.get(f"cam{c + 1}.{f}", f"{loop.name}.cam{c + 1}.{f}")

        K = loop.K[c] if loop.K[c] is not None else np.array([values[name(f)] for f in ("fx", "fy", "cx", "cy")])
        D = loop.D[c].copy()
        for i, f in enumerate(("k1", "k2", "p1", "p2", "k3")):
            if name(f) in values:
                D[i] = values[name(f)]
        out.append(CameraInfo(np.asarray(K, float), D, name=f"{loop.name}_cam{c + 1}"))
    return out
