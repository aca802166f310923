"""Large blocks are evaluated a chunk of configurations at a time (`problem.CHUNK`, issue 17: temporaries stay
below glibc's mmap limit); the result must be the unchunked one, for every loop type and every field."""

from __future__ import annotations

import numpy as np
import pytest

import closedloop.problem as problem_module
from closedloop import RobotModel
from closedloop.calibration import build_problem
from closedloop.data import JointLog
from closedloop.loops.spec import parse_loop
from closedloop.models import ROBOTS
from closedloop.selection import initial_values
from test_loop_state import Q0, SPECS


@pytest.mark.parametrize("kind", sorted(SPECS))
def test_chunked_evaluation_is_the_whole(kind, monkeypatch):
    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(1)
    lp = parse_loop(SPECS[kind], panda)
    th = Q0 + rng.normal(0.0, 0.05, (23, 7))
    extra = {c: rng.normal(0.0, 0.1, len(th)) for c in lp.columns()}
    joints = [f"panda_joint{i}" for i in range(1, 8)]
    log = JointLog(joints, th, None, None, extra) if extra else JointLog(joints, th)
    problem = build_problem(panda, log, [lp])
    x = initial_values(problem, {}) + rng.normal(0.0, 1e-3, len(problem.params))
    whole = [problem._evaluate(x, True, None, None), problem._evaluate(x, False, None, None),
             problem._evaluate(x, True, None, [])]
    monkeypatch.setattr(problem_module, "CHUNK", 5)  # 23 configurations: chunks of 5, 5, 5, 5, 3
    chunked = [problem._evaluate(x, True, None, None), problem._evaluate(x, False, None, None),
               problem._evaluate(x, True, None, [])]
    for a_list, b_list in zip(whole, chunked):
        for a, b in zip(a_list, b_list):
            for name in ("r", "J", "Jq", "valid", "cov", "rows"):
                u, v = getattr(a, name), getattr(b, name)
                assert (u is None) == (v is None) or name in ("valid", "cov"), (kind, name)
                if u is not None and v is not None:
                    assert u.shape == v.shape and np.allclose(u, v, rtol=0, atol=1e-12), (kind, name)


def test_structure_on_a_sample_is_the_whole(monkeypatch):
    """The structural analysis reads at most `identifiability.STRUCTURE_ROWS` configurations per loop: on 700
    noisy self-motion configurations of a Panda weld, 350 of them (every other) give the same reduction, gauge
    and calibrated values as all 700."""
    import closedloop.identifiability as ident
    from closedloop import CalibrationOptions, calibrate
    from closedloop.loops import WeldLoop
    from closedloop.truth import make_dataset

    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(3)
    ds = make_dataset(panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 700, rng,
                      stride=1)
    log = JointLog(ds.joints, ds.readings + rng.normal(0.0, 1e-5, ds.readings.shape))
    out = {}
    for rows in (10_000, 350):
        monkeypatch.setattr(ident, "STRUCTURE_ROWS", rows)
        out[rows] = calibrate(panda, log, [WeldLoop("fixture", "panda_hand")], CalibrationOptions())
    a, b = out[10_000], out[350]
    assert a.status == b.status and a.gauge == b.gauge
    assert np.allclose(a.values, b.values, rtol=0, atol=1e-12)
    assert a.verdict.status == "ok"
