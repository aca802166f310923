"""Large blocks are evaluated a chunk of configurations at a time (`problem.CHUNK`: temporaries stay
below glibc's mmap limit); the result must be the unchunked one, for every loop type and every field."""

from __future__ import annotations

import numpy as np
import pytest
from test_loop_state import Q0, SPECS

import closedloop.problem.problem as problem_module
from closedloop import RobotModel
from closedloop.analysis.selection import initial_values
from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import build_problem
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop


@pytest.mark.parametrize("stacked", [False, True], ids=["pinocchio", "stacked-threads"])
@pytest.mark.parametrize("kind", sorted(SPECS))
def test_chunked_evaluation_is_the_whole(kind, stacked, monkeypatch):
    """Chunked by Pinocchio's loop, one chunk after the other; or with stacked kinematics, the chunks on two
    threads (`parallel.chunks`), each in a workspace of its own."""
    import closedloop.parallel.chunks as chunks

    if stacked:
        monkeypatch.setattr(problem_module, "STACKED_ROWS", 0)
        monkeypatch.setattr(chunks, "CHUNK_THREADS", 2)
        monkeypatch.setattr(chunks, "cpus", lambda: 2)  # two threads on any machine
    threads: list[int] = []

    def spy(work, starts, slots):
        threads.append(len(slots))
        chunks.for_each_chunk(work, starts, slots)

    monkeypatch.setattr(problem_module, "for_each_chunk", spy)
    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(1)
    lp = parse_loop(SPECS[kind], panda)
    th = Q0 + rng.normal(0.0, 0.05, (23, 7))
    extra = {c: rng.normal(0.0, 0.1, len(th)) for c in lp.columns()}
    joints = [f"panda_joint{i}" for i in range(1, 8)]
    log = JointLog(joints, th, None, None, extra) if extra else JointLog(joints, th)
    problem = build_problem(panda, log, [lp])
    x = initial_values(problem, {}) + rng.normal(0.0, 1e-3, len(problem.params))
    whole = [
        problem._evaluate(x, True, None, None),
        problem._evaluate(x, False, None, None),
        problem._evaluate(x, True, None, []),
    ]
    monkeypatch.setattr(problem_module, "CHUNK", 5)  # 23 configurations: chunks of 5, 5, 5, 5, 3
    chunked = [
        problem._evaluate(x, True, None, None),
        problem._evaluate(x, False, None, None),
        problem._evaluate(x, True, None, []),
    ]
    for a_list, b_list in zip(whole, chunked):
        for a, b in zip(a_list, b_list):
            for name in ("r", "J", "Jq", "valid", "cov", "rows"):
                u, v = getattr(a, name), getattr(b, name)
                assert (u is None) == (v is None) or name in ("valid", "cov"), (kind, name)
                if u is not None and v is not None:
                    assert u.shape == v.shape and np.allclose(u, v, rtol=0, atol=1e-12), (kind, name)
    assert set(threads) == ({2} if stacked else {1}), threads  # a Panda: every frame on revolute joints


@pytest.mark.slow
def test_structure_on_a_sample_is_the_whole(monkeypatch):
    """The structural analysis reads a sample of each loop's configurations (`identifiability.STRUCTURE_ROWS`):
    on 700 noisy self-motion configurations of a Panda weld, the default sample (128 of them, evenly spaced) and
    the fewest allowed (64) give the same reduction, gauge and calibrated values as all 700."""
    import closedloop.analysis.identifiability as ident
    from closedloop import CalibrationOptions, calibrate
    from closedloop.loops import WeldLoop
    from closedloop.studies.truth import make_dataset

    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(3)
    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 700, rng, stride=1
    )
    log = JointLog(ds.joints, ds.readings + rng.normal(0.0, 1e-5, ds.readings.shape))
    out = {}
    for rows, bounds in ((10_000, (10_000, 10_000)), (ident.STRUCTURE_ROWS, ident.STRUCTURE_CONFIGS), (1, (64, 64))):
        monkeypatch.setattr(ident, "STRUCTURE_ROWS", rows)
        monkeypatch.setattr(ident, "STRUCTURE_CONFIGS", bounds)
        out[bounds] = calibrate(panda, log, [WeldLoop("fixture", "panda_hand")], CalibrationOptions())
    a = out[(10_000, 10_000)]
    assert a.verdict.status == "ok"
    for b in out.values():
        assert a.fit.status == b.fit.status and a.scale.gauge == b.scale.gauge
        assert np.allclose(a.fit.values, b.fit.values, rtol=0, atol=1e-12)


def _weld_problem(seed: int, n: int):
    """A Panda weld problem on n configurations near Q0, and a parameter vector 1e-3 off its start."""
    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(seed)
    th = Q0 + rng.normal(0.0, 0.05, (n, 7))
    problem = build_problem(
        panda, JointLog([f"panda_joint{i}" for i in range(1, 8)], th), [parse_loop(SPECS["weld"], panda)]
    )
    return problem, initial_values(problem, {}) + rng.normal(0.0, 1e-3, len(problem.params))


def test_large_jacobian_evaluation_keeps_its_residual_and_jq(monkeypatch):
    """Above `MEMO_ROWS` the parameter Jacobian is not kept, but the residual and Jq of that evaluation are:
    the stages after a solve (closure level, outlier screen) ask for them at the solution, and must get the
    same values without a pass over all rows."""
    problem, x = _weld_problem(2, 40)
    monkeypatch.setattr(problem_module, "MEMO_ROWS", 10)
    calls = []
    real = problem._evaluate
    monkeypatch.setattr(problem, "_evaluate", lambda *a: calls.append(a[1:]) or real(*a))
    full = problem.evaluate(x, True, columns=[0, 3, 5])
    with pytest.raises(ValueError):  # shared with the memo: read-only, no caller changes what is kept
        full[0].r[:] = 0.0
    kept = problem.evaluate(x, True, columns=[])
    assert len(calls) == 1
    again = real(x, True, None, [])
    assert np.array_equal(kept[0].r, again[0].r) and np.array_equal(kept[0].Jq, again[0].Jq)
    assert kept[0].J.shape[-1] == 0
    problem.evaluate(x, True, columns=[0])  # a parameter Jacobian is evaluated again
    assert len(calls) == 2


def test_whitening_by_chunks_and_in_place_is_the_whole(monkeypatch):
    """`noise.whiten` forms W_i^-1/2 and the whitened rows `_CHUNK` configurations at a time, the Jacobian in
    place with `overwrite`: the same numbers as all at once, for both square roots."""
    import closedloop.estimate.noise as noise_module

    problem, x = _weld_problem(4, 23)
    sigma = np.full(7, 1e-4)
    for symmetric in (True, False):
        r1, J1, used1 = noise_module.whiten(problem.evaluate(x), sigma, "noise", symmetric=symmetric)
        monkeypatch.setattr(noise_module, "_CHUNK", 5)
        evals = problem.evaluate(x)
        r2, J2, used2 = noise_module.whiten(evals, sigma, "noise", symmetric=symmetric, overwrite=True)
        monkeypatch.undo()
        assert J2.base is evals[0].J or J2 is evals[0].J  # in place: no second copy of the rows
        assert np.array_equal(r1, r2) and np.array_equal(J1, J2)  # the same arithmetic per configuration
        assert np.array_equal(used1[0][0], used2[0][0]) and used1[0][1] == used2[0][1]


def test_a_pickled_problem_leaves_its_caches_behind(monkeypatch):
    """A result crosses processes (pool, Ray) with its problem: the memo of evaluations and the chunks'
    workspace stay behind, and the copy evaluates to the same numbers."""
    import pickle

    problem, x = _weld_problem(5, 60)
    monkeypatch.setattr(problem_module, "CHUNK", 16)  # the workspace is used
    before = problem.evaluate(x)
    bare = len(pickle.dumps(problem))
    assert problem.__dict__.get("_memo") and problem.__dict__.get("_work")
    copy = pickle.loads(pickle.dumps(problem))
    assert "_memo" not in copy.__dict__ and "_work" not in copy.__dict__
    after = copy.evaluate(x)
    assert np.array_equal(before[0].r, after[0].r) and np.array_equal(before[0].J, after[0].J)
    problem.__dict__.pop("_memo")
    problem.__dict__.pop("_work")
    assert len(pickle.dumps(problem)) == bare
