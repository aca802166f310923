"""What a loop closes on in the simulator: a door on a hinge, a plane with a sliding puck, a tracker.

Each is drawn or placed from the true tool pose at the grasp configuration (so the loop starts
closed) and added to the MuJoCo spec by the loop type that uses it (:mod:`closedloop.sims.loop_types`):

* :func:`door_hinge_pose`: the hinge frame (z vertical) ``radius`` from the handle, perpendicular to
  the line from the robot base to the handle (:class:`~closedloop.sims.scenarios.DoorGeometry`);
* :func:`draw_plane`, :func:`add_puck`: a tilted plane through the tool point and the passive puck
  (two slide joints spanning the plane, a ball joint) the stylus tip is connected to;
* :func:`draw_tracker`: the external tracker's frame (open loops).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from closedloop.sims.scenarios import DoorGeometry, PlaneGeometry, TrackerGeometry

if TYPE_CHECKING:
    import mujoco

__all__ = [
    "TOOL_SITE",
    "TARGET_SITE",
    "LOOP_EQ",
    "DOOR_PREFIX",
    "DOOR_JOINT",
    "PUCK_PREFIX",
    "quat_wxyz",
    "door_hinge_pose",
    "draw_plane",
    "draw_tracker",
    "add_puck",
]

TOOL_SITE = "tool_site"
TARGET_SITE = "loop_target"
LOOP_EQ = "loop"
DOOR_PREFIX = "door_"
DOOR_JOINT = DOOR_PREFIX + "hinge"
PUCK_PREFIX = "puck_"


def quat_wxyz(rot: np.ndarray) -> np.ndarray:
    """MuJoCo's (w, x, y, z) quaternion of a rotation matrix."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot, dtype=float).reshape(9))
    return q


def door_hinge_pose(tool: pin.SE3, geom: DoorGeometry) -> pin.SE3:
    """Hinge frame (z vertical) placed ``geom.radius`` from the handle, see :class:`DoorGeometry`."""
    p = tool.translation
    u = np.array([p[0], p[1], 0.0])
    nu = np.linalg.norm(u)
    u = u / nu if nu > 1e-6 else np.array([1.0, 0.0, 0.0])
    t = np.array([-u[1], u[0], 0.0])  # door x axis (from hinge to handle)
    rot = np.column_stack([t, np.cross([0.0, 0.0, 1.0], t), [0.0, 0.0, 1.0]])
    return pin.SE3(rot, p - geom.radius * t)


def draw_plane(tool_point: np.ndarray, geom: PlaneGeometry, rng: np.random.Generator) -> pin.SE3:
    """Plane frame (z = unit normal, n_z > 0) through ``tool_point``, see :class:`PlaneGeometry`."""
    tilt = float(rng.uniform(*geom.tilt))
    az = float(rng.uniform(-np.pi, np.pi))
    spin = float(rng.uniform(-np.pi, np.pi))
    axis = np.array([np.cos(az), np.sin(az), 0.0])
    rot = pin.exp3(tilt * axis) @ pin.exp3(np.array([0.0, 0.0, spin]))
    return pin.SE3(rot, np.asarray(tool_point, dtype=float).copy())


def draw_tracker(geom: TrackerGeometry, rng: np.random.Generator) -> pin.SE3:
    """Tracker frame in the world, see :class:`TrackerGeometry` (uniformly random orientation)."""
    dist = float(rng.uniform(*geom.distance))
    az = float(rng.uniform(-np.pi, np.pi))
    h = float(rng.uniform(*geom.height))
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    rot = pin.Quaternion(quat[0], quat[1], quat[2], quat[3]).normalized().matrix()
    return pin.SE3(rot, np.array([dist * np.cos(az), dist * np.sin(az), h]))


def add_puck(spec: mujoco.MjSpec, plane: pin.SE3, geom: PlaneGeometry, gravcomp: bool) -> None:
    """The passive puck: two slide joints along the plane's x and y axes, then a ball joint."""
    import mujoco

    frame = spec.worldbody.add_body(name=PUCK_PREFIX + "plane", pos=plane.translation, quat=quat_wxyz(plane.rotation))
    m = geom.puck_mass
    slider = frame.add_body(name=PUCK_PREFIX + "slider_x")
    jx = slider.add_joint(name=PUCK_PREFIX + "x", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1.0, 0.0, 0.0])
    carriage = slider.add_body(name=PUCK_PREFIX + "slider_y")
    jy = carriage.add_joint(name=PUCK_PREFIX + "y", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0.0, 1.0, 0.0])
    puck = carriage.add_body(name=PUCK_PREFIX + "puck")
    jb = puck.add_joint(name=PUCK_PREFIX + "ball", type=mujoco.mjtJoint.mjJNT_BALL)
    for j in (jx, jy):
        j.range = [-geom.slide_range, geom.slide_range]
        j.limited = mujoco.mjtLimited.mjLIMITED_TRUE
    for j in (jx, jy, jb):
        j.armature = 1e-3
        j.damping = np.full_like(np.atleast_1d(j.damping), 0.05)
    for b in (slider, carriage, puck):
        # a small sphere carries the mass (the saved XML keeps geoms, not a spec-only inertial)
        g = b.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.01, 0.0, 0.0])
        g.mass = m
        g.contype = 0
        g.conaffinity = 0
        b.gravcomp = 1.0 if gravcomp else 0.0
    puck.add_site(name=TARGET_SITE, size=[0.02, 0.02, 0.02])
