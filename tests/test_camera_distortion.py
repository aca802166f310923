"""Lens distortion (k1 k2 p1 p2 k3): Jacobians against finite differences, recovery, camera_info files."""

from __future__ import annotations

import numpy as np
import pytest
from camera_head_support import FRAMES, MARKER, head_robot

from closedloop.errors import InputError, LoopError
from closedloop.io.camera_info import CameraInfo, read_camera_info, write_camera_info
from closedloop.loops.camera.loop import CameraLoop
from closedloop.loops.camera.model import distort, image_ray, project_lens, undistort
from closedloop.loops.spec import parse_loop

D_TRUE = [np.array([-0.21, 0.08, 0.0012, -0.0008, -0.015]), np.array([0.12, -0.05, -0.0006, 0.0010, 0.01])]


def _fd(f, x, h=1e-7):
    cols = []
    for k in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        cols.append((f(xp) - f(xm)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_projection_and_undistortion_jacobians():
    """d uv / d (point, intrinsics, distortion) and the inverse model's Jacobians to 1e-7 relative."""
    rng = np.random.default_rng(3)
    pc = np.column_stack([rng.uniform(-0.4, 0.4, (5, 2)), rng.uniform(0.8, 1.5, 5)])
    k = np.array([600.0, 590.0, 321.0, 242.0])
    d = D_TRUE[0]
    uv, Jp, Jk, Jd = project_lens(pc, k, d)
    for i in range(5):
        for J, f, x in (
            (Jp[i], lambda v: project_lens(v[None], k, d, False)[0][0], pc[i]),
            (Jk[i], lambda v: project_lens(pc[i : i + 1], v, d, False)[0][0], k),
            (Jd[i], lambda v: project_lens(pc[i : i + 1], k, v, False)[0][0], d),
        ):
            Jn = _fd(f, x.copy())
            assert np.abs(J - Jn).max() <= 1e-6 * max(np.abs(J).max(), 1.0)
    xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    xd, yd, _, _ = distort(xn, yn, d)
    xu, yu, A, B = undistort(xd, yd, d)
    assert np.abs(xu - xn).max() < 1e-14 and np.abs(yu - yn).max() < 1e-14
    ray, Ru, Rk, Rd = image_ray(uv, k, d)
    assert np.allclose(ray[:, :2], np.column_stack([xn, yn]), atol=1e-13)
    for i in range(5):
        for J, f, x in (
            (Ru[i], lambda v: image_ray(v[None], k, d)[0][0], uv[i]),
            (Rk[i], lambda v: image_ray(uv[i : i + 1], v, d)[0][0], k),
            (Rd[i], lambda v: image_ray(uv[i : i + 1], k, v)[0][0], d),
        ):
            Jn = _fd(f, x.copy(), h=1e-6)
            assert np.abs(J - Jn).max() <= 1e-6 * max(np.abs(J).max(), 1.0)


def test_distortion_recovered_noise_free():
    """A world camera with a distorted lens (k1 k2 p1 p2 k3, intrinsics, pose unknown) watching the UR5's
    marker: every estimated parameter, the five coefficients included, recovered to 1e-8 from exact pixels."""
    from test_loops_camera import K1, TIP, UR5, X1, estimated_errors, robot_of, ur5_readings, vec_of

    from closedloop.calibration.pipeline import CalibrationOptions, build_problem, calibrate
    from closedloop.io.logs import JointLog
    from closedloop.studies.truth import draw_truth

    robot = robot_of(UR5)
    joints = robot.supporting_joints("tool0")
    th = ur5_readings(60, seed=7)
    make = lambda: CameraLoop("cam", "tool0", dist=("k1", "k2", "p1", "p2", "k3"), sigma_px=0.3)  # noqa: E731
    opt = CalibrationOptions(weighting="none", robust=None)
    truth_loop = CameraLoop("cam", "tool0", K=[K1], poses=[X1], tip=TIP, D=[D_TRUE[0]])
    zero_px = np.zeros((len(th), len(truth_loop.columns())))

    def pixels(prob, values):
        uv = truth_loop.residual_frames(prob.loop_frame_poses(values, 0, th), np.zeros(0), zero_px)
        return {c: uv[:, k].copy() for k, c in enumerate(truth_loop.columns())}

    prob = build_problem(
        robot, JointLog(joints, th, None, None, {c: np.zeros(len(th)) for c in make().columns()}), [make()]
    )
    res0 = calibrate(robot, JointLog(joints, th, None, None, pixels(prob, prob.nominal)), [make()], opt)
    names = [n for n, s in zip(res0.fit.names, res0.fit.status) if s == "estimated" and not n.startswith("cam.")]
    truth = prob.nominal.copy()
    for k, v in draw_truth(robot, names, np.random.default_rng(7)).items():
        truth[prob.index[k]] = v
    res = calibrate(robot, JointLog(joints, th, None, None, pixels(prob, truth)), [make()], opt)
    true_by_name = dict(zip(prob.names, truth))
    true_by_name |= {f"cam.cam1.{f}": float(v) for f, v in zip(("x", "y", "z", "rx", "ry", "rz"), vec_of(X1))}
    true_by_name |= {f"cam.cam1.{f}": float(v) for f, v in zip(("fx", "fy", "cx", "cy"), K1)}
    true_by_name |= {f"cam.cam1.{f}": float(v) for f, v in zip(("k1", "k2", "p1", "p2", "k3"), D_TRUE[0])}
    true_by_name |= {f"cam.tip_{a}": float(v) for a, v in zip("xyz", TIP)}
    est, err = estimated_errors(res, true_by_name)
    names = [res.fit.names[i] for i in est]
    assert {f"cam.cam1.{f}" for f in ("k1", "k2", "p1", "p2", "k3")} <= set(names)
    assert np.abs(err).max() < 1e-8, names[int(np.argmax(np.abs(err)))]
    assert res.fit.residuals_after[0].max_px < 1e-8


def test_camera_info_round_trip_and_spec(tmp_path):
    """ROS camera_info and OpenCV FileStorage YAML read; written files read back; info<c>= in a spec."""
    info = CameraInfo(np.array([610.5, 608.25, 319.5, 239.75]), D_TRUE[0], 640, 480, "left")
    write_camera_info(tmp_path / "left.yaml", info)
    back = read_camera_info(tmp_path / "left.yaml")
    assert np.array_equal(back.K, info.K) and np.array_equal(back.D, info.D)
    assert (back.width, back.height, back.name) == (640, 480, "left")
    (tmp_path / "cv.yaml").write_text(
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n"
        "   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 505., 240., 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n   data: [ -0.1, 0.01, 0., 0. ]\n"
    )
    cv = read_camera_info(tmp_path / "cv.yaml")
    assert np.array_equal(cv.K, [500, 505, 320, 240]) and np.array_equal(cv.D, [-0.1, 0.01, 0, 0, 0])
    (tmp_path / "ros2.yaml").write_text(
        "width: 640\nheight: 480\nk: [400, 0, 300, 0, 401, 200, 0, 0, 1]\n"
        "d: [0.1, 0, 0, 0, 0]\ndistortion_model: plumb_bob\n"
    )
    assert np.array_equal(read_camera_info(tmp_path / "ros2.yaml").K, [400, 401, 300, 200])
    robot = head_robot()
    lp = parse_loop(f"camera:frame=tool0,to={'+'.join(FRAMES)},info1={tmp_path / 'left.yaml'},dist=k1+k2", robot)
    assert np.array_equal(lp.K[0], info.K) and lp.K[1] is None and np.array_equal(lp.D[0], info.D)
    assert [p.name for p in lp.parameters() if p.field.endswith(("k1", "k2"))] == [
        "camera.cam1.k1",
        "camera.cam1.k2",
        "camera.cam2.k1",
        "camera.cam2.k2",
    ]
    (tmp_path / "bad.yaml").write_text("camera_matrix: {rows: 3, cols: 3, data: [1, 2, 3]}\n")
    with pytest.raises(InputError, match="bad.yaml.*9"):
        read_camera_info(tmp_path / "bad.yaml")
    with pytest.raises(LoopError, match="info1") as exc:
        parse_loop(f"camera:frame=tool0,info1={tmp_path / 'missing.yaml'}", robot)
    assert "\n" not in str(exc.value)
    with pytest.raises(LoopError, match="k4"):
        parse_loop("camera:frame=tool0,dist=k1+k4", robot)
    assert MARKER.shape == (3,)
