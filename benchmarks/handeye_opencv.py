"""Against AX = XB: OpenCV's hand-eye solvers vs closedloop calibrating the robot and the camera together.

Eye-in-hand: a camera (known intrinsics, 640 x 480, f = 600 px) on the UR5's flange (tool0) at an unknown
pose X, looking at a 5 x 4 board (40 mm pitch) lying on the table at an unknown pose.  The true robot has
kinematic errors of the size real arms have: every joint placement off by U(-2, 2) mm and U(-2, 2) mrad,
every joint offset by U(-5, 5) mrad.  Pixels: exact projection + 0.3 px noise; joint readings + 1e-5 rad.

* OpenCV (the field's tools, which assume the robot's kinematics exact): per image the board pose by
  solvePnP, the flange pose by the NOMINAL kinematics; cv2.calibrateHandEye (Tsai, Park, Horaud, Andreff,
  Daniilidis) gives X, the board in the base is the average of T_flange X T_board_in_camera;
  cv2.calibrateRobotWorldHandEye (Shah, Li) gives X and the board in the base together.
* closedloop: a camera loop per board point used (the centre and the four corners; camera on tool0, the
  point fixed in the world), ``camera:frame=universe,to=tool0,K1=..,sigma_px=0.3``: the robot's placements
  and offsets, the camera pose and the point, together (each loop has its own camera pose until loops can
  share parameters); the centre's loop predicts.

Held-out (30 configurations not used to fit): the board centre predicted from the joint readings
(in the image: px RMS; in space: its position in the camera frame, mm RMS, against the truth).  The
length scale: pixels do not see it (thesis 5.4), so closedloop holds one robot length at its nominal
value; the in-space error includes that length's own error.

    pip install -r benchmarks/requirements-handeye.txt
    python benchmarks/handeye_opencv.py [--seed 1] [--n 60]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load, machine  # noqa: E402

from closedloop.calibration import CalibrationOptions, calibrate  # noqa: E402
from closedloop.data import JointLog  # noqa: E402
from closedloop.loops.camera import CameraLoop  # noqa: E402
from closedloop.models import example_robot_data_dir  # noqa: E402
from closedloop.parameters import RobotParameters  # noqa: E402
from closedloop.robot import RobotModel  # noqa: E402

K = np.array([600.0, 600.0, 319.5, 239.5])
KM = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1.0]])
X_TRUE = pin.SE3(pin.exp3(np.array([0.02, -0.03, 0.01])), np.array([0.03, -0.05, 0.04]))  # camera in tool0
BOARD = pin.SE3(pin.exp3(np.array([np.pi, 0.0, 0.1])), np.array([0.55, 0.05, 0.0]))  # board in the base
GRID = np.array([[0.04 * i - 0.08, 0.04 * j - 0.06, 0.0] for i in range(5) for j in range(4)])
Q_DOWN = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])
ERR_M, ERR_RAD, ERR_OFFSET = 2e-3, 2e-3, 5e-3  # kinematic errors of an uncalibrated arm
METHODS = {"Tsai": "CALIB_HAND_EYE_TSAI", "Park": "CALIB_HAND_EYE_PARK", "Horaud": "CALIB_HAND_EYE_HORAUD",
           "Andreff": "CALIB_HAND_EYE_ANDREFF", "Daniilidis": "CALIB_HAND_EYE_DANIILIDIS"}


def flange_poses(robot, rp, values, theta) -> list[pin.SE3]:
    state = rp.apply(values)
    out = []
    fid = robot.frame_id("tool0")
    for q in robot.configurations(theta * state.scale + state.offset, rp.joints):
        pin.framesForwardKinematics(state.model, state.data, q)
        out.append(pin.SE3(state.data.oMf[fid]))
    return out


def project(T_cam: pin.SE3, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = (P - T_cam.translation) @ T_cam.rotation
    return np.column_stack([K[0] * pc[:, 0] / pc[:, 2] + K[2], K[1] * pc[:, 1] / pc[:, 2] + K[3]]), pc


def make_data(robot, rp, truth, rng, n):
    """Readings where the true camera sees the whole board; pixels of every board point."""
    P = np.array([BOARD.act(g) for g in GRID])
    th, uv = [], []
    while len(th) < n:
        t = Q_DOWN + rng.uniform(-0.35, 0.35, 6)
        T = flange_poses(robot, rp, truth, t[None])[0] * X_TRUE
        px, pc = project(T, P)
        if pc[:, 2].min() > 0.15 and np.all((px > 0) & (px < [640, 480])):
            th.append(t)
            uv.append(px)
    return np.array(th), np.array(uv)


def average_se3(Ts: list[pin.SE3]) -> pin.SE3:
    U, _, Vt = np.linalg.svd(sum(T.rotation for T in Ts))
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return pin.SE3(R, np.mean([T.translation for T in Ts], axis=0))


def opencv_fits(flange: list[pin.SE3], uv: np.ndarray) -> dict[str, tuple[pin.SE3, pin.SE3]]:
    """{method: (X camera in flange, board in base)} from the nominal flange poses and solvePnP."""
    import cv2

    Rg, tg, Rt, tt = [], [], [], []
    board_in_cam = []
    for F, px in zip(flange, uv):
        ok, rvec, tvec = cv2.solvePnP(GRID, px, KM, None, flags=cv2.SOLVEPNP_ITERATIVE)
        B = pin.SE3(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        board_in_cam.append(B)
        Rg.append(F.rotation), tg.append(F.translation), Rt.append(B.rotation), tt.append(B.translation)
    out = {}
    for name, flag in METHODS.items():
        R, t = cv2.calibrateHandEye(Rg, tg, Rt, tt, method=getattr(cv2, flag))
        X = pin.SE3(R, t.reshape(3))
        out[name] = (X, average_se3([F * X * B for F, B in zip(flange, board_in_cam)]))
    # robot-world-hand-eye: base->world... OpenCV's convention: inputs world->cam (board) and base->gripper
    Rb2g = [F.inverse().rotation for F in flange]
    tb2g = [F.inverse().translation for F in flange]
    for name, flag in (("RWHE Shah", "CALIB_ROBOT_WORLD_HAND_EYE_SHAH"), ("RWHE Li", "CALIB_ROBOT_WORLD_HAND_EYE_LI")):
        Rbw, tbw, Rgc, tgc = cv2.calibrateRobotWorldHandEye(Rt, tt, Rb2g, tb2g, method=getattr(cv2, flag))
        base_to_world = pin.SE3(Rbw, tbw.reshape(3))  # T_world_base: a point in base -> world(board) frame
        gripper_to_cam = pin.SE3(Rgc, tgc.reshape(3))  # T_cam_gripper
        out[name] = (gripper_to_cam.inverse(), base_to_world.inverse())
    return out


def held_out_errors(T_cams: list[pin.SE3], point: np.ndarray, T_true: list[pin.SE3], uv_true: np.ndarray):
    """RMS image (px) and camera-frame position (mm) errors of `point` (base frame) seen from predicted cameras."""
    px, pc = zip(*(project(T, point[None]) for T in T_cams))
    _, pt = zip(*(project(T, point[None]) for T in T_true))
    e_px = np.linalg.norm(np.vstack(px) - uv_true, axis=1)
    e_mm = 1e3 * np.linalg.norm(np.vstack(pc) - np.vstack(pt), axis=1)
    return float(np.sqrt(np.mean(e_px ** 2))), float(np.sqrt(np.mean(e_mm ** 2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--n", type=int, default=60, help="training configurations")
    ap.add_argument("--test", type=int, default=30, help="held-out configurations")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    robot = RobotModel.from_file(example_robot_data_dir() / "ur_description/urdf/ur5_robot.urdf")
    joints = robot.supporting_joints("tool0")
    rp = RobotParameters(robot, joints)
    truth = np.array([p.nominal for p in rp.params])
    for i, p in enumerate(rp.params):
        if p.kind == "placement":
            truth[i] += rng.uniform(-ERR_M, ERR_M) if p.unit == "m" else rng.uniform(-ERR_RAD, ERR_RAD)
        elif p.kind == "offset":
            truth[i] += rng.uniform(-ERR_OFFSET, ERR_OFFSET)
    nominal = np.array([p.nominal for p in rp.params])
    th, uv = make_data(robot, rp, truth, rng, args.n + args.test)
    uv = uv + rng.normal(scale=0.3, size=uv.shape)
    readings = th + rng.normal(scale=1e-5, size=th.shape)
    tr, te = slice(0, args.n), slice(args.n, None)
    centre = BOARD.translation  # the board's centre point (the grid is centred on it)
    T_true = [F * X_TRUE for F in flange_poses(robot, rp, truth, th[te])]
    centre_uv_true = np.vstack([project(T, centre[None])[0] for T in T_true])
    rows = []
    t0 = time.perf_counter()
    fits = opencv_fits(flange_poses(robot, rp, nominal, readings[tr]), uv[tr])
    t_cv = time.perf_counter() - t0
    F_test_nom = flange_poses(robot, rp, nominal, readings[te])
    for name, (X, board) in fits.items():
        cams = [F * X for F in F_test_nom]
        # the board centre (origin of the board frame) as OpenCV's calibration places it in the base
        rows.append((f"OpenCV {name}", *held_out_errors(cams, board.translation, T_true, centre_uv_true),
                     t_cv / len(fits)))
    # closedloop: the board centre (exact pixels of the centre: the grid's centre is not a grid point, so its
    # pixel is the true projection + noise like the others)
    pts = [centre] + [BOARD.act(GRID[k]) for k in (0, 3, 16, 19)]
    F_true_tr = flange_poses(robot, rp, truth, th[tr])
    extra, loops = {}, []
    for m, P in enumerate(pts):
        px = np.vstack([project(F * X_TRUE, P[None])[0] for F in F_true_tr])
        px = px + rng.normal(scale=0.3, size=(args.n, 2))
        extra[f"p{m}:u1"], extra[f"p{m}:v1"] = px[:, 0], px[:, 1]
        loops.append(CameraLoop(f"p{m}", "universe", "tool0", K=[K], sigma_px=0.3))
    log = JointLog(joints, readings[tr], None, None, extra)
    known = {"elbow_joint.z": float(truth[rp.index["elbow_joint.z"]])}
    for label, fix in (("closedloop (robot + camera)", {}), ("closedloop, upper arm length known", known)):
        t0 = time.perf_counter()
        res = calibrate(robot, log, loops, CalibrationOptions(noise=1e-5, fix=fix))
        t_cl = time.perf_counter() - t0
        vals = dict(zip(res.names, res.values))
        robot_vals = np.array([vals.get(p.name, p.nominal) for p in rp.params])
        Xc = pin.SE3(pin.exp3(np.array([vals[f"p0.cam1.{a}"] for a in ("rx", "ry", "rz")])),
                     np.array([vals[f"p0.cam1.{a}"] for a in "xyz"]))
        point = np.array([vals[f"p0.tip_{a}"] for a in "xyz"])
        cams = [F * Xc for F in flange_poses(robot, rp, robot_vals, readings[te])]
        rows.append((label, *held_out_errors(cams, point, T_true, centre_uv_true), t_cl))
    print(f"machine: {machine()}; {load()}")
    print(f"UR5 eye-in-hand, seed {args.seed}: {args.n} training / {args.test} held-out configurations; "
          "robot errors 2 mm, 2 mrad, offsets 5 mrad; 0.3 px, 1e-5 rad noise")
    print(f"{'method':<30}{'image px RMS':>14}{'space mm RMS':>14}{'time s':>9}")
    for name, e_px, e_mm, t in rows:
        print(f"{name:<30}{e_px:14.3f}{e_mm:14.3f}{t:9.3f}")
    best = min(r[1] for r in rows[:-2])
    best_mm = min(r[2] for r in rows[:-2])
    print(f"best OpenCV / closedloop: image {best / rows[-2][1]:.1f}x; space {best_mm / rows[-2][2]:.1f}x "
          f"(one length known: {best_mm / rows[-1][2]:.1f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
