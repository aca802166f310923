"""`closedloop impedance simulate ...` and `closedloop impedance identify DATA ...` (printing lives here)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from closedloop.errors import InputError


def add_parser(subparsers) -> None:
    """Register `impedance` with its `simulate` and `identify` subcommands."""
    p = subparsers.add_parser("impedance", help="time-varying joint impedance identification (thesis Part II)")
    sub = p.add_subparsers(dest="impedance_command", required=True)

    s = sub.add_parser("simulate", help="simulate perturbed cyclic movements with ground truth")
    s.add_argument("--out", required=True, help="output folder: data.csv|.h5, truth.csv, posture_*.csv")
    s.add_argument("--case", choices=["forearm", "robot"], default="forearm")
    s.add_argument("--engine", choices=["mujoco", "rk4"], default="mujoco", help="forearm integrator")
    s.add_argument("--cycles", type=int, default=100)
    s.add_argument(
        "--stiffness",
        default="constant:20",
        help="K(t): constant:V | step:V0,V1,T | square:V0,V1,P | dip:V,DEPTH,WIDTH",
    )
    s.add_argument("--damping", default="constant:1", help="B(t), same forms")
    s.add_argument("--noise", type=float, default=0.05, help="noise std / perturbation std (default 0.05)")
    s.add_argument("--voluntary", type=float, default=0.0, help="voluntary torque RMS, N m (3 Hz band)")
    s.add_argument("--prbs-phase", choices=["random", "locked"], default="random")
    s.add_argument("--no-gravity", action="store_true", help="horizontal plane")
    s.add_argument("--postures", action="store_true", help="also simulate holding 0, 0.5 and 1 rad (10 s each)")
    s.add_argument("--format", choices=["csv", "h5"], default="csv")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_simulate)

    i = sub.add_parser("identify", help="identify I(t), B(t), K(t) from a recording")
    i.add_argument("data", help="CSV or HDF5: time (s), angle (rad), torque (N m), [command, event, block]")
    i.add_argument("--method", choices=["default", "thesis", "ols", "iv"], default="default")
    i.add_argument("--prefilter", default=None, help="zero-phase low-pass (Hz) or 'none'")
    i.add_argument("--lag-ms", type=float, default=None)
    i.add_argument("--pool-ms", type=float, default=None)
    i.add_argument("--smooth-ms", type=float, default=None)
    i.add_argument("--segment", default="events", help="events | peak-velocity | onsets:FILE (one time per line, s)")
    i.add_argument("--period", type=float, default=None, help="cycle length (s); default: median onset spacing")
    i.add_argument("--align", default="none", choices=["none", "peak-velocity", "rms", "peak-velocity+rms"])
    i.add_argument("--max-shift-ms", type=float, default=50.0)
    i.add_argument("--bootstrap", type=int, default=200, metavar="R", help="resamples for 95 %% bands (0: none)")
    i.add_argument("--folds", type=int, default=5, help="k-fold free-run VAF on held-out cycles (0: none)")
    i.add_argument("--truth", help="truth CSV (t, I, B, K) to compare with")
    i.add_argument("--posture", action="append", default=[], metavar="FILE", help="posture record (repeatable)")
    i.add_argument("--out", help="results table, .csv or .json")
    i.add_argument("--plot", help="figure, .png or .svg")
    i.add_argument("--seed", type=int, default=0)
    i.set_defaults(func=cmd_identify)


def cmd_simulate(args: argparse.Namespace) -> int:
    from closedloop.impedance.data import write_record
    from closedloop.impedance.model import ExperimentConfig, ForearmParams
    from closedloop.impedance.results import write_truth
    from closedloop.impedance.simulation import simulate
    from closedloop.io.schemas import check_number

    args.noise = check_number("--noise", args.noise, 0.0, 1e6)
    args.voluntary = check_number("--voluntary", args.voluntary, 0.0, 1e6)
    args.cycles = check_number("--cycles", args.cycles, 1, 10**6, integer=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    arm = ForearmParams(gravity=not args.no_gravity)
    cfg = ExperimentConfig(
        n_cycles=args.cycles,
        stiffness=args.stiffness,
        damping=args.damping,
        noise=args.noise,
        voluntary_rms=args.voluntary,
        prbs_phase=args.prbs_phase,
        seed=args.seed,
        arm=arm,
    )
    if args.case == "robot":
        from closedloop.impedance.mujoco_sim import simulate_robot

        sim = simulate_robot(cfg)
    else:
        if args.engine == "mujoco":
            from closedloop.impedance.mujoco_sim import forearm_truth
        sim = simulate(cfg, args.engine)
        if args.engine == "mujoco":
            sim.truth = forearm_truth(cfg)
    data = out / f"data.{args.format}"
    write_record(data, sim.record)
    write_truth(out / "truth.csv", sim.truth)
    print(
        f"simulated {cfg.n_cycles} cycles ({args.case}, {args.engine if args.case == 'forearm' else 'mujoco'}) "
        f"in {sim.seconds:.2f} s -> {data}"
    )
    print(
        f"  noise std: angle {sim.noise_std[0]:.3g} rad, torque {sim.noise_std[1]:.3g} N m; "
        f"truth -> {out / 'truth.csv'}"
    )
    if args.postures and args.case == "forearm":
        k0, b0 = cfg.stiffness.values[0], cfg.damping.values[0]  # postures: the profiles' base values
        for q in (0.0, 0.5, 1.0):
            pc = ExperimentConfig(
                n_cycles=5,
                cycles_per_block=5,
                stiffness=k0,
                damping=b0,
                noise=args.noise,
                posture=q,
                seed=args.seed + 1,
                arm=arm,
            )
            ps = simulate(pc, "rk4")
            write_record(out / f"posture_{q:g}.{args.format}", ps.record)
            kq = ps.truth["K"][0]
            print(f"  posture {q:g} rad -> {out / f'posture_{q:g}.{args.format}'} (true K_eff {kq:.2f} N m/rad)")
    return 0


def _onsets(rec, args):
    from closedloop.impedance.data import (
        ImpedanceDataError,
        onsets_from_events,
        onsets_from_peak_velocity,
        onsets_from_times,
    )

    if args.segment == "events":
        return onsets_from_events(rec)
    if args.segment == "peak-velocity":
        if not args.period:
            raise InputError("--segment peak-velocity needs --period")
        return onsets_from_peak_velocity(rec, args.period)
    if args.segment.startswith("onsets:"):
        f = Path(args.segment[7:])
        if not f.is_file():
            raise ImpedanceDataError(f"{f}: no such onsets file")
        try:
            times = np.loadtxt(f, ndmin=1)
        except ValueError:
            raise ImpedanceDataError(f"{f}: onsets must be one number (s) per line") from None
        return onsets_from_times(rec, times)
    raise InputError(f"--segment {args.segment}: expected events, peak-velocity or onsets:FILE")


def cmd_identify(args: argparse.Namespace) -> int:
    from closedloop.impedance.bootstrap import bootstrap, free_run_vaf
    from closedloop.impedance.data import read_record, segment
    from closedloop.impedance.estimate import EstimateOptions, estimate, posture_fit
    from closedloop.impedance.metrics import coverage, rel_errors
    from closedloop.impedance.results import read_truth, resample_truth, write_results
    from closedloop.io.schemas import check_number

    args.max_shift_ms = check_number("--max-shift-ms", args.max_shift_ms, 0.0, 1e6)
    args.bootstrap = check_number("--bootstrap", args.bootstrap, 0, 10**6, integer=True)
    args.folds = check_number("--folds", args.folds, 0, 10**6, integer=True)
    for opt_name, path, kinds in (
        ("--plot", args.plot, (".png", ".svg", ".pdf")),
        ("--out", args.out, (".csv", ".json")),
    ):
        if path and Path(path).suffix.lower() not in kinds:
            raise InputError(f"{opt_name} {path}: give a {', '.join(kinds)} file")
    t0 = time.perf_counter()
    rec = read_record(args.data)
    pre = None if args.prefilter is None else (0.0 if args.prefilter.lower() == "none" else _float(args.prefilter))
    opt = EstimateOptions.for_method(
        args.method, prefilter_hz=pre, lag_ms=args.lag_ms, pool_ms=args.pool_ms, smooth_ms=args.smooth_ms
    )
    ens = segment(rec, _onsets(rec, args), period=args.period, align=args.align, max_shift_s=args.max_shift_ms / 1e3)
    est = estimate(ens, options=opt, warn=False)
    t_est = time.perf_counter() - t0
    print(
        f"identified I(t), B(t), K(t) from {ens.n} cycles of {ens.length / ens.fs:.3g} s ({args.method}) "
        f"in {t_est:.2f} s"
    )
    if any(ens.excluded.values()):
        print("  excluded cycles: " + ", ".join(f"{k} {v}" for k, v in ens.excluded.items() if v))
    summary = {"method": args.method, "cycles": ens.n, "excluded": ens.excluded, "warnings": list(est.warnings)}
    if ens.alignment is not None and args.align != "none":
        a = ens.alignment.summary()
        summary["alignment"] = a
        print(
            f"  alignment {a['method']}: shifts mean {a['mean_ms']:.1f} ms, std {a['std_ms']:.1f} ms, "
            f"max |{a['max_abs_ms']:.1f}| ms, {a['at_limit']} at the limit"
        )
        summary["warnings"] += a["warnings"]
    bands = bootstrap(ens, opt, args.bootstrap, seed=args.seed) if args.bootstrap > 0 else None
    fit = free_run_vaf(ens, opt, args.folds, seed=args.seed) if args.folds > 1 else None
    for k, unit in (("I", "kg m^2"), ("B", "N m s/rad"), ("K", "N m/rad")):
        v = getattr(est, k)
        print(
            f"  {k}: median {np.nanmedian(v):.4g} {unit}, range {np.nanmin(v):.4g} .. {np.nanmax(v):.4g}"
            + (f", mean 95 % band half-width {np.nanmean(bands.hi[k] - bands.lo[k]) / 2:.3g}" if bands else "")
        )
    print(
        f"  natural frequency median {np.nanmedian(est.wn) / 2 / np.pi:.3g} Hz, "
        f"damping ratio {np.nanmedian(est.zeta):.3g}"
    )
    if fit is not None:
        summary["vaf_free_run"] = fit.vaf
        print(f"  free-run VAF on held-out cycles ({fit.folds}-fold): {fit.vaf:.2f} %")
        if not fit.vaf > 90.0:
            summary["warnings"].append(
                f"free-run VAF {fit.vaf:.3g} % on held-out cycles: the identified model "
                "does not predict the perturbations"
            )
    posture = {}
    for f in args.posture:
        prec = read_record(f)
        pens = segment(prec, _posture_onsets(prec, args.period), period=args.period)
        posture[Path(f).stem] = posture_fit(pens, args.method if args.method != "thesis" else "default")
        print(
            f"  posture {Path(f).stem}: I {posture[Path(f).stem][0]:.4g}, B {posture[Path(f).stem][1]:.4g}, "
            f"K {posture[Path(f).stem][2]:.4g}"
        )
    summary["posture"] = posture
    truth = None
    if args.truth:
        truth = resample_truth(read_truth(args.truth), est.t)
        err = rel_errors(est, truth)
        summary["errors_vs_truth_percent"] = err
        line = "  mean |error| vs truth: " + ", ".join(f"{k} {v:.2f} %" for k, v in err.items())
        if bands:
            cov = {k: coverage(bands.lo[k], bands.hi[k], truth[k]) for k in "IBK"}
            summary["band_coverage"] = cov
            line += "; band coverage " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in cov.items())
        print(line)
    for w in summary["warnings"]:
        print(f"  warning: {w}", file=sys.stderr)
    if args.out:
        print(f"  wrote {write_results(args.out, est, bands, fit, summary)}")
    if args.plot:
        from closedloop.impedance.plots import plot_impedance

        print(f"  wrote {plot_impedance(args.plot, est, ens, bands, truth, posture)}")
    return 0


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise InputError(f"--prefilter {text}: expected a frequency in Hz or 'none'") from None


def _posture_onsets(rec, period: float | None):
    """Posture records: event onsets if present, else consecutive chunks of `period` (default 2 s)."""
    from closedloop.impedance.data import onsets_from_events, onsets_from_times

    if rec.event is not None and np.any(rec.event):
        return onsets_from_events(rec)
    return onsets_from_times(rec, np.arange(rec.time[0], rec.time[-1], period or 2.0))
