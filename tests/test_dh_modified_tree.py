"""D-H tables as robot makers write them: Craig's modified convention row by row, and trees (a torso with
two arms), against forward kinematics written by hand; their parameter Jacobians against finite
differences; written back and read again unchanged; calibrated from measured points on both branches."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.calibration.pipeline import build_problem, calibrate
from closedloop.errors import ModelError
from closedloop.io.logs import JointLog
from closedloop.loops.measured import MeasuredPointLoop
from closedloop.model.dh import load_dh
from closedloop.model.robot import RobotModel
from closedloop.output.urdf import write_dh

TREE = """name: upper_body
units: {length: m, angle: rad}
joints:
  - {name: torso, s: 0.30, a: 0.02, alpha: 1.5708}
  - {name: l1, parent: torso, s: 0.10, a: 0.20, alpha: 0.3, convention: modified}
  - {name: l2, s: 0.05, a: 0.25, alpha: -1.5708, convention: modified}
  - {name: l3, s: 0.02, a: 0.20, alpha: 0.4}
  - {name: r1, parent: torso, s: -0.10, a: -0.20, alpha: -0.3, convention: modified}
  - {name: r2, s: 0.05, a: 0.25, alpha: 1.5708}
  - {name: r3, s: 0.03, a: 0.18, alpha: 0.0, convention: hayati}
"""


def rx(t):
    return pin.SE3(pin.exp3(np.array([t, 0.0, 0.0])), np.zeros(3))


def rz(t):
    return pin.SE3(pin.exp3(np.array([0.0, 0.0, t])), np.zeros(3))


def ry(t):
    return pin.SE3(pin.exp3(np.array([0.0, t, 0.0])), np.zeros(3))


def tr(x, y, z):
    return pin.SE3(np.eye(3), np.array([x, y, z], dtype=float))


def A(row: dict, th: float) -> pin.SE3:
    """The row's link transform as the conventions define it (module doc of closedloop.model.dh)."""
    s, a, al = row.get("s", 0.0), row.get("a", 0.0), row.get("alpha", 0.0)
    conv = row.get("convention", "dh")
    if conv == "modified":  # Craig: Rot(x, alpha_{i-1}) Trans(x, a_{i-1}) Rot(z, theta_i) Trans(z, d_i)
        return rx(al) * tr(a, 0, 0) * rz(th) * tr(0, 0, s)
    if conv == "hayati":
        return rz(th) * tr(s, 0, 0) * rx(a) * ry(al)
    return rz(th) * tr(0, 0, s) * tr(a, 0, 0) * rx(al)


ROWS = {
    "torso": {"s": 0.30, "a": 0.02, "alpha": 1.5708},
    "l1": {"s": 0.10, "a": 0.20, "alpha": 0.3, "convention": "modified"},
    "l2": {"s": 0.05, "a": 0.25, "alpha": -1.5708, "convention": "modified"},
    "l3": {"s": 0.02, "a": 0.20, "alpha": 0.4},
    "r1": {"s": -0.10, "a": -0.20, "alpha": -0.3, "convention": "modified"},
    "r2": {"s": 0.05, "a": 0.25, "alpha": 1.5708},
    "r3": {"s": 0.03, "a": 0.18, "alpha": 0.0, "convention": "hayati"},
}


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    path = tmp_path_factory.mktemp("dh") / "upper_body.yaml"
    path.write_text(TREE)
    return RobotModel.from_file(path)


def test_tree_and_modified_rows_match_the_conventions_by_hand(tree):
    table = tree.dh
    assert table.is_tree and table.end_frames() == {"l3": "l3_end", "r3": "r3_end"}
    rng = np.random.default_rng(0)
    data = tree.model.createData()
    for _ in range(5):
        th = rng.uniform(-2, 2, 7)
        q = tree.configurations(th[None], tree.joint_names)[0]
        pin.framesForwardKinematics(tree.model, data, q)
        t = dict(zip(tree.joint_names, th))
        for branch in ("l", "r"):
            T = A(ROWS["torso"], t["torso"])
            for k in (1, 2, 3):
                T = T * A(ROWS[f"{branch}{k}"], t[f"{branch}{k}"])
            got = data.oMf[tree.frame_id(f"{branch}3_end")]
            assert np.abs(got.homogeneous - T.homogeneous).max() < 1e-12


def test_tree_jacobian_matches_finite_differences(tree):
    """Every D-H parameter column (modified heads, tails before a modified row, tree branches) is exact."""
    rng = np.random.default_rng(1)
    th = rng.uniform(-1.5, 1.5, (6, 7))
    loops = [MeasuredPointLoop("left", "l3_end"), MeasuredPointLoop("right", "r3_end")]
    extra = {f"{n}:{c}": np.zeros(12) for n in ("left", "right") for c in "xyz"}
    log = JointLog(tree.joint_names, np.vstack([th, th]), None, np.repeat(["left", "right"], 6), extra)
    prob = build_problem(tree, log, loops)
    x = prob.nominal + rng.normal(scale=1e-2, size=len(prob.nominal))
    J = np.concatenate([ev.J.reshape(-1, len(x)) for ev in prob.evaluate(x, True)])
    h = 1e-6
    for k, p in enumerate(prob.params[: prob.n_robot]):
        if p.kind != "dh":
            continue
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        rp = np.concatenate([ev.r.ravel() for ev in prob.evaluate(xp, False)])
        rm = np.concatenate([ev.r.ravel() for ev in prob.evaluate(xm, False)])
        assert np.abs((rp - rm) / (2 * h) - J[:, k]).max() < 1e-7, p.name


def test_written_tree_reads_back_the_same(tree, tmp_path):
    values = {"l1.alpha": 0.31, "l1.a": 0.21, "r2.s": 0.051, "torso.theta_off": 0.01}
    out = tmp_path / "cal.yaml"
    write_dh(tree, values, out)
    back = load_dh(out)
    assert [(r.name, r.parent, r.convention) for r in back.rows] == [
        (r.name, r.parent, r.convention) for r in tree.dh.rows
    ]
    by = {r.name: r for r in back.rows}
    assert by["l1"].alpha == pytest.approx(0.31, abs=1e-12) and by["r2"].s == pytest.approx(0.051, abs=1e-12)
    assert by["torso"].theta_off == pytest.approx(0.01, abs=1e-12)


def test_tree_calibrated_from_both_hands(tree):
    """A tracker sees both hands: the torso and both arms' geometry recovered to 1e-8 from exact data."""
    rng = np.random.default_rng(2)
    N = 60
    th = rng.uniform(-1.5, 1.5, (N, 7))
    loops = [MeasuredPointLoop("left", "l3_end"), MeasuredPointLoop("right", "r3_end")]
    zeros = {f"{n}:{c}": np.zeros(2 * N) for n in ("left", "right") for c in "xyz"}
    labels = np.repeat(["left", "right"], N)
    prob = build_problem(tree, JointLog(tree.joint_names, np.vstack([th, th]), None, labels, zeros), loops)
    res0 = calibrate(
        tree, JointLog(tree.joint_names, np.vstack([th, th]), None, labels, _points(prob, prob.nominal, th)), loops
    )
    est = [
        n
        for n, st in zip(res0.fit.names, res0.fit.status)
        if st == "estimated" and "." in n and not n.startswith(("left", "right"))
    ]
    assert {"l1.alpha", "l1.a", "r1.alpha", "r1.a", "l2.alpha"} <= set(est)
    truth = prob.nominal.copy()
    for n in est:
        truth[prob.index[n]] += rng.normal(scale=2e-3)
    log = JointLog(tree.joint_names, np.vstack([th, th]), None, labels, _points(prob, truth, th))
    res = calibrate(tree, log, [MeasuredPointLoop("left", "l3_end"), MeasuredPointLoop("right", "r3_end")])
    err = max(abs(res.value(n) - truth[prob.index[n]]) for n in est)
    assert res.converged and err < 1e-8


def _points(prob, values, th):
    """The hands' positions in the base (the tracker at the base, the tip at the end frames): each loop's
    columns hold its own rows (left first, then right), zeros on the other loop's."""
    N = len(th)
    out = {}
    for bi, name in enumerate(("left", "right")):
        TA, _ = prob.loop_poses(values, bi, th)
        for k, c in enumerate("xyz"):
            col = np.zeros(2 * N)
            col[bi * N : (bi + 1) * N] = TA[:, k, 3]
            out[f"{name}:{c}"] = col
    return out


def test_parent_must_be_a_row_above(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("joints:\n  - {name: a, s: 0.1}\n  - {name: b, parent: c, s: 0.1}\n  - {name: c, s: 0.1}\n")
    with pytest.raises(ModelError, match=r"row 2 \('b'\): parent 'c' is not a row above"):
        load_dh(path)
