"""The robot zoo, quick subset: every calibration is either right or not reported as ok.

Data come from `zoo.py`, a generator independent of closedloop's parametrization (errors on
every joint origin in the parent frame, fixed joints included; loops closed with Pinocchio on
the true model), and are judged by what the calibrated URDF does: forward kinematics of the
tool from raw readings against the truth after the best base/tool transforms (and length
scale only for loops that cannot see it).  Right means: noise-free, tool positions within
0.1 mm and orientations within 1 mrad over the whole joint range, relative motions within
0.2 mm, fitted scale within 3.8 % (a calibrator that fixes a real link length of 10 cm or
more at its nominal value is off by at most sqrt(3) (2 mm / 10 cm + 2 mrad)); with noise, 5x
more than the largest tool error std the noise alone leaves (Cramer-Rao bound of the zoo's own
parametrization, `zoo_judge.predicted_std`).  The full zoo is `benchmarks/zoo.py`.

Each case states what it does: right with verdict 'ok', or the one refusal it is allowed (a verdict
other than 'ok' giving a named reason), counted from what the calibrator does today and no more.  A
refusal is never a pass by default: a case that is right today fails the day it is flagged, and an
exception (a refusal by error, or a crash) fails every case.
"""

from __future__ import annotations

import functools

import numpy as np
import pinocchio as pin
import pytest
import zoo

from closedloop import RobotModel, read_log

WELD_7DOF = ["panda", "xarm7", "baxter_left", "tiago", "g1_left"]
POINT_6DOF = ["ur5", "kinova", "z1"]


def _check(outcome: zoo.Outcome, refusal: str | None = None) -> None:
    """Right with verdict 'ok'; or, where `refusal` is given (the refusal the case is allowed), a verdict
    other than 'ok' one of whose reasons contains `refusal`.  An error raised by `calibrate` or a crash
    (no judgement at all) fails either way."""
    if outcome.judgement is None:  # calibrate raised: a refusal by error is not an answer
        pytest.fail(f"raised instead of answering: {outcome.line()}", pytrace=False)
    if refusal is None:
        if not (outcome.right and outcome.status == "ok"):
            pytest.fail(f"not right with verdict ok: {outcome.line()}", pytrace=False)
        return
    reasons = outcome.result.verdict.reasons
    if not (outcome.refused and any(refusal in r for r in reasons)):
        pytest.fail(f"expected a verdict other than ok saying {refusal!r}: {outcome.line()} {reasons}", pytrace=False)


# ----------------------------------------------------------------------------- the harness itself
def test_generator_closes_loops_on_the_true_model_and_judge_sees_errors():
    """Configurations satisfy the loop on the true model; the judge gives ~0 for the truth, mm for the nominal."""
    case = zoo.make_case("panda", "weld", n=20, seed=3)
    kin = zoo.Kin(case.true_model, case.joints)
    T = kin.poses(case.q_true)
    ref = pin.SE3(T[0])
    err = [np.linalg.norm(pin.log6(ref.actInv(pin.SE3(t))).vector) for t in T]
    assert max(err) < 1e-11
    spread = np.ptp(case.q_true, axis=0)  # spread over the self-motion (the Panda's elbow hardly moves)
    assert spread.max() > 0.3 and spread.min() > 0.01
    np.testing.assert_allclose(case.readings, case.q_true - [case.true_offsets[j] for j in case.joints])
    log = read_log(case.log_csv, RobotModel.from_file(case.nominal_urdf).joint_names)
    np.testing.assert_array_equal(log.columns(case.joints), case.readings)
    tol = case.tolerances()
    truth = zoo.judge(case, zoo.folded_truth_urdf(case))
    assert truth.pos_max < 1e-10 and truth.rot_max < 1e-10 and abs(truth.scale - 1) < 1e-10
    nominal = zoo.judge(case, case.nominal_urdf)
    assert nominal.pos_max > 20 * tol["pos"] and not nominal.right(tol)


def test_judge_fits_scale_only_where_the_loop_cannot_see_it(tmp_path):
    """A truth scaled by 1.3 is right up to scale for a weld (scale 1.3 reported, so 'wrong'), not for a tracker."""
    case = zoo.make_case("ur5", "point", n=10, seed=1)
    folded = zoo.folded_truth_urdf(case)
    import xml.etree.ElementTree as ET

    root = ET.parse(folded).getroot()
    for o in root.iter("origin"):
        o.set("xyz", " ".join(repr(1.3 * float(v)) for v in o.get("xyz").split()))
    big = tmp_path / "big.urdf"
    big.write_text(ET.tostring(root, encoding="unicode"))
    j = zoo.judge(case, big)
    assert j.pos_max < 1e-9 and abs(j.scale - 1.3) < 1e-9 and not j.right(case.tolerances())
    assert case.tolerances()["scale"] < 0.04
    case.loop = "measured_point"
    j = zoo.judge(case, big)
    assert j.scale == 1.0 and j.pos_max > 0.05


def test_predicted_std_scales_with_noise_and_is_worse_for_one_weld_pose():
    """Cramer-Rao tolerance: linear in the joint noise; one weld pose determines the tool far less than a tracker."""
    a = zoo.make_case("panda", "weld", n=30, sigma=1e-5, seed=4)
    b = zoo.make_case("panda", "weld", n=30, sigma=2e-5, seed=4)
    t = zoo.make_case("panda", "measured_point", n=30, sigma=1e-5, sigma_t=1e-9, seed=4)
    sa, sb, st = zoo.predicted_std(a), zoo.predicted_std(b), zoo.predicted_std(t)
    assert abs(sb["pos"] / sa["pos"] - 2.0) < 1e-3 and abs(sb["rot"] / sa["rot"] - 2.0) < 1e-3
    assert 1e-6 < st["pos"] < 1e-4 < sa["pos"]
    assert a.tolerances()["pos"] > 1e-4 + 4.9 * sa["pos"]


@pytest.mark.parametrize("loop", ["point", "plane", "hinge", "measured_point"])
def test_generator_loop_types(loop):
    case = zoo.make_case("ur5", loop, n=12, seed=2, sigma_t=1e-5 if loop == "measured_point" else 0.0)
    kin = zoo.Kin(case.true_model, case.joints)
    p = kin.poses(case.q_true)[:, :3, 3]
    if loop == "point":
        assert np.abs(p - p[0]).max() < 1e-11
    elif loop == "plane":  # coplanar: the centred points have rank 2
        assert np.linalg.svd(p - p.mean(0), compute_uv=False)[2] < 1e-11
    elif loop == "hinge":  # the tool frame turns about one fixed line: relative rotations share one axis
        T = kin.poses(case.q_true)
        axes = [pin.log3(T[0, :3, :3].T @ t[:3, :3]) for t in T[1:]]
        axes = np.array([a / np.linalg.norm(a) * np.sign(a @ axes[0]) for a in axes])
        assert np.abs(axes - axes[0] @ T[0, :3, :3].T @ T[0, :3, :3]).max() < 1e-9
    else:
        log = read_log(case.log_csv, case.joints)
        assert set(log.extra) == {"meas:x", "meas:y", "meas:z"}


# ----------------------------------------------------------------------------- the quick zoo
@functools.lru_cache(maxsize=None)
def _exact(robot: str, loop: str) -> zoo.Outcome:
    return zoo.run_case(zoo.make_case(robot, loop, n=60, seed=0))


# the refusals the exact cases are allowed (one of eight): the G1's weld holds its size by a 50 mm length, so a
# 2 mm error of that length moves the size by 4 % (the judge sees 9 %, not right); the verdict says so.
# Every other exact case is right with verdict ok.
EXACT_REFUSALS = {("g1_left", "weld"): "which stands for a length of only"}


@pytest.mark.parametrize("robot", WELD_7DOF)
def test_zoo_weld_7dof(robot):
    _check(_exact(robot, "weld"), EXACT_REFUSALS.get((robot, "weld")))


@pytest.mark.parametrize("robot", POINT_6DOF)
def test_zoo_point_6dof(robot):
    _check(_exact(robot, "point"), EXACT_REFUSALS.get((robot, "point")))


def test_zoo_exact_cases_refuse_no_more_than_allowed():
    """A calibrator that refuses everything would pass a test that takes 'refused' for right: of the eight
    exact cases, no more refuse than `EXACT_REFUSALS` allows, and every other one is right with verdict ok."""
    outs = {(r, "weld"): _exact(r, "weld") for r in WELD_7DOF} | {(r, "point"): _exact(r, "point") for r in POINT_6DOF}
    accepted = [k for k, o in outs.items() if o.judgement is not None and o.right and o.status == "ok"]
    if len(accepted) < len(outs) - len(EXACT_REFUSALS):
        pytest.fail(
            f"only {len(accepted)} of {len(outs)} right with verdict ok (allowed refusals: {len(EXACT_REFUSALS)}):\n"
            + "\n".join(o.line() for o in outs.values()),
            pytrace=False,
        )


def test_zoo_noisy_tracker():
    """Joint noise 1e-4 rad, tracker noise 10 um: right within the noise's own bound, verdict ok (no refusal
    allowed: 0.05 mm against a tolerance of 0.34 mm)."""
    _check(zoo.run_case(zoo.make_case("xarm7", "measured_point", n=60, sigma=1e-4, sigma_t=1e-5, seed=1)))


def test_zoo_noisy_weld():
    """Joint noise 1e-5 rad on one weld pose (weakly conditioned: a few mm over the workspace is all it allows):
    right within the noise's own bound, verdict ok (no refusal allowed: 4.1 mm against 15 mm)."""
    _check(zoo.run_case(zoo.make_case("panda", "weld", n=60, sigma=1e-5, seed=1)))


def test_zoo_corrupted_rows():
    """10 % of the rows replaced by random readings: the robust fit is right, and the verdict is 'suspect' for
    exactly those rows (the one refusal allowed: the rejected rows, which a user must look at)."""
    o = zoo.run_case(zoo.make_case("ur5", "point", n=100, seed=0, corrupt_rows=0.10, tag="rows10"))
    _check(o, "10 of 100 configurations rejected as outliers")
    assert o.right, o.line()


def _held_length(urdf: str, joint: str, following: str) -> float:
    """The length along `joint`'s axis from its parent's origin to the origin of the `following` joint: the
    projection of `joint`'s origin on its axis (in the parent frame) plus that of `following`'s origin (in
    `joint`'s frame).  Where the neighbouring axes cross this one at right angles (the Panda's joint 3), it is
    the distance between their common normals along the axis, the length a held `<joint>.z` stands for."""
    import xml.etree.ElementTree as ET

    joints = {j.get("name"): j for j in ET.fromstring(urdf).findall("joint")}
    vec = lambda el, key: np.array([float(v) for v in el.find(key[0]).get(key[1]).split()])
    a = vec(joints[joint], ("axis", "xyz"))
    a /= np.linalg.norm(a)
    R = pin.rpy.rpyToMatrix(*vec(joints[joint], ("origin", "rpy")))
    return float((R @ a) @ vec(joints[joint], ("origin", "xyz")) + a @ vec(joints[following], ("origin", "xyz")))


def test_zoo_rough_start():
    """A nominal model 10x further from the truth (2 cm, 20 mrad, 0.2 rad offsets): right, verdict ok (no
    refusal allowed), and the size the one the held length gives.

    A weld closes at any size: the calibration holds `panda_joint3.z` (316 mm along joint 3's axis, between
    joints 2 and 4) at its nominal value, so the calibrated robot is the true one scaled by nominal / true
    length.  Its error here is the zoo's perturbation of two origins along that axis (up to 2 cm each: up to
    13 %; this seed 10 %).  The judge's generic size tolerance (sqrt(3) (2 cm / 10 cm + 20 mrad) = 38 %, for
    any held length of 10 cm or more) says little here, so the size is held to the length's own prediction:
    what that leaves out is of second order, tilts of up to sqrt(3) x 20 mrad of joints 3 and 4 times the
    origins' off-axis offsets (at most 28 mm and 20 mm) and L (1 - cos tilt), under 2 mm in all, 0.6 % of
    316 mm (seeds 0-7 measured: within 0.08 %)."""
    case = zoo.make_case("panda", "weld", n=60, seed=1, err_m=2e-2, err_rad=2e-2, offset_rad=0.2, tag="rough")
    o = zoo.run_case(case)
    _check(o)
    assert o.result.scale.gauge == "panda_joint3.z", o.result.scale.gauge
    truth = (case.nominal_urdf.parent / "truth.urdf").read_text()
    predicted = _held_length(case.nominal_urdf.read_text(), "panda_joint3", "panda_joint4") / _held_length(
        truth, "panda_joint3", "panda_joint4"
    )
    assert abs(predicted - 1.0) > 0.05  # the size is off, and by the held length's error (seed 1: 0.907)
    assert abs(o.judgement.scale / predicted - 1.0) < 0.006, (o.judgement.scale, predicted)


def test_zoo_point_contact_states_the_size_it_cannot_see():
    """A point contact closes at any size: right, ok, and the verdict says the size is the model's (a field and
    its last reason), not a 'suspect' for a limit of the data the report states."""
    o = _exact("ur5", "point")
    v = o.result.verdict
    assert o.right and v.status == "ok", o.line()
    assert v.evidence["size_measured"] is False and v.evidence["size_held_by"] == o.result.scale.gauge
    assert v.reasons == [f"size not measured: held by the model's {o.result.scale.gauge}"]
    tracker = zoo.run_case(zoo.make_case("ur5", "measured_point", n=60, seed=0))
    assert tracker.result.verdict.evidence["size_measured"] is True and tracker.result.verdict.reasons == []


def test_zoo_corrupted_first_row_on_a_door():
    """One cell set to 1e6 in the first configuration of a door (hinge) loop: the hinge's start is fitted to
    the arc of the other configurations (`hinge.arc_inliers`), the screen rejects the row, and the fit is
    right and ok (it was 'ok' with the tool 3.27 mm off: the hinge started from the corrupted row)."""
    case = zoo.make_case("ur10", "hinge", n=40, seed=14, corrupt_cells=1, cell_value=1e6, tag="cell")
    assert list(case.corrupted) == [0]
    o = zoo.run_case(case)
    assert o.right and o.status == "ok", o.line()
    assert [r.row for r in o.result.outliers.rejected] == [1]


@pytest.mark.slow
def test_zoo_door_with_a_corrupted_cell_does_not_crawl():
    """A UR5 door (hinge) loop, exact data, one cell set to 1e6: the corrupted row is rejected and the fit is
    right and ok.  From the robust refit's point the weighted fit sat a hair above zero, where its Jacobian
    misses the weighting's own slope: no damped step lowered the cost, and the steps cut to 1/128 gained a
    percent each for 200 iterations, the answer 1.7 mm off and 'failed' (not converged).  Such a solve
    now stops as a crawl (`lm.CRAWL_ITERATIONS`), the plain loop-closure fit finishes the descent, and of the
    fits that close alike the one whose solver reached a minimum is kept (`solve._better`)."""
    case = zoo.make_case("ur5", "hinge", n=40, seed=71, corrupt_cells=1, cell_value=1e6, tag="cell")
    o = zoo.run_case(case)
    assert o.right and o.status == "ok", o.line()
    assert o.result.fit.solver_status == "converged", o.result.fit.solver_message
    assert [r.row for r in o.result.outliers.rejected] == [int(c) + 1 for c in case.corrupted]
    assert o.judgement.pos_max < 1e-6, o.line()  # exact data: the true robot, not merely within the bar
