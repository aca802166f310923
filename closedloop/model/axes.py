"""Joints a contact point cannot see: the point on the last revolute joints' axes.

A point loop (ball in a socket, a stylus on a plane, a tracked marker) measures where a point of the
tool is, never how the tool is turned.  When the point lies on the axis of the chain's last revolute
joint, turning that joint does not move it: the joint's offset, and the placement of its axis about
the point, leave the closure unchanged (a zero column of the identification Jacobian, thesis 3.4.1),
and a fit that starts there sits on a saddle of the cost.  The same holds for the joint before it
when the point lies on its axis too (a spherical wrist's centre is on all three), and so on down the
chain until a joint that moves the point.

`blind_joints` reads this off the structure of the nominal model: walking from the point's frame to
the base, each one-DOF joint's twist (its axis and moment, `pinocchio.computeJointJacobian`) gives
the point's speed per unit joint speed, ``|v + w x p|``, which is the point's distance from the axis
for a revolute joint; the walk stops at the first joint that moves the point (a prismatic joint
always does).  The joints before the last ones are judged at the configuration given, since the
later ones, turning about axes through the point, do not move it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

__all__ = ["BlindJoint", "blind_joints", "point_on_axis_message", "AXIS_TOLERANCE"]

#: a contact point closer than this to a revolute axis (m) is taken to lie on it
AXIS_TOLERANCE = 1e-3


@dataclass(frozen=True)
class BlindJoint:
    """A joint whose motion does not move the contact point: its name and the point's distance from its axis."""

    joint: str
    distance: float


def blind_joints(
    model: pin.Model, frame_id: int, point, q: np.ndarray | None = None, tol: float = AXIS_TOLERANCE
) -> list[BlindJoint]:
    """The last joints of the chain to `frame_id` whose axes pass within `tol` of `point` (module doc).

    Args:
        model: the nominal robot.
        frame_id: the contact point's frame.
        point: the contact point in that frame (m; the frame's origin when no tip is given).
        q: the configuration the chain is judged at (default: neutral; only the joints before a blind
            one depend on it, and only through joints that do not move the point).
        tol: a point closer than this to a revolute axis lies on it (m).

    Returns:
        the blind joints, last first (empty: the last joint moves the point).
    """
    data = model.createData()
    q = pin.neutral(model) if q is None else np.asarray(q, dtype=float)
    pin.forwardKinematics(model, data, q)
    pin.updateFramePlacements(model, data)
    p_world = data.oMf[frame_id].act(np.asarray(point, dtype=float))
    out: list[BlindJoint] = []
    jid = int(model.frames[frame_id].parentJoint)
    while jid > 0:
        jm = model.joints[jid]
        if jm.nv != 1:
            break
        J = pin.computeJointJacobian(model, data, q, jid)  # LOCAL: the joint's twist in its own frame
        twist = J[:, jm.idx_v]
        v, w = twist[:3], twist[3:]
        if np.linalg.norm(w) < 1e-12:  # prismatic: it always moves the point
            break
        p = data.oMi[jid].actInv(p_world)
        distance = float(np.linalg.norm(v + np.cross(w, p)) / np.linalg.norm(w))
        if distance >= tol:
            break
        out.append(BlindJoint(model.names[jid], distance))
        jid = int(model.parents[jid])
    return out


def point_on_axis_message(where: str, frame: str, blind: list[BlindJoint], tip_given: bool, fix: str) -> str:
    """The one line that names a contact point on the last joints' axes, and the fix."""
    names = ", ".join(f"{b.joint} ({b.distance * 1e3:.2f} mm away)" for b in blind)
    point = "the given tip" if tip_given else f"the origin of {frame}"
    return (
        f"{where}: the contact point ({point}) lies on the axis of joint(s) {names}: turning "
        f"{'it' if len(blind) == 1 else 'them'} does not move the point, so a point loop cannot see "
        f"{'that joint' if len(blind) == 1 else 'those joints'}; {fix}"
    )
