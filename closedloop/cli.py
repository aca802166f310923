"""The `closedloop` command line.  Printing happens here and only here.

User mistakes (`InputError`) print one line and exit with code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from .errors import ClosedLoopError, ConvergenceError, InputError, NotIdentifiableError

EXIT_INPUT = 2
EXIT_FAILED = 3  # a calibration whose verdict is 'failed' (the report says why)
EXIT_INTERNAL = 70


class _Progress:
    """A short progress line on stderr (one line, rewritten in place on a terminal)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.t0 = time.perf_counter()
        self.last = (None, -1.0)  # (stage, time) of the last line printed

    def __call__(self, stage: str, it: int, value: float) -> None:
        if self.quiet:
            return
        msg = f"  {stage}"
        if stage == "solving":
            msg += f": iteration {it}, cost {value:.3e}"
        elif stage == "validating":
            msg += ": k-fold held-out refits"
        elif stage == "simulating":
            msg += f": {it}/{int(value)} configurations"
        msg += f"  [{time.perf_counter() - self.t0:.1f} s]"
        now = time.perf_counter()
        if self.tty:
            print("\r" + msg.ljust(70), end="", file=sys.stderr, flush=True)
        elif stage != self.last[0] or now - self.last[1] > 1.0:  # logs: stage changes, then once a second
            print(msg, file=sys.stderr, flush=True)
            self.last = (stage, now)

    def done(self) -> None:
        if self.tty and not self.quiet:
            print(file=sys.stderr)


def _parse_noise(text: str | float | None):
    """``--noise 1e-4`` or ``--noise j1=1e-4,j2=2e-4``: every value a finite number > 0 (rad or m)."""
    from .schemas import parse_number

    if text is None:
        return None
    if not isinstance(text, str):
        text = repr(text)
    if "=" not in text:
        v = parse_number(text, f"--noise {text}")
        if not 0 < v <= 10:
            raise InputError(f"--noise {text}: the joint noise must be > 0 and <= 10 (a std in rad or m)")
        return v
    out = {}
    for part in text.split(","):
        k, _, v = (t.strip() for t in part.partition("="))
        if not k:
            raise InputError(f"--noise {part}: expected joint=value")
        out[k] = parse_number(v, f"--noise {part}")
        if not 0 < out[k] <= 10:
            raise InputError(f"--noise {part}: the joint noise must be > 0 and <= 10 (a std in rad or m)")
    return out


def _parse_bounds(items: list[str]) -> dict[str, tuple[float, float]]:
    """``--bound NAME=LOW:HIGH`` (an empty side is unbounded); LOW <= HIGH."""
    from .schemas import parse_number

    out = {}
    for item in items:
        name, eq, rng = item.partition("=")
        lo, colon, hi = rng.partition(":")
        if not eq or not colon or not name.strip():
            raise InputError(f"--bound {item}: expected NAME=LOW:HIGH")
        lo_v = parse_number(lo, f"--bound {item}", allow_inf=True) if lo.strip() else -np.inf
        hi_v = parse_number(hi, f"--bound {item}", allow_inf=True) if hi.strip() else np.inf
        if lo_v > hi_v:
            raise InputError(f"--bound {item}: the lower bound {lo.strip()} exceeds the upper bound {hi.strip()}")
        out[name.strip()] = (lo_v, hi_v)
    return out


def _check_number(opt: str, value, lo: float, hi: float, *, integer: bool = False, lo_open: bool = False):
    """A numeric option in range (``lo < v`` when `lo_open`, else ``lo <= v``; ``v <= hi``), as float/int."""
    from .schemas import is_number, parse_number

    v = parse_number(value, f"{opt} {value}") if isinstance(value, str) else value
    if not is_number(v) or (integer and float(v) != int(v)):
        raise InputError(f"{opt} {value}: expected {'a whole number' if integer else 'a finite number'}")
    if v < lo or (lo_open and v == lo) or v > hi:
        raise InputError(f"{opt} {value}: must be {'>' if lo_open else '>='} {lo:g} and <= {hi:g}")
    return int(v) if integer else float(v)


def _check_calibrate_options(args) -> tuple:
    """`calibrate`'s output paths and numeric options, checked before any work: (noise, bounds, cv given?)."""
    from .export import check_outputs

    check_outputs({"--out": args.out, "--report": args.report, "--html": getattr(args, "html", None)},
                  [args.model, args.log])
    if getattr(args, "plots", None):
        check_outputs({"--plots": args.plots}, [args.model, args.log], directory=True)
    args.snr = _check_number("--snr", args.snr, 0.0, 1e6, lo_open=True)
    args.max_iter = _check_number("--max-iter", args.max_iter, 1, 10**6, integer=True)
    cv_given = args.cv is not None  # (default None: 5 folds, fewer on a short log)
    args.cv = _check_number("--cv", args.cv, 0, 10**6, integer=True) if cv_given else 5
    if args.cv == 1:
        raise InputError("--cv 1: K-fold validation needs K >= 2 (or 0 to disable)")
    for spec in args.loop:
        _check_loop_numbers(spec)
    return _parse_noise(args.noise), _parse_bounds(args.bound), cv_given


def _check_loop_numbers(spec: str) -> None:
    """Numbers inside a ``--loop`` spec (closure, axis, point, ...) are decimal, finite and within 1e6."""
    import re

    from .schemas import MAX_ABS, parse_number

    for token in re.split(r"[\s,=:\"']+", spec):
        if re.fullmatch(r"[-+]?(\d[\d_]*\.?[\d_]*|\.\d[\d_]*)([eE][-+]?\d+)?|[-+]?(nan|inf|infinity)", token,
                        re.IGNORECASE):
            v = parse_number(token, f"--loop {spec}")
            if abs(v) > MAX_ABS:
                raise InputError(f"--loop {spec}: {token} is out of range (|value| <= {MAX_ABS:g})")


# --------------------------------------------------------------------------- commands
def cmd_calibrate(args) -> int:
    from .calibration import CalibrationOptions, calibrate
    from .export import OutputSet, write_model
    from .loops.spec import default_loops, parse_loop
    from .parameters import parse_fix
    from .report import build_report, write_report
    from .robot import RobotModel

    from .data import check_loop_column
    from .export import check_model_output

    noise, bounds, cv_given = _check_calibrate_options(args)  # outputs and numbers, before any work
    if args.threads is not None:
        args.threads = _check_number("--threads", args.threads, 0, 4096, integer=True)
    robot = RobotModel.from_file(args.model)
    check_model_output(robot.kind, args.out, args.model)
    loops = [parse_loop(s, robot) for s in args.loop] or default_loops(robot)
    if not loops:
        raise InputError("no --loop given: say how the chain is closed, e.g. --loop weld:frame=<tool frame>")
    from .cli_tools import read_log_or_bag

    lg = read_log_or_bag(args.log, robot, args.degrees)  # a CSV log or a ROS bag
    check_loop_column(lg, [lp.name for lp in loops])
    if args.cv > len(lg):
        if cv_given:
            raise InputError(f"--cv {args.cv}: more folds than the {len(lg)} rows of {args.log}")
        args.cv = len(lg) if len(lg) >= 2 else 0
    from .calibration import build_problem

    names = build_problem(robot, lg, loops).names
    opts = CalibrationOptions(identify=args.identify.split(",") if args.identify else None,
                              fix=parse_fix(args.fix, names), noise=noise,
                              weighting=args.weighting, max_iter=args.max_iter, snr=args.snr,
                              bounds=bounds, robust=None if args.robust == "off" else args.robust,
                              threads=args.threads)
    prog = _Progress(args.quiet)
    t0 = time.perf_counter()
    res = calibrate(robot, lg, loops, opts, progress=prog)
    prog.done()
    elapsed = time.perf_counter() - t0
    report = build_report(res, args.model, args.log)
    report["solver"]["seconds"] = elapsed
    cv = None
    if args.cv and res.converged:
        from .validation import cross_validate

        prog("validating", 0, 0.0)
        cv = cross_validate(robot, lg, loops, opts, k=args.cv)
        report["validation"] = {"k": args.cv, "test": cv["test"], "train": cv["train"],
                                "test_whitened_rms": cv.get("test_whitened_rms"),
                                "parameter_spread": cv.get("parameter_spread"),
                                "inconsistent": cv.get("inconsistent"),
                                "folds_converged": [f["converged"] for f in cv["folds"]]}
        prog.done()
    from .report import verdict_record
    from .verdict import judge

    res.verdict = judge(res, cv)  # the fit's evidence and the held-out folds'
    report["verdict"] = verdict_record(res.verdict)
    failed = res.verdict.status == "failed"
    write_out = args.out and (not failed or args.force)
    with OutputSet(order=[args.out if write_out else None, args.report]):  # published whole, model first
        if args.report:
            write_report(report, args.report)
        if write_out:
            write_model(robot, res.as_dict(), args.out)
    _print_summary(res, elapsed, args, report, wrote_model=bool(write_out))
    from .cli_tools import write_figures

    write_figures(res, report, args)  # --html / --plots
    if res.verdict.status == "suspect":
        print(f"warning: {args.log}: calibration is suspect: {'; '.join(res.verdict.reasons)}", file=sys.stderr)
    if failed:
        print(f"error: {args.log}: calibration failed: {'; '.join(res.verdict.reasons)}"
              + ("" if write_out or not args.out else f"; no model written to {args.out} (--force writes it)"),
              file=sys.stderr)
        return EXIT_FAILED
    return 0


def _print_summary(res, elapsed: float, args, report: dict, wrote_model: bool = True) -> None:
    b, a = res.residuals_before, res.residuals_after
    print(f"verdict: {res.verdict.status}" + (f" ({'; '.join(res.verdict.reasons)})" if res.verdict.reasons else ""))
    print(f"calibrated {len(res.estimated)} parameters from {sum(r.n for r in a)} configurations "
          f"in {res.iterations} iterations ({elapsed:.2f} s): {res.solver_status}")
    for rb, ra in zip(b, a):
        parts = []
        if rb.rms_m is not None:
            parts.append(f"{rb.rms_m * 1e3:.4g} mm -> {ra.rms_m * 1e3:.4g} mm")
        if rb.rms_rad is not None:
            parts.append(f"{rb.rms_rad * 1e3:.4g} mrad -> {ra.rms_rad * 1e3:.4g} mrad")
        if rb.rms_px is not None:
            parts.append(f"{rb.rms_px:.4g} px -> {ra.rms_px:.4g} px")
        print(f"  loop {ra.loop}: closure RMS " + ", ".join(parts))
    est = "estimated" if res.sigma_estimated else "given"
    print(f"  joint noise {res.sigma:.3g} ({est}); chi2/dof {res.chi2 / max(res.dof, 1):.3g}")
    if res.dropped:
        print(f"  {len(res.dropped)} redundant parameters dropped (see report: identifiability.dropped)")
    for c in res.weak:
        print(f"  not identifiable: {c.describe()}")
    for n in res.notes:
        print(f"  note: {n}")
    cv = report.get("validation")
    if cv:
        for t in cv["test"]:
            parts = [f"{t['rms_m'] * 1e3:.4g} mm" if t.get("rms_m") is not None else "",
                     f"{t['rms_rad'] * 1e3:.4g} mrad" if t.get("rms_rad") is not None else "",
                     f"{t['rms_px']:.4g} px" if t.get("rms_px") is not None else ""]
            print(f"  {cv['k']}-fold validation, loop {t['loop']}: held-out closure RMS "
                  + ", ".join(p for p in parts if p))
    for rj in res.rejected[:10]:
        print(f"  rejected: log row {rj.row} (loop {rj.loop}), {rj.standardized:.3g} robust standard deviations")
    if args.out and wrote_model:
        print(f"  wrote {args.out}")
    if args.report:
        print(f"  wrote {args.report}")


def cmd_inspect(args) -> int:
    from .parameters import RobotParameters
    from .robot import RobotModel

    robot = RobotModel.from_file(args.model)
    info = robot.describe()
    info["parameters"] = RobotParameters(robot, robot.joint_names).names
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"{info['source']} ({info['kind']}): {len(info['joints'])} movable joints")
    for j in info["joints"]:
        print(f"  {j['name']:<24} {j['type']:<10} axis {j['axis']}  [{j['lower']:.3g}, {j['upper']:.3g}]")
    for n, t in info["unsupported_joints"].items():
        print(f"  {n:<24} {t} (not calibrated)")
    for n, m in info.get("mimic_joints", {}).items():
        print(f"  {n:<24} mimics {m} (URDF <mimic>: no loop may pass through it)")
    print(f"frames: {', '.join(info['frames'])}")
    first = info["joints"][0]["name"] if info["joints"] else ""
    fields = [p.split(".", 1)[1] for p in info["parameters"] if p.split(".", 1)[0] == first]
    print(f"parameters per joint (<joint>.<field>): {', '.join(fields)}")
    return 0


def cmd_check(args) -> int:
    from .check import check_report

    tols = {o: _check_number(f"--{o.replace('_', '-')}", getattr(args, o), 0.0, 1e6, lo_open=True)
            for o in ("tol_m", "tol_rad", "tol_scale", "tol_px")}
    truth = _load_json(args.truth, "truth file")
    report = _load_json(args.report, "report file")
    rows, ok = check_report(truth, report, **tols, truth_source=args.truth, report_source=args.report)
    print(f"{'parameter':<28}{'true':>14}{'calibrated':>14}{'error':>12}{'tol':>10}  result")
    for r in rows:
        cal = "" if r["calibrated"] is None else f"{r['calibrated']:14.6g}"
        err = "" if r["error"] is None else f"{r['error']:12.3g}"
        tol = "" if r["tol"] is None else f"{r['tol']:10.3g}"
        print(f"{r['name']:<28}{r['true']:14.6g}{cal:>14}{err:>12}{tol:>10}  {r['result']}")
    bad = sum(r["result"] == "FAIL" for r in rows)
    print(f"{sum(r['result'] == 'ok' for r in rows)} within tolerance, {bad} outside, "
          f"{sum(r['result'] not in ('ok', 'FAIL') for r in rows)} not compared")
    return 0 if ok else 1


def cmd_simulate(args) -> int:
    try:
        from .sims import SCENARIOS, simulate
    except ImportError as exc:  # pragma: no cover - packaging error
        raise ClosedLoopError(f"the simulator is not installed ({exc})") from None
    from .cli_tools import resolve_scenario
    from .sims.camera_scene import SCENARIOS as CAMERA_SCENARIOS, simulate_cli as camera_simulate

    if getattr(args, "scenario", None) in CAMERA_SCENARIOS:  # the head-camera scenarios (sims/camera_scene.py)
        return camera_simulate(args)
    args.scenario = resolve_scenario(args)  # a built-in, a scenario YAML, or --robot + --loop
    if args.scenario not in SCENARIOS:
        raise InputError(f"unknown scenario '{args.scenario}' (known: {', '.join(sorted(SCENARIOS))})")
    from .export import check_outputs
    from .sims.dataset import check_dataset_dir

    args.n = _check_number("--n", args.n, 1, 10**7, integer=True)
    args.seed = _check_number("--seed", args.seed, 0, 2**63 - 1, integer=True)
    check_outputs({"--out": args.out}, directory=True)
    check_dataset_dir(Path(args.out), replace=getattr(args, "replace", False))
    overrides = _sim_overrides(args.set, SCENARIOS[args.scenario].settings)
    prog = _Progress(args.quiet)
    t0 = time.perf_counter()
    result = simulate(args.scenario, n=args.n, seed=args.seed, out_dir=Path(args.out),
                      progress=lambda i, n: prog("simulating", i, n), **overrides)
    prog.done()
    print(f"simulated {args.n} configurations of {args.scenario} in {time.perf_counter() - t0:.1f} s -> {args.out}")
    summary = getattr(result, "summary", None)
    if callable(summary):
        print(summary())
    return 0


def _sim_overrides(items: list[str], defaults) -> dict:
    """``--set KEY=VALUE`` items checked against the scenario's settings (type of each default)."""
    import dataclasses

    from .schemas import check_settings, is_number

    kinds = {f.name: type(getattr(defaults, f.name)) for f in dataclasses.fields(defaults)}
    kinds.update(soft=bool, stiff=bool)  # presets
    out: dict = {}
    for item in items:
        key, eq, text = (t.strip() for t in item.partition("="))
        if not eq or not key:
            raise InputError(f"--set {item}: expected KEY=VALUE")
        if key not in kinds:
            raise InputError(f"--set {item}: unknown setting '{key}' (known: {', '.join(sorted(kinds))})")
        kind, default = kinds[key], getattr(defaults, key, False)
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0"):
                raise InputError(f"--set {item}: '{key}' takes true or false")
            out[key] = text.lower() in ("true", "1")
        elif kind in (str, type(None)):  # a name (None: off by default)
            out[key] = None if kind is type(None) and text.lower() in ("", "none", "off") else text
        else:
            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                value = None
            n = len(default) if kind is tuple else 1
            nums = value if isinstance(value, list) else [value]
            if len(nums) != n or not all(is_number(v) for v in nums):
                want = f"a list of {n} numbers, e.g. {json.dumps(list(default))}" if kind is tuple else "a number"
                raise InputError(f"--set {item}: '{key}' takes {want}")
            if kind is int and not float(nums[0]).is_integer():
                raise InputError(f"--set {item}: '{key}' takes a whole number")
            out[key] = tuple(nums) if kind is tuple else kind(nums[0])
        v = out[key]
        check_settings({key: list(v) if isinstance(v, tuple) else v}, f"--set {item}")
    merged = {k: list(v) if isinstance(v, tuple) else v for k, v in {**defaults.as_dict(), **out}.items()}
    check_settings(merged, "--set")  # types and ranges (kp > 0, timestep > 0, noise >= 0, select a method...)
    return out


def _load_json(path: str, what: str = "JSON file"):
    from .schemas import load_json

    return load_json(path, what)


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="closedloop", description="Closed-loop kinematic calibration of robots.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = p.add_subparsers(dest="command", required=True)

    from .cli_tools import loop_help

    c = sub.add_parser("calibrate", help="calibrate a model from a joint log", epilog=loop_help(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("model", help="URDF, MJCF (.xml) or D-H table (.yaml)")
    c.add_argument("log", help="CSV: header of joint names, one row per configuration; or a ROS bag "
                               "(.bag, ROS 2 bag directory, .mcap, .db3) of sensor_msgs/JointState")
    c.add_argument("--loop", action="append", default=[], metavar="SPEC",
                   help="loop closure TYPE:key=value,..., e.g. weld:frame=panda_hand (repeatable; types below)")
    c.add_argument("--html", help="self-contained HTML report with figures")
    c.add_argument("--plots", metavar="DIR", help="write the report's figures as PNG files in DIR")
    c.add_argument("--config", help="YAML file holding any of these options (the command line wins)")
    c.add_argument("--out", help="calibrated model (URDF or D-H YAML, like the input)")
    c.add_argument("--report", help="JSON report")
    c.add_argument("--identify", help="comma-separated parameter patterns (placement, offset, scale, loop, globs)")
    c.add_argument("--fix", action="append", default=[], metavar="NAME[=VALUE]", help="hold a parameter fixed")
    c.add_argument("--noise", help="joint reading std (rad), one number or joint=value,...; default: estimated")
    c.add_argument("--weighting", choices=["noise", "none"], default="noise",
                   help="noise: errors-in-variables weighting (default); none: plain loop residual (thesis)")
    c.add_argument("--bound", action="append", default=[], metavar="NAME=LOW:HIGH", help="bound a parameter")
    c.add_argument("--snr", type=_float_arg, default=1.0, help="SVD truncation: keep directions above snr * noise")
    c.add_argument("--robust", choices=["auto", "huber", "cauchy", "off"], default="auto",
                   help="outliers: auto (default) rejects configurations the noise cannot explain, after a robust "
                        "refit; huber/cauchy keep a robust loss in the final fit; off trusts every row")
    c.add_argument("--force", action="store_true",
                   help="write the calibrated model even when the verdict is 'failed'")
    c.add_argument("--cv", type=_int_arg, default=None, metavar="K",
                   help="K-fold held-out validation in the report (default 5; 0 disables)")
    c.add_argument("--max-iter", type=_int_arg, default=100)
    c.add_argument("--threads", type=_int_arg, default=None, metavar="N",
                   help="BLAS threads for the fit (default: 1 for small problems, more only for very large "
                        "ones on idle cores; 0: keep the environment's setting)")
    c.add_argument("--degrees", action="store_true", help="the log is in degrees")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_calibrate)

    i = sub.add_parser("inspect", help="list a model's joints, frames and parameter names")
    i.add_argument("model")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_inspect)

    from .cli_tools import add_simulate_robot_options, scenario_help

    s = sub.add_parser("simulate", help="generate a closed-chain dataset in MuJoCo", epilog=scenario_help(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("scenario", nargs="?", help="a scenario name (below) or a scenario YAML file")
    add_simulate_robot_options(s)
    s.add_argument("--n", type=_int_arg, default=200)
    s.add_argument("--seed", type=_int_arg, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scenario setting")
    s.add_argument("--replace", action="store_true", help="replace the dataset already in --out (refused otherwise)")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_simulate)

    k = sub.add_parser("check", help="compare a calibration report with simulation truth")
    k.add_argument("truth")
    k.add_argument("report")
    k.add_argument("--tol-m", type=_float_arg, default=1e-3, help="tolerance for lengths (m)")
    k.add_argument("--tol-rad", type=_float_arg, default=5e-3, help="tolerance for angles (rad)")
    k.add_argument("--tol-scale", type=_float_arg, default=5e-3, help="tolerance for scale factors")
    k.add_argument("--tol-px", type=_float_arg, default=1.0, help="tolerance for camera intrinsics (px)")
    k.set_defaults(func=cmd_check)

    from .cli_tools import add_extract_parser, cmd_loops

    add_extract_parser(sub)
    from .batch import add_parser as add_batch  # closedloop batch MANIFEST (many jobs, any executor)

    add_batch(sub)
    lp = sub.add_parser("loops", help="list the loop types, their keys and an example each")
    lp.set_defaults(func=cmd_loops)
    from .impedance.cli import add_parser as add_impedance  # closedloop impedance simulate|identify

    add_impedance(sub)
    return p


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (an `InputError`, exit 2) instead of a usage block."""

    def error(self, message: str):
        raise InputError(f"{self.prog}: {message} (see {self.prog} --help)")


class _ArgTypeError(argparse.ArgumentTypeError, ValueError):
    """A bad option value: argparse reports it in one line; a --config loader catches the ValueError."""


def _float_arg(text: str) -> float:
    from .schemas import parse_number

    try:
        return parse_number(text, text)
    except InputError as exc:
        raise _ArgTypeError(str(exc)) from None


def _int_arg(text: str) -> int:
    v = _float_arg(text)
    if v != int(v):
        raise _ArgTypeError(f"{text}: expected a whole number")
    return int(v)


def _join_negative_numbers(argv: list[str]) -> list[str]:
    """``--noise -1e-4`` -> ``--noise=-1e-4``: argparse takes '-1e-4' for an option (and prints usage)."""
    import re

    neg = re.compile(r"^-(\d|\.\d|inf|nan)", re.IGNORECASE)
    out: list[str] = []
    for a in argv:
        if out and neg.match(a) and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


class _Signal(KeyboardInterrupt):
    """SIGTERM / SIGHUP raised as an exception, so that every cleanup (temporary outputs) runs."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _raise_signal(signum, _frame):
    raise _Signal(signum)


def main(argv: list[str] | None = None) -> int:
    """Run one command.  Exit codes: 0 ok, 1 check outside tolerance, 2 a user's mistake (one line on
    stderr), 130 interrupted (Ctrl-C; 128 + signal number for SIGTERM/SIGHUP), 70 an internal error."""
    import signal
    import threading

    from .cli_tools import parse_args

    argv = _join_negative_numbers(list(sys.argv[1:] if argv is None else argv))
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            handlers[sig] = signal.signal(sig, _raise_signal)
    verbose = "-v" in argv or "--verbose" in argv
    try:
        args = parse_args(build_parser(), argv)  # applies a subcommand's --config FILE
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s")
        return args.func(args)
    except SystemExit as exc:  # --help, --version, a --config loader that already printed its line
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(f"error: {exc.code}", file=sys.stderr)
        return EXIT_INPUT
    except (ConvergenceError, NotIdentifiableError) as exc:  # the data cannot give a calibration: failed
        print(f"error: calibration failed: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except ClosedLoopError as exc:  # InputError and its kin: the user's mistake, one line
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", None)
        print(("\n" if sys.stderr.isatty() else "") + "interrupted" + (f" (signal {signum})" if signum else "")
              + "; outputs not yet published were discarded", file=sys.stderr)
        return 128 + signum if signum else 130
    except OSError as exc:  # a file system refusal the checks could not foresee (disk full, ...)
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT
    except MemoryError:
        print("error: out of memory (a smaller log or fewer parameters may fit)", file=sys.stderr)
        return EXIT_INPUT
    except Exception as exc:  # a bug: still one line, the traceback with -v
        if verbose:
            import traceback

            traceback.print_exc()
        print(f"error: internal error ({type(exc).__name__}: {_one_line(exc)}); this is a bug in closedloop, "
              "please report it (rerun with -v for the traceback)", file=sys.stderr)
        return EXIT_INTERNAL
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 2000 else text[:1997] + "..."


if __name__ == "__main__":
    sys.exit(main())
