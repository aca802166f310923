"""The per-row steps of a long log stay linear in memory and near-linear in time, and give the figures the
exact (quadratic) forms give: the nearest-neighbour search, the left-out prediction, the log reader."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import build_problem
from closedloop.estimate import model_error
from closedloop.estimate.model_error import nearest_other, neighbour_correlation
from closedloop.io.logs import JointLog, read_log
from closedloop.loops.measured import MeasuredPointLoop
from closedloop.model.robot import RobotModel


def brute_nearest(p: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """The nearest other row of p to each of `rows`, from every distance (a row of them at a time)."""
    rows = np.arange(p.shape[0]) if rows is None else rows
    out = []
    for i in rows:
        d2 = np.sum((p - p[i]) ** 2, axis=1)
        d2[i] = np.inf
        out.append(np.argmin(d2))
    return np.array(out)


@pytest.mark.parametrize("n", [3, 700, model_error.KD_TREE_ROWS + 100])
def test_nearest_other_is_the_exact_nearest(n):
    """Blocks of exact distances (short logs) and the k-d tree (long ones) find the exact nearest other
    row; a duplicated row's nearest is at distance 0 (its copy), never itself."""
    rng = np.random.default_rng(n)
    p = rng.uniform(-2, 2, (n, 6))
    p[1] = p[0]
    nn = nearest_other(p)
    exact = brute_nearest(p)
    d = np.linalg.norm(p - p[nn], axis=1)
    assert np.all(nn != np.arange(n))
    np.testing.assert_allclose(d, np.linalg.norm(p - p[exact], axis=1), rtol=0, atol=1e-12)
    assert d[0] == 0.0 and d[1] == 0.0
    some = np.array([0, n // 2, n - 1])
    np.testing.assert_array_equal(nearest_other(p, some), nn[some])


def test_neighbour_search_of_a_long_log_holds_no_n_by_n_matrix():
    """200,000 configurations along a path through joint space: the search's peak memory is a few arrays of
    N rows (an N x N matrix of distances would be 320 GB)."""
    rng = np.random.default_rng(3)
    p = np.cumsum(rng.normal(0.0, 0.01, (200_000, 7)), axis=0)
    rows = np.linspace(0, p.shape[0] - 1, 256).astype(int)
    tracemalloc.start()
    nn = nearest_other(p, rows)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 5 * p.nbytes  # p is 11 MB; an N x N matrix, 320 GB
    np.testing.assert_array_equal(nn, brute_nearest(p, rows))


@pytest.fixture(scope="module")
def ur5():
    robot = RobotModel.from_file(ROBOTS["ur5"].path)
    return robot, robot.supporting_joints("tool0")


def test_sampled_neighbour_correlation_estimates_the_whole(ur5, monkeypatch):
    """Above NEIGHBOUR_SAMPLE configurations the correlation pools that many of them: on a smooth misfit
    and on noise it matches the correlation over all configurations within its standard error."""
    robot, joints = ur5
    rng = np.random.default_rng(6)
    n = 6000
    th = rng.uniform(-1.5, 1.5, (n, 6))
    zeros = {f"m:{c}": np.zeros(n) for c in "xyz"}
    prob = build_problem(robot, JointLog(joints, th, None, None, zeros), [MeasuredPointLoop("m", "tool0")])
    smooth = np.column_stack([np.sin(th[:, 0]), np.cos(th[:, 1]), np.sin(th[:, 2] + th[:, 1])]).ravel()
    noise = rng.standard_normal(3 * n)
    sampled = [neighbour_correlation(prob, smooth), neighbour_correlation(prob, noise)]
    monkeypatch.setattr(model_error, "NEIGHBOUR_SAMPLE", n)
    whole = [neighbour_correlation(prob, smooth), neighbour_correlation(prob, noise)]
    assert whole[0] > 0.6 and abs(whole[1]) < 0.05
    assert sampled[0] == pytest.approx(whole[0], abs=0.05)
    assert sampled[1] == pytest.approx(whole[1], abs=0.05)


LOG = "a,b,c\n0.1,-2.5e-3,.5\n1,+2,3.\n"


@pytest.mark.parametrize(
    "text, fault",
    [
        (LOG, None),
        (LOG.replace("\n", "\r\n"), None),
        ("\ufeff" + LOG, None),
        (LOG.replace("+2", "nan"), "line 3, column 'b': value is nan"),
        (LOG.replace("+2", "1_000"), "line 3, column 'b': '1_000' is not a number"),
        (LOG.replace("+2", "2e7"), "line 3, column 'b': 2e7 is out of range"),
        (LOG + "\n\n4,5,6\n", None),
        (LOG.replace("1,+2,3.", "1,+2"), "line 3 has 2 fields"),
        (LOG + "# a comment\n7,8,9\n", None),
    ],
)
def test_the_common_log_is_read_at_once_as_line_by_line(tmp_path, text, fault):
    """A log of joint columns only is parsed at once (NumPy's reader); every log it cannot take whole (a
    blank or comment line, a bad cell) falls to the line-by-line reading: the same values, the same line
    numbers, the same one-line faults."""
    from closedloop.errors import LogError

    path = tmp_path / "log.csv"
    path.write_bytes(text.encode("utf-8"))
    if fault is not None:
        with pytest.raises(LogError, match=fault):
            read_log(path, ["a", "b", "c"])
        return
    lg = read_log(path, ["a", "b", "c"])
    rows = [ln for ln in text.lstrip("\ufeff").splitlines()[1:] if ln.strip() and not ln.startswith("#")]
    np.testing.assert_array_equal(lg.angles, [[float(v) for v in ln.split(",")] for ln in rows])
    numbers = [i + 1 for i, ln in enumerate(text.lstrip("\ufeff").splitlines()) if ln in rows]
    assert [int(v) for v in lg.lines[:, 1]] == numbers
    assert lg.where(1) == f"{path} line {numbers[1]}"


EXTRA = "a,tau:a,b,meas\n0.1,5,-2.5e-3,.5\n1,-3e2,+2,3.\n0.3,7,0.2,1\n"


@pytest.mark.parametrize(
    "text",
    [
        EXTRA,
        EXTRA.replace("-3e2", "nan"),  # another column's cell that is no finite number: NaN, read at once
        EXTRA.replace("-3e2", "inf"),
        EXTRA.replace("-3e2", "x"),  # not a number at all: NaN, line by line
        EXTRA.replace("-3e2", "2e9"),  # another column is not a joint's reading: no range
        EXTRA.replace("tau:a", "c"),  # a column naming no joint of the model
    ],
)
def test_a_log_with_other_columns_is_read_at_once_as_line_by_line(tmp_path, text, monkeypatch):
    """A log with columns besides the joints' (torques, measurements) is parsed at once too: the same joint
    readings, other columns, line numbers as the line-by-line reading (the reference: the fast path off)."""
    from closedloop.io import logs

    path = tmp_path / "log.csv"
    path.write_text(text)
    fast = read_log(path, ["a", "b"])
    assert (logs._plain_log(path, {"a", "b"}) is None) == (",x," in text)  # at once, but for a word in a cell
    monkeypatch.setattr(logs, "_plain_log", lambda *a: None)
    slow = read_log(path, ["a", "b"])
    assert fast.joints == slow.joints == ["a", "b"]
    np.testing.assert_array_equal(fast.angles, slow.angles)
    assert list(fast.extra) == list(slow.extra)
    for k in slow.extra:
        np.testing.assert_array_equal(fast.extra[k], slow.extra[k])
    np.testing.assert_array_equal(fast.lines, slow.lines)


def test_a_joints_bad_cell_beside_other_columns_is_named(tmp_path):
    from closedloop.errors import LogError

    path = tmp_path / "log.csv"
    path.write_text(EXTRA.replace("+2", "nan"))
    with pytest.raises(LogError, match="line 3, column 'b': value is nan"):
        read_log(path, ["a", "b"])
