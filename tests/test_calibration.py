"""Ground-truth recovery with the weld loop (acceptance numbers)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from support import closed_chain, dh_transform, geodesic

from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.errors import NotIdentifiableError
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.loops.spec import default_loops
from closedloop.model.robot import RobotModel
from closedloop.problem.problem import CalibrationProblem, LoopBlock
from closedloop.studies.synthetic import self_motion


def compare(res, ds):
    """Max error over estimated robot parameters, closure translation and rotation (geodesic)."""
    truth = ds.truth_dict()
    robot_err = max(
        abs(res.value(n) - truth[n])
        for n, s in zip(res.fit.names, res.fit.status)
        if s == "estimated" and not n.startswith("fixture.")
    )
    t_err = max(abs(res.value(f"fixture.{a}") - truth[f"fixture.{a}"]) for a in "xyz")
    r_err = geodesic([res.value(f"fixture.r{a}") for a in "xyz"], [truth[f"fixture.r{a}"] for a in "xyz"])
    return robot_err, t_err, r_err


@pytest.mark.slow
def test_panda_weld_noise_free(panda, panda_weld):
    """From the nominal model every identifiable parameter to 1e-6 (we get ~1e-13), closure RMS < 1e-9 m."""
    res = calibrate(panda, panda_weld.log(), [WeldLoop("fixture", "panda_hand")])
    assert res.converged
    assert max(compare(res, panda_weld)) < 1e-8
    after = res.fit.residuals_after[0]
    assert after.rms_m < 1e-9 and after.rms_rad < 1e-9
    before = res.fit.residuals_before[0]
    assert before.rms_m > 1e-3  # the nominal model was really wrong
    assert not res.identifiability.weak
    records = res.parameters  # a list of named records, in the parameters' order
    assert len(records) == len(res.fit.names) and [p.name for p in records] == res.fit.names
    assert [p.value for p in records] == [float(v) for v in res.fit.values]


def test_panda_weld_noisy(panda, panda_weld):
    """1e-4 rad joint noise: estimated noise matches, every identifiable parameter within 3 standard errors."""
    rng = np.random.default_rng(11)
    noisy = panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape)
    res = calibrate(panda, JointLog(panda_weld.joints, noisy), [WeldLoop("fixture", "panda_hand")])
    assert res.converged
    assert res.noise.sigma_estimated and abs(res.noise.sigma / 1e-4 - 1.0) < 0.15
    truth = panda_weld.truth_dict()
    z = [
        abs(res.value(n) - truth[n]) / res.fit.std[k]
        for k, (n, s) in enumerate(zip(res.fit.names, res.fit.status))
        if s == "estimated" and not n.startswith("fixture.r")
    ]
    assert len(z) == len(res.fit.estimated) - 3
    assert max(z) < 3.0, max(z)
    # The same with the noise given: chi-square consistent with the model.
    res2 = calibrate(
        panda, JointLog(panda_weld.joints, noisy), [WeldLoop("fixture", "panda_hand")], CalibrationOptions(noise=1e-4)
    )
    assert abs(res2.noise.chi2 / res2.noise.dof - 1.0) < 0.1


def test_reduction_names_what_absorbed_what(panda, panda_weld):
    """Over-parameterised requests are reduced and the report says what absorbed each dropped parameter."""
    res = calibrate(
        panda,
        panda_weld.log(),
        [WeldLoop("fixture", "panda_hand")],
        CalibrationOptions(identify=["placement", "offset", "scale", "loop"]),
    )
    dropped = {d.name: d for d in res.identifiability.dropped}
    # rz of a z-axis joint is its offset (thesis: 4 of 6 placement components per joint)
    assert "panda_joint3.rz" in dropped
    assert dropped["panda_joint3.rz"].absorbed_into[0][0] == "panda_joint3.offset"
    # the base placement is the gauge of the unknown closure
    for f in ("x", "y", "z", "rx", "ry", "rz"):
        assert f"panda_joint1.{f}" in dropped
        assert all(n.startswith("fixture.") for n, _ in dropped[f"panda_joint1.{f}"].absorbed_into)
    # k = 0 trivial solution: one scale fixed and said so
    assert any("scale factor" in n and "4.2.2" in n for n in res.notes)
    # the length gauge (thesis 3.3)
    assert any("length scale" in n for n in res.notes)
    assert res.converged and max(compare(res, panda_weld)) < 1e-8


def test_user_fixed_length_replaces_default(panda, panda_weld):
    res = calibrate(
        panda, panda_weld.log(), [WeldLoop("fixture", "panda_hand")], CalibrationOptions(fix={"panda_joint4.x": None})
    )
    assert not any("length scale" in n for n in res.notes)
    assert res.fit.status[res.fit.names.index("panda_joint4.x")] == "fixed"


@pytest.mark.slow
def test_joint_that_never_moves_is_reported(panda, panda_weld):
    th = panda_weld.readings.copy()
    th[:, 3] = th[0, 3]
    res = calibrate(
        panda,
        JointLog(panda_weld.joints, th),
        [WeldLoop("fixture", "panda_hand")],
        CalibrationOptions(identify=["placement", "offset", "scale", "loop"]),
    )
    assert any("panda_joint4 never moves" in n for n in res.notes)
    assert res.fit.status[res.fit.names.index("panda_joint4.scale")] in ("dropped", "fixed")
    with pytest.raises(NotIdentifiableError):
        calibrate(panda, JointLog(panda_weld.joints, np.tile(th[:1], (20, 1))), [WeldLoop("fixture", "panda_hand")])


def test_dh_closed_chain_from_rough_guess(tmp_path):
    """7R D-H chain closing on itself, recovered from 0.1 m / 0.3 rad errors with one length fixed, to 1e-8."""
    rng = np.random.default_rng(3)
    rows, theta = closed_chain(rng)
    T = np.eye(4)
    for (s, a, al), t in zip(rows, theta):
        T = T @ dh_transform(t, s, a, al)
    assert np.abs(T - np.eye(4)).max() < 1e-12  # the independent model closes
    offs = rng.uniform(-0.2, 0.2, 7)
    joints = [
        {"name": f"j{i + 1}", "s": s, "a": a, "alpha": al, "theta_off": float(o), "lower": -10, "upper": 10}
        for i, ((s, a, al), o) in enumerate(zip(rows, offs))
    ]
    true_path = tmp_path / "true.yaml"
    true_path.write_text(yaml.safe_dump({"name": "c7", "closes": True, "joints": joints}))
    truth_robot = RobotModel.from_file(true_path)
    prob = CalibrationProblem(
        truth_robot, truth_robot.joint_names, [LoopBlock(default_loops(truth_robot)[0], theta[None], np.arange(1))]
    )
    readings = self_motion(prob, prob.nominal, (theta - offs)[None], 100, rng, step=0.05)
    guess = [
        {
            **j,
            "s": j["s"] + float(rng.uniform(-0.1, 0.1)),
            "a": j["a"] + float(rng.uniform(-0.1, 0.1)),
            "alpha": j["alpha"] + float(rng.uniform(-0.3, 0.3)),
            "theta_off": j["theta_off"] + float(rng.uniform(-0.3, 0.3)),
        }
        for j in joints
    ]
    guess[0]["s"] = joints[0]["s"]  # the one known length
    guess_path = tmp_path / "guess.yaml"
    guess_path.write_text(yaml.safe_dump({"name": "c7", "closes": True, "joints": guess}))
    robot = RobotModel.from_file(guess_path)
    res = calibrate(
        robot, JointLog(robot.joint_names, readings), default_loops(robot), CalibrationOptions(fix={"j1.s": None})
    )
    assert res.converged and not res.identifiability.weak
    assert len(res.fit.estimated) == 27  # 4 per joint, one length fixed
    err = max(abs(res.fit.values[k] - prob.nominal[k]) for k in res.fit.estimated)
    assert err < 1e-8, err
    assert res.fit.residuals_after[0].rms_m < 1e-10


def test_absorbed_combinations_are_in_physical_units(panda, panda_weld):
    """What a dropped parameter's effect equals is given in the parameters' own units (m, rad, m per rad):
    a change d of the dropped parameter moves every loop's residual as the named changes c_j d of the kept
    ones do, checked by finite differences at the solution; a rotation of the base joint is a rotation of
    the fixture by the same angle (the fixture's rotation vector r moves by dr, a rotation Jexp3(r) dr)."""
    import pinocchio as pin

    res = calibrate(panda, panda_weld.log(), [WeldLoop("fixture", "panda_hand")])
    dropped = {d.name: d for d in res.identifiability.dropped}
    base = dict(dropped["panda_joint1.offset"].absorbed_into)
    dr = np.array([base.get(f"fixture.r{a}", 0.0) for a in "xyz"])
    r = np.array([res.value(f"fixture.r{a}") for a in "xyz"])
    assert np.linalg.norm(pin.Jexp3(r) @ dr) == pytest.approx(1.0, rel=0.02), base
    problem, x = res.problem, np.asarray(res.fit.values, dtype=float)
    r0 = np.concatenate([e.r.ravel() for e in problem.evaluate(x, False)])
    checked = 0
    for d in res.identifiability.dropped:
        if not d.absorbed_into or len(d.absorbed_into) >= 6 or d.name not in problem.index:
            continue  # none, or the description keeps only the six largest terms
        h = 1e-6
        moved = x.copy()
        moved[problem.index[d.name]] += h
        by_dropped = np.concatenate([e.r.ravel() for e in problem.evaluate(moved, False)]) - r0
        if np.linalg.norm(by_dropped) < 1e-12:
            continue  # no effect at all on these data
        moved = x.copy()
        for n, c in d.absorbed_into:
            moved[problem.index[n]] += c * h
        by_kept = np.concatenate([e.r.ravel() for e in problem.evaluate(moved, False)]) - r0
        # 10 %: the reduction is read where it was decided (projected readings, a subsample), the differences
        # here at the solution's own readings; scaled units are off by the ratio of priors (0.05 or 20)
        assert np.linalg.norm(by_kept - by_dropped) < 0.1 * np.linalg.norm(by_dropped), d.describe()
        checked += 1
    assert checked >= 3
