"""The executor's per-job time limit (`--job-timeout`): a job past it is stopped and recorded, the others
run; a job stuck where the limit's signal cannot reach it ends its worker a little later, the pool goes on."""

from __future__ import annotations

import signal
import time

import pytest

from closedloop.parallel import executor as ex
from closedloop.parallel.engine import hard_grace


def nap(payload: float) -> float:
    """Sleep `payload` seconds (a job that hangs when it is long)."""
    time.sleep(payload)
    return payload


def deaf_nap(payload: float) -> float:
    """Sleep with the limit's signal blocked, as native code that never returns to Python."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
    try:
        time.sleep(payload)
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGALRM})
    return payload


@pytest.mark.parametrize("engine", ["serial", "local"])
def test_a_job_past_its_limit_is_stopped_the_others_run(engine):
    with ex.get_engine(engine, jobs=2, timeout=1.0) as eng:
        t0 = time.monotonic()
        outs = ex.run(nap, [0.01, 120.0, 0.02], eng, errors="record")
        wall = time.monotonic() - t0
    assert outs[0] == 0.01 and outs[2] == 0.02
    stuck = outs[1]
    assert isinstance(stuck, ex.Outcome) and stuck.error == "JobTimeout: stopped after 1 s (the per-job time limit)"
    assert 1.0 <= stuck.seconds < 1.0 + hard_grace(1.0)
    assert wall < 60  # not the job's 120 s


@pytest.mark.slow
def test_a_job_deaf_to_the_limit_ends_its_worker_and_is_recorded():
    # each try ends its worker at 1 s + hard_grace; a new pool, then alone: three tries (~20 s)
    with ex.get_engine("local", jobs=2, timeout=1.0) as eng:
        outs = ex.run(deaf_nap, [0.01, 120.0, 0.02], eng, errors="record")
    assert outs[0] == 0.01 and outs[2] == 0.02
    assert isinstance(outs[1], ex.Outcome) and outs[1].error.startswith("WorkerCrashed")
