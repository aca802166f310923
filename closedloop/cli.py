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

from .errors import ClosedLoopError, InputError

EXIT_INPUT = 2


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


def _parse_noise(text: str | None):
    if text is None:
        return None
    if "=" not in text:
        try:
            return float(text)
        except ValueError:
            raise InputError(f"--noise {text}: expected a number or joint=value pairs") from None
    out = {}
    for part in text.split(","):
        k, _, v = part.partition("=")
        try:
            out[k.strip()] = float(v)
        except ValueError:
            raise InputError(f"--noise {part}: '{v}' is not a number") from None
    return out


def _parse_bounds(items: list[str]) -> dict[str, tuple[float, float]]:
    out = {}
    for item in items:
        name, _, rng = item.partition("=")
        lo, _, hi = rng.partition(":")
        try:
            out[name.strip()] = (float(lo) if lo.strip() else -np.inf, float(hi) if hi.strip() else np.inf)
        except ValueError:
            raise InputError(f"--bound {item}: expected NAME=LOW:HIGH") from None
    return out


# --------------------------------------------------------------------------- commands
def cmd_calibrate(args) -> int:
    from .calibration import CalibrationOptions, calibrate
    from .data import read_log
    from .export import refuse_overwrite, write_model
    from .loops.spec import default_loops, parse_loop
    from .parameters import parse_fix
    from .report import build_report, write_report
    from .robot import RobotModel

    robot = RobotModel.from_file(args.model)
    loops = [parse_loop(s, robot) for s in args.loop] or default_loops(robot)
    if not loops:
        raise InputError("no --loop given: say how the chain is closed, e.g. --loop weld:frame=<tool frame>")
    for out in (args.out, args.report):
        if out:
            refuse_overwrite(out, args.model, args.log)
    lg = read_log(args.log, robot.joint_names, degrees=args.degrees,
                  linear=[j for j, info in robot.joints.items() if info.kind == "prismatic"])
    from .calibration import build_problem

    names = build_problem(robot, lg, loops).names
    opts = CalibrationOptions(identify=args.identify.split(",") if args.identify else None,
                              fix=parse_fix(args.fix, names), noise=_parse_noise(args.noise),
                              weighting=args.weighting, max_iter=args.max_iter, snr=args.snr,
                              bounds=_parse_bounds(args.bound), robust=args.robust)
    prog = _Progress(args.quiet)
    t0 = time.perf_counter()
    res = calibrate(robot, lg, loops, opts, progress=prog)
    prog.done()
    elapsed = time.perf_counter() - t0
    report = build_report(res, args.model, args.log)
    report["solver"]["seconds"] = elapsed
    if args.cv and res.converged:
        from .validation import cross_validate

        prog("validating", 0, 0.0)
        cv = cross_validate(robot, lg, loops, opts, k=args.cv)
        report["validation"] = {"k": args.cv, "test": cv["test"], "train": cv["train"],
                                "test_whitened_rms": cv.get("test_whitened_rms"),
                                "parameter_spread": cv.get("parameter_spread"),
                                "inconsistent": cv.get("inconsistent")}
        prog.done()
    if not res.converged:
        if args.report:
            write_report(report, args.report)
        print(f"error: {args.log}: calibration did not converge ({res.solver_message}); "
              f"report written to {args.report}" if args.report else
              f"error: {args.log}: calibration did not converge ({res.solver_message})", file=sys.stderr)
        return EXIT_INPUT
    if args.report:
        write_report(report, args.report)
    if args.out:
        write_model(robot, res.as_dict(), args.out)
    _print_summary(res, elapsed, args, report)
    return 0


def _print_summary(res, elapsed: float, args, report: dict) -> None:
    b, a = res.residuals_before, res.residuals_after
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
    if args.out:
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
    print(f"frames: {', '.join(info['frames'])}")
    first = info["joints"][0]["name"] if info["joints"] else ""
    fields = [p.split(".", 1)[1] for p in info["parameters"] if p.split(".", 1)[0] == first]
    print(f"parameters per joint (<joint>.<field>): {', '.join(fields)}")
    return 0


def cmd_check(args) -> int:
    from .check import check_report

    truth = _load_json(args.truth)
    report = _load_json(args.report)
    rows, ok = check_report(truth, report, tol_m=args.tol_m, tol_rad=args.tol_rad, tol_scale=args.tol_scale,
                              tol_px=args.tol_px)
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
    if args.scenario not in SCENARIOS:
        raise InputError(f"unknown scenario '{args.scenario}' (known: {', '.join(sorted(SCENARIOS))})")
    if args.n < 1:
        raise InputError("--n must be at least 1")
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
            if len(nums) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                          and np.isfinite(v) for v in nums):
                want = f"a list of {n} numbers, e.g. {json.dumps(list(default))}" if kind is tuple else "a number"
                raise InputError(f"--set {item}: '{key}' takes {want}")
            if kind is int and not float(nums[0]).is_integer():
                raise InputError(f"--set {item}: '{key}' takes a whole number")
            out[key] = tuple(nums) if kind is tuple else kind(nums[0])
    return out


def _load_json(path: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON (line {exc.lineno})") from None


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="closedloop", description="Closed-loop kinematic calibration of robots.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("calibrate", help="calibrate a model from a joint log")
    c.add_argument("model", help="URDF, MJCF (.xml) or D-H table (.yaml)")
    c.add_argument("log", help="CSV: header of joint names, one row per configuration")
    c.add_argument("--loop", action="append", default=[], metavar="SPEC",
                   help="loop closure, e.g. weld:frame=panda_hand (repeatable; see README)")
    c.add_argument("--out", help="calibrated model (URDF or D-H YAML, like the input)")
    c.add_argument("--report", help="JSON report")
    c.add_argument("--identify", help="comma-separated parameter patterns (placement, offset, scale, loop, globs)")
    c.add_argument("--fix", action="append", default=[], metavar="NAME[=VALUE]", help="hold a parameter fixed")
    c.add_argument("--noise", help="joint reading std (rad), one number or joint=value,...; default: estimated")
    c.add_argument("--weighting", choices=["noise", "none"], default="noise",
                   help="noise: errors-in-variables weighting (default); none: plain loop residual (thesis)")
    c.add_argument("--bound", action="append", default=[], metavar="NAME=LOW:HIGH", help="bound a parameter")
    c.add_argument("--snr", type=float, default=1.0, help="SVD truncation: keep directions above snr * noise")
    c.add_argument("--robust", choices=["huber", "cauchy"], help="robust loss; suspect configurations are reported")
    c.add_argument("--cv", type=int, default=5, metavar="K",
                   help="K-fold held-out validation in the report (default 5; 0 disables)")
    c.add_argument("--max-iter", type=int, default=100)
    c.add_argument("--degrees", action="store_true", help="the log is in degrees")
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_calibrate)

    i = sub.add_parser("inspect", help="list a model's joints, frames and parameter names")
    i.add_argument("model")
    i.add_argument("--json", action="store_true")
    i.set_defaults(func=cmd_inspect)

    s = sub.add_parser("simulate", help="generate a closed-chain dataset in MuJoCo")
    s.add_argument("scenario")
    s.add_argument("--n", type=int, default=200)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scenario setting")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_simulate)

    k = sub.add_parser("check", help="compare a calibration report with simulation truth")
    k.add_argument("truth")
    k.add_argument("report")
    k.add_argument("--tol-m", type=float, default=1e-3, help="tolerance for lengths (m)")
    k.add_argument("--tol-rad", type=float, default=5e-3, help="tolerance for angles (rad)")
    k.add_argument("--tol-scale", type=float, default=5e-3, help="tolerance for scale factors")
    k.add_argument("--tol-px", type=float, default=1.0, help="tolerance for camera intrinsics (px)")
    k.set_defaults(func=cmd_check)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except ClosedLoopError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
