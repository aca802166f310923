"""A fleet of simulated robots through `closedloop batch`, on the serial engine, a local pool and a
simulated multi-node Ray cluster: wall time, per-job overhead, throughput per core, the driver's peak
memory; and the extrapolation to 10,000 robots.

Usage::

    python benchmarks/bench_fleet.py [--robots 100 300 1000] [--configs 200] [--engines serial local ray split]
                                     [--rounds R] [--workers 2] [--out out/bench_fleet]

The fleet (`closedloop.studies.fleet`): Pandas welded to a fixture, one geometry, each robot with its
own joint offsets (1 mrad) and noise (1e-4 rad), `--configs` configurations per log, no k-fold or
region validation (one calibration per job, and its workspace accuracy).  Each engine runs the same command a fleet owner types, in its
own process (the driver), on a fresh output folder:

* ``serial``: ``closedloop batch fleet.yaml --jobs 1`` (the driver calibrates);
* ``local``: ``--jobs W`` (a pool of W worker processes);
* ``ray``: ``--ray ADDRESS``, a `ray.cluster_utils.Cluster` started here: a head that runs no tasks and
  W nodes of one CPU each, every one its own raylet, object store and workers (as separate machines,
  sharing this machine's cores and file system);
* ``split``: W serial commands at once, each on every W-th job of the fleet (``fleet-part1.yaml``...): W
  cores busy with the same jobs and no engine at all, the reference for what two jobs running side by
  side cost (caches, memory bandwidth and the hypervisor shared).

**Under the same load.**  On a shared machine a job's CPU time itself grows with the load (caches,
memory bandwidth, a hypervisor's other guests): 20 % between loads of 3 and 11 here.  Runs measured apart
are then not comparable, so ``--rounds R`` runs the engines in turn R times, the order reversed every
other round (S L R | R L S | ...: a load rising or falling over the rounds weighs on each engine alike),
and compares each engine with the serial run of its own round (`interleaved`: the ratio of the jobs' own
CPU and of the jobs per CPU second, per round, their median and range).  Every run records the load it
ran under: ``others_load``, the cores every other process on the machine kept busy meanwhile (the
machine's CPU time from /proc/stat less the command's own), beside the load average.

Figures, per engine and fleet size N (W workers; 1 for serial).  A job's own time is measured inside its
worker: the summary's ``seconds`` (wall) and ``cpu_seconds`` (CPU of the job's thread) of the whole job,
from reading its robot's files to publishing its folder.  Everything else is overhead:

* ``wall``: the command, start to exit (Python start, the pool or the connection to the cluster, the
  jobs, the summary);
* ``overhead/job wall`` = (wall x W - sum of the jobs' own wall times) / N: the time the workers did not
  spend in jobs (Python start, imports, dispatch, result transfer, idle workers at the start and the end);
* ``overhead/job CPU`` = (CPU of the driver and of every worker process - sum of the jobs' own CPU) / N:
  the same in CPU seconds, sampled from /proc every 0.1 s.  On a shared machine this is the figure to
  read: a process waiting for a core uses no CPU, while the wall figure grows with the load;
* ``driver CPU/job``: the driver process's CPU time per job (for serial it runs the jobs too);
* the Ray cluster's services (GCS, raylets, object stores, agents) are counted apart, in CPU seconds over
  the command: a cost of the cluster per second it runs, not of a job;
* ``marginal``: the overheads' increase between the two largest fleets, per added job, free of every
  fixed cost (start-up, imports, the tail): what one more job costs;
* ``per worker``: N / wall / W jobs per second; ``per CPU s``: N / the command's CPU seconds (the
  throughput per core: what a core busy with the command alone would do, whatever share of it the load
  left); each also as a ratio to the serial engine's at the same N (with ``--rounds``: of the same round);
* ``worker processes``: the processes below the driver (the pool's fork server, resource tracker and
  workers), or the Ray worker processes that ran during the command;
* ``resume``: the same command run again on the finished folders (nothing to run: reading the manifest
  and every job's record, the summary);
* ``driver peak``: the driver process's peak resident memory (VmHWM, sampled every 0.1 s).

The 10,000-robot figures are extrapolated from the two largest fleets run (method printed with them).

``--report N``: instead, the fleet report of N robots on two dates, two of them (``arm00017``,
``arm00064``) with joint 4's offset jumped by 800 urad on the second date, calibrated on the local pool;
writes ``fleet.json``, ``fleet.html`` and the plot (``--png``, the docs' figure) and prints the robots
that need attention first.

``--ray-jobs R``: instead, a job's own CPU in a Ray worker against a plain process, one job at a time in
both, R rounds in turn of the first ``--robots`` size (`ray_job_cpu`): whether a Ray worker makes a job
cost more than it does elsewhere, apart from two jobs running side by side.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path[:0] = [str(HERE), str(ROOT)]

from machine import header  # noqa: E402

from closedloop.studies.fleet import FleetDrift, FleetSpec, configurations, robot_name, write_fleet  # noqa: E402

#: the engines measured: ``split`` is W serial commands at once, each on every W-th job (no engine at all)
ENGINES = ["serial", "split", "local", "ray"]


def geometry(out: Path, n: int):
    """The fleet's geometry, drawn once and kept in `out` (drawing it takes tens of seconds)."""
    path = out / f"geometry-{n}.npz"
    if path.exists():
        z = np.load(path, allow_pickle=False)
        return str(z["model"]), [str(j) for j in z["joints"]], z["pool"], json.loads(str(z["truth"]))
    model, joints, pool, truth = configurations(n)
    out.mkdir(parents=True, exist_ok=True)
    np.savez(path, model=model, joints=np.array(joints), pool=pool, truth=json.dumps(truth))
    return model, joints, pool, truth


def _proc(pid: int) -> tuple[float, float]:
    """(peak resident memory in MB, CPU seconds) of a live process, from /proc."""
    hwm = 0.0
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                hwm = float(line.split()[1]) / 1024.0
    return hwm, _cpu(pid)


def _cpu(pid: int, thread: int | None = None) -> float:
    """CPU seconds (user + system) a live process has used (all its threads, not its children's), or one
    of its threads (`thread`: its id; the process's own id is its main thread)."""
    path = f"/proc/{pid}/stat" if thread is None else f"/proc/{pid}/task/{thread}/stat"
    with open(path) as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def _side_threads(pid: int) -> float:
    """CPU seconds a live process's threads other than its main thread have used (a Ray driver's or
    worker's own threads: its RPC, event loop and reporting threads; a job runs in the main thread)."""
    total = _cpu(pid)
    return total - _cpu(pid, pid)


def _tree_cpu(pids: list[int]) -> dict[int, float]:
    out = {}
    for pid in pids:
        try:
            out[pid] = _cpu(pid)
        except (OSError, IndexError, ValueError):
            pass
    return out


def _is_ray_worker(pid: int) -> bool:
    """A Ray worker process (titled ``ray::IDLE`` or ``ray::TASK``), not one of the cluster's services
    (GCS, raylets, object stores, and each node's agents, titled ``ray::DashboardAgent`` and
    ``ray::RuntimeEnvAgent``)."""
    try:
        title = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0]
    except OSError:
        return False
    return title.startswith(b"ray::") and not title.endswith(b"Agent")


def _machine_busy() -> float:
    """CPU seconds every process on this machine has used since boot (all CPUs), from /proc/stat."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    idle = f[3] + f[4]  # idle, iowait
    return (sum(f[:8]) - idle) / os.sysconf("SC_CLK_TCK")  # (guest time is counted in user already)


def run_driver(args: list[str], cluster: bool = False) -> dict:
    """`run_drivers` of one command."""
    return run_drivers([args], cluster)


def run_drivers(commands: list[list[str]], cluster: bool = False) -> dict:
    """Run ``closedloop batch ...`` once per command, all at once; their wall time (start to the last
    exit), the drivers' peak memory (the largest) and CPU time (summed), and the CPU time of the
    processes working for them meanwhile (below them: the pool's fork server and workers; with
    `cluster`, every process below this one: the Ray cluster's raylets, stores, services and workers),
    sampled every 0.1 s from /proc: a process's last sample counts (one that lives less than 0.1 s is
    missed), less what it had used before the drivers started; of the drivers' and the workers' CPU, the
    part their threads other than the main one used (``driver_side_cpu``, ``workers_side_cpu``: a job
    runs in its worker's main thread, Ray's own threads beside it).  ``others_load``: the cores every other
    process on the machine kept busy on average meanwhile (the machine's CPU time from /proc/stat, less
    this command's): the load the figures were measured under."""
    from closedloop.fleet.batch import descendants

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    before = _tree_cpu(descendants()) if cluster else {}
    busy0, t0 = _machine_busy(), time.perf_counter()
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "closedloop.cli.main", "batch", *args, "--quiet"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            text=True,
        )
        for args in commands
    ]
    drivers = {p.pid for p in procs}
    peak, cpu, seen, workers = 0.0, dict.fromkeys(drivers, 0.0), {}, set()
    side: dict[int, float] = {}  # drivers and workers: CPU of their threads but the main one (last sample)
    while any(p.poll() is None for p in procs):
        for p in procs:
            try:
                hwm, used = _proc(p.pid)
                peak, cpu[p.pid] = max(peak, hwm), max(cpu[p.pid], used)  # (an exited, unreaped one has no memory)
            except (OSError, IndexError, ValueError):
                pass
        below = descendants() if cluster else [q for p in procs for q in descendants(p.pid)]
        now = _tree_cpu([q for q in below if q not in drivers])
        workers.update(q for q in now if q not in workers and (not cluster or _is_ray_worker(q)))
        seen.update(now)
        for q in [*drivers, *workers]:
            try:
                side[q] = max(side.get(q, 0.0), _side_threads(q))
            except (OSError, IndexError, ValueError):
                pass
        time.sleep(0.1)
    outs = [p.communicate() for p in procs]
    wall, busy = time.perf_counter() - t0, _machine_busy() - busy0
    for p, (_, err) in zip(procs, outs):
        if p.returncode not in (0, 3):
            raise RuntimeError(f"batch exited {p.returncode}: {err[-2000:]}")
    if cluster:  # (the drivers' own children have ended with them)
        seen.update(_tree_cpu([q for q in descendants() if q not in drivers]))
    used = {pid: v - before.get(pid, 0.0) for pid, v in seen.items()}
    others = sum(v for pid, v in used.items() if pid in workers)
    services = sum(v for pid, v in used.items() if pid not in workers)
    ours = sum(cpu.values()) + others + services
    return {
        "wall": wall,
        "peak_mb": peak,
        "cpu": sum(cpu.values()),
        "others_cpu": others,
        "services_cpu": services,
        "driver_side_cpu": sum(side.get(q, 0.0) for q in drivers),
        "workers_side_cpu": sum(side.get(q, 0.0) for q in workers),
        "others_load": max(0.0, busy - ours) / wall,
        "worker_processes": len(workers),
        "code": max(p.returncode for p in procs),
    }


def forget(address: str) -> None:
    """Ray's cluster utilities note a new cluster as this machine's current one (``ray.init()`` with no
    address joins it): un-note it, so another program's ``ray.init()`` here starts its own."""
    from ray._private.utils import get_ray_address_file, read_ray_address

    if read_ray_address() == address:
        os.unlink(get_ray_address_file(None))


def start_cluster(workers: int, attempts: int = 3):
    """A head (no tasks) and `workers` nodes of one CPU.  Ray gives a node 30 s to register; on a
    loaded machine it may need more: up to `attempts` tries."""
    from ray.cluster_utils import Cluster

    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    for attempt in range(attempts):
        t0 = time.perf_counter()
        c = None
        try:
            c = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
            for _ in range(workers):
                c.add_node(num_cpus=1)
            c.wait_for_nodes()
            forget(c.address)  # another program's ray.init() here must not join this cluster
            return c, time.perf_counter() - t0
        except Exception as exc:
            if c is not None:
                c.shutdown()
            if attempt == attempts - 1:
                raise
            print(f"ray: the cluster did not start ({exc}); again", flush=True)
    raise AssertionError("unreachable")


def split(manifest: Path, parts: int) -> list[Path]:
    """The manifest's jobs in `parts` manifests beside it (``fleet-part1.yaml``...), every `parts`-th job
    in each: what `parts` serial commands at once run (the engine ``split``)."""
    import yaml

    doc = yaml.safe_load(manifest.read_text())
    out = []
    for k in range(parts):
        path = manifest.with_name(f"{manifest.stem}-part{k + 1}.yaml")
        path.write_text(yaml.safe_dump({**doc, "jobs": doc["jobs"][k::parts]}, sort_keys=False))
        out.append(path)
    return out


def measure(engine: str, n: int, folder: Path, geo, args, address: str | None, round_: int = 0) -> dict:
    """Run the fleet of `n` robots on `engine` from scratch, then the same command again (the resume)."""
    if folder.exists():
        shutil.rmtree(folder)
    manifest = write_fleet(folder, FleetSpec(robots=n, seed=n), geo)
    how = {"serial": ["--jobs", "1"], "split": ["--jobs", "1"], "local": ["--jobs", str(args.workers)]}
    how["ray"] = ["--ray", str(address)]
    manifests = split(manifest, args.workers) if engine == "split" else [manifest]
    commands = [[str(m), *how[engine]] for m in manifests]
    first = run_drivers(commands, cluster=engine == "ray")
    rows = []
    for m in manifests:  # (the rerun's rows give the job folders' times)
        with open(m.with_name(m.stem + ".summary.csv")) as fh:
            rows += list(csv.DictReader(fh))
    again = run_drivers(commands, cluster=engine == "ray")  # every folder finished: nothing to run
    assert len(rows) == n and all(r["status"] == "ok" for r in rows), "a job failed"
    seconds = np.array([float(r["seconds"]) for r in rows])
    cpu = np.array([float(r["cpu_seconds"]) for r in rows])
    return {
        "engine": engine,
        "robots": n,
        "workers": 1 if engine == "serial" else args.workers,
        "round": round_,
        "wall_s": first["wall"],
        "resume_s": again["wall"],
        "job_s": float(seconds.mean()),
        "sum_job_s": float(seconds.sum()),
        "job_cpu_s": float(cpu.mean()),
        "sum_job_cpu_s": float(cpu.sum()),
        "driver_peak_mb": first["peak_mb"],
        "driver_cpu_s": first["cpu"],
        "others_cpu_s": first["others_cpu"],
        "services_cpu_s": first["services_cpu"],
        "driver_side_cpu_s": first["driver_side_cpu"],
        "workers_side_cpu_s": first["workers_side_cpu"],
        "others_load": first["others_load"],
        "worker_processes": first["worker_processes"],
        "verdicts_ok": sum(r["verdict"] == "ok" for r in rows),
        "load": os.getloadavg()[0],
    }


def overhead(r: dict) -> float:
    """Wall seconds per job the W workers spent on anything but their jobs: (wall x W - sum of the jobs'
    own times) / N."""
    return (r["wall_s"] * r["workers"] - r["sum_job_s"]) / r["robots"]


def total_cpu(r: dict) -> float:
    """CPU seconds of the whole command: the driver, and every worker and service it kept busy."""
    return r["driver_cpu_s"] + r.get("others_cpu_s", 0.0)


def cpu_overhead(r: dict) -> float:
    """CPU seconds per job spent on anything but the jobs themselves: (CPU of the command - the jobs' own
    CPU) / N.  Load-independent, unlike the wall figure: a process waiting for a core uses none."""
    return (total_cpu(r) - r["sum_job_cpu_s"]) / r["robots"]


def per_core(r: dict) -> float:
    """Jobs per second per worker over the whole command."""
    return r["robots"] / r["wall_s"] / r["workers"]


def per_cpu(r: dict) -> float:
    """Jobs per CPU second of the whole command: what a core busy with it alone would do."""
    return r["robots"] / total_cpu(r)


def _pair(rows: list[dict], engine: str) -> tuple[dict, dict] | None:
    rs = sorted((r for r in rows if r["engine"] == engine), key=lambda r: r["robots"])
    return (rs[-2], rs[-1]) if len(rs) >= 2 else None


def marginal(rows: list[dict]) -> list[str]:
    """The overhead of one more job, free of every fixed cost (Python start, the workers' imports, the
    pool or the connection, the ramp-up and the tail): the difference of the total overheads of the two
    largest fleets divided by the difference of their sizes, in wall time ((wall x W - S) differences, S
    the sum of the jobs' own times) and in CPU time ((CPU of the command - the jobs' own CPU) differences)."""
    out = ["marginal overhead per job (between the two largest fleets of each engine):"]
    for engine in dict.fromkeys(r["engine"] for r in rows):
        pair = _pair(rows, engine)
        if pair is None or "sum_job_cpu_s" not in pair[0]:
            continue
        a, b = pair
        dn = b["robots"] - a["robots"]
        wall = (overhead(b) * b["robots"] - overhead(a) * a["robots"]) / dn
        job = (b["sum_job_s"] - a["sum_job_s"]) / dn
        cpu = (cpu_overhead(b) * b["robots"] - cpu_overhead(a) * a["robots"]) / dn
        job_cpu = (b["sum_job_cpu_s"] - a["sum_job_cpu_s"]) / dn
        out.append(
            f"  {engine:<6} {a['robots']} -> {b['robots']} robots: wall {wall * 1e3:+.1f} ms per job "
            f"({100 * wall / job:+.1f} % of a job's own {job:.3f} s); CPU {cpu * 1e3:+.1f} ms per job "
            f"({100 * cpu / job_cpu:+.1f} % of a job's own {job_cpu:.3f} s), of which the driver's "
            f"{(b['driver_cpu_s'] - a['driver_cpu_s']) * 1e3 / dn:.1f} ms; driver peak "
            f"{(b['driver_peak_mb'] - a['driver_peak_mb']) * 1024 / dn:+.2f} KB per robot"
        )
    return out


def extrapolate(rows: list[dict], n_target: int = 10_000) -> list[str]:
    """The 10,000-robot figures of each engine (method in the first line)."""
    lines = [
        f"extrapolation to {n_target} robots on the same W workers.  Method: the command's wall time, CPU time, "
        "the driver's peak memory and its CPU time on a line in N through the two largest fleets measured (the "
        "intercept: start-up and fixed costs; the slope: a job's own time / W plus its marginal overhead):"
    ]
    for engine in dict.fromkeys(r["engine"] for r in rows):
        pair = _pair(rows, engine)
        if pair is None:
            continue
        a, b = pair
        dn = b["robots"] - a["robots"]

        def at(f) -> float:
            return f(b) + (f(b) - f(a)) / dn * (n_target - b["robots"])

        w = b["workers"]
        lines.append(
            f"  {engine:<6} W={w}: wall {at(lambda r: r['wall_s']) / 3600:.2f} h "
            f"({(b['wall_s'] - a['wall_s']) / dn * 1e3:.0f} ms per robot); CPU {at(total_cpu) / 3600:.2f} h; "
            f"driver peak {at(lambda r: r['driver_peak_mb']):.0f} MB; driver CPU {at(lambda r: r['driver_cpu_s']):.0f} s"
        )
    lines.append(
        "  on C cores the jobs' part divides by C / W (the jobs are independent); the driver's CPU per job does "
        "not: one driver dispatches at most 1 / (its CPU per job) jobs per second"
    )
    return lines


def table(rows: list[dict]) -> list[str]:
    serial = {r["robots"]: r for r in rows if r["engine"] == "serial"}
    out = [
        "| engine | robots | workers | wall [s] | job wall / CPU [s] | overhead/job wall [ms] (% of job) "
        "| overhead/job CPU [ms] (% of job) | driver CPU/job [ms] | jobs/s per worker (vs serial) "
        "| jobs per CPU s (vs serial) | cluster services CPU [s] | resume [s] | driver peak [MB] | load |",
        "|" + "---|" * 14,
    ]
    for r in rows:
        if "sum_job_cpu_s" not in r:  # (measured before the jobs' CPU time was recorded)
            continue
        s = serial.get(r["robots"])
        vs = f" ({per_core(r) / per_core(s):.2f}x)" if s else ""
        vs_cpu = f" ({per_cpu(r) / per_cpu(s):.2f}x)" if s else ""
        out.append(
            f"| {r['engine']} | {r['robots']} | {r['workers']} | {r['wall_s']:.1f} | {r['job_s']:.3f} / "
            f"{r['job_cpu_s']:.3f} | {overhead(r) * 1e3:.1f} ({100 * overhead(r) / r['job_s']:.1f} %) | "
            f"{cpu_overhead(r) * 1e3:.1f} ({100 * cpu_overhead(r) / r['job_cpu_s']:.1f} %) | "
            f"{r['driver_cpu_s'] * 1e3 / r['robots']:.1f} | {per_core(r):.3f}{vs} | {per_cpu(r):.3f}{vs_cpu} | "
            f"{r.get('services_cpu_s', 0.0):.0f} | {r['resume_s']:.1f} | {r['driver_peak_mb']:.0f} | {_load(r)} |"
        )
    return out


STARTUP = r"""
import json, resource, sys, time

def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime

marks = [("start", time.perf_counter(), cpu())]
def mark(what):
    marks.append((what, time.perf_counter(), cpu()))

import ray
mark("import ray")
import closedloop.fleet.batch
import closedloop.parallel.engines
mark("import closedloop")
ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False)
mark("ray.init (connect)")

@ray.remote(num_cpus=1)
def start(i):
    import os, time
    time.sleep(0.5)  # (each task on its own node's worker)
    return os.getpid()

pids = ray.get([start.remote(i) for i in range(int(sys.argv[2]))])
mark("workers started (a task each)")

@ray.remote(num_cpus=1)
def warm(i):
    import importlib, os, time
    c = time.process_time()
    for m in closedloop.fleet.batch.run_row.needs:
        importlib.import_module(m)
    time.sleep(0.5)
    return os.getpid(), time.process_time() - c

needs = ray.get([warm.remote(i) for i in range(int(sys.argv[2]))])
mark("a job's imports in each worker")
print(json.dumps({"workers": pids, "imports_cpu": [c for _, c in needs]}), flush=True)
sys.stdin.readline()  # the benchmark samples the idle workers meanwhile
mark("idle")
ray.shutdown()
mark("ray.shutdown")
print(json.dumps([[w, round(t - t0, 3), round(c - c0, 3)] for (_, t0, c0), (w, t, c) in zip(marks, marks[1:])]))
"""


def ray_startup(workers: int, repeats: int, idle: float = 20.0) -> list[str]:
    """What Ray costs a batch before its first job and while it runs, apart from any job: a driver
    connecting to a running cluster (`start_cluster`), step by step (wall and the driver's CPU), the CPU of
    each worker process's start (Ray's own, then a job's imports, `run_row.needs`), and the CPU per second
    of wall of the driver, of each idle worker and of the cluster's services.  `repeats` drivers in turn."""
    from closedloop.fleet.batch import descendants

    cluster, startup = start_cluster(workers)
    lines = [f"ray: a head (no tasks) and {workers} nodes of 1 CPU started in {startup:.1f} s"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    try:
        for _ in range(repeats):
            p = subprocess.Popen(
                [sys.executable, "-c", STARTUP, cluster.address, str(workers)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                env=env,
                text=True,
            )
            assert p.stdin is not None and p.stdout is not None
            started = json.loads(p.stdout.readline())
            pids = started["workers"]
            services = [q for q in descendants() if q not in pids and q != p.pid]
            a, t0 = _tree_cpu([p.pid, *pids, *services]), time.perf_counter()
            time.sleep(idle)
            b, dt = _tree_cpu([p.pid, *pids, *services]), time.perf_counter() - t0
            worker_cpu = {q: a[q] for q in pids}  # (the workers' CPU before idling: their start, the imports)
            p.stdin.write("\n")
            p.stdin.flush()
            steps = json.loads(p.communicate()[0].splitlines()[-1])

            def rate(qs) -> float:
                return sum(b[q] - a[q] for q in qs if q in a and q in b) / dt * 1e3

            lines.append(
                "  driver: "
                + "; ".join(f"{w} {t:.2f} s wall, {c:.2f} s CPU" for w, t, c in steps if w != "idle")
                + f".  Each worker's start: {', '.join(f'{c:.2f}' for c in worker_cpu.values())} s of CPU, "
                + f"of which a job's imports {', '.join(f'{c:.2f}' for c in started['imports_cpu'])} s.  "
                + f"Idle, per second of wall: the driver {rate([p.pid]):.1f} ms of CPU, each worker "
                + f"{', '.join(f'{rate([q]):.1f}' for q in pids)} ms, the cluster's services "
                + f"{rate(services):.1f} ms.  Load: {_load({'load': os.getloadavg()[0]})}"
            )
            print(lines[-1], flush=True)
    finally:
        cluster.shutdown()
    return lines


ONE_BY_ONE = r"""
from closedloop.fleet.batch import run_row
from closedloop.fleet.manifest import read_manifest
from closedloop.parallel.engine import call, limit_threads, warm


def one_by_one(manifest):
    limit_threads()
    warm(run_row)
    return [call(run_row, i, job, None).cpu for i, job in enumerate(read_manifest(manifest))]
"""


def ray_job_cpu(n: int, rounds: int, out: Path, geo) -> list[str]:
    """A job's own CPU in a Ray worker against a plain process, one job at a time in both (no second
    job beside it): `rounds` rounds of the same `n` robots, in turn (the order reversed every other
    round), each in a fresh folder; the Ray worker (a cluster of one CPU started here) warm before the
    first round, the plain process (``python -c``, no Ray imported) a new one each round, its imports
    before the first job's clock as a worker's.  Whether running in a Ray worker makes a job cost more."""
    import ray

    namespace: dict = {}
    exec(ONE_BY_ONE, namespace)

    def fleet(tag: str) -> str:
        folder = out / "job-cpu" / tag
        if folder.exists():
            shutil.rmtree(folder)
        return str(write_fleet(folder, FleetSpec(robots=n, seed=n), geo))

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        remote = ray.remote(num_cpus=1)(namespace["one_by_one"])
        ray.get(remote.remote(fleet("warm")))
        cpu: dict[str, list[float]] = {"plain": [], "ray": []}
        for k in range(rounds):
            for how in ["plain", "ray"][:: -1 if k % 2 else 1]:
                manifest = fleet(f"{how}{k}")
                if how == "ray":
                    jobs = ray.get(remote.remote(manifest))
                else:
                    code = ONE_BY_ONE + "\nimport json, sys\nprint(json.dumps(one_by_one(sys.argv[1])))"
                    run = subprocess.run(
                        [sys.executable, "-c", code, manifest], capture_output=True, text=True, env=env
                    )
                    if run.returncode:
                        raise RuntimeError(run.stderr[-2000:])
                    jobs = json.loads(run.stdout.splitlines()[-1])
                cpu[how].append(float(np.mean(jobs)))
    finally:
        ray.shutdown()
    ratio = [r / p for r, p in zip(cpu["ray"], cpu["plain"])]
    return [
        f"a job's own CPU, one job at a time, {rounds} rounds of {n} robots: in a Ray worker "
        f"{np.mean(cpu['ray']):.4f} s, in a plain process {np.mean(cpu['plain']):.4f} s "
        f"({np.mean(cpu['ray']) / np.mean(cpu['plain']):.3f}x); per round {min(ratio):.2f}-{max(ratio):.2f}x, "
        f"median {np.median(ratio):.3f}x.  Load: {_load({'load': os.getloadavg()[0]})}"
    ]


def report_demo(n: int, out: Path, geo, workers: int, png: str | None) -> None:
    """The fleet report of `n` robots on two dates, two of them drifted (module docstring)."""
    from closedloop.fleet.report import fig_drift, fleet_report, read_summary, write_fleet_report

    folder = out / f"report-{n}"
    drifted = [robot_name(17), robot_name(64)]
    spec = FleetSpec(
        robots=n,
        dates=["2026-03-02", "2026-03-09"],
        seed=5,
        drift=[FleetDrift(r, "panda_joint4", 800e-6) for r in drifted],
    )
    manifest = write_fleet(folder, spec, geo)
    run = run_driver([str(manifest), "--jobs", str(workers)])
    report = fleet_report(read_summary(manifest.with_name("fleet.summary.csv")))
    write_fleet_report(report, folder / "fleet.json", folder / "fleet.html")
    if png:
        Path(png).write_bytes(fig_drift(report))
    print(f"{n} robots x 2 dates on {workers} workers: {run['wall']:.0f} s; drifted: {', '.join(drifted)}")
    print(f"attention: {report['attention']}")
    for r in report["robots"][:5]:
        print(f"  {r['robot']}: {r['attention']}, max |z| {r['drift']['max_z']}, {'; '.join(r['drift']['flagged'])}")
    print(f"wrote {folder / 'fleet.html'}" + (f" and {png}" if png else ""))


def _load(r: dict) -> str:
    """The load a run was measured under: the cores other processes kept busy meanwhile (``others_load``,
    measured since it is), and the load average at its end."""
    own = f"{r['others_load']:.2f} cores, " if "others_load" in r else ""
    return f"{own}avg {r['load']:.1f}"


def extra(engine: dict, serial: dict) -> dict[str, float]:
    """Where an engine's CPU per job goes beyond the serial engine's, in seconds per job (two runs of the
    same fleet): ``jobs``, the jobs' own CPU; ``driver``, the driver's main thread outside jobs (the
    serial driver runs the jobs: its CPU less theirs): imports, the manifest, dispatching and receiving,
    the summary; ``driver threads``, its other threads (Ray's RPC, event loop and reporting threads);
    ``workers``, the worker processes' main threads outside jobs (their start, imports, the engine's
    machinery per task); ``worker threads``, their other threads.  The parts add up to the difference of
    the whole commands' CPU per job; the cluster's services are not in it (counted apart)."""
    n = engine["robots"]
    runs_jobs = ("serial", "split")  # (engines whose drivers run the jobs)

    def driver(r: dict) -> float:
        return (
            r["driver_cpu_s"]
            - (r["sum_job_cpu_s"] if r["engine"] in runs_jobs else 0.0)
            - r.get("driver_side_cpu_s", 0.0)
        )

    def workers(r: dict) -> float:
        jobs = 0.0 if r["engine"] in runs_jobs else r["sum_job_cpu_s"]
        return r.get("others_cpu_s", 0.0) - jobs - r.get("workers_side_cpu_s", 0.0)

    out = {
        "jobs": (engine["sum_job_cpu_s"] - serial["sum_job_cpu_s"]) / n,
        "driver": (driver(engine) - driver(serial)) / n,
        "driver threads": (engine.get("driver_side_cpu_s", 0.0) - serial.get("driver_side_cpu_s", 0.0)) / n,
        "workers": (workers(engine) - workers(serial)) / n,
        "worker threads": (engine.get("workers_side_cpu_s", 0.0) - serial.get("workers_side_cpu_s", 0.0)) / n,
    }
    if "driver_side_cpu_s" not in engine or "driver_side_cpu_s" not in serial:  # (not measured: in the main parts)
        del out["driver threads"], out["worker threads"]
    return out


def interleaved(rows: list[dict]) -> list[str]:
    """Each engine against the serial engine of the same round (`--rounds`: the engines run in turn, the
    order reversed every other round, so a load that rises or falls over the rounds weighs on each
    alike): per round the ratio of the jobs' own CPU (engine / serial) and of the jobs per CPU second of
    the whole command (engine / serial; within 10 %: 0.90 or more), and the other processes' load
    during each of the two runs, and where the engine's extra CPU per job goes (`extra`); then the median
    and the range over the rounds."""
    rounds: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        if "session" in r:
            rounds.setdefault((r["session"], r["robots"], r["round"]), {})[r["engine"]] = r
    out = ["interleaved rounds, each engine against the serial run of the same round:"]
    engines = dict.fromkeys(e for rs in rounds.values() for e in rs if e != "serial")
    for engine in engines:
        pairs = [(rs["serial"], rs[engine]) for rs in rounds.values() if "serial" in rs and engine in rs]
        if not pairs:
            continue
        job = [b["job_cpu_s"] / a["job_cpu_s"] for a, b in pairs]
        cpu = [per_cpu(b) / per_cpu(a) for a, b in pairs]
        for (a, b), j, c in zip(pairs, job, cpu):
            out.append(
                f"  {engine:<6} {b['robots']} robots, round {b['round']}: job CPU {b['job_cpu_s']:.3f} s against "
                f"serial's {a['job_cpu_s']:.3f} ({j:.2f}x); jobs per CPU s {per_cpu(b):.2f} against "
                f"{per_cpu(a):.2f} ({c:.2f}x); others' load {b.get('others_load', float('nan')):.2f} and "
                f"{a.get('others_load', float('nan')):.2f} cores"
            )
            if a["robots"] == b["robots"]:
                x = extra(b, a)
                out.append(
                    "           its CPU per job beyond serial's: "
                    + ", ".join(f"{k} {v * 1e3:+.1f} ms" for k, v in x.items())
                    + f" ({sum(x.values()) * 1e3:+.1f} ms, {100 * sum(x.values()) / a['job_cpu_s']:+.1f} % of a job)"
                )
        out.append(
            f"  {engine:<6} median over {len(pairs)} round(s): job CPU {np.median(job):.2f}x "
            f"({min(job):.2f}-{max(job):.2f}), jobs per CPU s {np.median(cpu):.2f}x ({min(cpu):.2f}-{max(cpu):.2f})"
        )
    return out if len(out) > 1 else []


def all_results(path: Path) -> list[dict]:
    """Every measurement in `path` (one JSON object a line), in the order made."""
    rows = [json.loads(text) for text in path.read_text().splitlines()]
    for r in rows:
        r.setdefault("resume_s", r.get("fixed_s", float("nan")))  # (named so by an earlier version)
    return rows


def load_results(path: Path) -> list[dict]:
    """The latest measurement of each engine and fleet size in `path`."""
    latest = {(r["engine"], r["robots"]): r for r in all_results(path)}
    return sorted(latest.values(), key=lambda r: (r["robots"], ENGINES.index(r["engine"])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--configs", type=int, default=200)
    ap.add_argument("--engines", nargs="+", default=["serial", "local", "ray"], choices=ENGINES)
    ap.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="run the engines in turn this many times (the order reversed every other round)",
    )
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="out/bench_fleet")
    ap.add_argument("--report", type=int, metavar="N", help="the fleet report of N robots on two dates instead")
    ap.add_argument("--png", help="with --report: write the report's plot here too")
    ap.add_argument(
        "--ray-jobs",
        type=int,
        metavar="R",
        help="instead, a job's own CPU in a Ray worker against a plain process, one job at a time, R rounds "
        "of the first --robots size (`ray_job_cpu`)",
    )
    ap.add_argument("--table", action="store_true", help="only print the table of the measurements in --out")
    ap.add_argument(
        "--ray-startup",
        type=int,
        metavar="R",
        help="instead, what Ray costs a batch apart from its jobs (`ray_startup`), R drivers in turn",
    )
    args = ap.parse_args()
    out = Path(args.out)
    if args.table:
        every = all_results(out / "results.jsonl")
        rows = load_results(out / "results.jsonl")
        for line in [*table(rows), "", *marginal(rows), "", *extrapolate(rows), "", *interleaved(every)]:
            print(line)
        return
    print(header(), flush=True)
    if args.ray_startup:
        ray_startup(args.workers, args.ray_startup)
        return
    geo = geometry(out, args.configs)
    if args.report:
        report_demo(args.report, out, geo, args.workers, args.png)
        return
    if args.ray_jobs:
        for line in ray_job_cpu(args.robots[0], args.ray_jobs, out, geo):
            print(line)
        return
    cluster, address = None, None
    if "ray" in args.engines:
        cluster, startup = start_cluster(args.workers)
        address = cluster.address
        print(f"ray: a head (no tasks) and {args.workers} nodes of 1 CPU started in {startup:.1f} s", flush=True)
    results = out / "results.jsonl"  # every measurement of every run, so sizes run apart are tabled together
    session = time.strftime("%Y-%m-%dT%H:%M:%S")
    try:
        for n in args.robots:
            for k in range(args.rounds):
                for engine in args.engines[:: -1 if k % 2 else 1]:
                    r = {**measure(engine, n, out / f"{engine}-{n}", geo, args, address, k), "session": session}
                    line = json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()})
                    print(line, flush=True)
                    with open(results, "a") as fh:
                        fh.write(line + "\n")
    finally:
        if cluster is not None:
            cluster.shutdown()
    rows = load_results(results)
    this = [r for r in all_results(results) if r.get("session") == session]
    for line in [*table(rows), "", *marginal(rows), "", *extrapolate(rows), "", *interleaved(this)]:
        print(line)
    print(header())


if __name__ == "__main__":
    main()
