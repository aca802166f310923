"""Benchmark of the time-varying impedance identification: the defaults' accuracy, time resolution, band
coverage and speed, on the independent elbow (`closedloop.impedance.elbow`) and on the thesis forearm.

    python benchmarks/bench_impedance.py [--reps 5] [--out out/bench_impedance] [--all]

Prints the tables quoted in docs/guide/impedance.md and writes `results.json` to --out.  Defaults section:
100 cycles of 2 s at 600 Hz, 5 % noise, `--reps` realisations per truth; "before" is the previous default
(pre-filter 20 Hz, pooling +-15 ms, no step detection, no IV switch).  Speed: the `identify` pipeline
(read the CSV, segment, estimate, bootstrap 200, 5-fold free-run VAF) timed in this process (wall and CPU)
and the whole command (`python -m closedloop.cli.main impedance identify`, interpreter start included,
run with the user's BLAS thread setting, not this script's), `--reps` times with the machine otherwise
idle and `--reps` times with one core held by a busy process, with the load average.  `--speed` runs that
section alone.  `--all` adds the older tables (methods, thesis estimator, alignment traps, robot).
"""

from __future__ import annotations

import os

_USER_ENV = dict(os.environ)  # the command is timed as a user runs it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from machine import busy_cores, machine  # noqa: E402

from closedloop.impedance.bootstrap import bootstrap, free_run_vaf  # noqa: E402
from closedloop.impedance.data import onsets_from_events, segment  # noqa: E402
from closedloop.impedance.elbow import ElbowConfig, simulate_elbow  # noqa: E402
from closedloop.impedance.estimate import EstimateOptions, estimate, posture_fit  # noqa: E402
from closedloop.impedance.metrics import bias_random, coverage, mean_rise_time, median_errors, rel_errors  # noqa: E402
from closedloop.impedance.model import ExperimentConfig  # noqa: E402
from closedloop.impedance.mujoco_sim import forearm_truth, simulate_robot  # noqa: E402
from closedloop.impedance.plots import plot_impedance  # noqa: E402
from closedloop.impedance.simulation import simulate  # noqa: E402

METHODS = {
    "default (20 Hz)": ("default", {}),
    "default, 10 Hz": ("default", {"prefilter_hz": 10.0}),
    "OLS": ("ols", {}),
    "IV (2SLS)": ("iv", {}),
    "thesis": ("thesis", {}),
}


def ens_of(sim, **kw):
    return segment(sim.record, onsets_from_events(sim.record), **kw)


def sims(reps, **kw):
    return [simulate(ExperimentConfig(seed=100 + r, **kw)) for r in range(reps)]


def method_table(runs, title, rise=False):
    print(f"\n{title}")
    print(
        "| method | mean abs error I / B / K (%) | bias I / B / K (%) | random I / B / K (%) |"
        + (" K rise 10-90 % (ms) |" if rise else "")
    )
    print("|---|---|---|---|" + ("---|" if rise else ""))
    out = {}
    for name, (m, kw) in METHODS.items():
        ests = [estimate(e, m, warn=False, **kw) for e, _ in runs]
        truth = runs[0][1]
        err = np.mean([list(rel_errors(est, t).values()) for est, (_, t) in zip(ests, runs)], axis=0)
        br = bias_random(ests, truth)
        row = {"error": err.tolist(), "bias": [br[k][0] for k in "IBK"], "random": [br[k][1] for k in "IBK"]}
        line = (
            f"| {name} | {' / '.join(f'{x:.2f}' for x in err)} | {' / '.join(f'{x:.2f}' for x in row['bias'])}"
            f" | {' / '.join(f'{x:.2f}' for x in row['random'])} |"
        )
        if rise:
            rt = mean_rise_time(truth["t"], np.stack([e.K for e in ests]), truth["K"])
            row["rise_ms"] = 1e3 * rt
            line += f" {1e3 * rt:.1f} |"
        print(line)
        out[name] = row
    return out


def speed_and_main_figure(res: dict, out: Path) -> None:
    """Speed; the MuJoCo forearm with finite-difference truth, bands and postures (main figure)."""
    cfg = ExperimentConfig(n_cycles=100, noise=0.05, seed=1)
    t = time.perf_counter()
    sm = simulate(cfg, "mujoco")
    t_mj = time.perf_counter() - t
    t = time.perf_counter()
    sr = simulate(cfg, "rk4")
    t_rk = time.perf_counter() - t
    t = time.perf_counter()
    tr_fd = forearm_truth(cfg)
    t_tr = time.perf_counter() - t
    ens = ens_of(sm)
    estimate(ens, warn=False)
    t = time.perf_counter()
    est = estimate(ens, warn=False)
    t_est = time.perf_counter() - t
    opt = EstimateOptions()
    t = time.perf_counter()
    bands = bootstrap(ens, opt, 200)
    t_boot = time.perf_counter() - t
    t = time.perf_counter()
    fit = free_run_vaf(ens, opt)
    t_vaf = time.perf_counter() - t
    res["speed_s"] = {
        "simulate_mujoco_100": t_mj,
        "simulate_rk4_100": t_rk,
        "truth_fd": t_tr,
        "estimate": t_est,
        "bootstrap_200": t_boot,
        "free_run_vaf_5fold": t_vaf,
    }
    print("\nspeed (s): " + ", ".join(f"{k} {v:.2f}" for k, v in res["speed_s"].items()))
    print(f"MuJoCo vs RK4 twin: max |angle diff| {np.max(np.abs(sm.record.angle - sr.record.angle)):.1e} rad")

    # --- main figure: MuJoCo data, finite-difference truth, postures ---
    post = {}
    for q in (0.0, 0.5, 1.0):
        ps = simulate(ExperimentConfig(n_cycles=5, cycles_per_block=5, noise=0.05, posture=q, seed=7))
        post[f"posture {q:g} rad"] = posture_fit(ens_of(ps))
    err = rel_errors(est, tr_fd)
    t = est.t
    dip_est = np.mean(est.K[np.abs(t - 1) < 0.15]) - np.mean(est.K[(t < 0.15) | (t > 1.85)])
    dip_true = np.mean(tr_fd["K"][np.abs(t - 1) < 0.15]) - np.mean(tr_fd["K"][(t < 0.15) | (t > 1.85)])
    cov = {k: coverage(bands.lo[k], bands.hi[k], tr_fd[k]) for k in "IBK"}
    res["mujoco_default"] = {
        "error": err,
        "vaf": fit.vaf,
        "K_dip_est": dip_est,
        "K_dip_true": dip_true,
        "coverage": cov,
        "posture": post,
    }
    print(
        f"MuJoCo data, default: errors {err}, free-run VAF {fit.vaf:.3f} %, gravity K dip {dip_est:.2f} "
        f"(true {dip_true:.2f}) N m/rad, coverage {cov}"
    )
    plot_impedance(
        out / "impedance_default.png",
        est,
        ens,
        bands,
        tr_fd,
        post,
        "default estimator, MuJoCo forearm, N = 100, 5 % noise",
    )


def tables_and_coverage(res: dict, out: Path, reps: int) -> None:
    """Error tables per method (constant and square-wave K), free-run VAF, bootstrap coverage."""
    opt = EstimateOptions()
    runs = [(ens_of(s), s.truth) for s in sims(reps, n_cycles=100, noise=0.05)]
    res["constant"] = method_table(runs, "constant K = 20, B = 1 (with gravity), N = 100, 5 % noise")
    vafs = [free_run_vaf(e, opt).vaf for e, _ in runs[:3]]
    res["vaf_free_run"] = vafs
    print(f"free-run VAF, default, held-out cycles (5-fold), 3 realisations: {np.round(vafs, 3).tolist()}")
    sq = [(ens_of(s), s.truth) for s in sims(reps, n_cycles=100, noise=0.05, stiffness="square:20,8,0.5")]
    res["square"] = method_table(sq, "square-wave K 20 <-> 8 N m/rad (0.5 s period), N = 100, 5 % noise", rise=True)
    e_sq = estimate(sq[0][0])
    plot_impedance(
        out / "impedance_square.png",
        e_sq,
        sq[0][0],
        bootstrap(sq[0][0], opt, 200),
        sq[0][1],
        title="square-wave stiffness, default estimator",
    )
    covs = []
    for e, tr in runs:
        b = bootstrap(e, opt, 200)
        covs.append([coverage(b.lo[k], b.hi[k], tr[k]) for k in "IBK"])
    covs = np.array(covs)
    res["coverage"] = {"mean": covs.mean(0).tolist(), "min": covs.min(0).tolist()}
    print(
        f"\nbootstrap 95 % band coverage over {reps} realisations, I / B / K: mean "
        f"{np.round(100 * covs.mean(0), 1).tolist()} %, min {np.round(100 * covs.min(0), 1).tolist()} %"
    )


def voluntary_and_thesis(res: dict, out: Path, reps: int) -> None:
    """IV vs TLS under voluntary torque variability; the literal thesis estimator at 5 % and 0.01 %."""
    print("\nvoluntary torque 0.5 N m RMS (3 Hz), 5 % noise: median |error| I / B / K (%)")
    vol = {}
    for n in (100, 300):
        vr = [(ens_of(s), s.truth) for s in sims(max(2, reps // 2), n_cycles=n, noise=0.05, voluntary_rms=0.5)]
        for m in ("default", "iv"):
            med = np.mean([list(median_errors(estimate(e, m, warn=False), tr).values()) for e, tr in vr], axis=0)
            sgn = np.mean(
                [[np.nanmedian(getattr(estimate(e, m, warn=False), k) / tr[k]) - 1 for k in "IB"] for e, tr in vr],
                axis=0,
            )
            vol[f"{m} N={n}"] = {"median_error": med.tolist(), "median_bias_IB": sgn.tolist()}
            print(
                f"  {'TLS (default)' if m == 'default' else 'IV (2SLS)'} N = {n}: {np.round(med, 1).tolist()}"
                f"  (median bias I {100 * sgn[0]:+.0f} %, B {100 * sgn[1]:+.0f} %)"
            )
        if n == 100:
            e0, tr0 = vr[0]
            plot_impedance(
                out / "impedance_voluntary_tls.png",
                estimate(e0, warn=False),
                e0,
                None,
                tr0,
                title="voluntary variability 0.5 N m: TLS (biased)",
            )
            plot_impedance(
                out / "impedance_voluntary_iv.png",
                estimate(e0, "iv", warn=False),
                e0,
                bootstrap(e0, EstimateOptions.for_method("iv"), 100),
                tr0,
                title="voluntary variability 0.5 N m: IV with the commanded PRBS",
            )
    res["voluntary"] = vol
    print("\nthesis estimator (h = 1 sample, TLS, no pre-filter), N = 100: median |error| I / B / K (%)")
    th = {}
    for noise in (0.05, 1e-4):
        s = simulate(ExperimentConfig(n_cycles=100, noise=noise, seed=5))
        e = ens_of(s)
        med = median_errors(estimate(e, "thesis", warn=False), s.truth)
        medd = median_errors(estimate(e, warn=False), s.truth)
        th[str(noise)] = {"thesis": med, "default": medd}
        print(
            f"  noise {100 * noise:g} %: thesis {[round(v, 1) for v in med.values()]}, "
            f"default {[round(v, 2) for v in medd.values()]}"
        )
        if noise == 0.05:
            plot_impedance(
                out / "impedance_thesis_5pct.png",
                estimate(e, "thesis", warn=False),
                e,
                None,
                s.truth,
                title="literal thesis estimator at 5 % noise (fails)",
            )
    res["thesis"] = th


def traps_and_robot(res: dict, out: Path) -> None:
    """Alignment on periodic data, PRBS locked to the cycle clock, and the robot case."""
    opt = EstimateOptions()
    s = simulate(ExperimentConfig(n_cycles=100, noise=0.05, seed=9))
    trap = {}
    for al in ("none", "peak-velocity", "peak-velocity+rms"):
        e = segment(s.record, onsets_from_events(s.record), align=al, max_shift_s=0.05)
        r = e.alignment.summary()
        trap[al] = {
            "error": rel_errors(estimate(e, warn=False), s.truth),
            "shift_std_ms": r["std_ms"],
            "max_shift_ms": r["max_abs_ms"],
        }
        print(
            f"alignment {al}: shifts std {r['std_ms']:.1f} ms, max {r['max_abs_ms']:.1f} ms; errors "
            f"{ {k: round(v, 2) for k, v in trap[al]['error'].items()} }"
        )
    res["alignment"] = trap
    s = simulate(ExperimentConfig(n_cycles=100, noise=0.0, seed=9, prbs_phase="locked"))
    e = ens_of(s)
    lk = {}
    for m in ("thesis", "default"):
        est_l = estimate(e, m, warn=False)
        lk[m] = {"warnings": est_l.warnings, "vaf": free_run_vaf(e, EstimateOptions.for_method(m)).vaf}
        print(
            f"PRBS locked to the cycle clock, noise-free, {m}: free-run VAF {lk[m]['vaf']:.1f} %; "
            f"warnings: {est_l.warnings[:1]}"
        )
    res["locked_prbs"] = lk

    # --- robot case ---
    rs = simulate_robot(
        ExperimentConfig(n_cycles=100, noise=0.05, seed=1, stiffness="dip:20,0.5,0.15", damping="dip:1,0.3,0.15")
    )
    er = estimate(ens_of(rs))
    res["robot"] = rel_errors(er, rs.truth)
    print(f"robot elbow (two-link arm, impedance controller with K, B dips): errors {res['robot']}")
    plot_impedance(
        out / "impedance_robot.png",
        er,
        ens_of(rs),
        bootstrap(ens_of(rs), opt, 200),
        rs.truth,
        title="robot case: elbow of a two-link arm under a time-varying impedance controller",
    )


BEFORE = EstimateOptions(prefilter_hz=20.0, pool_ms=15.0, edges=False, auto_iv=False)
ELBOW = {
    "constant": {},
    "gravity dip": {"stiffness": "dip"},
    "B ramp": {"stiffness": "ramp-b"},
    "square K": {"stiffness": "square"},
    "voluntary 0.5 N m": {"voluntary_rms": 0.5},
}


def _away_and_rise(est, truth, fs):
    T = np.r_[truth["K"], truth["K"][:1]]
    jumps = np.r_[np.flatnonzero(np.abs(np.diff(T)) > 0.2 * np.ptp(T)) + 1, 0]
    d = np.min(np.abs(np.arange(len(est.t))[:, None] - jumps[None, :]), axis=1) / fs
    away = 100 * np.mean(np.abs(est.K[d > 0.05] / truth["K"][d > 0.05] - 1))
    return away, 1e3 * mean_rise_time(est.t, est.K, truth["K"])


def defaults_on_elbow(res: dict, reps: int) -> None:
    """Mean absolute error I / B / K (%), square-wave K away from steps and rise, band coverage."""
    print(f"\nindependent elbow, 100 cycles, 5 % noise, {reps} realisations per truth")
    print("| truth | default: error I / B / K (%) | band coverage I / B / K (%) | before: error I / B / K (%) |")
    print("|---|---|---|---|")
    out = {}
    for name, kw in ELBOW.items():
        errs, covs, olds, extra, methods = [], [], [], [], set()
        for r in range(reps):
            rec, truth = simulate_elbow(ElbowConfig(seed=100 + r, **kw))
            ens = segment(rec, onsets_from_events(rec))
            est = estimate(ens, warn=False)
            methods.add(est.options.method)
            old = estimate(ens, options=BEFORE, warn=False)
            errs.append(list(rel_errors(est, truth).values()))
            olds.append(list(rel_errors(old, truth).values()))
            b = bootstrap(ens, est.options, 200, seed=r, est=est)
            covs.append([100 * coverage(b.lo[k], b.hi[k], truth[k]) for k in "IBK"])
            if "square" in name:
                extra.append(_away_and_rise(est, truth, ens.fs) + _away_and_rise(old, truth, ens.fs))
        e, c, o = np.mean(errs, 0), np.mean(covs, 0), np.mean(olds, 0)
        out[name] = {"error": e.tolist(), "coverage": c.tolist(), "coverage_min": np.min(covs, 0).tolist()}
        out[name]["before"] = o.tolist()
        out[name]["method"] = sorted(methods)
        print(
            f"| {name} ({'/'.join(sorted(methods))}) | {' / '.join(f'{x:.2f}' for x in e)} | "
            f"{' / '.join(f'{x:.0f}' for x in c)} (min {' / '.join(f'{x:.0f}' for x in np.min(covs, 0))}) | "
            f"{' / '.join(f'{x:.2f}' for x in o)} |"
        )
        if extra:
            x = np.mean(extra, 0)
            out[name]["K_away_rise"] = x.tolist()
            print(
                f"|   square K: away from steps (> 50 ms) | {x[0]:.2f} %, rise 10-90 % {x[1]:.1f} ms | | "
                f"{x[2]:.2f} %, rise {x[3]:.1f} ms |"
            )
    res["elbow"] = out


def defaults_on_forearm(res: dict, reps: int) -> None:
    """The thesis forearm (the project's own simulator): constant and square-wave K."""
    print(f"\nthesis forearm (RK4), 100 cycles, 5 % noise, {reps} realisations")
    out = {}
    for name, kw in (("constant", {}), ("square K 20 <-> 8", {"stiffness": "square:20,8,0.5"})):
        rows = []
        for r in range(reps):
            s = simulate(ExperimentConfig(n_cycles=100, noise=0.05, seed=200 + r, **kw))
            ens = ens_of(s)
            est, old = estimate(ens, warn=False), estimate(ens, options=BEFORE, warn=False)
            row = list(rel_errors(est, s.truth).values()) + list(rel_errors(old, s.truth).values())
            if "square" in name:
                row += list(_away_and_rise(est, s.truth, ens.fs)) + list(_away_and_rise(old, s.truth, ens.fs))
            rows.append(row)
        m = np.mean(rows, 0)
        out[name] = m.tolist()
        line = f"  {name}: default {' / '.join(f'{x:.2f}' for x in m[:3])} %, before {' / '.join(f'{x:.2f}' for x in m[3:6])} %"
        if "square" in name:
            line += f"; K away {m[6]:.2f} % (before {m[8]:.2f} %), rise {m[7]:.1f} ms (before {m[9]:.1f} ms)"
        print(line)
    res["forearm"] = out


def _command(path: Path) -> tuple[float, float, float]:
    """Wall and CPU seconds of one whole `impedance identify` run (a child process), and the load."""
    import resource
    import subprocess

    load = os.getloadavg()[0]
    ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "closedloop.cli.main", "impedance", "identify", str(path)],
        check=True,
        capture_output=True,
        env=_USER_ENV,
    )
    wall = time.perf_counter() - t
    ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, ch1.ru_utime + ch1.ru_stime - ch0.ru_utime - ch0.ru_stime, load


def speed(res: dict, out: Path, repeats: int = 5) -> None:
    """identify on 100 cycles (the elbow, constant truth) with its default bootstrap: wall and CPU."""
    from closedloop.impedance.data import read_record, write_record

    rec, _ = simulate_elbow(ElbowConfig(seed=7))
    path = out / "elbow100.csv"
    write_record(path, rec)
    rows = []
    for _ in range(repeats):
        load = os.getloadavg()[0]
        w0, c0 = time.perf_counter(), time.process_time()
        r = read_record(path)
        ens = segment(r, onsets_from_events(r))
        est = estimate(ens, warn=False)
        w1, c1 = time.perf_counter(), time.process_time()
        bootstrap(ens, est.options, 200, est=est)
        w2, c2 = time.perf_counter(), time.process_time()
        free_run_vaf(ens, est.options, 5)
        w3, c3 = time.perf_counter(), time.process_time()
        wall, cpu, _ = _command(path)
        rows.append([w3 - w0, c3 - c0, w1 - w0, w2 - w1, w3 - w2, wall, load, c1 - c0, c2 - c1, c3 - c2, cpu])
    with busy_cores(1):
        busy = np.array([_command(path) for _ in range(repeats)])
    a = np.array(rows)
    med = np.median(a, 0)
    res["speed"] = {
        "pipeline_wall_s": med[0],
        "pipeline_cpu_s": med[1],
        "read_segment_estimate_wall_s": med[2],
        "bootstrap_200_wall_s": med[3],
        "vaf_5fold_wall_s": med[4],
        "cli_wall_s": med[5],
        "cli_cpu_s": med[10],
        "load_1min": a[:, 6].tolist(),
        "cpu_s_estimate_bootstrap_vaf": med[7:10].tolist(),
        "all": a.tolist(),
        "cli_one_core_busy": {
            "wall_s": busy[:, 0].tolist(),
            "cpu_s": busy[:, 1].tolist(),
            "load_1min": busy[:, 2].tolist(),
        },
    }
    print(
        f"\nspeed, identify on 100 cycles (median of {repeats}; load average {a[:, 6].min():.1f}-{a[:, 6].max():.1f} "
        f"on this machine): pipeline {med[0]:.2f} s wall / {med[1]:.2f} s CPU (read+segment+estimate "
        f"{med[2]:.2f}, bootstrap 200 {med[3]:.2f}, VAF {med[4]:.2f}; CPU {med[7]:.2f} / {med[8]:.2f} / "
        f"{med[9]:.2f}); whole command {med[5]:.2f} s wall / {med[10]:.2f} s CPU "
        f"(min {a[:, 5].min():.2f}, max {a[:, 5].max():.2f})"
    )
    print(
        f"whole command with one core held by a busy process (load average {busy[:, 2].min():.1f}-"
        f"{busy[:, 2].max():.1f}): {np.median(busy[:, 0]):.2f} s wall (min {busy[:, 0].min():.2f}, max "
        f"{busy[:, 0].max():.2f}) / {np.median(busy[:, 1]):.2f} s CPU"
    )


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default="out/bench_impedance")
    ap.add_argument("--all", action="store_true", help="also the older tables and figures")
    ap.add_argument("--speed", action="store_true", help="only the speed section")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = {"machine": machine(), "reps": a.reps}
    print(f"machine: {res['machine']}; {a.reps} realisations per condition")
    speed(res, out, a.reps)
    if not a.speed:
        defaults_on_elbow(res, a.reps)
        defaults_on_forearm(res, a.reps)
    if a.all and not a.speed:
        speed_and_main_figure(res, out)
        tables_and_coverage(res, out, a.reps)
        voluntary_and_thesis(res, out, a.reps)
        traps_and_robot(res, out)
    (out / "results.json").write_text(json.dumps(res, indent=1, default=float))
    print(f"\nwrote {out}/results.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
