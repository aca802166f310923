"""Generate closedloop/assets/utah_mit_hand.urdf from the nominal Table 4.1 (closedloop/assets/dh/utah_mit_thumb_finger.yaml).

    python closedloop/assets/dh/make_hand_urdf.py            # rewrites closedloop/assets/utah_mit_hand.urdf

How the 8-row loop maps to two branches on a palm (thesis 4.2.1, Fig. 4-1/4-3)
-----------------------------------------------------------------------------
The loop's rows j0..j7 run from the thumb's distal joint (the base frame -1
lies on its axis) to the palm and out to the finger tip: A_j = Rz(theta_j') C_j
maps frame j to frame j-1 and joint j turns about z_{j-1}.  The palm is link
3: it carries frame 2' = frame 2 * Rz(theta_3') (the palm reference of 4.5)
and frame 3 = 2' * C_3 on the finger's first axis.  Rooting the tree at the
palm (URDF link ``palm``, its frame = 2'):

* finger branch (forward rows): ``finger_j4`` origin C_3 Rz(theta_off_4), then
  ``finger_j5`` C_4 Rz(theta_off_5), ``finger_j6`` C_5 Rz(theta_off_6),
  ``finger_j7`` C_6 Rz(theta_off_7); axes +z.
* thumb branch (rows run backwards): frame 2' -> 2 is Rz(-theta_3'), frame
  j -> j-1 is A_j^-1 = C_{j-1}^-1 Rz(-theta_{j-1}'), so ``thumb_j3`` has origin
  Rz(-theta_off_3), ``thumb_j2`` C_2^-1 Rz(-theta_off_2), ``thumb_j1``
  C_1^-1 Rz(-theta_off_1), ``thumb_j0`` C_0^-1 Rz(-theta_off_0); axes -z, so
  a URDF joint value is the SAME reading as the loop's (Rz(-q) = reversed joint).
* offsets are folded into the origins, so both models take the same readings
  (URDF joint thumb_jN / finger_jN = D-H row jN, scale 1).
* tips: ``thumb_tip`` sits in the thumb's distal link (frame -1) 0.735 in
  along +x (the middle phalanx lies along -x at theta_0' = 0); ``finger_tip``
  sits in the finger's distal link 0.735 in along -x (theta_off_7 = pi turns
  the x axis back; the guessed tip link C_7 runs along -x too).  0.735 in is the
  tip length of 4.5 [57].  The grasp (plate) is the unknown weld between them:
  ``--loop weld:frame=finger_tip,to=thumb_tip``.  With the D-H chain closed
  (A_0 ... A_7 = I) the pose of finger_tip in thumb_tip is the constant
  Tx(-0.735) C_7^-1 Tx(-0.735), so the URDF loop is the D-H loop with the
  tip link re-expressed as an unknown grasp.

Inertials are nominal (aluminium-ish phalanges, 20-50 g) so MuJoCo loads it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "utah_mit_hand.urdf"
INCH = 0.0254
TIP = 0.735 * INCH


def _rot(axis, a):
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _T(R=np.eye(3), t=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def constant(row) -> np.ndarray:
    """Constant part of a row (after Rz(theta')), metres / radians."""
    if row["convention"] == "dh":
        return _T(t=(row["a"], 0, row["s"])) @ _T(_rot("x", row["alpha"]))
    return _T(t=(row["s"], 0, 0)) @ _T(_rot("x", row["a"]) @ _rot("y", row["alpha"]))


def rpy(R) -> tuple[float, float, float]:
    """URDF rpy (R = Rz(y) Ry(p) Rx(r))."""
    p = float(np.arcsin(-np.clip(R[2, 0], -1, 1)))
    if abs(np.cos(p)) < 1e-9:
        return float(np.arctan2(-R[1, 2], R[1, 1])), p, 0.0
    return float(np.arctan2(R[2, 1], R[2, 2])), p, float(np.arctan2(R[1, 0], R[0, 0]))


def table_rows() -> list[dict]:
    import yaml

    doc = yaml.safe_load((HERE / "utah_mit_thumb_finger.yaml").read_text())
    rows = []
    for r in doc["joints"]:
        hay = r["convention"] == "hayati"
        rows.append({"name": r["name"], "convention": r["convention"], "theta_off": r["theta_off"],
                     "s": r["s"] * INCH, "a": r["a"] if hay else r["a"] * INCH, "alpha": r["alpha"]})
    return rows


def _origin(T) -> str:
    x, y, z = (f"{v:.10g}" for v in T[:3, 3])
    r, p, yw = (f"{v:.10g}" for v in rpy(T[:3, :3]))
    return f'<origin xyz="{x} {y} {z}" rpy="{r} {p} {yw}"/>'


def _link(name: str, mass: float, com=(0, 0, 0)) -> str:
    i = mass * (0.01 ** 2) / 2.5
    c = " ".join(f"{v:.6g}" for v in com)
    return (f'  <link name="{name}">\n    <inertial><origin xyz="{c}" rpy="0 0 0"/><mass value="{mass}"/>'
            f'<inertia ixx="{i:.3e}" ixy="0" ixz="0" iyy="{i:.3e}" iyz="0" izz="{i:.3e}"/></inertial>\n  </link>\n')


def _joint(name, parent, child, T, axis) -> str:
    return (f'  <joint name="{name}" type="revolute">\n    <parent link="{parent}"/><child link="{child}"/>\n'
            f'    {_origin(T)}\n    <axis xyz="0 0 {axis}"/>\n'
            f'    <limit lower="-3.14159" upper="3.14159" effort="5" velocity="5"/>\n  </joint>\n')


def _fixed(name, parent, child, T) -> str:
    return (f'  <joint name="{name}" type="fixed">\n    <parent link="{parent}"/><child link="{child}"/>\n'
            f'    {_origin(T)}\n  </joint>\n')


def build() -> str:
    rows = table_rows()
    C = [constant(r) for r in rows]
    off = [r["theta_off"] for r in rows]
    inv = np.linalg.inv
    out = ['<?xml version="1.0"?>\n<!-- GENERATED by closedloop/assets/dh/make_hand_urdf.py from '
           'closedloop/assets/dh/utah_mit_thumb_finger.yaml (nominal Table 4.1); see the generator for the mapping. -->\n'
           '<robot name="utah_mit_hand">\n']
    out.append(_link("palm", 0.2))
    # thumb: palm(2') -> thumb_base(2) -> thumb_proximal(1) -> thumb_middle(0) -> thumb_distal(-1)
    thumb = [("thumb_j3", "palm", "thumb_base", _T(_rot("z", -off[3]))),
             ("thumb_j2", "thumb_base", "thumb_proximal", inv(C[2]) @ _T(_rot("z", -off[2]))),
             ("thumb_j1", "thumb_proximal", "thumb_middle", inv(C[1]) @ _T(_rot("z", -off[1]))),
             ("thumb_j0", "thumb_middle", "thumb_distal", inv(C[0]) @ _T(_rot("z", -off[0])))]
    for name, parent, child, T in thumb:
        out.append(_link(child, 0.03))
        out.append(_joint(name, parent, child, T, -1))
    finger = [("finger_j4", "palm", "finger_base", C[3] @ _T(_rot("z", off[4]))),
              ("finger_j5", "finger_base", "finger_proximal", C[4] @ _T(_rot("z", off[5]))),
              ("finger_j6", "finger_proximal", "finger_middle", C[5] @ _T(_rot("z", off[6]))),
              ("finger_j7", "finger_middle", "finger_distal", C[6] @ _T(_rot("z", off[7])))]
    for name, parent, child, T in finger:
        out.append(_link(child, 0.03))
        out.append(_joint(name, parent, child, T, 1))
    out.append(_link("thumb_tip", 0.001))
    out.append(_fixed("thumb_tip_joint", "thumb_distal", "thumb_tip", _T(t=(TIP, 0, 0))))
    out.append(_link("finger_tip", 0.001))
    out.append(_fixed("finger_tip_joint", "finger_distal", "finger_tip", _T(t=(-TIP, 0, 0))))
    out.append("</robot>\n")
    return "".join(out)


if __name__ == "__main__":
    import logging

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    OUT.write_text(build())
    logging.getLogger(__name__).info("wrote %s", OUT)
