"""closedloop.parallel.executor: the same results on every engine (serial, local pool, a real Ray cluster),
seeds per job, failures isolated, worker crashes recorded; the studies moved onto it unchanged."""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

from closedloop import CalibrationOptions
from closedloop.parallel import executor as ex
from closedloop.studies.montecarlo import monte_carlo, weld_scenario
from closedloop.validation.kfold import cross_validate


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

    import ray  # in the test extra: a real local Ray cluster (imported here, not when a worker collects this file)

    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
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


@pytest.mark.slow
def test_seeds_per_job_not_per_worker(cluster, local):
    """SeedSequence(seed).spawn(n)[i] drives job i: identical on 1 process, 2 workers, 2 Ray CPUs."""
    serial = ex.run(noisy_sum, range(12), "serial", shared=(10.0,), seed=7)
    expect = [
        10.0 * i + np.random.default_rng(s).normal(size=1000).sum()
        for i, s in enumerate(np.random.SeedSequence(7).spawn(12))
    ]
    assert serial == expect
    assert ex.run(noisy_sum, range(12), local, shared=(10.0,), seed=7) == serial
    assert ex.run(noisy_sum, range(12), "ray", shared=(10.0,), seed=7) == serial
    assert ex.run(noisy_sum, range(12), "serial", shared=(10.0,), seed=8) != serial


@pytest.mark.slow
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


@pytest.mark.slow
def test_ray_chunks_same_results_a_lost_chunk_run_again_job_by_job(cluster):
    """40 small jobs on 2 CPUs travel several to a Ray task: the same values as one process; a chunk whose
    worker dies has its jobs run again one per task, so only the job that kills its worker is lost."""
    eng = ex.get_engine("ray")
    assert eng.chunk_size(40) == 5 and eng.chunk_size(7) == 1
    serial = ex.run(noisy_sum, range(40), "serial", shared=(10.0,), seed=7)
    outs = sorted(ex.imap(noisy_sum, range(40), eng, shared=(10.0,), seed=7), key=lambda o: o.index)
    assert [o.value for o in outs] == serial
    assert len({o.worker for o in outs[:5]}) == 1  # the first chunk: one task, one worker
    # no retries: the job that kills its worker is recorded at its first death alone (each death costs a new worker)
    outs = sorted(ex.imap(flaky, range(40), ex.RayEngine(retries=0)), key=lambda o: o.index)
    assert [o.index for o in outs] == list(range(40))
    assert [o.value for o in outs if o.ok] == [i * i for i in range(40) if i not in (3, 5)]
    assert outs[3].error == "ValueError: job 3 is bad"
    assert outs[5].error.startswith("WorkerCrashed"), outs[5].error


def test_a_job_s_cpu_time_is_its_own_thread_s():
    """An outcome's `cpu` counts the job's CPU time, not the time it waited."""

    def busy(payload: float) -> None:
        t0 = __import__("time").thread_time()
        while __import__("time").thread_time() - t0 < payload:
            pass

    def idle(payload: float) -> None:
        __import__("time").sleep(payload)

    out = ex.call(busy, 0, 0.2, None)
    # the thread's CPU clock and the wall clock are read one after the other, each at its own resolution:
    # a busy job's CPU may exceed its wall time by that much (8 us seen), never by more
    assert out.ok and 0.2 <= out.cpu <= out.seconds + 1e-3
    out = ex.call(idle, 0, 0.2, None)
    assert out.ok and out.seconds >= 0.2 and out.cpu < 0.05


def test_a_job_s_imports_are_outside_its_clock_and_time_limit(tmp_path, monkeypatch):
    """The modules a job function `needs` are imported before its clock and time limit start."""
    (tmp_path / "slow_to_import.py").write_text("import time\n\ntime.sleep(1.0)\nVALUE = 7\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(__import__("sys").modules, "slow_to_import", raising=False)

    @ex.needs("slow_to_import")
    def job(payload: int) -> int:
        import slow_to_import

        return slow_to_import.VALUE + payload

    out = ex.call(job, 0, 1, None, timeout=0.5)
    assert out.ok and out.value == 8 and out.seconds < 0.5, out.error
    monkeypatch.delitem(__import__("sys").modules, "slow_to_import")


SERIAL_THREADS = """
import json
from closedloop.parallel import executor as ex


@ex.needs("pinocchio")  # loads OpenMP (libgomp) as it is imported
def job(payload):
    from threadpoolctl import threadpool_info

    return {i["internal_api"]: i["num_threads"] for i in threadpool_info()}


print(json.dumps(ex.run(job, [0], ex.SerialEngine(threads=1))[0]))
"""


@pytest.mark.slow
def test_the_serial_engine_limits_the_thread_pools_a_job_s_imports_load():
    """`SerialEngine(threads=1)` (``--jobs 1``) runs its jobs with one BLAS and one OpenMP thread as the
    other engines' workers do, OpenMP loaded by the job's `needs` included (in a fresh process whose
    default is 3 threads)."""
    import json
    import subprocess
    import sys

    env = {**os.environ, "OMP_NUM_THREADS": "3", "OPENBLAS_NUM_THREADS": "3"}
    done = subprocess.run([sys.executable, "-c", SERIAL_THREADS], capture_output=True, text=True, env=env, check=True)
    assert json.loads(done.stdout.splitlines()[-1]) == {"openblas": 1, "openmp": 1}


def test_progress_counts():
    seen = []
    ex.run(flaky, [0, 1, 3], "serial", errors="record", progress=lambda *told: seen.append(told), task="runs")
    assert seen == [
        ("runs", 1, 3, "1 ok, 0 failed, 1 running"),
        ("runs", 2, 3, "2 ok, 0 failed, 1 running"),
        ("runs", 3, 3, "2 ok, 1 failed, 0 running"),
    ]
    p = ex.JobCounts(10, done=4, failed=1)
    assert p.finished == 5 and p.note() == "4 ok, 1 failed, 0 running"


@pytest.mark.slow
def test_studies_identical_on_every_engine(cluster, local, scenario):
    """Monte Carlo draws and k-fold refits: bit-identical on serial, local pool and Ray."""
    sc = scenario
    opts = CalibrationOptions(noise=1e-4, fix={"panda_joint4.x": None})  # one length sets the scale (thesis 3.3)
    mc = {
        e: monte_carlo(sc, 1e-4, 4, seed=1, weightings=("noise",), options=opts, executor=e)
        for e in ("serial", local, "ray")
    }
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


# --------------------------------------------------------------------------- the other studies
@pytest.mark.slow
def test_pose_pools_identical_on_every_engine(cluster, local):
    """One A-optimal selection per candidate pool, and the random-subset baseline seeded per chunk:
    the same designs on serial, local pool and Ray; selection beats the best of 60 random draws."""
    from closedloop import calibrate
    from closedloop.design.poses import pool_blocks, random_designs, select_pools, trace_covariance

    sc = weld_scenario(n=1, seed=2, pool="manifold", n_pool=120)
    th = sc.pool[::3] + np.random.default_rng(5).normal(0, 1e-4, sc.pool[::3].shape)
    res = calibrate(sc.robot, sc.log(th), sc.loops, CalibrationOptions(noise=1e-4, fix={"panda_joint4.x": None}))
    pools = [sc.pool[i::3] for i in range(3)]  # three interleaved candidate pools of 40 configurations
    sels = {e: select_pools(res, None, pools, 12, "exchange-a", executor=e) for e in ("serial", local, "ray")}
    B, _ = pool_blocks(res, None, pools[1])
    rnd = {e: random_designs(B, 12, draws=60, seed=3, chunk=20, executor=e) for e in ("serial", local, "ray")}
    for e in (local, "ray"):
        assert [s.indices.tolist() for s in sels[e]] == [s.indices.tolist() for s in sels["serial"]], e
        assert [s.trace for s in sels[e]] == [s.trace for s in sels["serial"]], e
        assert np.array_equal(rnd[e].indices, rnd["serial"].indices) and np.array_equal(
            rnd[e].traces, rnd["serial"].traces
        ), e
    assert rnd["serial"].indices.shape == (60, 12) and len(np.unique(rnd["serial"].indices[0])) == 12
    assert not np.array_equal(random_designs(B, 12, draws=60, seed=4, chunk=20).indices, rnd["serial"].indices)
    for p, s in zip(pools, sels["serial"]):
        Bp, _ = pool_blocks(res, None, p)
        r = random_designs(Bp, 12, draws=60, seed=3, chunk=20)
        assert len(set(s.indices.tolist())) == 12
        assert trace_covariance(Bp, s.indices) < 0.9 * r.traces.min() and r.median > 2.5 * trace_covariance(
            Bp, s.indices
        )


@pytest.mark.slow
def test_impedance_bootstrap_chunks_identical_on_every_engine(cluster, local):
    """The bootstrap's resamples in chunks of 10 as jobs, seeded per chunk: the same bands everywhere."""
    from closedloop.impedance.bootstrap import bootstrap
    from closedloop.impedance.data import onsets_from_events, segment
    from closedloop.impedance.estimate import EstimateOptions
    from closedloop.impedance.metrics import coverage
    from closedloop.impedance.model import ExperimentConfig
    from closedloop.impedance.simulation import simulate

    sim = simulate(ExperimentConfig(n_cycles=60, noise=0.05, seed=21))
    ens = segment(sim.record, onsets_from_events(sim.record))
    bands = {
        e: bootstrap(ens, EstimateOptions(), n_boot=40, seed=1, chunk=10, executor=e) for e in ("serial", local, "ray")
    }
    for e in (local, "ray"):
        for k in ("I", "B", "K", "wn", "zeta"):
            assert np.array_equal(bands[e].lo[k], bands["serial"].lo[k], equal_nan=True), (e, k)
            assert np.array_equal(bands[e].hi[k], bands["serial"].hi[k], equal_nan=True), (e, k)
    other = bootstrap(ens, EstimateOptions(), n_boot=40, seed=2, chunk=10)
    assert not np.array_equal(other.hi["K"], bands["serial"].hi["K"])
    assert coverage(bands["serial"].lo["K"], bands["serial"].hi["K"], sim.truth["K"]) > 0.7


@pytest.mark.slow
def test_simulate_sweep_on_every_engine_resumable_failure_isolated(cluster, local, tmp_path):
    """`simulate --seeds`: one dataset per seed, identical whichever engine ran it, finished seeds not
    redone, a failing scenario recorded without stopping the others."""
    from closedloop.cli.main import main
    from closedloop.cli.sweep import parse_seeds, run_sweep
    from closedloop.errors import InputError
    from closedloop.sims import SCENARIOS, simulate

    sc = SCENARIOS["panda_weld"]
    broken = dataclasses.replace(sc, name="broken_weld", tool_frame="no_such_frame")
    scen = {"panda_weld": sc, "broken_weld": broken}
    rows = {}
    for e in ("serial", local, "ray"):
        name = e if isinstance(e, str) else "local"
        rows[name] = run_sweep(scen, [0, 1], 8, tmp_path / name, engine=e)
        assert [(r.scenario, r.seed, r.status) for r in rows[name]] == [
            ("panda_weld", 0, "ok"),
            ("panda_weld", 1, "ok"),
            ("broken_weld", 0, "failed"),
            ("broken_weld", 1, "failed"),
        ]
        for seed in (0, 1):
            log = (tmp_path / name / "panda_weld" / f"seed_{seed:03d}" / "log.csv").read_bytes()
            assert log == (tmp_path / "serial" / "panda_weld" / f"seed_{seed:03d}" / "log.csv").read_bytes(), e
    assert "no_such_frame" in rows["serial"][2].error
    direct = simulate("panda_weld", 8, 1, tmp_path / "direct")
    assert (tmp_path / "direct" / "log.csv").read_bytes() == (
        tmp_path / "serial" / "panda_weld" / "seed_001" / "log.csv"
    ).read_bytes() and len(direct.readings) == 8
    # the CLI: one scenario -> OUT/seed_NNN; run again with more seeds: the finished ones are not redone
    out = tmp_path / "cli"
    assert (
        main(["simulate", "panda_weld", "--seeds", "0-1", "--n", "8", "--jobs", "2", "--out", str(out), "--quiet"]) == 0
    )
    mtime = (out / "seed_000" / "truth.json").stat().st_mtime_ns
    assert (
        main(["simulate", "panda_weld", "--seeds", "0-2", "--n", "8", "--jobs", "1", "--out", str(out), "--quiet"]) == 0
    )
    assert (out / "seed_000" / "truth.json").stat().st_mtime_ns == mtime
    with open(out / "sweep.csv") as fh:
        assert [r.split(",")[2] for r in fh.read().splitlines()[1:]] == ["resumed", "resumed", "ok"]
    assert (out / "seed_000" / "log.csv").read_bytes() == (
        tmp_path / "serial" / "panda_weld" / "seed_000" / "log.csv"
    ).read_bytes()
    assert (out / "seed_002" / "log.csv").read_bytes() != (out / "seed_000" / "log.csv").read_bytes()
    assert parse_seeds("0-3,7,2") == [0, 1, 2, 3, 7]
    with pytest.raises(InputError, match="runs backwards"):
        parse_seeds("5-2")


def test_simulate_without_seeds_is_one_dataset(tmp_path, capsys):
    """`--scenario X` (the singular of --scenarios) without --seeds writes one dataset into --out as before;
    --jobs without --seeds is a one-line input error."""
    from closedloop.cli.main import main

    assert (
        main(
            [
                "simulate",
                "--scenario",
                "panda_weld",
                "--n",
                "5",
                "--seed",
                "3",
                "--out",
                str(tmp_path / "one"),
                "--quiet",
            ]
        )
        == 0
    )
    assert (tmp_path / "one" / "truth.json").exists() and not (tmp_path / "one" / "seed_003").exists()
    capsys.readouterr()
    assert main(["simulate", "panda_weld", "--jobs", "2", "--out", str(tmp_path / "two")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--seeds" in err[0]


def big_sum(table: np.ndarray, payload: int) -> float:
    return float(table[payload].sum())


def test_large_shared_objects_travel_once_through_a_file(local):
    """A study's shared objects above 256 KiB go to the workers through one temporary file (not with
    every job); the values are right and the file is gone afterwards."""
    import glob
    import tempfile

    table = np.arange(40 * 10_000, dtype=float).reshape(40, 10_000)  # 3.2 MB pickled
    folders = ["/dev/shm", tempfile.gettempdir()]
    before = {p for f in folders for p in glob.glob(f"{f}/closedloop-shared-*")}
    assert ex.run(big_sum, range(40), local, shared=(table,)) == [float(r.sum()) for r in table]
    assert {p for f in folders for p in glob.glob(f"{f}/closedloop-shared-*")} == before


def test_sweep_refuses_to_overwrite_another_dataset(tmp_path):
    """A seed folder holding a dataset of another size or settings is not taken as finished, nor
    silently overwritten: an input error, unless --replace."""
    from closedloop.cli.main import main

    out = str(tmp_path / "s")
    assert main(["simulate", "panda_weld", "--seeds", "0", "--n", "5", "--jobs", "1", "--out", out, "--quiet"]) == 0
    assert main(["simulate", "panda_weld", "--seeds", "0", "--n", "6", "--jobs", "1", "--out", out, "--quiet"]) == 2
    assert (
        main(
            [
                "simulate",
                "panda_weld",
                "--seeds",
                "0",
                "--n",
                "5",
                "--set",
                "kp=90",
                "--jobs",
                "1",
                "--out",
                out,
                "--quiet",
            ]
        )
        == 2
    )
    assert (
        main(
            ["simulate", "panda_weld", "--seeds", "0", "--n", "6", "--jobs", "1", "--out", out, "--quiet", "--replace"]
        )
        == 0
    )
    import json

    assert json.loads((tmp_path / "s" / "seed_000" / "truth.json").read_text())["samples"]["recorded"] == 6
