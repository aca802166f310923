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
