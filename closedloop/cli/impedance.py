"""`closedloop impedance simulate ...` and `closedloop impedance identify DATA ...` (printing lives here)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from closedloop.errors import InputError, require


def add_parser(subparsers) -> None:
    """Register `impedance` with its `simulate` and `identify` subcommands."""
    p = subparsers.add_parser("impedance", help="time-varying joint impedance identification (thesis Part II)")
    sub = p.add_subparsers(dest="impedance_command", required=True)

    s = sub.add_parser("simulate", help="simulate perturbed cyclic movements with ground truth")
    s.add_argument("--out", required=True, metavar="DIR", help="output folder: data.csv|.h5, truth.csv, posture_*")
    s.add_argument("--case", choices=["forearm", "robot"], default="forearm", help="the thesis forearm or a robot")
    s.add_argument("--engine", choices=["mujoco", "rk4"], default="mujoco", help="forearm integrator")
    s.add_argument("--cycles", default="100", help="number of usable cycles (default 100)")
    s.add_argument(
        "--stiffness",
        default="constant:20",
        help="K(t), N m/rad, positive: constant:V | step:V0,V1,T | square:V0,V1,P | dip:V,DEPTH,WIDTH",
    )
    s.add_argument("--damping", default="constant:1", help="B(t), N m s/rad, not negative; same forms")
    s.add_argument("--noise", default="0.05", help="noise std / perturbation std (default 0.05)")
    s.add_argument("--voluntary", default="0", help="voluntary torque RMS, N m (3 Hz band; default 0)")
    s.add_argument("--prbs-phase", choices=["random", "locked"], default="random", help="PRBS clock per cycle")
    s.add_argument("--no-gravity", action="store_true", help="horizontal plane")
    s.add_argument(
        "--shoulder",
        metavar="ANGLE,K,B",
        help="robot case: the shoulder's held angle (rad), stiffness (N m/rad) and damping (N m s/rad) "
        "(default 0.5,200000,500: still at the elbow's frequencies)",
    )
    s.add_argument("--postures", action="store_true", help="also simulate holding 0, 0.5 and 1 rad (10 s each)")
    s.add_argument("--format", choices=["csv", "h5"], default="csv", help="record format (h5 needs h5py)")
    s.add_argument("--seed", default="0", help="random seed, a whole number >= 0 (default 0)")
    s.set_defaults(func=cmd_simulate)

    i = sub.add_parser("identify", help="identify I(t), B(t), K(t) from a recording")
    i.add_argument("data", help="CSV or HDF5: time (s), angle (rad), torque (N m), [command, event, block]")
    i.add_argument(
        "--columns",
        metavar="NAME=COLUMN,...",
        help="map the file's column names to time, angle, torque, command, event, block (e.g. command=perturbation)",
    )
    i.add_argument("--torque-sign", choices=["1", "-1"], default="1", help="-1: the torque was recorded reversed")
    i.add_argument(
        "--method",
        choices=["default", "thesis", "ols", "iv"],
        default="default",
        help="default: TLS, switching to IV when the command shows voluntary torque",
    )
    i.add_argument(
        "--prefilter",
        default="auto",
        metavar="HZ|auto|none",
        help="zero-phase low-pass: Hz, 'auto' (from the data) or 'none'",
    )
    i.add_argument("--lag-ms", default=None, help="lag spacing of the discrete model, ms (> 0; default 20)")
    i.add_argument("--pool-ms", default=None, help="equations pooled over +-ms (>= 0; default 20, IV 50)")
    i.add_argument("--smooth-ms", default=None, help="Gaussian smoothing of the parameters, ms (>= 0)")
    i.add_argument(
        "--segment",
        default="auto",
        help="auto | events | peak-velocity | onsets:FILE (a list of times or a CSV with an 'onset' or 'time' column)",
    )
    i.add_argument("--period", default=None, help="cycle length (s, > 0); default: median onset spacing")
    i.add_argument(
        "--align",
        default="auto",
        choices=["auto", "none", "peak-velocity", "rms", "peak-velocity+rms"],
        help="auto (default): the onsets checked against the model, the cycles re-aligned by it when they are "
        "off (with a note); none: checked only (a warning); peak-velocity, rms: the thesis's alignment, then auto",
    )
    i.add_argument("--max-shift-ms", default="50", help="largest alignment shift, ms (default 50)")
    i.add_argument("--bootstrap", default="200", metavar="R", help="resamples for 95 %% bands (0: none; default 200)")
    i.add_argument("--folds", default="5", help="k-fold free-run VAF on held-out cycles (0: none; default 5)")
    i.add_argument("--truth", metavar="FILE", help="truth CSV (t, I, B, K) to compare with")
    i.add_argument("--posture", action="append", default=[], metavar="FILE", help="posture record (repeatable)")
    i.add_argument("--out", metavar="FILE", help="results table, .csv or .json (written whole, never onto an input)")
    i.add_argument("--plots", metavar="DIR", help="write the figure as DIR/impedance.png")
    i.add_argument("--seed", default="0", help="bootstrap and fold seed, a whole number >= 0 (default 0)")
    i.set_defaults(func=cmd_identify)


def cmd_simulate(args: argparse.Namespace) -> int:
    from closedloop.impedance.data import record_bytes
    from closedloop.impedance.model import ExperimentConfig, ForearmParams, Profile
    from closedloop.impedance.results import write_truth
    from closedloop.impedance.simulation import simulate
    from closedloop.io.files import OutputSet, atomic_write_text, check_outputs
    from closedloop.run.options import check_number

    args.noise = check_number("--noise", args.noise, 0.0, 10.0)
    args.voluntary = check_number("--voluntary", args.voluntary, 0.0, 1e3)
    args.cycles = check_number("--cycles", args.cycles, 1, 10**5, integer=True)
    args.seed = check_number("--seed", args.seed, 0, 10**9, integer=True)
    if args.format == "h5":
        require("h5py", "--format h5", "impedance")
    shoulder = None
    if args.shoulder is not None:
        if args.case != "robot":
            raise InputError("--shoulder: only the robot case has a shoulder (--case robot)")
        parts = args.shoulder.split(",")
        if len(parts) != 3:
            raise InputError(f"--shoulder {args.shoulder}: give ANGLE,K,B (rad, N m/rad, N m s/rad)")
        angle = check_number("--shoulder angle", parts[0], -3.2, 3.2)
        k = check_number("--shoulder stiffness", parts[1], 1e-3, 1e9)
        b = check_number("--shoulder damping", parts[2], 0.0, 1e7)
        shoulder = (float(angle), float(k), float(b))
    if args.case == "robot":  # what only the forearm simulates is refused, not ignored
        for given, opt in ((args.voluntary > 0, "--voluntary"), (args.postures, "--postures")):
            if given:
                raise InputError(f"{opt}: the robot case does not simulate it (only --case forearm does)")
    check_outputs({"--out": args.out}, directory=True)
    out = Path(args.out)
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

        sim = simulate_robot(cfg) if shoulder is None else simulate_robot(cfg, shoulder)
    else:
        if args.engine == "mujoco":
            from closedloop.impedance.mujoco_sim import forearm_truth
        sim = simulate(cfg, args.engine)
        if args.engine == "mujoco":
            sim.truth = forearm_truth(cfg)
    data = out / f"data.{args.format}"
    lines = [
        f"simulated {cfg.n_cycles} cycles ({args.case}, {args.engine if args.case == 'forearm' else 'mujoco'}) "
        f"in {sim.seconds:.2f} s -> {data}",
        f"  noise std: angle {sim.noise_std[0]:.3g} rad, torque {sim.noise_std[1]:.3g} N m; "
        f"truth -> {out / 'truth.csv'}",
    ]
    with OutputSet(order=[data, out / "truth.csv"]):  # the whole set, or nothing (a full disk included)
        atomic_write_text(data, record_bytes(sim.record, args.format))
        write_truth(out / "truth.csv", sim.truth)
        if args.postures and args.case == "forearm":
            k0, b0 = cfg.stiffness.values[0], cfg.damping.values[0]  # postures: the profiles' base values
            for q in (0.0, 0.5, 1.0):
                pc = ExperimentConfig(
                    n_cycles=5,
                    cycles_per_block=5,
                    stiffness=Profile("constant", (k0,)),
                    damping=Profile("constant", (b0,)),
                    noise=args.noise,
                    posture=q,
                    seed=args.seed + 1,
                    arm=arm,
                )
                ps = simulate(pc, "rk4")
                atomic_write_text(out / f"posture_{q:g}.{args.format}", record_bytes(ps.record, args.format))
                kq = ps.truth["K"][0]
                lines.append(
                    f"  posture {q:g} rad -> {out / f'posture_{q:g}.{args.format}'} (true K_eff {kq:.2f} N m/rad)"
                )
    print("\n".join(lines))
    return 0


def read_onsets(path: Path) -> np.ndarray:
    """Onset times (s) from a plain list (one per line) or a CSV with a header: the column named onset,
    onsets, onset_time, time, t or start (case-insensitive), or the only column."""
    from closedloop.impedance.data import ImpedanceDataError
    from closedloop.io.schemas import parse_number

    if not path.is_file():
        raise ImpedanceDataError(f"{path}: no such onsets file")
    try:
        lines = [ln.strip() for ln in path.read_text().splitlines()]
    except UnicodeDecodeError:
        raise ImpedanceDataError(f"{path}: not a text file of onset times") from None
    rows = [
        (k + 1, [c.strip() for c in ln.replace(";", ",").replace("\t", ",").split(",")]) for k, ln in enumerate(lines)
    ]
    rows = [(k, r) for k, r in rows if any(r) and not r[0].startswith("#")]
    if not rows:
        raise ImpedanceDataError(f"{path}: no onset times")
    col = 0
    first = rows[0][1]
    try:
        [float(c) for c in first]
    except ValueError:  # a header row
        names = [c.lower() for c in first]
        for want in ("onset", "onsets", "onset_time", "onset_s", "time", "t", "start"):
            if want in names:
                col = names.index(want)
                break
        else:
            if len(names) != 1:
                raise ImpedanceDataError(
                    f"{path}: no onset column among {', '.join(first)} (name it 'onset' or 'time')"
                ) from None
        rows = rows[1:]
    times = []
    for k, r in rows:
        if col >= len(r):
            raise ImpedanceDataError(f"{path}: line {k} has {len(r)} columns, the onsets are in column {col + 1}")
        times.append(parse_number(r[col], f"{path}: line {k}", ImpedanceDataError))
    return np.asarray(times, float)


def _cycle_period(rec) -> float:
    """The movement's period (s) from the angle's spectrum: the strongest frequency below 5 Hz."""
    from closedloop.impedance.filters import welch

    a = rec.angle[: min(len(rec.angle), int(600 * rec.fs))]
    a = np.nan_to_num(a - np.nanmean(a))
    f, P = welch(a, fs=rec.fs, nperseg=min(len(a), int(60 * rec.fs)))
    band = (f > 0.05) & (f < 5)
    if not band.any():
        raise InputError("cannot find the movement's period: give --period or --segment")
    return float(1.0 / f[band][np.argmax(P[band])])


def _onsets(rec, args, notes: list[str]):
    from closedloop.impedance.data import onsets_from_events, onsets_from_peak_velocity, onsets_from_times

    seg = args.segment
    if seg == "auto":
        if rec.event is not None and len(onsets_from_events(rec)) >= 3:
            seg = "events"
        else:
            seg = "peak-velocity"
            if not args.period:
                args.period = round(_cycle_period(rec), 3)
            notes.append(
                f"no event column with cycle onsets: cycles cut by peak velocity, period {args.period:g} s "
                "(give --segment onsets:FILE or an 'event' column if the pacing is known)"
            )
    if seg == "events":
        return onsets_from_events(rec)
    if seg == "peak-velocity":
        if not args.period:
            raise InputError("--segment peak-velocity needs --period")
        return onsets_from_peak_velocity(rec, args.period)
    if seg.startswith("onsets:"):
        return onsets_from_times(rec, read_onsets(Path(seg[7:])))
    raise InputError(f"--segment {args.segment}: expected auto, events, peak-velocity or onsets:FILE")


def _check_identify_options(args: argparse.Namespace) -> None:
    """Every option of `identify` checked where it is parsed: one line, before any work."""
    from closedloop.io.files import check_outputs
    from closedloop.io.schemas import parse_number
    from closedloop.run.options import check_number

    args.max_shift_ms = check_number("--max-shift-ms", args.max_shift_ms, 0.0, 1e4)
    args.bootstrap = check_number("--bootstrap", args.bootstrap, 0, 10**5, integer=True)
    args.folds = check_number("--folds", args.folds, 0, 1000, integer=True)
    if args.folds == 1:
        raise InputError("--folds 1: give 0 (no VAF) or at least 2 folds")
    args.seed = check_number("--seed", args.seed, 0, 10**9, integer=True)
    if args.lag_ms is not None:
        args.lag_ms = check_number("--lag-ms", args.lag_ms, 0.0, 1000.0, lo_open=True)
    if args.pool_ms is not None:
        args.pool_ms = check_number("--pool-ms", args.pool_ms, 0.0, 1000.0)
    if args.smooth_ms is not None:
        args.smooth_ms = check_number("--smooth-ms", args.smooth_ms, 0.0, 1000.0)
    if args.period is not None:
        args.period = check_number("--period", args.period, 0.0, 1e4, lo_open=True)
    pre = str(args.prefilter).strip().lower()
    if pre in ("auto", "none"):
        args.prefilter = {"auto": "auto", "none": 0.0}[pre]
    else:
        v = parse_number(args.prefilter, f"--prefilter {args.prefilter}")
        if v <= 0:
            raise InputError(f"--prefilter {args.prefilter}: a cut-off in Hz must be > 0 (or 'none', 'auto')")
        args.prefilter = v
    from closedloop.impedance.data import parse_columns

    args.columns = parse_columns(args.columns)
    if args.out and Path(args.out).suffix.lower() not in (".csv", ".json"):
        raise InputError(f"--out {args.out}: give a .csv, .json file")
    if args.plots:
        require("matplotlib", "--plots", "impedance")
    from closedloop.impedance.data import is_hdf5

    for f in [args.data, *args.posture]:
        if Path(f).is_file() and is_hdf5(f):
            require("h5py", f"{f} (an HDF5 record)", "impedance")
    onsets = args.segment[7:] if args.segment.startswith("onsets:") else None
    inputs = [args.data, args.truth, onsets, *args.posture]
    check_outputs({"--out": args.out}, inputs)
    check_outputs({"--plots": args.plots}, inputs, directory=True)
    if args.plots:
        check_outputs({"--plots": str(Path(args.plots) / "impedance.png")}, inputs)


def cmd_identify(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from closedloop.impedance.bootstrap import bootstrap, free_run_vaf
    from closedloop.impedance.data import read_record, segment
    from closedloop.impedance.estimate import EstimateOptions, estimate, posture_fit
    from closedloop.impedance.metrics import coverage, rel_errors
    from closedloop.impedance.results import read_truth, resample_truth, write_results
    from closedloop.impedance.timing import check_timing
    from closedloop.io.files import OutputSet

    _check_identify_options(args)
    t0 = time.perf_counter()
    rec = read_record(args.data, args.columns, float(args.torque_sign))
    truth_raw = read_truth(args.truth) if args.truth else None
    notes = list(rec.notes)
    opt = EstimateOptions.for_method(
        args.method,
        prefilter_hz=args.prefilter,
        lag_ms=args.lag_ms,
        pool_ms=args.pool_ms,
        smooth_ms=args.smooth_ms,
    )
    align = "none" if args.align in ("auto", "none") else args.align
    onsets = _onsets(rec, args, notes)
    ens = segment(rec, onsets, period=args.period, align=align, max_shift_s=args.max_shift_ms / 1e3)
    est = estimate(ens, options=opt, warn=False)
    if np.nanmedian(est.I) < 0 and np.nanmedian(est.K) < 0:
        raise InputError(
            f"{args.data}: the estimated inertia and stiffness are negative (median I {np.nanmedian(est.I):.3g}): "
            "is the torque sign reversed? (positive torque must turn toward increasing angle; --torque-sign -1)"
        )
    timing = check_timing(rec, ens, est, opt, args.align != "none", args.max_shift_ms / 1e3, onsets, args.period)
    ens, est = timing.ensemble, timing.estimate
    notes += timing.notes + est.notes
    opt = est.options
    t_est = time.perf_counter() - t0
    method = opt.method if opt.method != "default" else "default, TLS"
    out = [
        f"identified I(t), B(t), K(t) from {ens.n} cycles of {ens.length / ens.fs:.3g} s ({method}, pre-filter "
        + (f"{opt.prefilter_hz:g} Hz" if opt.prefilter_hz else "none")
        + f") in {t_est:.2f} s"
    ]
    if any(ens.excluded.values()):
        out.append("  excluded cycles: " + ", ".join(f"{k} {v}" for k, v in ens.excluded.items() if v))
    warnings = list(est.warnings) + timing.warnings
    summary = {
        "method": opt.method,
        "prefilter_hz": opt.prefilter_hz,
        "cycles": ens.n,
        "excluded": ens.excluded,
        "notes": notes,
        "warnings": warnings,
        "onset_check": timing.summary,
    }
    if ens.alignment is not None and align != "none":
        a = ens.alignment.summary()
        summary["alignment"] = a
        out.append(
            f"  alignment {a['method']}: shifts mean {a['mean_ms']:.1f} ms, std {a['std_ms']:.1f} ms, "
            f"max |{a['max_abs_ms']:.1f}| ms, {a['at_limit']} at the limit"
        )
        warnings += [w for w in a["warnings"] if w not in warnings]
    bands = bootstrap(ens, opt, args.bootstrap, seed=args.seed, est=est) if args.bootstrap > 0 else None
    fit = free_run_vaf(ens, replace(opt, auto_iv=False), args.folds, seed=args.seed) if args.folds > 1 else None
    for k, unit in (("I", "kg m^2"), ("B", "N m s/rad"), ("K", "N m/rad")):
        v = getattr(est, k)
        out.append(
            f"  {k}: median {np.nanmedian(v):.4g} {unit}, range {np.nanmin(v):.4g} .. {np.nanmax(v):.4g}"
            + (f", mean 95 % band half-width {np.nanmean(bands.hi[k] - bands.lo[k]) / 2:.3g} {unit}" if bands else "")
        )
    out.append(
        f"  natural frequency median {np.nanmedian(est.wn) / 2 / np.pi:.3g} Hz, "
        f"damping ratio {np.nanmedian(est.zeta):.3g}"
    )
    if bands is not None:
        expected = {
            k: float(100 * np.nanmean(bands.std[k] / np.abs(getattr(est, k)))) for k in "IBK"
        }  # the bootstrap's std, relative, averaged over the cycle
        summary["expected_error_percent"] = expected
        out.append("  expected error (bootstrap std): " + ", ".join(f"{k} {v:.2f} %" for k, v in expected.items()))
        if bands.bias is not None:
            bias = {k: float(100 * np.nanmean(np.abs(bands.bias[k] / getattr(est, k)))) for k in "IBK"}
            summary["simulated_bias_percent"] = bias
            out.append(
                "  estimator bias at this model (simulated; the 95 % bands are widened by it): "
                + ", ".join(f"{k} {v:.2f} %" for k, v in bias.items())
            )
        worst = max(expected.values())
        if worst > 2.0:
            need = int(np.ceil(ens.n * (worst / 1.5) ** 2))
            warnings.append(
                f"{ens.n} cycles give an expected error up to {worst:.1f} % (bootstrap std); about {need} cycles "
                "would bring it to 1.5 %"
            )
    from closedloop.impedance.modelcheck import model_check

    check = model_check(ens, est, seed=args.seed)
    if check is None:
        summary["model_check"] = {"made": False, "reason": f"not made for the {opt.method} estimate"}
    else:
        summary["model_check"] = {"made": True, **check.summary()}
        out.append("  " + check.line())
        if check.fires:
            warnings.append(check.warning())
    if fit is not None:
        summary["vaf_free_run"] = fit.vaf
        iv = opt.method == "iv"
        out.append(
            f"  free-run VAF (variance accounted for) on held-out cycles ({fit.folds}-fold): {fit.vaf:.2f} %"
            + (" (unmeasured voluntary torque moves the limb too: no model predicts all of it)" if iv else "")
        )
        if not fit.vaf > 90.0 and not iv:
            warnings.append(
                f"free-run VAF {fit.vaf:.3g} % on held-out cycles: the identified model does not predict the "
                "perturbations (unmeasured torque? compare with --method iv)"
            )
    posture = {}
    for f in args.posture:
        prec = read_record(f, args.columns, float(args.torque_sign))
        pens = segment(prec, _posture_onsets(prec, args.period), period=args.period)
        posture[Path(f).stem] = posture_fit(pens, args.method if args.method not in ("thesis", "iv") else "default")
        out.append(
            f"  posture {Path(f).stem}: I {posture[Path(f).stem][0]:.4g}, B {posture[Path(f).stem][1]:.4g}, "
            f"K {posture[Path(f).stem][2]:.4g}"
        )
    summary["posture"] = posture
    truth = None
    if truth_raw is not None:
        truth = resample_truth(truth_raw, est.t)
        err = rel_errors(est, truth)
        summary["errors_vs_truth_percent"] = err
        line = "  mean |error| vs truth: " + ", ".join(f"{k} {v:.2f} %" for k, v in err.items())
        if bands:
            cov = {k: coverage(bands.lo[k], bands.hi[k], truth[k]) for k in "IBK"}
            summary["band_coverage"] = cov
            line += "; band coverage " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in cov.items())
        out.append(line)
    out += [f"  note: {n}" for n in notes]
    print("\n".join(out))
    for w in warnings:
        print(f"  warning: {w}", file=sys.stderr)
    fig = str(Path(args.plots) / "impedance.png") if args.plots else None
    with OutputSet(order=[args.out, fig]):  # published together, whole
        if args.out:
            write_results(args.out, est, bands, fit, summary)
        if fig:
            from closedloop.impedance.plots import plot_impedance

            plot_impedance(fig, est, ens, bands, truth, posture)
    for p in (args.out, fig):
        if p:
            print(f"  wrote {p}")
    return 0


def _posture_onsets(rec, period: float | None):
    """Posture records: event onsets if present, else consecutive chunks of `period` (default 2 s)."""
    from closedloop.impedance.data import onsets_from_events, onsets_from_times

    if rec.event is not None and np.any(rec.event):
        return onsets_from_events(rec)
    return onsets_from_times(rec, np.arange(rec.time[0], rec.time[-1], period or 2.0))
