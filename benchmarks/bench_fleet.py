"""A fleet of simulated robots through `closedloop batch`, on the serial engine, a local pool and a
simulated multi-node Ray cluster: wall time, per-job overhead, throughput per core, the driver's peak
memory; and the extrapolation to 10,000 robots.

Usage::

    python benchmarks/bench_fleet.py [--robots 100 300 1000] [--configs 200] [--engines serial local ray]
                                     [--workers 2] [--out out/bench_fleet]

The fleet (`closedloop.studies.fleet`): Pandas welded to a fixture, one geometry, each robot with its
own joint offsets (1 mrad) and noise (1e-4 rad), `--configs` configurations per log, no k-fold
validation (one calibration per job).  Each engine runs the same command a fleet owner types, in its
own process (the driver), on a fresh output folder:

* ``serial``: ``closedloop batch fleet.yaml --jobs 1`` (the driver calibrates);
* ``local``: ``--jobs W`` (a pool of W worker processes);
* ``ray``: ``--ray ADDRESS``, a `ray.cluster_utils.Cluster` started here: a head that runs no tasks and
  W nodes of one CPU each, every one its own raylet, object store and workers (as separate machines,
  sharing this machine's cores and file system).

Figures, per engine and fleet size N (W workers; 1 for serial):

* ``wall``: the command, start to exit (Python start, the pool or the connection to the cluster, the
  jobs, the summary);
* ``fixed``: the same command run again on the finished folders (nothing to do: start-up, reading the
  manifest and the N job records, the summary): the cost that does not scale with the jobs run;
* ``job``: mean of the jobs' own times (the summary's ``seconds``, measured inside the job);
* ``overhead/job`` = ((wall - fixed) x W - sum of the jobs' times) / N: dispatch, result transfer,
  workers idle at the start and the end, in ms and as a share of a job's own time;
* ``per core``: jobs per second per worker, (N / (wall - fixed)) / W, and its ratio to the serial
  engine's;
* ``driver peak``: the driver process's peak resident memory (VmHWM, sampled every 0.1 s) and its CPU
  time (the pool's or the cluster's workers not included).

The 10,000-robot figures are extrapolated from the largest fleet run (method printed with them).

``--report N``: instead, the fleet report of N robots on two dates, two of them (``arm00017``,
``arm00064``) with joint 4's offset jumped by 800 urad on the second date, calibrated on the local pool;
writes ``fleet.json``, ``fleet.html`` and the plot (``--png``, the docs' figure) and prints the robots
that need attention first.
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
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return hwm, (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def run_driver(args: list[str]) -> dict:
    """Run `closedloop batch ...`; its wall time, exit code and the driver's peak memory and CPU time."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-m", "closedloop.cli.main", "batch", *args, "--quiet"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )
    peak, cpu = 0.0, 0.0
    while p.poll() is None:
        try:
            hwm, used = _proc(p.pid)
            peak, cpu = max(peak, hwm), max(cpu, used)  # (an exited, unreaped process has no memory lines)
        except (OSError, IndexError, ValueError):
            pass
        time.sleep(0.1)
    out, err = p.communicate()
    wall = time.perf_counter() - t0
    if p.returncode not in (0, 3):
        raise RuntimeError(f"batch exited {p.returncode}: {err[-2000:]}")
    return {"wall": wall, "peak_mb": peak, "cpu": cpu, "code": p.returncode}


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


def measure(engine: str, n: int, folder: Path, geo, args, address: str | None) -> dict:
    if folder.exists():
        shutil.rmtree(folder)
    manifest = write_fleet(folder, FleetSpec(robots=n, seed=n), geo)
    how = {"serial": ["--jobs", "1"], "local": ["--jobs", str(args.workers)], "ray": ["--ray", str(address)]}[engine]
    first = run_driver([str(manifest), *how])
    with open(manifest.with_name("fleet.summary.csv")) as fh:  # (the rerun's rows give the job folders' times)
        rows = list(csv.DictReader(fh))
    again = run_driver([str(manifest), *how])  # every folder finished: the fixed cost alone
    assert len(rows) == n and all(r["status"] == "ok" for r in rows), "a job failed"
    seconds = np.array([float(r["seconds"]) for r in rows])
    w = 1 if engine == "serial" else args.workers
    run = first["wall"] - again["wall"]
    overhead = (run * w - seconds.sum()) / n
    return {
        "engine": engine,
        "robots": n,
        "workers": w,
        "wall_s": first["wall"],
        "fixed_s": again["wall"],
        "job_s": float(seconds.mean()),
        "sum_job_s": float(seconds.sum()),
        "run_s": run,
        "overhead_ms": overhead * 1e3,
        "overhead_pct": 100.0 * overhead / seconds.mean(),
        "per_core_jobs_s": n / run / w,
        "driver_peak_mb": first["peak_mb"],
        "driver_cpu_s": first["cpu"],
        "verdicts_ok": sum(r["verdict"] == "ok" for r in rows),
        "load": os.getloadavg()[0],
    }


def marginal(rows: list[dict]) -> list[str]:
    """The overhead of one more job, free of every fixed cost (Python start, the workers' imports, the
    pool or the connection, the ramp-up and the tail): the difference of the total overheads of the two
    largest fleets, ((run2 x W - S2) - (run1 x W - S1)) / (N2 - N1), S the sum of the jobs' own times."""
    out = ["marginal overhead per job (between the two largest fleets of each engine):"]
    for engine in dict.fromkeys(r["engine"] for r in rows):
        rs = sorted((r for r in rows if r["engine"] == engine), key=lambda r: r["robots"])
        if len(rs) < 2:
            continue
        a, b = rs[-2], rs[-1]
        w = b["workers"]
        per = ((b["run_s"] * w - b["sum_job_s"]) - (a["run_s"] * w - a["sum_job_s"])) / (b["robots"] - a["robots"])
        job = (b["sum_job_s"] - a["sum_job_s"]) / (b["robots"] - a["robots"])
        out.append(
            f"  {engine:<6} {a['robots']} -> {b['robots']} robots: {per * 1e3:+.1f} ms per job, {100 * per / job:+.1f} % "
            f"of a job's own {job:.3f} s"
        )
    return out


def _line(rs: list[dict], key: str) -> tuple[float, float]:
    """Intercept and slope in N of `key` through the two largest fleets (one fleet: a constant)."""
    if len(rs) < 2:
        return rs[-1][key], 0.0
    a, b = rs[-2], rs[-1]
    slope = (b[key] - a[key]) / (b["robots"] - a["robots"])
    return b[key] - slope * b["robots"], slope


def extrapolate(rows: list[dict], n_target: int = 10_000) -> list[str]:
    """The 10,000-robot figures of each engine (method in the first line)."""
    lines = [
        f"extrapolation to {n_target} robots, per engine on its W workers.  Method: wall = fixed(N) + N x "
        "(job + overhead) / W, with job the mean job time and overhead the marginal overhead per job of the "
        "two largest fleets (one fleet: its overall overhead); fixed(N), the driver's peak memory and its CPU "
        "time on a line through the two largest fleets (one fleet: held constant, growth unknown):"
    ]
    for engine in dict.fromkeys(r["engine"] for r in rows):
        rs = sorted((r for r in rows if r["engine"] == engine), key=lambda r: r["robots"])
        big, w = rs[-1], rs[-1]["workers"]
        if len(rs) >= 2:
            a = rs[-2]
            dn = big["robots"] - a["robots"]
            over = ((big["run_s"] * w - big["sum_job_s"]) - (a["run_s"] * w - a["sum_job_s"])) / dn
            job = (big["sum_job_s"] - a["sum_job_s"]) / dn
        else:
            over, job = big["overhead_ms"] / 1e3, big["job_s"]
        f0, f1 = _line(rs, "fixed_s")
        m0, m1 = _line(rs, "driver_peak_mb")
        c0, c1 = _line(rs, "driver_cpu_s")
        fixed = f0 + f1 * n_target
        wall = fixed + n_target * (job + over) / w
        lines.append(
            f"  {engine:<6} W={w}: wall {wall / 3600:.2f} h (fixed {fixed:.0f} s + {n_target} x ({job:.3f} s + "
            f"{over * 1e3:.1f} ms) / {w}); driver peak {m0 + m1 * n_target:.0f} MB ({m1 * 1024:+.2f} KB per robot); "
            f"driver CPU {c0 + c1 * n_target:.0f} s ({c1 * 1e3:.2f} ms per robot: at most "
            f"{1 / c1 if c1 > 0 else float('inf'):.0f} jobs/s from one driver)"
        )
    lines.append("  on C cores the job part divides by C (the jobs are independent); the driver's CPU per job does not")
    return lines


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[100, 300])
    ap.add_argument("--configs", type=int, default=200)
    ap.add_argument("--engines", nargs="+", default=["serial", "local", "ray"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="out/bench_fleet")
    ap.add_argument("--report", type=int, metavar="N", help="the fleet report of N robots on two dates instead")
    ap.add_argument("--png", help="with --report: write the report's plot here too")
    args = ap.parse_args()
    out = Path(args.out)
    print(header(), flush=True)
    geo = geometry(out, args.configs)
    if args.report:
        report_demo(args.report, out, geo, args.workers, args.png)
        return
    cluster, address = None, None
    if "ray" in args.engines:
        cluster, startup = start_cluster(args.workers)
        address = cluster.address
        print(f"ray: a head (no tasks) and {args.workers} nodes of 1 CPU started in {startup:.1f} s", flush=True)
    results = out / "results.jsonl"  # every measurement of every run, so sizes run apart are tabled together
    try:
        for n in args.robots:
            for engine in args.engines:
                r = measure(engine, n, out / f"{engine}-{n}", geo, args, address)
                line = json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()})
                print(line, flush=True)
                with open(results, "a") as fh:
                    fh.write(line + "\n")
    finally:
        if cluster is not None:
            cluster.shutdown()
    latest = {}
    for text in results.read_text().splitlines():  # the latest measurement of each engine and size
        r = json.loads(text)
        latest[(r["engine"], r["robots"])] = r
    rows = sorted(latest.values(), key=lambda r: (r["robots"], ["serial", "local", "ray"].index(r["engine"])))
    serial = {r["robots"]: r["per_core_jobs_s"] for r in rows if r["engine"] == "serial"}
    print(
        f"\n| engine | robots | workers | wall [s] | fixed [s] | job [s] | overhead/job [ms] (% of job) "
        f"| jobs/s per core (vs serial) | driver peak [MB] | driver CPU [s] |\n|{'---|' * 10}"
    )
    for r in rows:
        ratio = f" ({r['per_core_jobs_s'] / serial[r['robots']]:.2f}x)" if r["robots"] in serial else ""
        print(
            f"| {r['engine']} | {r['robots']} | {r['workers']} | {r['wall_s']:.1f} | {r['fixed_s']:.1f} | "
            f"{r['job_s']:.3f} | {r['overhead_ms']:.1f} ({r['overhead_pct']:.1f} %) | {r['per_core_jobs_s']:.3f}{ratio} | "
            f"{r['driver_peak_mb']:.0f} | {r['driver_cpu_s']:.1f} |"
        )
    print()
    for line in marginal(rows):
        print(line)
    print()
    for line in extrapolate(rows):
        print(line)
    print(header())


if __name__ == "__main__":
    main()
