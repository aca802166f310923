"""Against AX = XB: OpenCV's hand-eye solvers vs closedloop calibrating the robot and the camera together.

Eye-in-hand: a camera (known intrinsics, 640 x 480, f = 600 px) on the UR5's flange (tool0) at an unknown
pose X, looking at a 5 x 4 board (40 mm pitch) lying on the table at an unknown pose, 0.4-0.6 m away.  The
true robot has kinematic errors of the size real arms have: every joint placement off by U(-2, 2) mm and
U(-2, 2) mrad, every joint offset by U(-5, 5) mrad.  Data: `n` training and `test` held-out configurations
(joints within +-0.35 rad of a pose looking down, the whole board in view), pixels of the 20 board points
= exact projection + 0.3 px noise, joint readings + 1e-5 rad.  Both methods get the same data: the same
joint readings, the same noisy pixels of the same 20 points, and the board's geometry.

* OpenCV (the field's tools, which take the robot's kinematics as exact): per image the board pose by
  solvePnP (the board's geometry gives it the scale), the flange pose by the NOMINAL kinematics;
  cv2.calibrateHandEye (Tsai, Park, Horaud, Andreff, Daniilidis) gives X, the board in the base is the
  average of T_flange X T_board_in_camera; cv2.calibrateRobotWorldHandEye (Shah, Li) gives X and the
  board in the base together.
* closedloop: one camera loop per board point (the point fixed in the world, the camera on tool0,
  ``camera:frame=universe,to=tool0,K1=..,sigma_px=0.3,cam1=@cam``), all sharing one camera pose
  (`closedloop.problem.shared`), the robot's placements and offsets identified with it.  Two variants:
  "scale held" (pixels alone: they do not see the overall size, thesis 5.4, so closedloop holds one
  robot length, elbow_joint.z, at its nominal value, 1-2 mm off) and "+ board geometry" (the board's 190
  point-to-point distances as `--distance` measurements, 10 um each: what OpenCV's solvePnP knows).

Held-out error (configurations not used to fit), the board centre (the mean of the 20 points) predicted
from the joint readings alone:

* image: |pi(p_hat) - pi(p_true)| RMS in px, against the noise-free truth;
* space: |p_hat - p_true| RMS in mm, p the centre in the CAMERA frame, p = X^-1 T_flange(q)^-1 c: predicted
  with each method's own robot model (OpenCV: nominal; closedloop: calibrated), own X and own centre c,
  against the true robot, X and centre.  The camera frame is physical, so the metric does not depend
  on where a method puts the robot's base (the base's placement is not identifiable from a hand camera:
  comparing base-frame positions, as an earlier version of this script did, measured that gauge, about
  6 mm for every method).  "along sight" is its component along the line of sight (the depth).

The table is for the first seed; the summary gives per seed the best OpenCV method and the ratio best
OpenCV / closedloop (+ board geometry), image and space.

    pip install -r benchmarks/requirements-handeye.txt
    python benchmarks/handeye_opencv.py [--seeds 1-10] [--n 60] [--test 30]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load, machine  # noqa: E402

from closedloop.assets.catalog import example_robot_data_dir  # noqa: E402
from closedloop.calibration.pipeline import CalibrationOptions, calibrate  # noqa: E402
from closedloop.io.logs import JointLog  # noqa: E402
from closedloop.loops.camera.loop import CameraLoop  # noqa: E402
from closedloop.loops.settings import share
from closedloop.model.parameters import RobotParameters  # noqa: E402
from closedloop.model.robot import RobotModel  # noqa: E402
from closedloop.problem.distances import DistanceLoop  # noqa: E402

K = np.array([600.0, 600.0, 319.5, 239.5])
KM = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1.0]])
X_TRUE = pin.SE3(pin.exp3(np.array([0.02, -0.03, 0.01])), np.array([0.03, -0.05, 0.04]))  # camera in tool0
BOARD = pin.SE3(pin.exp3(np.array([np.pi, 0.0, 0.1])), np.array([0.55, 0.05, 0.0]))  # board in the base
GRID = np.array([[0.04 * i - 0.08, 0.04 * j - 0.06, 0.0] for i in range(5) for j in range(4)])  # mean 0
Q_DOWN = np.array([0.0, -1.9, 1.9, -1.57, -1.57, 0.0])
ERR_M, ERR_RAD, ERR_OFFSET = 2e-3, 2e-3, 5e-3  # kinematic errors of an uncalibrated arm
SIGMA_PX, SIGMA_Q = 0.3, 1e-5
METHODS = {
    "Tsai": "CALIB_HAND_EYE_TSAI",
    "Park": "CALIB_HAND_EYE_PARK",
    "Horaud": "CALIB_HAND_EYE_HORAUD",
    "Andreff": "CALIB_HAND_EYE_ANDREFF",
    "Daniilidis": "CALIB_HAND_EYE_DANIILIDIS",
}
RWHE = {"RWHE Shah": "CALIB_ROBOT_WORLD_HAND_EYE_SHAH", "RWHE Li": "CALIB_ROBOT_WORLD_HAND_EYE_LI"}


@dataclass
class Scene:
    """One draw: the robot, its true and nominal parameters, readings and pixels (training first)."""

    robot: RobotModel
    rp: RobotParameters
    truth: np.ndarray
    nominal: np.ndarray
    theta: np.ndarray  # (n + test, 6) true joint angles
    readings: np.ndarray  # theta + noise
    uv: np.ndarray  # (n + test, 20, 2) noisy pixels of the board points
    n: int  # training configurations

    def flange(self, values: np.ndarray, theta: np.ndarray) -> list[pin.SE3]:
        """tool0 in the base for joint angles `theta` with robot parameters `values`."""
        state = self.rp.apply(values)
        fid = self.robot.frame_id("tool0")
        out = []
        for q in self.robot.configurations(theta * state.scale + state.offset, self.rp.joints):
            pin.framesForwardKinematics(state.model, state.data, q)
            out.append(pin.SE3(state.data.oMf[fid]))
        return out


def project(T_cam: pin.SE3, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and camera-frame positions (N, 3) of base-frame points P seen by a camera at T_cam."""
    pc = (P - T_cam.translation) @ T_cam.rotation
    return np.column_stack([K[0] * pc[:, 0] / pc[:, 2] + K[2], K[1] * pc[:, 1] / pc[:, 2] + K[3]]), pc


def simulate(seed: int, n: int, test: int) -> Scene:
    """A robot with kinematic errors and configurations where the true camera sees the whole board."""
    rng = np.random.default_rng(seed)
    robot = RobotModel.from_file(example_robot_data_dir() / "ur_description/urdf/ur5_robot.urdf")
    rp = RobotParameters(robot, robot.supporting_joints("tool0"))
    nominal = np.array([p.nominal for p in rp.params])
    truth = nominal.copy()
    for i, p in enumerate(rp.params):
        if p.kind == "placement":
            truth[i] += rng.uniform(-ERR_M, ERR_M) if p.unit == "m" else rng.uniform(-ERR_RAD, ERR_RAD)
        elif p.kind == "offset":
            truth[i] += rng.uniform(-ERR_OFFSET, ERR_OFFSET)
    scene = Scene(robot, rp, truth, nominal, np.zeros((0, 6)), np.zeros((0, 6)), np.zeros((0, len(GRID), 2)), n)
    P = np.array([BOARD.act(g) for g in GRID])
    th, uv = [], []
    while len(th) < n + test:
        t = Q_DOWN + rng.uniform(-0.35, 0.35, 6)
        px, pc = project(scene.flange(truth, t[None])[0] * X_TRUE, P)
        if pc[:, 2].min() > 0.15 and np.all((px > 0) & (px < [640, 480])):
            th.append(t)
            uv.append(px)
    scene.theta = np.array(th)
    scene.uv = np.array(uv) + rng.normal(scale=SIGMA_PX, size=(len(th), len(GRID), 2))
    scene.readings = scene.theta + rng.normal(scale=SIGMA_Q, size=scene.theta.shape)
    return scene


def average_se3(Ts: list[pin.SE3]) -> pin.SE3:
    U, _, Vt = np.linalg.svd(sum(T.rotation for T in Ts))
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    return pin.SE3(R, np.mean([T.translation for T in Ts], axis=0))


def opencv_fits(flange: list[pin.SE3], uv: np.ndarray) -> dict[str, tuple[pin.SE3, np.ndarray]]:
    """{method: (X camera in flange, board centre in the base)} from the nominal flange poses and solvePnP."""
    import cv2

    Rg, tg, Rt, tt = [], [], [], []
    board_in_cam = []
    for F, px in zip(flange, uv):
        _, rvec, tvec = cv2.solvePnP(GRID, px, KM, None, flags=cv2.SOLVEPNP_ITERATIVE)
        B = pin.SE3(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        board_in_cam.append(B)
        Rg.append(F.rotation), tg.append(F.translation), Rt.append(B.rotation), tt.append(B.translation)
    out = {}
    for name, flag in METHODS.items():
        R, t = cv2.calibrateHandEye(Rg, tg, Rt, tt, method=getattr(cv2, flag))
        X = pin.SE3(R, t.reshape(3))
        out[name] = (X, average_se3([F * X * B for F, B in zip(flange, board_in_cam)]).translation)
    # robot-world-hand-eye, OpenCV's convention: world (board) -> camera and base -> gripper in; base -> world
    # (T_board_base) and gripper -> camera (T_cam_gripper) out
    Rb2g = [F.inverse().rotation for F in flange]
    tb2g = [F.inverse().translation for F in flange]
    for name, flag in RWHE.items():
        Rbw, tbw, Rgc, tgc = cv2.calibrateRobotWorldHandEye(Rt, tt, Rb2g, tb2g, method=getattr(cv2, flag))
        out[name] = (pin.SE3(Rgc, tgc.reshape(3)).inverse(), pin.SE3(Rbw, tbw.reshape(3)).inverse().translation)
    return out


def closedloop_fit(scene: Scene, board: bool) -> tuple[pin.SE3, np.ndarray, np.ndarray, float]:
    """(X, board centre in the base, robot parameters, seconds) from the training data.

    One camera loop per board point, one shared camera pose; `board`: the
    board's point-to-point distances as measurements (else one robot length
    is held at its nominal value).
    """
    tr = slice(0, scene.n)
    extra, loops = {}, []
    for m in range(len(GRID)):
        extra[f"b{m:02d}:u1"], extra[f"b{m:02d}:v1"] = scene.uv[tr, m, 0], scene.uv[tr, m, 1]
        loops.append(share(CameraLoop(f"b{m:02d}", "universe", "tool0", K=[K], sigma_px=SIGMA_PX), "cam1", "cam"))
    if board:
        loops += [
            DistanceLoop(loops, f"b{a:02d}.tip", f"b{b:02d}.tip", float(np.linalg.norm(GRID[a] - GRID[b])))
            for a, b in itertools.combinations(range(len(GRID)), 2)
        ]
    log = JointLog(scene.rp.joints, scene.readings[tr], None, None, extra)
    t0 = time.perf_counter()
    res = calibrate(scene.robot, log, loops, CalibrationOptions(noise=SIGMA_Q))
    seconds = time.perf_counter() - t0
    if not res.converged:
        logging.getLogger(__name__).error("closedloop did not converge: %s", res.fit.solver_message)
    vals = res.as_dict()
    robot_vals = np.array([vals.get(p.name, p.nominal) for p in scene.rp.params])
    X = pin.SE3(
        pin.exp3(np.array([vals[f"cam.cam1.{a}"] for a in ("rx", "ry", "rz")])),
        np.array([vals[f"cam.cam1.{a}"] for a in "xyz"]),
    )
    centre = np.mean([[vals[f"b{m:02d}.tip_{a}"] for a in "xyz"] for m in range(len(GRID))], axis=0)
    return X, centre, robot_vals, seconds


def held_out(scene: Scene, robot_vals: np.ndarray, X: pin.SE3, centre: np.ndarray) -> tuple[float, float, float]:
    """Image px RMS, camera-frame mm RMS and its along-sight mm RMS of the predicted board centre (docstring)."""
    te = slice(scene.n, None)
    p_hat = np.vstack([project(F * X, centre[None])[1] for F in scene.flange(robot_vals, scene.readings[te])])
    p_true = np.vstack(
        [project(F * X_TRUE, BOARD.translation[None])[1] for F in scene.flange(scene.truth, scene.theta[te])]
    )
    uv_hat, uv_true = (K[:2] * p[:, :2] / p[:, 2:] + K[2:] for p in (p_hat, p_true))
    d = p_hat - p_true
    along = np.sum(d * p_true, axis=1) / np.linalg.norm(p_true, axis=1)

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.square(x))))

    return rms(np.linalg.norm(uv_hat - uv_true, axis=1)), 1e3 * rms(np.linalg.norm(d, axis=1)), 1e3 * rms(along)


def run_seed(seed: int, n: int, test: int) -> list[tuple[str, float, float, float, float]]:
    """Rows (method, image px, space mm, along sight mm, seconds): the OpenCV methods, then closedloop's two."""
    scene = simulate(seed, n, test)
    t0 = time.perf_counter()
    fits = opencv_fits(scene.flange(scene.nominal, scene.readings[:n]), scene.uv[:n])
    t_cv = (time.perf_counter() - t0) / len(fits)
    rows = [(f"OpenCV {name}", *held_out(scene, scene.nominal, X, c), t_cv) for name, (X, c) in fits.items()]
    for label, board in (("closedloop, scale held", False), ("closedloop + board geometry", True)):
        X, c, vals, seconds = closedloop_fit(scene, board)
        rows.append((label, *held_out(scene, vals, X, c), seconds))
    return rows


def parse_seeds(text: str) -> list[int]:
    """'1-10' or '1,4,7' -> seeds."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-10", help="draws: '1-10' or '1,4,7' (the table is the first's)")
    ap.add_argument("--n", type=int, default=60, help="training configurations")
    ap.add_argument("--test", type=int, default=30, help="held-out configurations")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="%(name)s: %(message)s")
    seeds = parse_seeds(args.seeds)
    t0 = time.perf_counter()
    print(f"machine: {machine()}; {load()}")
    print(
        f"UR5 eye-in-hand, {args.n} training / {args.test} held-out configurations; robot errors 2 mm, 2 mrad, "
        f"offsets 5 mrad; {SIGMA_PX} px, {SIGMA_Q:g} rad noise"
    )
    summary = []
    for k, seed in enumerate(seeds):
        rows = run_seed(seed, args.n, args.test)
        if k == 0:
            print(
                f"\nseed {seed}\n{'method':<30}{'image px RMS':>14}{'space mm RMS':>14}{'along sight':>13}{'time s':>9}"
            )
            for name, e_px, e_mm, e_los, t in rows:
                print(f"{name:<30}{e_px:14.3f}{e_mm:14.3f}{e_los:13.3f}{t:9.3f}")
            print(
                f"\n{'seed':>4}  {'best OpenCV (space)':<22}{'px':>7}{'mm':>7}   {'closedloop+board px':>19}"
                f"{'mm':>7}   {'ratio image':>11}{'space':>7}"
            )
        cv = rows[:-2]
        best = min(cv, key=lambda r: r[2])
        best_px = min(r[1] for r in cv)
        cl = rows[-1]
        summary.append((best_px / cl[1], best[2] / cl[2]))
        print(
            f"{seed:>4}  {best[0]:<22}{best[1]:7.3f}{best[2]:7.3f}   {cl[1]:19.3f}{cl[2]:7.3f}   "
            f"{summary[-1][0]:10.1f}x{summary[-1][1]:6.1f}x"
        )
    r = np.array(summary)
    print(
        f"best OpenCV / closedloop + board geometry over {len(seeds)} seeds: image median {np.median(r[:, 0]):.1f}x "
        f"(min {r[:, 0].min():.1f}x), space median {np.median(r[:, 1]):.1f}x (min {r[:, 1].min():.1f}x); "
        f"{time.perf_counter() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
