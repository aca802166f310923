"""`closedloop calibrate`: a model and a log to a calibrated model, its report and its verdict.

Printing happens here (and in the other `cli_*` modules) and only here.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

from closedloop.cli.parse import check_loop_numbers
from closedloop.errors import EXIT_FAILED, InputError, require
from closedloop.io.schemas import check_number, parse_bounds, parse_noise


class Progress:
    """A progress line on stderr, on a terminal only: rewritten in place and erased when done, so that no
    stale line is left in a log or a CI output (where nothing is written)."""

    def __init__(self, quiet: bool, stream=None):
        self.stream = sys.stderr if stream is None else stream
        self.quiet = quiet
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0 = time.perf_counter()
        self.shown = False  # a line is on the screen

    def __call__(self, stage: str, it: int, value: float) -> None:
        if self.quiet or not self.tty:
            return
        msg = f"  {stage}"
        if stage == "solving":
            msg += f": iteration {it}, cost {value:.3e}"
        elif stage == "validating":
            msg += ": k-fold held-out refits" + (f", {it} of {int(value)} done" if value else "")
        elif stage == "simulating":
            msg += f": {it}/{int(value)} configurations"
        msg += f"  [{time.perf_counter() - self.t0:.1f} s]"
        print("\r" + msg.ljust(70), end="", file=self.stream, flush=True)
        self.shown = True

    def done(self) -> None:
        """Erase the line (the summary says what was done)."""
        if self.shown:
            print("\r" + " " * 70 + "\r", end="", file=self.stream, flush=True)
            self.shown = False


def check_calibrate_options(args) -> tuple:
    """`calibrate`'s output paths and numeric options, checked before any work: (noise, bounds, cv given?)."""
    from closedloop.io.files import check_outputs

    check_outputs(
        {"--out": args.out, "--report": args.report, "--html": getattr(args, "html", None)}, [args.model, args.log]
    )
    if getattr(args, "plots", None):
        check_outputs({"--plots": args.plots}, [args.model, args.log], directory=True)
    if getattr(args, "html", None) or getattr(args, "plots", None):
        require("matplotlib", f"--{'html' if args.html else 'plots'}", "report")  # refused now, not after the fit
    args.snr = check_number("--snr", args.snr, 0.0, 1e6, lo_open=True)
    args.max_iter = check_number("--max-iter", args.max_iter, 1, 10**6, integer=True)
    cv_given = args.cv is not None  # (default None: 5 folds, fewer on a short log)
    args.cv = check_number("--cv", args.cv, 0, 10**6, integer=True) if cv_given else 5
    if args.cv == 1:
        raise InputError("--cv 1: K-fold validation needs K >= 2 (or 0 to disable)")
    for spec in args.loop:
        check_loop_numbers(spec)
    return parse_noise(args.noise), parse_bounds(args.bound), cv_given


def check_loop_geometry(model_path, robot, lg, loops: list, specs: list[str] | None = None) -> list[str]:
    """Before any work: refuse a loop through joints ``closedloop simulate --robot`` held fixed
    (`closedloop.io.robot_files.HELD`: the log has no readings of them, the model calls them rigid),
    one line naming them; return a warning for each point loop whose contact point lies on the last
    joint's axis (`closedloop.loops.point.contact_on_axis`: that joint cannot move the point, its
    parameters are not seen and the fit is degenerate), naming the joint and the fix.

    A contact on the axis is named, not refused: the fit still calibrates the joints that move the
    point (the UR5 socket scenario's stylus lies on the flange axis), but a stylus off the axis sees
    the last joint too.  `specs`: the ``--loop`` texts of `loops`, for the messages.
    """
    import numpy as np

    from closedloop.io.robot_files import held_on_chain
    from closedloop.loops.point import PointLoop, contact_on_axis
    from closedloop.model.axes import point_on_axis_message

    warnings = []
    for k, lp in enumerate(loops):
        frames = [f for f in (lp.frame_a, lp.frame_b) if f not in ("universe", "world")]
        held = held_on_chain(model_path, frames) if robot.kind == "urdf" else []
        if held:
            raise InputError(
                f"{model_path}: loop '{lp.name}' passes joint(s) {', '.join(held)}, which the simulation held "
                "fixed (not driven: the log has no readings of them); simulate this loop "
                f"(closedloop simulate --robot ROBOT --loop {specs[k] if specs and k < len(specs) else '...'}), "
                "or calibrate the loop that was simulated"
            )
        if isinstance(lp, PointLoop):
            joints = robot.supporting_joints(lp.frame_a)
            rows = np.ones(len(lg), bool) if lg.loop is None else lg.loop == lp.name
            blind = contact_on_axis(robot, lp, lg.columns(joints)[rows], joints)
            if blind:
                warnings.append(
                    point_on_axis_message(
                        f"loop '{lp.name}' on {lp.frame_a}",
                        lp.frame_a,
                        blind,
                        lp.tip is not None,
                        "its parameters are left to the model; to calibrate it, hold a stylus off the axis "
                        '(its tip, if measured: tip="x y z" in the frame)',
                    )
                )
    return warnings


def cmd_calibrate(args) -> int:
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.cli.evaluate import require_log
    from closedloop.io.files import OutputSet
    from closedloop.io.logs import check_loop_column
    from closedloop.loops.spec import default_loops, parse_loop
    from closedloop.model.parameters import parse_fix
    from closedloop.model.robot import RobotModel
    from closedloop.output.report import build_report, write_report
    from closedloop.output.urdf import check_model_output, write_model

    require_log(args)  # the positional log, unless each loop names its file
    noise, bounds, cv_given = check_calibrate_options(args)  # outputs and numbers, before any work
    if args.threads is not None:
        args.threads = check_number("--threads", args.threads, 0, 4096, integer=True)
    robot = RobotModel.from_file(args.model)
    check_model_output(robot.kind, args.out, args.model)
    loops = [parse_loop(s, robot) for s in args.loop] or default_loops(robot)
    if not loops:
        raise InputError("no --loop given: say how the chain is closed, e.g. --loop weld:frame=<tool frame>")
    from closedloop.cli.evaluate import rig_inputs

    lg, loops = rig_inputs(args, robot, loops)  # a CSV log or a ROS bag, or each loop's file; known distances
    check_loop_column(lg, [lp.name for lp in loops])
    geometry = check_loop_geometry(args.model, robot, lg, loops, args.loop)  # before any work
    for line in geometry:
        print(f"warning: {line}", file=sys.stderr)
    if args.cv > len(lg):
        if cv_given:
            raise InputError(f"--cv {args.cv}: more folds than the {len(lg)} rows of {args.log}")
        args.cv = len(lg) if len(lg) >= 2 else 0
    from closedloop.calibration.pipeline import build_problem

    names = build_problem(robot, lg, loops).names
    from closedloop.cli.evaluate import input_record, resolve_weighting

    inputs_note = resolve_weighting(args)  # --readings commanded: plain least squares unless --weighting is given
    opts = CalibrationOptions(
        identify=args.identify.split(",") if args.identify else None,
        fix=parse_fix(args.fix, names),
        noise=noise,
        weighting=args.weighting,
        max_iter=args.max_iter,
        snr=args.snr,
        bounds=bounds,
        robust=None if args.robust == "off" else args.robust,
        threads=args.threads,
    )
    prog = Progress(args.quiet)
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate(robot, lg, loops, opts, progress=prog)
    prog.done()
    elapsed = time.perf_counter() - t0
    if inputs_note:
        res.notes.append(inputs_note)
    res.notes.extend(geometry)
    report_inputs = input_record(args, lg, res)  # readings, weighting, where the torques come from
    if report_inputs["torques"] == "gravity":
        res.notes.append("joint torques: gravity from the model's inertials (the log has no tau:<joint> columns)")
    report = build_report(res, args.model, args.log, row_name=lg.where)
    report["inputs"] = report_inputs
    report["solver"]["seconds"] = elapsed
    report["solver"]["cpu_seconds"] = time.process_time() - c0
    t1, c1 = time.perf_counter(), time.process_time()
    cv = (
        fold_validation(robot, lg, loops, opts, args, report, prog, res, cv_given)
        if args.cv and res.converged
        else None
    )
    from closedloop.calibration.verdict import judge
    from closedloop.cli.evaluate import fixture_validation
    from closedloop.output.report import verdict_record

    lofo = fixture_validation(robot, lg, loops, opts, report, args, prog) if res.converged else None
    # the held-out refits' time (k-fold and fixtures): with the fit's, the work of the command
    report["solver"]["validation_seconds"] = time.perf_counter() - t1
    report["solver"]["validation_cpu_seconds"] = time.process_time() - c1
    verdict = judge(res, cv, fixtures=lofo)  # the fit's evidence, the held-out folds' and fixtures'
    res = replace(res, verdict=verdict)
    report["verdict"] = verdict_record(verdict)
    failed = verdict.status == "failed"
    write_out = args.out and (not failed or args.force)
    from closedloop.output.report import sensors_path, write_sensors

    report["outputs"] = {"model": str(args.out) if write_out else None}  # `closedloop evaluate --calibration`
    sensors = sensors_path(args.out) if write_out else None  # what the model file cannot carry, beside it
    with OutputSet(order=[args.out if write_out else None, sensors, args.report]):  # published whole, model first
        if args.report:
            write_report(report, args.report)
        if write_out:
            from closedloop.output.urdf import model_frames

            write_model(robot, res.as_dict(), args.out, frames=model_frames(res))  # with tool points and fixtures
            if write_sensors(res, args.out, robot.kind) is None:
                sensors = None
    if not args.quiet:
        print_summary(res, elapsed, args, report, wrote_model=bool(write_out))
        if sensors is not None:
            print(f"  wrote {sensors}")
    from closedloop.cli.tools import write_figures

    write_figures(res, report, args, row_name=lg.where)  # --html / --plots
    if verdict.status == "suspect":
        print(f"warning: {args.log}: calibration is suspect: {'; '.join(own_reasons(verdict))}", file=sys.stderr)
    if failed:
        print(
            f"error: {args.log}: calibration failed: {'; '.join(own_reasons(verdict))}"
            + ("" if write_out or not args.out else f"; no model written to {args.out} (--force writes it)"),
            file=sys.stderr,
        )
        return EXIT_FAILED
    return 0


def fold_validation(robot, lg, loops: list, opts, args, report: dict, prog, res, cv_given: bool = True) -> dict | None:
    """K-fold held-out validation (`validation.cross_validate`), into the report; the rows `res` rejected
    as outliers are not judged (they stay in the refits' data).

    A training fold the refit cannot use (too few rows for the parameters) ends the validation: with the
    default K it is skipped with a note (None), with ``--cv K`` given it is an input error naming the folds.
    """
    from closedloop.errors import ClosedLoopError
    from closedloop.validation.kfold import cross_validate

    prog("validating", 0, 0.0)
    try:
        cv = cross_validate(
            robot,
            lg,
            loops,
            opts,
            k=args.cv,
            progress=lambda done, k: prog("validating", done, k),
            exclude=[rj.row - 1 for rj in res.rejected],
        )
    except ClosedLoopError as exc:
        prog.done()
        n_train = len(lg) - -(-len(lg) // args.cv)
        why = f"{args.cv}-fold validation refits on {n_train} of the {len(lg)} rows, and one failed: {exc}"
        if cv_given:
            raise InputError(f"--cv {args.cv}: {why} (fewer folds, or --cv 0)") from None
        res.notes.append(f"k-fold validation skipped: {why}")
        report["validation"] = {"k": args.cv, "skipped": why}
        return None
    report["validation"] = {
        "k": args.cv,
        "excluded_rows": [i + 1 for i in cv["excluded"]],
        "test": cv["test"],
        "train": cv["train"],
        "test_whitened_rms": cv.get("test_whitened_rms"),
        "parameter_spread": cv.get("parameter_spread"),
        "inconsistent": cv.get("inconsistent"),
        "folds_converged": [f["converged"] for f in cv["folds"]],
    }
    prog.done()
    return cv


def own_reasons(verdict) -> list[str]:
    """The verdict's reasons, those of its own status without their label (the others keep theirs)."""
    own = f"{verdict.status}: "
    return [r[len(own) :] if r.startswith(own) else r for r in verdict.reasons]


SHOWN_WEAK = 5  # combinations not identified printed in the summary (all of them are in the report)


def print_summary(res, elapsed: float, args, report: dict, wrote_model: bool = True) -> None:
    b, a = res.residuals_before, res.residuals_after
    import numpy as np

    # a known distance (closedloop.problem.distances) is one residual row, no configuration, nothing held out
    blocks = res.problem.blocks
    distances = {bl.loop.name for bl in blocks if getattr(bl.loop, "parameter_only", False)}
    rows = [bl.rows for bl in blocks if bl.loop.name not in distances]
    n_conf = int(np.unique(np.concatenate(rows)).size) if rows else 0
    reasons = list(dict.fromkeys(own_reasons(res.verdict)))
    print(f"verdict: {res.verdict.status}" + (f" ({'; '.join(reasons)})" if reasons else ""))
    print(
        f"calibrated {len(res.estimated)} parameters from {n_conf} configurations "
        f"in {res.iterations} iterations ({elapsed:.2f} s): "
        # the solver's own word only where the verdict does not overrule it
        + (res.solver_status if res.verdict.status != "failed" else f"the solver stopped ({res.solver_message})")
    )
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
    for c in res.weak[:SHOWN_WEAK]:
        print(f"  not identifiable: {c.describe()}")
    if len(res.weak) > SHOWN_WEAK:
        print(
            f"  ... and {len(res.weak) - SHOWN_WEAK} more combinations not identifiable "
            "(report: identifiability.not_identifiable)"
        )
    for n in dict.fromkeys(res.notes):  # each note once
        print(f"  note: {n}")
    cv = report.get("validation")
    if cv and "test" in cv:  # (a skipped validation is among the notes)
        for t in (t for t in cv["test"] if t["loop"] not in distances):
            parts = [
                f"{t['rms_m'] * 1e3:.4g} mm" if t.get("rms_m") is not None else "",
                f"{t['rms_rad'] * 1e3:.4g} mrad" if t.get("rms_rad") is not None else "",
                f"{t['rms_px']:.4g} px" if t.get("rms_px") is not None else "",
            ]
            left = len(cv.get("excluded_rows", []))
            print(
                f"  {cv['k']}-fold validation, loop {t['loop']}: held-out closure RMS "
                + ", ".join(p for p in parts if p)
                + (f" (the {left} rejected rows not judged)" if left else "")
            )
    from closedloop.cli.evaluate import fixture_lines

    for line in fixture_lines(report.get("fixture_validation")):
        print(line)
    for rj in report.get("rejected", [])[:10]:  # named by file and line (`JointLog.where`)
        print(
            f"  rejected: {rj.get('where') or 'log row ' + str(rj['row'])} (loop {rj['loop']}), "
            f"{rj['standardized']:.3g} robust standard deviations"
        )
    if args.out and wrote_model:
        print(f"  wrote {args.out}")
    if args.report:
        print(f"  wrote {args.report}")
