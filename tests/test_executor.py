"""closedloop.executor: the same results on every engine (serial, local pool, a real Ray cluster),
seeds per job, failures isolated, worker crashes recorded; the studies moved onto it unchanged."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest
import ray  # in the test extra: these tests run a real local Ray cluster

from closedloop import CalibrationOptions
from closedloop import executor as ex
from closedloop.montecarlo import monte_carlo, weld_scenario
from closedloop.validation import cross_validate


def noisy_sum(scale: float, payload: int, rng: np.random.Generator) -> float:
    """A seeded job: depends on the job's own stream only."""
    return float(scale * payload + rng.normal(size=1000).sum())


def flaky(payload: int) -> int:
    if payload == 3:
        raise ValueError(f"job {payload} is bad")
    if payload == 5:
        os._exit(7)  # the worker process dies (a crash in native code)
    return payload * payload


@pytest.fixture(scope="module", autouse=True)
def one_blas_thread():
    """As in the workers: threaded BLAS on small matrices stalls on a shared machine."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


@pytest.fixture(scope="module")
def cluster():
    import sys

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers do not see tests/
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def local():
    with ex.get_engine("local", jobs=2) as eng:
        yield eng


@pytest.fixture(scope="module")
def scenario():
    """A Panda welded to a fixture, 40 exact configurations spread over the whole self-motion."""
    sc = weld_scenario(n=1, seed=2, pool="manifold", n_pool=40)
    return dataclasses.replace(sc, theta=sc.pool, pool=None)


def test_seeds_per_job_not_per_worker(cluster, local):
    """SeedSequence(seed).spawn(n)[i] drives job i: identical on 1 process, 2 workers, 2 Ray CPUs."""
    serial = ex.run(noisy_sum, range(12), "serial", shared=(10.0,), seed=7)
    expect = [10.0 * i + np.random.default_rng(s).normal(size=1000).sum()
              for i, s in enumerate(np.random.SeedSequence(7).spawn(12))]
    assert serial == expect
    assert ex.run(noisy_sum, range(12), local, shared=(10.0,), seed=7) == serial
    assert ex.run(noisy_sum, range(12), "ray", shared=(10.0,), seed=7) == serial
    assert ex.run(noisy_sum, range(12), "serial", shared=(10.0,), seed=8) != serial


def test_failures_isolated(cluster, local):
    """An exception is recorded; a worker that dies is recorded; the other jobs finish."""
    for engine in (local, "ray"):
        outs = sorted(ex.imap(flaky, range(8), engine), key=lambda o: o.index)
        assert [o.index for o in outs] == list(range(8))
        assert [o.value for o in outs if o.ok] == [i * i for i in (0, 1, 2, 4, 6, 7)], engine
        assert outs[3].error == "ValueError: job 3 is bad" and "flaky" in outs[3].traceback
        assert outs[5].error.startswith("WorkerCrashed"), outs[5].error
    with pytest.raises(ValueError, match="job 3 is bad"):
        ex.run(flaky, [1, 3], "serial")
    rec = ex.run(flaky, [1, 3], "serial", errors="record")
    assert rec[0] == 1 and not rec[1].ok


def test_progress_counts():
    seen = []
    ex.run(flaky, [0, 1, 3], "serial", errors="record", progress=lambda p: seen.append((p.done, p.failed, p.total)))
    assert seen == [(1, 0, 3), (2, 0, 3), (2, 1, 3)]
    p = ex.Progress(10, done=4, failed=1)
    assert "5/10 finished (4 ok, 1 failed)" in p.line()


def test_studies_identical_on_every_engine(cluster, local, scenario):
    """Monte Carlo draws and k-fold refits: bit-identical on serial, local pool and Ray."""
    sc = scenario
    opts = CalibrationOptions(noise=1e-4, fix={"panda_joint4.x": None})  # one length sets the scale (thesis 3.3)
    mc = {e: monte_carlo(sc, 1e-4, 4, seed=1, weightings=("noise",), options=opts, executor=e)
          for e in ("serial", local, "ray")}
    ref = mc["serial"]
    assert ref.stats["noise"].estimates.shape == (4, len(ref.names))
    for e, m in mc.items():
        for w in ref.stats:
            assert np.array_equal(m.stats[w].estimates, ref.stats[w].estimates), (e, w)
    th = sc.theta + np.random.default_rng(5).normal(0, 1e-4, sc.theta.shape)
    cv = {e: cross_validate(sc.robot, sc.log(th), sc.loops, opts, k=3, executor=e) for e in ("serial", local, "ray")}
    for e, c in cv.items():
        assert [f["values"] for f in c["folds"]] == [f["values"] for f in cv["serial"]["folds"]], e
        assert c["test"] == cv["serial"]["test"] and c["parameter_spread"] == cv["serial"]["parameter_spread"]
    # the refits predict held-out rows at the noise level (1e-4 rad through a ~1 m arm: well below 1 mm)
    assert all(t["rms_m"] < 1e-3 for t in cv["serial"]["test"])


def test_unknown_engine_is_an_input_error():
    from closedloop.errors import InputError

    with pytest.raises(InputError, match="unknown engine 'dask'"):
        ex.get_engine("dask")
