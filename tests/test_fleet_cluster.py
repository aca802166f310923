"""`closedloop batch` on a simulated multi-node Ray cluster (`ray.cluster_utils.Cluster`: a head that runs
no tasks and two nodes of one CPU, on this machine), with faults: a node killed while it runs a job, the
driver killed with SIGKILL mid-batch and the same command run again, a job that hangs past
`--job-timeout`, a robot whose log holds a value that is not a number.  Each ends with every job done
exactly once (counted from the job folders and the summary's rows) and the summary whole.

Signals wait for markers, never for a delay: a node is killed when one of its worker processes carries
Ray's title of a running task (``ray::_ray_call``), the driver when three job folders are published; a
hanging job is a log that is a named pipe no one writes (a stalled network mount), which blocks the job
in ``open``.
"""

from __future__ import annotations

import csv
import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

# Ray is imported by the tests that run (all slow), not when a worker collects this file (0.8 s)
if importlib.util.find_spec("ray") is None:
    pytest.skip("the test extra installs Ray", allow_module_level=True)

from closedloop.fleet.batch import MARKER  # noqa: E402
from closedloop.studies.fleet import FleetSpec, configurations, robot_name, write_fleet  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATE = "2026-03-02"


@pytest.fixture(scope="module")
def geometry():
    """The fleet's Panda weld geometry: 40 configurations over the whole self-motion."""
    return configurations(40)


def forget(address: str) -> None:
    """Ray's cluster utilities note a new cluster as this machine's current one (``ray.init()`` with no
    address joins it): un-note it, so another program's ``ray.init()`` here starts its own."""
    from ray._private.utils import get_ray_address_file, read_ray_address

    if read_ray_address() == address:
        os.unlink(get_ray_address_file(None))


@pytest.fixture(scope="module")
def cluster():
    """Three Ray nodes on this machine: a head with no CPU for tasks (it runs the cluster's services),
    two nodes of one CPU each; a dead node is noticed within ~2 s (health checks every 0.5 s)."""
    from ray.cluster_utils import Cluster

    env = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env]))  # the workers import closedloop
    head = {
        "num_cpus": 0,
        "include_dashboard": False,
        "_system_config": {
            "health_check_initial_delay_ms": 0,
            "health_check_period_ms": 500,
            "health_check_failure_threshold": 4,
        },
    }
    c = None
    try:
        for attempt in range(3):  # Ray gives a node 30 s to register: a loaded machine may need another try
            try:
                c = Cluster(initialize_head=True, head_node_args=head)
                nodes = [c.add_node(num_cpus=1) for _ in range(2)]
                c.wait_for_nodes()
                break
            except Exception:
                if c is not None:
                    c.shutdown()
                    c = None
                if attempt == 2:
                    raise
        assert c is not None
        forget(c.address)  # another program's ray.init() here must not join this cluster
        yield c, nodes
    finally:
        if c is not None:
            c.shutdown()
        if env is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = env


def batch(manifest: Path, address: str, *extra: str) -> subprocess.Popen:
    """`closedloop batch MANIFEST --ray ADDRESS` as a fleet owner runs it, in its own process."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.Popen(
        [sys.executable, "-m", "closedloop.cli.main", "batch", str(manifest), "--ray", address, "--quiet", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )


def summary(manifest: Path) -> list[dict]:
    with open(manifest.with_name("fleet.summary.csv")) as fh:
        return list(csv.DictReader(fh))


def published(folder: Path) -> list[str]:
    """The jobs whose folder is finished (its marker written, the folder renamed into place): not a hidden
    temporary folder that holds its marker but is not renamed yet (``.NAME.tmp-*``, `io.files.OutputSet`)."""
    return sorted(
        p.parent.name for p in (folder / "calibrated").glob(f"*/{MARKER}") if not p.parent.name.startswith(".")
    )


def task_processes(raylet_pid: int | None = None) -> list[int]:
    """Worker processes running a task now (Ray titles them ``ray::_ray_call`` while they do), below
    `raylet_pid` when given."""
    from closedloop.fleet.batch import descendants

    pids = descendants(raylet_pid) if raylet_pid else [int(p) for p in os.listdir("/proc") if p.isdigit()]
    out = []
    for pid in pids:
        try:
            if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(b"ray::_ray_call"):
                out.append(pid)
        except OSError:
            continue
    return out


def wait_for(what: str, test, seconds: float = 120.0, proc: subprocess.Popen | None = None):
    """Poll `test` (every 20 ms) until it is true; fail after `seconds`, or when `proc` ended first."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        value = test()
        if value:
            return value
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"the batch ended before {what}: {proc.communicate()[1][-2000:]}")
        time.sleep(0.02)
    pytest.fail(f"no {what} within {seconds:.0f} s")


def every_job_once(manifest: Path, names: list[str]) -> list[dict]:
    """Every job has one finished folder and one summary row; returns the rows."""
    rows = summary(manifest)
    assert sorted(r["name"] for r in rows) == sorted(names)  # the summary whole, each job once
    assert published(manifest.parent) == sorted(names)  # each job's folder published once
    return rows


@pytest.mark.slow
def test_a_bad_robot_and_a_hanging_one_do_not_stop_the_others(tmp_path, geometry, cluster):
    c, _ = cluster
    spec = FleetSpec(robots=4, dates=[DATE], seed=1)
    bad, stuck = robot_name(1), robot_name(2)
    manifest = write_fleet(tmp_path, spec, geometry, bad=(bad,))
    log = tmp_path / "logs" / f"{stuck}-{DATE}.csv"
    log.unlink()
    os.mkfifo(log)  # its job blocks reading it, as on a network mount that stopped answering
    t0 = time.monotonic()
    p = batch(manifest, c.address, "--job-timeout", "4")
    out, err = p.communicate(timeout=180)
    assert p.returncode == 1, err  # a job could not run
    rows = {r["name"]: r for r in summary(manifest)}
    assert len(rows) == 4
    assert rows[f"{bad}-{DATE}"]["status"] == "failed"
    assert "n/a" in rows[f"{bad}-{DATE}"]["error"] and "\n" not in rows[f"{bad}-{DATE}"]["error"]
    assert rows[f"{stuck}-{DATE}"]["status"] == "failed"
    assert rows[f"{stuck}-{DATE}"]["error"].startswith("JobTimeout: stopped after 4 s"), rows[f"{stuck}-{DATE}"]
    # ran to its limit; stopped by the soft one (the message above: the hard one ends the worker, recorded as a
    # crash), however late a loaded machine lets the job's handler run
    assert float(rows[f"{stuck}-{DATE}"]["seconds"]) >= 4.0
    ok = [n for n, r in rows.items() if r["status"] == "ok"]
    assert sorted(ok) == [f"{robot_name(i)}-{DATE}" for i in (0, 3)]
    assert published(tmp_path) == sorted(ok)
    assert all(rows[n]["verdict"] == "ok" for n in ok)
    assert f"failed: {stuck}-{DATE}: JobTimeout" in err and f"failed: {bad}-{DATE}:" in err
    assert time.monotonic() - t0 < 120


@pytest.mark.slow
def test_the_driver_killed_then_run_again_resumes(tmp_path, geometry, cluster):
    import ray

    c, nodes = cluster
    raylets = [node.all_processes[ray._private.ray_constants.PROCESS_TYPE_RAYLET][0].process.pid for node in nodes]
    n = 10
    manifest = write_fleet(tmp_path, FleetSpec(robots=n, dates=[DATE], seed=2), geometry)
    names = [f"{robot_name(i)}-{DATE}" for i in range(n)]
    p = batch(manifest, c.address)
    wait_for("three published jobs", lambda: len(published(tmp_path)) >= 3, proc=p)
    p.send_signal(signal.SIGKILL)
    p.communicate()
    # Ray ends the dead driver's tasks; a task that was writing its folder may publish it first
    # (this cluster's: another Ray cluster on the machine may be running tasks of its own)
    wait_for("the dead driver's tasks ended", lambda: not any(task_processes(r) for r in raylets), seconds=60)
    before = published(tmp_path)
    assert 3 <= len(before) < n
    p = batch(manifest, c.address)
    out, err = p.communicate(timeout=180)
    assert p.returncode == 0, err
    rows = every_job_once(manifest, names)
    assert sorted(r["name"] for r in rows if r["resumed"] == "yes") == before  # not redone
    assert all(r["status"] == "ok" and r["verdict"] == "ok" for r in rows)
    assert f"{n - len(before)} job(s) run on ray" in out and f"{len(before)} finished earlier" in out
    assert not list((tmp_path / "calibrated").glob(".*tmp-*"))  # the killed run's temporaries removed


@pytest.mark.slow
def test_a_node_killed_mid_batch_its_jobs_run_elsewhere(tmp_path, geometry, cluster):
    import ray

    c, nodes = cluster
    n = 10
    manifest = write_fleet(tmp_path, FleetSpec(robots=n, dates=[DATE], seed=3), geometry)
    names = [f"{robot_name(i)}-{DATE}" for i in range(n)]
    victim = nodes[0]
    raylet = victim.all_processes[ray._private.ray_constants.PROCESS_TYPE_RAYLET][0].process.pid
    p = batch(manifest, c.address)
    wait_for("a published job", lambda: published(tmp_path), proc=p)  # the batch is under way
    wait_for("a job running on the node", lambda: task_processes(raylet), proc=p)
    c.remove_node(victim, allow_graceful=False)  # SIGKILL to the node's raylet, store and workers
    out, err = p.communicate(timeout=180)
    assert p.returncode == 0, err
    rows = every_job_once(manifest, names)
    assert all(r["status"] == "ok" and r["verdict"] == "ok" and r["resumed"] == "no" for r in rows)
    assert f"{n} job(s) run on ray" in out
