"""A log that repeats its poses: readings of one pose share that pose's error, and the error bars must say so.

A robot held at each of 40 poses while the log runs 25 rows per pose: the rows of one pose are not 25
independent measurements of the model when something they share (here one reading error per pose, as a
tiled log or an unmodelled effect of the pose makes it) is in their residual.  The noise-model error bars
count every row and come out too small by up to 5x (the square root of the repeats); the sandwich clustered
by cells of joint space (`model_error.configuration_cells`) counts the poses, and the verdict's check of the
error bars (the two variances agree) flags the log.  With independent reading noise on every row, the same
poses and repeats, the two agree and nothing is flagged.
"""

from __future__ import annotations

import numpy as np
import pytest
import zoo

from closedloop import CalibrationOptions, calibrate
from closedloop.io.logs import JointLog, read_log
from closedloop.loops.spec import parse_loop
from closedloop.model.robot import RobotModel

POSES, REPEATS, NOISE = 40, 25, 1e-4


@pytest.fixture(scope="module")
def case():
    return zoo.make_case("ur5", "point", n=POSES, sigma=0.0, seed=3)


def _result(case, shared: bool):
    robot = RobotModel.from_file(case.nominal_urdf)
    exact = read_log(case.log_csv, robot.joint_names)
    rng = np.random.default_rng(7)
    poses = exact.angles + (rng.normal(0.0, NOISE, exact.angles.shape) if shared else 0.0)
    rows = np.repeat(poses, REPEATS, axis=0) + rng.normal(0.0, NOISE, (POSES * REPEATS, poses.shape[1]))
    log = JointLog(list(exact.joints), rows)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    return calibrate(robot, log, loops, CalibrationOptions())


def test_a_pose_repeated_with_its_own_error_flags_the_error_bars(case):
    res = _result(case, shared=True)
    ratio = res.verdict.evidence["sandwich_variance_ratio"]
    assert ratio > 5.0, ratio  # 25 rows per pose, half their noise shared: about 1 + 24 / 2
    assert res.verdict.status == "suspect", res.verdict.describe()
    assert any("error bars are not reliable" in r for r in res.verdict.reasons), res.verdict.reasons


def test_a_pose_repeated_with_independent_noise_is_not_flagged(case):
    res = _result(case, shared=False)
    ratio = res.verdict.evidence["sandwich_variance_ratio"]
    assert 0.5 < ratio < 2.0, ratio
    assert not any("error bars are not reliable" in r for r in res.verdict.reasons), res.verdict.reasons


def test_the_sandwich_rests_on_its_clusters_not_its_rows():
    """Sandwich error bars (the plain fit's) are suspect below 3 clusters per parameter: a log of 100 poses
    each read 400 times rests on 100 clusters, not on 40,000 configurations."""
    from types import SimpleNamespace

    from closedloop.calibration.verdict import SUSPECT, Verdict, _error_bars
    from closedloop.estimate.model_error import SANDWICH
    from closedloop.records import VerdictRules

    def judged(cells):
        block = SimpleNamespace(theta=np.zeros((40000, 12)), loop=SimpleNamespace())
        noise = SimpleNamespace(error_bars=SANDWICH, model_error={"sandwich_cells": cells})
        res = SimpleNamespace(
            problem=SimpleNamespace(blocks=[block]), fit=SimpleNamespace(estimated=range(47)), noise=noise
        )
        v = Verdict()
        _error_bars(res, VerdictRules(), v)
        return v

    few = judged(100)
    assert (
        few.status == SUSPECT
        and "rests on 100 distinct poses (of 40000 configurations) for 47 parameters" in few.reasons[0]
    )
    assert judged(2739).status != SUSPECT


@pytest.mark.parametrize("n_poses, held_for", [(40, 25), (1500, 4)])  # centres compared exactly; by a k-d tree
def test_a_held_poses_readings_are_one_cell_wherever_the_grid_cuts_them(n_poses, held_for):
    """Poses of 14 joints held for several rows each, 3e-5 rad of noise per reading, cells 1 mrad wide: a grid
    cuts most poses' readings on some joint (the readings spread over 2e-4 rad); each pose is one cell all the
    same, and a log moving across the cells keeps cells of its own (a cell's rows span one cell width per
    joint)."""
    from types import SimpleNamespace

    from closedloop.estimate.model_error import configuration_cells

    rng = np.random.default_rng(4)
    poses = rng.uniform(-2.0, 2.0, (n_poses, 14))
    held = np.repeat(poses, held_for, axis=0) + rng.normal(0.0, 3e-5, (n_poses * held_for, 14))
    grid = np.floor(held / 1e-3)
    assert len({tuple(g) for g in grid}) > 1.5 * n_poses  # the premise: the grid alone cuts poses into pieces
    problem = SimpleNamespace(joints=list(range(14)), blocks=[SimpleNamespace(theta=held, loop=SimpleNamespace())])
    cells = configuration_cells(problem, np.full(14, 1e-3))[0]
    assert np.unique(cells).size == n_poses
    assert all(np.unique(cells[held_for * k : held_for * (k + 1)]).size == 1 for k in range(n_poses))
    moving = np.linspace(0.0, 0.5, 2000)[:, None] * np.ones(14) + rng.normal(0.0, 3e-5, (2000, 14))
    problem.blocks[0].theta = moving
    cells = configuration_cells(problem, np.full(14, 1e-3))[0]
    spans = [np.ptp(moving[cells == c, 0]) for c in np.unique(cells)]
    assert np.unique(cells).size > 250 and max(spans) < 3e-3
