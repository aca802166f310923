"""Imports paid only by what uses them, and BLAS thread control (closedloop.estimate.threads).

`import closedloop` and a calibration of a URDF load no scipy at all (scipy.stats / special /
optimize / linalg), no trimesh or yourdfpy, no matplotlib or mujoco, no camera code; the lazy
paths give the same values as the eager ones did.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest

HEAVY = [
    "scipy.stats",
    "scipy.special",
    "scipy.optimize",
    "scipy.linalg",
    "trimesh",
    "yourdfpy",
    "matplotlib",
    "mujoco",
    "closedloop.loops.camera.loop",
]


def _modules_after(code: str) -> list[str]:
    """The HEAVY modules present in a fresh interpreter after running `code`."""
    probe = code + f"\nimport json, sys\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_closedloop_loads_no_heavy_module():
    assert _modules_after("import closedloop") == []


def test_calibrate_and_write_urdf_load_no_heavy_module(tmp_path):
    code = f"""
import numpy as np
from closedloop import calibrate, JointLog, RobotModel
from closedloop.output.urdf import write_urdf
from closedloop.loops.spec import parse_loop
from closedloop.assets.catalog import ROBOTS
from closedloop.output.report import build_report, write_report
from closedloop.studies.truth import make_dataset
robot = RobotModel.from_file(ROBOTS["panda"].path)
loop = parse_loop("weld:frame=panda_hand,name=fixture", robot)
ds = make_dataset(robot, loop, [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 40, np.random.default_rng(0), stride=1)
res = calibrate(robot, JointLog(ds.joints, ds.readings), [loop])
write_urdf(robot, res.as_dict(), r"{tmp_path / "cal.urdf"}")
write_report(build_report(res), r"{tmp_path / "report.json"}")
"""
    assert _modules_after(code) == []


def test_the_loops_package_loads_each_loop_type_on_first_use():
    """`import closedloop.loops` loads `base` alone; a class asked for loads its module, which registers its type
    beside it (the weld included)."""
    code = """
import sys
import closedloop.loops as loops
kinds = ["weld", "point", "plane", "hinge", "passive", "measured", "camera.loop"]
assert not [k for k in kinds if "closedloop.loops." + k in sys.modules], sorted(sys.modules)
from closedloop.loops import spec
assert spec.REGISTRY == {}
assert loops.WeldLoop.__module__ == "closedloop.loops.weld" and set(spec.REGISTRY) == {"weld"}
factory, keys = spec.loop_type("point")
assert "closedloop.loops.point" in sys.modules and keys == {"frame", "to", "tip", "point", "name"}
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_camera_loop_registers_on_first_use():
    code = """
from closedloop.loops import spec
assert "camera" not in spec.REGISTRY
try:
    spec.parse_loop("nope:frame=x", None)
except Exception as exc:
    assert "camera" in str(exc), exc
from closedloop.loops import CameraLoop  # PEP 562: loads the module
assert "camera" in spec.REGISTRY and CameraLoop.__name__ == "CameraLoop"
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_written_urdf_origins_are_nominal_times_exp6_and_offset(tmp_path):
    """The edited XML gives Pinocchio exactly O exp6(p) Rot(axis, offset) and limits shifted by -offset."""
    from closedloop.assets.catalog import ROBOTS
    from closedloop.model.robot import RobotModel
    from closedloop.output.urdf import write_urdf

    robot = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(3)
    values = {}
    arm = [f"panda_joint{i}" for i in range(1, 8)]  # revolute about their z axes
    for j in arm:
        values.update({f"{j}.{f}": rng.normal(0.0, 0.01) for f in ("x", "y", "z", "rx", "ry", "rz")})
        values[f"{j}.offset"] = rng.normal(0.0, 0.05)
    write_urdf(robot, values, tmp_path / "cal.urdf")
    nom = pin.buildModelFromUrdf(str(robot.source))
    cal = pin.buildModelFromUrdf(str(tmp_path / "cal.urdf"))
    assert cal.njoints == nom.njoints and cal.nframes == nom.nframes
    for name in arm:
        k = nom.getJointId(name)
        twist = np.array([values[f"{name}.{f}"] for f in ("x", "y", "z", "rx", "ry", "rz")])
        off = values[f"{name}.offset"]
        want = nom.jointPlacements[k] * pin.exp6(twist) * pin.SE3(pin.exp3(np.array([0, 0, off])), np.zeros(3))
        assert np.abs(cal.jointPlacements[k].homogeneous - want.homogeneous).max() < 1e-12, name
        i = nom.joints[k].idx_q
        assert cal.lowerPositionLimit[i] == pytest.approx(nom.lowerPositionLimit[i] - off, abs=1e-12)
        assert cal.upperPositionLimit[i] == pytest.approx(nom.upperPositionLimit[i] - off, abs=1e-12)
    text = (tmp_path / "cal.urdf").read_text()
    assert text.startswith("<?xml") and text.count("<link") == robot.source.read_text().count("<link")


def test_chi2_in_plain_python_equals_scipy_stats():
    """robust.stats.chi2 (no scipy import) against scipy.stats.chi2, both tails, small and large dof."""
    from scipy import stats as sst

    from closedloop.estimate.robust import stats as plain
    from closedloop.output.report import _chi2_sf

    for m in (1, 2, 3, 5, 6, 27, 1173, 594_000):
        for p in (0.5, 0.05, 1e-4, 1e-9, 0.999):
            assert plain.chi2.isf(p, m) == pytest.approx(sst.chi2.isf(p, m), rel=1e-11), (p, m)
            assert plain.chi2.ppf(p, m) == pytest.approx(sst.chi2.ppf(p, m), rel=1e-11), (p, m)
        for x in (0.01, 0.3, 1.0, 4.2, 30.0):
            x *= max(m / 4, 1)
            assert plain.chi2.sf(x, m) == pytest.approx(sst.chi2.sf(x, m), rel=1e-9, abs=1e-300), (x, m)
        assert _chi2_sf(1.02 * m, m) == pytest.approx(sst.chi2.sf(1.02 * m, m), rel=1e-9)
    assert plain.chi2.isf(1e-300, 6) == pytest.approx(sst.chi2.isf(1e-300, 6), rel=1e-11)  # far tail
    assert plain.chi2.isf(0.0, 3) == np.inf and plain.chi2.ppf(0.0, 3) == 0.0
    assert plain.chi2.sf(np.inf, 6) == 0.0 and plain.chi2.sf(0.0, 6) == 1.0 and plain.chi2.sf(1e6, 6) == 0.0


def test_blas_threads_one_by_default_restored_and_an_explicit_count_caps_the_chunk_threads(monkeypatch):
    from threadpoolctl import threadpool_limits

    import closedloop.parallel.chunks as chunks
    from closedloop.estimate.threads import blas_threads, current_threads

    monkeypatch.setattr(chunks, "cpus", lambda: 8)
    before = current_threads()
    with blas_threads(None) as k:
        assert k == 1 and current_threads() == 1  # one BLAS thread
        assert chunks.chunk_threads(10) == chunks.CHUNK_THREADS  # the rows' threads as they are
    assert current_threads() == before  # restored
    with blas_threads(1) as k:
        assert k == 1 and current_threads() == 1  # explicit setting
        assert chunks.chunk_threads(10) == 1  # caps the rows' threads too
    assert current_threads() == before and chunks.chunk_threads(10) == chunks.CHUNK_THREADS
    with pytest.raises(RuntimeError):
        with blas_threads(1):
            raise RuntimeError("inside")
    assert current_threads() == before and chunks.chunk_threads(10) == chunks.CHUNK_THREADS  # restored on an exception
    with threadpool_limits(1, user_api="blas"):  # the user's own limit
        with blas_threads(None) as k:
            assert k == 1
        assert current_threads() == 1
    assert chunks.chunk_threads(1) == 1  # never more threads than chunks
