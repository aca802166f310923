"""Scaling out: 200 calibrations and a 200-draw Monte Carlo on each engine of closedloop.parallel.executor.

Usage::

    python benchmarks/bench_scale.py [--jobs 200] [--draws 200] [--configs 60] [--engines serial local ray]
    python benchmarks/bench_scale.py --cli [--rows 1000 10000 100000]
    python benchmarks/bench_scale.py --cli --load [--rows 1000 10000 100000 1000000]

``--cli``: one long log through the command line.  The README's main job (``panda_weld``, 1,000 simulated
configurations) tiled to each size with 1e-4 rad of fresh noise per row, then ``closedloop calibrate ...
--cv 0 --quiet`` as a child process: its wall time, CPU (user + system) and peak RSS (``os.wait4``'s
rusage of that child), against the floor, Pinocchio's forward kinematics and a LOCAL frame Jacobian over
the same rows (``floor.pinocchio_floor``).  The cost should grow no faster than the rows.

``--cli --load``: what the same command spends before its fit, per size, in a child process stopped once its
inputs are loaded: the CPU from the interpreter's start to the first line of ``run.inputs.load_inputs``
(imports, the parser), ``load_inputs`` itself, and of it reading the log (``io.joint_log.read_joint_log``)
and the gravity torques (``RobotModel.with_gravity_torques``); beside them what NumPy alone takes to read
the file (``np.loadtxt``) and Pinocchio alone to compute the same torques (``computeGeneralizedGravity``, a
call per row); and the CPU of ``closedloop calibrate --help``.

Engines: ``serial`` (this process, one BLAS thread), ``local`` (2 worker
processes), ``ray`` (a local Ray cluster started here with 2 CPUs).  For each:

* ``startup``: creating the engine and running 2 no-op jobs (pool / cluster start);
* ``no-op ms/job``: 400 no-op jobs on the warm engine, wall / 400: the
  dispatch cost of one job (pickling, queues, the scheduler);
* ``wall``: the workload on the warm engine; ``speedup`` = serial wall / wall;
* ``overhead ms/job`` = (wall x workers - sum of the jobs' own times) / jobs:
  what running a job elsewhere costs beyond the job itself (dispatch, result
  transfer, idle workers at the end);
* ``identical``: every result equal, bit for bit, to the serial run.

Then a projection of a nightly fleet of 10,000 robots on 100 nodes from the
measured job time and overheads: on paper, stated as such, never run.

``--studies`` adds the other studies on the same warm engines (wall, speedup, identical to serial):
``simulate`` over 20 seeds (panda_weld, 100 configurations each, ``cli_sweep.run_sweep``), the
impedance bootstrap (200 resamples in chunks of 25) and pose selection on 20 candidate pools
(``poses.select_pools``, exchange-A, K = 12 of 40).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from machine import header  # benchmarks/machine.py

from closedloop import CalibrationOptions, calibrate
from closedloop.io.logs import JointLog
from closedloop.parallel import executor as ex
from closedloop.studies.montecarlo import monte_carlo, weld_scenario

NOISE = 1e-4


def noop(payload: int) -> int:
    return payload


def calibration_job(robot, joints, loops, theta, opts, i: int, rng: np.random.Generator) -> np.ndarray:
    """One robot's calibration: its own noisy readings (its own seed), the weld loop, 1e-4 rad noise."""
    th = theta + rng.normal(0.0, NOISE, theta.shape)
    return calibrate(robot, JointLog(list(joints), th), loops, opts).values


def make_engine(name: str):
    if name == "serial":
        return ex.SerialEngine(threads=1)
    if name == "ray":
        import ray

        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    return ex.get_engine(name, jobs=2)


def study_inputs() -> dict:
    """The inputs of the other studies (built once, outside the timings)."""
    from closedloop.impedance.data import onsets_from_events, segment
    from closedloop.impedance.model import ExperimentConfig
    from closedloop.impedance.simulation import simulate as simulate_impedance
    from closedloop.sims import SCENARIOS

    sim = simulate_impedance(ExperimentConfig(n_cycles=100, noise=0.05, seed=21))
    pc = weld_scenario(n=1, seed=2, pool="manifold", n_pool=800)
    th = pc.pool[::20] + np.random.default_rng(5).normal(0, NOISE, pc.pool[::20].shape)
    res = calibrate(
        pc.robot, JointLog(list(pc.joints), th), pc.loops, CalibrationOptions(noise=NOISE, fix={"panda_joint4.x": None})
    )
    return {
        "scenarios": {"panda_weld": SCENARIOS["panda_weld"]},
        "ensemble": segment(sim.record, onsets_from_events(sim.record)),
        "result": res,
        "pools": [pc.pool[i::20] for i in range(20)],
    }


def measure_studies(eng, inputs: dict) -> dict:
    """Wall time (cold: the first run, workers import the simulator / impedance code; warm: the second)
    and results of the other studies on `eng` (see the module docstring)."""
    import tempfile
    from pathlib import Path

    from closedloop.cli.sweep import run_sweep
    from closedloop.design.poses import select_pools
    from closedloop.impedance.bootstrap import bootstrap
    from closedloop.impedance.estimate import EstimateOptions

    def sweep():
        with tempfile.TemporaryDirectory() as tmp:
            rows = run_sweep(inputs["scenarios"], list(range(20)), 100, Path(tmp), engine=eng)
            return [(Path(r.out) / "log.csv").read_bytes() for r in rows if r.status == "ok"]

    def boot():
        b = bootstrap(inputs["ensemble"], EstimateOptions(), n_boot=200, seed=1, executor=eng)
        return [b.lo[k] for k in "IBK"] + [b.hi[k] for k in "IBK"]

    def pools():
        return [
            s.indices for s in select_pools(inputs["result"], None, inputs["pools"], 12, "exchange-a", executor=eng)
        ]

    out = {}
    for key, fn in (("sweep", sweep), ("bootstrap", boot), ("pools", pools)):
        walls = []
        for _ in range(2):
            t0 = time.perf_counter()
            value = fn()
            walls.append(time.perf_counter() - t0)
        out[key] = (walls, value)
    return out


def _same(a, b) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(x, y, equal_nan=True) if isinstance(x, np.ndarray) else x == y for x, y in zip(a, b)
    )


def measure(name: str, sc, opts, n_jobs: int, n_draws: int, studies: dict | None = None) -> dict:
    t0 = time.perf_counter()
    eng = make_engine(name)
    ex.run(noop, range(2), eng)
    out = {"engine": name, "workers": eng.workers, "startup": time.perf_counter() - t0}
    t0 = time.perf_counter()
    ex.run(noop, range(400), eng)
    out["noop_ms"] = (time.perf_counter() - t0) / 400 * 1e3
    shared = (sc.robot, sc.joints, sc.loops, sc.theta, opts)
    t0 = time.perf_counter()
    outs = sorted(ex.imap(calibration_job, range(n_jobs), eng, shared=shared, seed=2026), key=lambda o: o.index)
    out["cal_wall"] = time.perf_counter() - t0
    assert all(o.ok for o in outs), [o.error for o in outs if not o.ok][:3]
    out["cal_job_s"] = float(np.mean([o.seconds for o in outs]))
    out["cal_overhead_ms"] = (out["cal_wall"] * eng.workers - sum(o.seconds for o in outs)) / n_jobs * 1e3
    out["cal_values"] = np.array([o.value for o in outs])
    t0 = time.perf_counter()
    mc = monte_carlo(sc, NOISE, n_draws, seed=1, weightings=("noise",), options=opts, executor=eng)
    out["mc_wall"] = time.perf_counter() - t0
    out["mc_estimates"] = mc.stats["noise"].estimates
    out["mc_ratio"] = mc.stats["noise"].trace_ratio
    if studies:
        out["studies"] = measure_studies(eng, studies)
    eng.close()
    if name == "ray":
        import ray

        ray.shutdown()
    return out


def projection(rows: list[dict], robots: int, nodes: int, cpus: int, job_s: float) -> list[str]:
    """Wall time of a nightly fleet, on paper: each CPU runs ceil(robots / CPUs) jobs of job_s plus the
    measured per-job overhead; one driver submits every job at the measured no-op dispatch cost."""
    lines = [
        f"projection (on paper, not run): {robots} robots, {job_s:g} s per robot (assumed: a "
        f"1,000-configuration log with 5-fold validation, bench_calibrate figures)"
    ]
    for r in rows:
        o = max(r["cal_overhead_ms"], 0.0) / 1e3
        if r["engine"] == "serial":
            lines.append(f"  serial, one process: {robots * (job_s + o) / 3600:.1f} h")
        elif r["engine"] == "local":  # a process pool does not span machines
            per_cpu = int(np.ceil(robots / cpus))
            lines.append(
                f"  local pool, one node of {cpus} CPUs: {per_cpu} jobs per CPU x ({job_s:g} s + "
                f"{o * 1e3:.0f} ms) = {per_cpu * (job_s + o) / 60:.0f} min"
            )
        else:
            per_cpu = int(np.ceil(robots / (nodes * cpus)))
            driver = robots * r["noop_ms"] / 1e3
            compute = per_cpu * (job_s + o)
            lines.append(
                f"  {r['engine']}, {nodes} nodes x {cpus} CPUs: {per_cpu} jobs per CPU x ({job_s:g} s + "
                f"{o * 1e3:.0f} ms) = {compute:.0f} s of compute; the driver submits {robots} jobs in "
                f">= {driver:.0f} s (no-op rate); about {max(compute, driver) / 60:.1f} min in all, the "
                f"driver's dispatch the bound when it exceeds the compute (cluster start, "
                f"{r['startup']:.0f} s here, not counted: a running cluster is joined with --ray auto)"
            )
    return lines


def tiled_logs(out: Path, rows: list[int], seed: int = 0) -> tuple[Path, dict[int, Path]]:
    """The main job's 1,000 simulated configurations (simulated once into `out`) tiled to each size in
    `rows`, with NOISE rad of fresh noise on every reading: (nominal URDF, {rows: log})."""
    import subprocess
    import sys

    sim = out / "sim"
    if not (sim / "log.csv").exists():
        cmd = [sys.executable, "-m", "closedloop.cli", "simulate", "panda_weld", "--n", "1000", "--seed", "1"]
        subprocess.run([*cmd, "--out", str(sim), "--quiet"], check=True)
    header = (sim / "log.csv").read_text().splitlines()[0].split(",")
    cols = [i for i, h in enumerate(header) if h.startswith("panda_joint")]
    base = np.loadtxt(sim / "log.csv", delimiter=",", skiprows=1)[:, cols]
    rng = np.random.default_rng(seed)
    logs = {}
    for n in rows:
        path = out / f"log{n}.csv"
        if not path.exists():
            th = np.tile(base, (-(-n // len(base)), 1))[:n] + rng.normal(0.0, NOISE, (n, len(cols)))
            np.savetxt(path, th, delimiter=",", header=",".join(header[i] for i in cols), comments="", fmt="%.17g")
        logs[n] = path
    return sim / "nominal.urdf", logs


def run_cli(urdf: Path, log: Path, out: Path) -> dict:
    """`closedloop calibrate` on `log` as a child process: wall, CPU and peak RSS of that child, exit code."""
    import os
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "closedloop.cli", "calibrate", str(urdf), str(log)]
    cmd += ["--loop", "weld:frame=panda_hand_tcp,name=fixture", "--cv", "0", "--quiet"]
    cmd += ["--out", str(out / "calibrated.urdf"), "--report", str(out / "report.json")]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, use = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode() if proc.stderr else ""
    return {
        "wall": wall,
        "cpu": use.ru_utime + use.ru_stime,
        "rss_mb": use.ru_maxrss / 1024,
        "code": os.waitstatus_to_exitcode(status),
        "error": err.strip().splitlines()[-1] if err.strip() else "",
    }


def cli_scale(rows: list[int], out: Path) -> None:
    """The table of ``--cli`` (module docstring)."""
    import json

    from floor import pinocchio_floor  # benchmarks/floor.py

    out.mkdir(parents=True, exist_ok=True)
    urdf, logs = tiled_logs(out, rows)
    print("\n`closedloop calibrate` of the main job's log tiled to N rows (1e-4 rad noise), --cv 0 --quiet")
    print(
        f"{'rows':>9}{'wall s':>9}{'CPU s':>8}{'peak RSS MB':>13}{'floor CPU s':>13}{'CPU/floor':>10}"
        f"{'CPU/row us':>11}  exit, verdict, iterations"
    )
    for n in rows:
        r = run_cli(urdf, logs[n], out)
        floor = pinocchio_floor("panda", n=n, repeat=1)[1]
        verdict = ""
        if r["code"] in (0, 3):
            rep = json.loads((out / "report.json").read_text())
            verdict = f"{rep.get('verdict', {}).get('status', '?')}, {rep.get('solver', {}).get('iterations', '?')}"
        print(
            f"{n:>9,}{r['wall']:>9.2f}{r['cpu']:>8.2f}{r['rss_mb']:>13.0f}{floor:>13.4f}{r['cpu'] / floor:>10.0f}"
            f"{r['cpu'] / n * 1e6:>11.1f}  {r['code']}, {verdict or r['error']}",
            flush=True,
        )


#: the child of ``--cli --load``: the command line with its loading stages timed (CPU), stopped after them
LOAD_CHILD = """
import json, sys, time
import closedloop.io.joint_log as joint_log
import closedloop.model.robot as robot
import closedloop.run.inputs as inputs
cpu = {}
def timed(owner, name, key):
    f = getattr(owner, name)
    def g(*a, **k):
        t = time.process_time()
        try:
            return f(*a, **k)
        finally:
            cpu[key] = cpu.get(key, 0.0) + time.process_time() - t
    setattr(owner, name, g)
timed(joint_log, "read_joint_log", "read")
timed(robot.RobotModel, "with_gravity_torques", "gravity")
load = inputs.load_inputs
def stop(o):
    cpu["start"] = time.process_time()
    load(o)
    cpu["load"] = time.process_time() - cpu["start"]
    raise SystemExit(0)
inputs.load_inputs = stop
from closedloop.cli.main import main
main(sys.argv[2:])
open(sys.argv[1], "w").write(json.dumps(cpu))
"""


def load_stages(urdf: Path, log: Path, out: Path) -> dict:
    """CPU seconds of the loading stages of `closedloop calibrate` on `log` (`LOAD_CHILD`), in a fresh process:
    ``start`` (interpreter start to the first line of load_inputs; the child's own CPU clock counts from the
    interpreter's start), ``load``, ``read`` and ``gravity``."""
    import json
    import subprocess
    import sys

    record = out / "load.json"
    cmd = [sys.executable, "-c", LOAD_CHILD, str(record), "calibrate", str(urdf), str(log)]
    cmd += ["--loop", "weld:frame=panda_hand_tcp,name=fixture", "--cv", "0", "--quiet"]
    cmd += ["--out", str(out / "calibrated.urdf"), "--report", str(out / "report.json")]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.loads(record.read_text())


def alone(urdf: Path, log: Path) -> tuple[float, float]:
    """CPU seconds of NumPy alone reading `log` (``np.loadtxt``) and of Pinocchio alone computing the gravity
    torques of its rows (``computeGeneralizedGravity``, a call per row)."""
    import pinocchio as pin

    t = time.process_time()
    theta = np.loadtxt(log, delimiter=",", skiprows=1, ndmin=2)
    numpy_s = time.process_time() - t
    model = pin.buildModelFromUrdf(str(urdf))
    data = model.createData()
    q = np.tile(pin.neutral(model), (len(theta), 1))
    q[:, : theta.shape[1]] = theta  # the arm's joints come first in the panda's configuration
    t = time.process_time()
    for qi in q:
        pin.computeGeneralizedGravity(model, data, qi)
    return numpy_s, time.process_time() - t


def load_scale(rows: list[int], out: Path) -> None:
    """The table of ``--cli --load`` (module docstring): median CPU of three runs per size."""
    import os
    import subprocess
    import sys

    out.mkdir(parents=True, exist_ok=True)
    urdf, logs = tiled_logs(out, rows)
    help_cpu = []
    for _ in range(3):
        proc = subprocess.Popen(
            [sys.executable, "-m", "closedloop.cli", "calibrate", "--help"], stdout=subprocess.DEVNULL
        )
        use = os.wait4(proc.pid, 0)[2]
        help_cpu.append(use.ru_utime + use.ru_stime)
    print(f"\n`closedloop calibrate --help`: {np.median(help_cpu):.2f} s CPU (median of 3)")
    print("\n`closedloop calibrate` before its fit, CPU seconds (median of 3 runs; NumPy and Pinocchio alone: one run)")
    print(
        f"{'rows':>9}{'to load_inputs':>16}{'load_inputs':>13}{'read log':>10}{'gravity':>9}"
        f"{'np.loadtxt':>12}{'Pinocchio g(q)':>16}{'load us/row':>13}"
    )
    for n in rows:
        runs = [load_stages(urdf, logs[n], out) for _ in range(3)]
        med = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in ("start", "load", "read", "gravity")}
        numpy_s, pinocchio_s = alone(urdf, logs[n])
        print(
            f"{n:>9,}{med['start']:>16.3f}{med['load']:>13.3f}{med['read']:>10.3f}{med['gravity']:>9.3f}"
            f"{numpy_s:>12.3f}{pinocchio_s:>16.3f}{med['load'] / n * 1e6:>13.2f}",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cli", action="store_true", help="one long log through the command line (module docstring)")
    ap.add_argument("--rows", type=int, nargs="+", default=[1000, 10_000, 100_000], help="--cli: log sizes")
    ap.add_argument("--load", action="store_true", help="--cli: the loading stages only (module docstring)")
    ap.add_argument("--out", default="out/bench_scale", help="--cli: where the logs and outputs go")
    ap.add_argument("--jobs", type=int, default=200, help="calibrations (one robot each)")
    ap.add_argument("--draws", type=int, default=200, help="Monte Carlo draws")
    ap.add_argument("--configs", type=int, default=60, help="configurations per calibration")
    ap.add_argument("--engines", nargs="+", default=["serial", "local", "ray"], choices=sorted(ex.ENGINES))
    ap.add_argument("--studies", action="store_true", help="also simulate over seeds, the bootstrap, pose pools")
    ap.add_argument(
        "--fleet",
        type=float,
        nargs=4,
        default=[10_000, 100, 32, 1.2],
        metavar=("ROBOTS", "NODES", "CPUS", "JOB_S"),
        help="the projection's fleet (on paper)",
    )
    args = ap.parse_args()
    print(header())
    if args.cli and args.load:
        load_scale(args.rows, Path(args.out))
        return
    if args.cli:
        cli_scale(args.rows, Path(args.out))
        return
    sc = weld_scenario(n=1, seed=2, pool="manifold", n_pool=args.configs)
    sc = dataclasses.replace(sc, theta=sc.pool, pool=None)
    opts = CalibrationOptions(noise=NOISE, fix={"panda_joint4.x": None})  # one length sets the scale
    studies = study_inputs() if args.studies else None
    rows = [measure(e, sc, opts, args.jobs, args.draws, studies) for e in args.engines]
    ref = rows[0]
    print(f"\n{args.jobs} calibrations and a {args.draws}-draw Monte Carlo, Panda weld, {args.configs} configurations")
    print(
        f"{'engine':<8}{'workers':>8}{'startup s':>10}{'no-op ms/job':>13}{'cal wall s':>11}{'speedup':>8}"
        f"{'job s':>7}{'overhead ms/job':>16}{'MC wall s':>10}{'speedup':>8}  identical"
    )
    for r in rows:
        same = np.array_equal(r["cal_values"], ref["cal_values"]) and np.array_equal(
            r["mc_estimates"], ref["mc_estimates"]
        )
        print(
            f"{r['engine']:<8}{r['workers']:>8}{r['startup']:>10.2f}{r['noop_ms']:>13.2f}{r['cal_wall']:>11.1f}"
            f"{ref['cal_wall'] / r['cal_wall']:>8.2f}{r['cal_job_s']:>7.3f}{r['cal_overhead_ms']:>16.1f}"
            f"{r['mc_wall']:>10.1f}{ref['mc_wall'] / r['mc_wall']:>8.2f}  {'yes' if same else 'NO'}"
        )
    print(f"Monte Carlo tr(cov)/tr(CRB) = {ref['mc_ratio']:.3f}")
    if studies:
        print(
            f"\n{'study (wall s: cold / warm; speedup warm)':<48}"
            + "".join(f"{r['engine']:>16}{'speedup':>8}" for r in rows)
            + "  identical"
        )
        for key, label in (
            ("sweep", "simulate panda_weld, 20 seeds x 100 cfg"),
            ("bootstrap", "impedance bootstrap, 200 resamples"),
            ("pools", "pose selection, 20 pools (exchange-A, 12/40)"),
        ):
            w0 = ref["studies"][key][0][1]
            same = all(_same(r["studies"][key][1], ref["studies"][key][1]) for r in rows)
            print(
                f"{label:<48}"
                + "".join(
                    f"{r['studies'][key][0][0]:>8.2f} /{r['studies'][key][0][1]:>6.2f}{w0 / r['studies'][key][0][1]:>8.2f}"
                    for r in rows
                )
                + f"  {'yes' if same else 'NO'}"
            )
    robots, nodes, cpus, job_s = args.fleet
    print("\n".join(projection(rows, int(robots), int(nodes), int(cpus), float(job_s))))


if __name__ == "__main__":
    main()
