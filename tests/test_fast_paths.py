"""The fast paths of the solve against the straightforward computations they replace."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.analysis.identifiability import project_to_closure
from closedloop.estimate.noise import cholesky_inverse, whiten
from closedloop.estimate.qr import r_factor
from closedloop.loops import WeldLoop
from closedloop.problem.problem import CalibrationProblem, LoopBlock


def _problem(panda, frame_b="universe", n=30, tau=False, seed=0):
    rng = np.random.default_rng(seed)
    joints = panda.supporting_joints("panda_hand")
    theta = rng.uniform(-1.0, 1.0, (n, len(joints)))
    block = LoopBlock(
        WeldLoop("w", "panda_hand", frame_b), theta, np.arange(n), rng.normal(0.0, 10.0, theta.shape) if tau else None
    )
    prob = CalibrationProblem(panda, joints, [block])
    x = prob.nominal + rng.normal(0.0, 0.02, prob.nominal.size)
    sl = prob.loop_slices[0]
    x[sl] = block.loop.initialize(*prob.loop_poses(x, 0))
    return prob, x


@pytest.mark.parametrize("frame_b", ["universe", "panda_link3"])
def test_reading_jacobian_equals_pinocchio_frame_jacobians(panda, frame_b):
    """Jq from the kinematic regressors (J = K S) equals the one from Pinocchio's LOCAL frame Jacobians."""
    prob, x = _problem(panda, frame_b)
    b = prob.blocks[0]
    ev = prob.evaluate(x, columns=[])[0]
    state = prob.rp.apply(x[: prob.n_robot])
    model, data = state.model, state.data
    fa, fb = panda.frame_id("panda_hand"), panda.frame_id(frame_b)
    idx_v = [panda.joint(j).idx_v for j in prob.joints]
    q = panda.configurations(prob.model_angles(state, b.theta, None), prob.joints)
    TA, TB = prob.loop_poses(x, 0)
    lev = b.loop.evaluate(TA, TB, x[prob.loop_slices[0]])
    for i, qi in enumerate(q):
        pin.computeJointJacobians(model, data, qi)
        pin.updateFramePlacements(model, data)
        jac = lev.dA[i] @ pin.getFrameJacobian(model, data, fa, pin.LOCAL)[:, idx_v]
        if fb:
            jac += lev.dB[i] @ pin.getFrameJacobian(model, data, fb, pin.LOCAL)[:, idx_v]
        assert np.abs(ev.Jq[i] - jac * state.scale).max() < 1e-12 * np.abs(jac).max()


def test_requested_columns_equal_the_full_jacobian(panda):
    """Any subset of columns, in any order, equals those columns of the full Jacobian (compliance included)."""
    prob, x = _problem(panda, tau=True)
    full = prob.evaluate(x)[0]
    cols = np.random.default_rng(1).permutation(len(prob.names))[:25]
    part = prob.evaluate(x, columns=cols)[0]
    assert np.abs(part.J - full.J[:, :, cols]).max() <= 1e-14 * np.abs(full.J).max()
    assert np.array_equal(part.Jq, full.Jq) and np.array_equal(part.r, full.r)
    assert prob.evaluate(x, columns=[])[0].J.shape == (30, 6, 0)


def test_cholesky_whitening_is_the_same_least_squares_problem(panda):
    """L^-1 in place of the symmetric W^-1/2: same |r|^2, J^T J and J^T r; singular W_i still take the eigen route."""
    prob, x = _problem(panda, n=40)
    ev = prob.evaluate(x)[0]
    ev.Jq[3] = 0.0  # a configuration whose closure error no joint noise can produce: W = 0
    ev.Jq[5, :, 2:] = 0.0  # and one seen by two joints only: W of rank 2
    sigma = np.full(len(prob.joints), 1e-4)
    r1, J1, used1 = whiten([ev], sigma, "noise")
    r2, J2, used2 = whiten([ev], sigma, "noise", symmetric=False)
    assert used1[0][1] == used2[0][1] == 6 + 4
    assert abs(r1 @ r1 - r2 @ r2) < 1e-10 * (r1 @ r1)  # round-off grows with the W_i's conditions (up to ~1e6 here)
    assert np.abs(J1.T @ J1 - J2.T @ J2).max() < 1e-10 * np.abs(J1.T @ J1).max()
    assert np.abs(J1.T @ r1 - J2.T @ r2).max() < 1e-10 * np.abs(J1.T @ r1).max()
    W = ev.Jq[:3] @ np.swapaxes(ev.Jq[:3], 1, 2)
    Linv, kappa = cholesky_inverse(W)
    assert np.abs(Linv @ W @ np.swapaxes(Linv, 1, 2) - np.eye(6)).max() < 1e-10
    assert np.all(kappa >= np.linalg.cond(W))


def test_projection_matches_pseudo_inverse_steps(panda, panda_weld):
    """Closure projection through Cholesky steps lands where the SVD pseudo-inverse steps land."""
    joints = panda_weld.joints
    prob = CalibrationProblem(
        panda,
        joints,
        [LoopBlock(WeldLoop("fixture", "panda_hand"), panda_weld.readings, np.arange(len(panda_weld.readings)))],
    )
    x = prob.nominal  # the nominal model: the true robot's configurations miss its closure by millimetres
    x[prob.loop_slices[0]] = prob.blocks[0].loop.initialize(*prob.loop_poses(x, 0))
    ref = prob.blocks[0].theta.copy()
    for _ in range(8):
        ev = prob.evaluate(x, True, [ref], columns=[])[0]
        ref = ref - np.einsum("nij,nj->ni", np.linalg.pinv(ev.Jq, rcond=1e-10), ev.r)
    out = project_to_closure(prob, x)[0][0]
    assert np.abs(out - ref).max() < 1e-12
    assert np.abs(prob.evaluate(x, False, [out])[0].r).max() < 1e-13


@pytest.mark.parametrize("rows", [60, 257, 5000, 70001])
def test_tall_skinny_qr(rows):
    A = np.random.default_rng(rows).normal(size=(rows, 28))
    R = r_factor(A)
    R_ref = np.linalg.qr(A, mode="r")
    assert np.abs(np.abs(R) - np.abs(R_ref)).max() < 1e-12 * np.abs(R_ref).max()


@pytest.mark.parametrize("model", ["panda", "dh_hand", "utah_hand"])
def test_frame_kinematics_are_pinocchios(panda, model, monkeypatch):
    """`frame_kinematics` (all rows at once, `model.stacked`) and its Pinocchio path (a configuration at a
    time, poses read off the regressors by `se3.poses_from_adjoints`) give Pinocchio's frame placements and
    LOCAL kinematic regressors, on a serial arm, a finger branch, a D-H end frame and a frame on the base,
    at a perturbed parameter vector."""
    from pathlib import Path

    from closedloop.assets.catalog import ROBOTS
    from closedloop.model.robot import RobotModel

    root = Path(__file__).resolve().parents[1] / "closedloop" / "assets"
    robot = {
        "panda": panda,
        "dh_hand": RobotModel.from_file(root / "dh" / "utah_mit_thumb_finger.yaml"),
        "utah_hand": RobotModel.from_file(ROBOTS["utah_hand"].path),
    }[model]
    m = robot.model
    frames = [f for f in range(1, len(m.frames)) if m.frames[f].parentJoint > 0][-3:] + [
        f for f in range(1, len(m.frames)) if m.frames[f].parentJoint == 0
    ][:1]
    joints = [n for n in robot.joint_names]
    rng = np.random.default_rng(4)
    theta = rng.uniform(-1.0, 1.0, (25, len(joints)))
    prob = CalibrationProblem(robot, joints, [LoopBlock(WeldLoop("w", m.frames[frames[0]].name), theta, np.arange(25))])
    state = prob.rp.apply(prob.nominal[: prob.n_robot] + rng.normal(0.0, 0.01, prob.n_robot))
    q = robot.configurations(prob.model_angles(state, theta, None), joints)
    assert all(robot.stacked.covers(m, f) for f in frames)
    import closedloop.problem.problem as problem_module

    monkeypatch.setattr(problem_module, "STACKED_ROWS", 1)  # all rows at once from one configuration on
    for kin in (
        prob.frame_kinematics(state, theta, frames, True),
        prob.frame_kinematics(state, theta, frames, False),
        prob.pinocchio_kinematics(state, q, frames, True),
        prob.pinocchio_kinematics(state, q, frames, False),
    ):
        for f in frames:
            T, K = kin[f]
            for i, qi in enumerate(q):
                pin.forwardKinematics(state.model, state.data, qi)
                ref = pin.updateFramePlacement(state.model, state.data, f).homogeneous
                assert np.abs(T[i] - ref).max() < 1e-14, m.frames[f].name
                if K is not None:
                    K_ref = pin.computeFrameKinematicRegressor(state.model, state.data, f, pin.LOCAL)
                    assert np.abs(K[i] - K_ref).max() < 1e-13 * max(1.0, np.abs(K_ref).max()), m.frames[f].name


PUBLIC_ROBOTS = [
    "pr2_description/urdf/pr2.urdf",  # revolute about unaligned axes, unbounded about x, a prismatic lift
    "tiago_pro_description/robots/tiago_pro.urdf",  # unbounded wheels about z, a prismatic torso
    "baxter_description/urdf/baxter.urdf",  # prismatic fingers
    "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
]


@pytest.mark.parametrize("path", PUBLIC_ROBOTS)
def test_stacked_kinematics_on_public_robots(path):
    """`StackedKinematics` against Pinocchio on robot files from example-robot-data with every joint type it
    computes, every frame, the joint placements perturbed as a calibration moves them."""
    from closedloop.assets.catalog import example_robot_data_dir
    from closedloop.model.stacked import StackedKinematics

    file = example_robot_data_dir() / path
    if not file.exists():
        pytest.skip(f"{file} is not in this example-robot-data")
    m = pin.buildModelFromUrdf(str(file))
    d = m.createData()
    stacked = StackedKinematics(m)
    rng = np.random.default_rng(3)
    for j in range(1, m.njoints):
        m.jointPlacements[j] = m.jointPlacements[j] * pin.exp6(pin.Motion(rng.normal(0.0, 0.05, 6)))
    q = np.array([pin.randomConfiguration(m, -np.ones(m.nq), np.ones(m.nq)) for _ in range(6)])
    frames = [f for f in range(1, m.nframes) if m.frames[f].parentJoint > 0]
    assert all(stacked.covers(m, f) for f in frames)
    K = {f: np.empty((len(q), 6, 6 * (m.njoints - 1))) for f in frames}
    T = stacked.frames(m, q, frames, K)
    for i, qi in enumerate(q):
        pin.forwardKinematics(m, d, qi)
        for f in frames:
            assert np.abs(T[f][i] - pin.updateFramePlacement(m, d, f).homogeneous).max() < 1e-13
            K_ref = pin.computeFrameKinematicRegressor(m, d, f, pin.LOCAL)
            assert np.abs(K[f][i] - K_ref).max() < 1e-13 * max(1.0, np.abs(K_ref).max())


@pytest.mark.parametrize("path", PUBLIC_ROBOTS)
def test_stacked_gravity_is_pinocchios(path, monkeypatch):
    """`StackedKinematics.gravity` (every configuration at once, in blocks of GRAVITY_ROWS) is Pinocchio's
    generalized gravity (RNEA at rest) at each configuration, on robot files with every joint type it
    computes, the joint placements perturbed."""
    from closedloop.assets.catalog import example_robot_data_dir
    from closedloop.model import stacked as stacked_module

    file = example_robot_data_dir() / path
    if not file.exists():
        pytest.skip(f"{file} is not in this example-robot-data")
    m = pin.buildModelFromUrdf(str(file))
    d = m.createData()
    rng = np.random.default_rng(5)
    for j in range(1, m.njoints):
        m.jointPlacements[j] = m.jointPlacements[j] * pin.exp6(pin.Motion(rng.normal(0.0, 0.05, 6)))
    q = np.array([pin.randomConfiguration(m, -np.ones(m.nq), np.ones(m.nq)) for _ in range(7)])
    monkeypatch.setattr(stacked_module, "GRAVITY_ROWS", 3)  # blocks of 3, 3 and 1
    g = stacked_module.StackedKinematics(m).gravity(m, q)
    ref = np.array([pin.computeGeneralizedGravity(m, d, qi) for qi in q])
    assert g is not None and g.shape == ref.shape
    assert np.abs(g - ref).max() < 1e-12 * max(1.0, np.abs(ref).max())
    assert np.abs(ref).max() > 0.1  # the robots weigh


@pytest.mark.parametrize("name", ["ur10", "kinova", "baxter_left", "talos_left", "g1_left"])
def test_poses_off_the_regressors_on_the_zoo(name, tmp_path):
    """The same check on zoo arms (`tests/zoo.py`: every joint origin perturbed, fixed joints too) at random
    configurations within their limits and a perturbed parameter vector: the tool's pose read off its
    kinematic regressor is Pinocchio's placement to 1e-14."""
    import zoo

    from closedloop.model.robot import RobotModel

    path = tmp_path / "robot.urdf"
    path.write_text(zoo.perturb_urdf(zoo.chain_urdf(zoo.ZOO[name]), np.random.default_rng(1), 2e-3, 2e-3))
    robot = RobotModel.from_file(path)
    joints = robot.supporting_joints(zoo.TOOL)
    rng = np.random.default_rng(2)
    lo = np.array([max(robot.joint(j).lower, -np.pi) for j in joints])
    hi = np.array([min(robot.joint(j).upper, np.pi) for j in joints])
    theta = rng.uniform(lo, hi, (30, len(joints)))
    prob = CalibrationProblem(robot, joints, [LoopBlock(WeldLoop("w", zoo.TOOL), theta, np.arange(30))])
    state = prob.rp.apply(prob.nominal[: prob.n_robot] + rng.normal(0.0, 0.01, prob.n_robot))
    f = robot.frame_id(zoo.TOOL)
    fast = prob.frame_kinematics(state, theta, [f], True)[f][0]
    plain = prob.frame_kinematics(state, theta, [f], False)[f][0]
    assert np.abs(fast - plain).max() < 1e-14 * max(1.0, np.abs(plain).max())
