"""`closedloop calibrate`: a model and a log to a calibrated model, its report and its verdict.

The arguments are derived from the run's options (`closedloop.run.options`), the run is
`closedloop.run.calibrate_files`; this module parses, shows progress and prints the summary.
"""

from __future__ import annotations

import sys

from closedloop.cli.parse import float_arg, int_arg
from closedloop.cli.progress import ProgressDisplay
from closedloop.errors import EXIT_FAILED


def add_arguments(c) -> None:
    """`calibrate`'s arguments, derived from the run's options (`closedloop.run.options`): each option's
    name, help, default, choices and form in one place; ``--config`` and ``--quiet`` are the command line's."""
    from closedloop.run.options import CLI, OPTIONS, default, flag

    for f in OPTIONS:
        m = f.metadata
        if CLI not in m["where"]:
            continue
        kind = m["kind"]
        kw: dict = {"help": m["help"]}
        if m["metavar"] and not m["positional"]:
            kw["metavar"] = m["metavar"]
        if kind == "bool":
            kw["action"] = "store_true"
        elif kind in ("texts", "fix", "bounds", "args"):
            kw |= {"action": "append", "default": []}
            if kind == "args":
                kw["nargs"] = "+"
        else:
            kw["default"] = default(f)
            if kind == "float":
                kw["type"] = float_arg
            elif kind == "int":
                kw["type"] = int_arg
            elif kind == "choice":
                kw["choices"] = list(m["choices"])
        if m["positional"]:
            if f.name == "log":
                kw["nargs"] = "?"
            c.add_argument(f.name, **kw)
        else:
            c.add_argument(flag(f.name), **kw)
        if f.name == "plots":
            c.add_argument("--config", help="YAML file holding any of these options (the command line wins)")
    c.add_argument("--quiet", action="store_true", help="no progress and no summary (errors and warnings only)")


def options_from_args(args):
    """The run's options from the parsed command line (and ``--config``), checked once
    (`closedloop.run.options.checked`): a bad value is one line ``--option value: ...``."""
    from closedloop.run.options import CLI, OPTIONS, CalibrateOptions, check_value, flag

    values = {f.name: getattr(args, f.name) for f in OPTIONS if CLI in f.metadata["where"]}
    for name, value in values.items():
        check_value(name, value, flag(name) if name not in ("model", "log") else name)
    return CalibrateOptions(**values)


def cmd_calibrate(args) -> int:
    from closedloop.run.calibrate import calibrate_files

    options = options_from_args(args)
    prog = ProgressDisplay(args.quiet)
    try:
        run = calibrate_files(options, progress=prog)
    finally:
        prog.close()
    res, report, verdict = run.result, run.report, run.verdict
    log_name = report.get("log") or options.log
    for message in run.messages:
        print(f"  {message}", file=sys.stderr)
    if not args.quiet:
        print_summary(res, run.seconds, options, report, wrote_model=run.model_written)
        if run.sensors is not None:
            print(f"  wrote {run.sensors}")
        suggested = ((report.get("accuracy") or {}).get("next_poses") or {}).get("file")
        if suggested:
            print(f"  wrote {suggested}")
        if options.html:
            print(f"  wrote {options.html}")
        if options.plots:
            print(f"  wrote {len(run.figures)} figures to {options.plots}")
    if verdict.status == "suspect":
        print(f"warning: {log_name}: calibration is suspect: {'; '.join(own_reasons(verdict))}", file=sys.stderr)
    if verdict.status == "failed":
        print(
            f"error: {log_name}: calibration failed: {'; '.join(own_reasons(verdict))}"
            + (
                ""
                if run.model_written or not options.out
                else f"; no model written to {options.out} (--force writes it)"
            ),
            file=sys.stderr,
        )
        return EXIT_FAILED
    return 0


def own_reasons(verdict) -> list[str]:
    """The verdict's reasons, those of its own status without their label (the others keep theirs)."""
    own = f"{verdict.status}: "
    return [r[len(own) :] if r.startswith(own) else r for r in verdict.reasons]


SHOWN_WEAK = 5  # combinations not identified printed in the summary (all of them are in the report)


def print_summary(res, elapsed: float, args, report: dict, wrote_model: bool = True) -> None:
    b, a = res.fit.residuals_before, res.fit.residuals_after
    import numpy as np

    # a known distance (closedloop.problem.distances) is one residual row, no configuration, nothing held out
    blocks = res.problem.blocks
    distances = {bl.loop.name for bl in blocks if getattr(bl.loop, "parameter_only", False)}
    rows = [bl.rows for bl in blocks if bl.loop.name not in distances]
    n_conf = int(np.unique(np.concatenate(rows)).size) if rows else 0
    reasons = list(dict.fromkeys(own_reasons(res.verdict)))
    print(f"verdict: {res.verdict.status}" + (f" ({'; '.join(reasons)})" if reasons else ""))
    from closedloop.cli.accuracy import accuracy_lines

    for line in accuracy_lines(report.get("accuracy")):
        print(line)
    print(
        f"calibrated {len(res.fit.estimated)} parameters from {n_conf} configurations "
        f"in {res.fit.iterations} iterations ({elapsed:.2f} s): "
        # the solver's own word only where the verdict does not overrule it
        + (
            res.fit.solver_status
            if res.verdict.status != "failed"
            else f"the solver stopped ({res.fit.solver_message})"
        )
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
    ratio = res.noise.chi2 / max(res.noise.dof, 1)
    if res.noise.joint_noise is None:  # a plain fit: its residual scale makes chi2/dof 1 by construction
        print(f"  {res.noise.describe()}")
    elif res.noise.sigma_estimated:  # chi2/dof is 1 by construction unless a task's own noise weighs in too
        fit = "" if abs(ratio - 1.0) < 5e-3 else f"; chi2/dof {ratio:.3g} with the task noise"
        print(f"  joint noise {res.noise.sigma:.3g} rad, estimated from the residual{fit}")
    else:
        print(f"  joint noise {res.noise.sigma:.3g} rad (given); chi2/dof {ratio:.3g}")
    if res.identifiability.dropped:
        print(
            f"  {len(res.identifiability.dropped)} redundant parameters dropped (see report: identifiability.dropped)"
        )
    for c in res.identifiability.weak[:SHOWN_WEAK]:
        print(f"  not identifiable: {c.describe()}")
    if len(res.identifiability.weak) > SHOWN_WEAK:
        print(
            f"  ... and {len(res.identifiability.weak) - SHOWN_WEAK} more combinations not identifiable "
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
    for line in fixture_lines(report.get("fixture_validation")):
        print(line)
    rejected = report.get("rejected", [])
    for rj in rejected[:10]:  # named by file and line (`JointLog.where`)
        print(
            f"  rejected: {rj.get('where') or 'log row ' + str(rj['row'])} (loop {rj['loop']}), "
            f"{rj['standardized']:.3g} robust standard deviations"
        )
    if len(rejected) > 10:
        print(f"  rejected: and {len(rejected) - 10} more (report: rejected)")
    if args.out and wrote_model:
        print(f"  wrote {args.out}")
    if args.report:
        print(f"  wrote {args.report}")


def fixture_lines(out: dict | None) -> list[str]:
    """The summary's lines for a leave-one-fixture-out record (`fixture_validation`), printed after the verdict."""
    lines = []
    for r in (out or {}).get("fixtures", []):
        if r.get("error"):
            lines.append(f"  held-out fixture {r['fixture']}: not validated ({r['error']})")
        elif r["calibrated_rms_m"] is not None:
            lines.append(
                f"  held-out fixture {r['fixture']}: closure RMS {r['calibrated_rms_m'] * 1e3:.4g} mm "
                f"(nominal model {r['nominal_rms_m'] * 1e3:.4g} mm)" + (" WORSE" if r["worse"] else "")
            )
    return lines
