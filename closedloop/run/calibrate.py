"""One calibration run, from files to files: load -> check -> calibrate -> validate -> judge -> write.

`calibrate_files` is what ``closedloop calibrate`` and each job of ``closedloop batch`` run, and what a
script calls to do the same from Python::

    from closedloop.run import CalibrateOptions, calibrate_files
    run = calibrate_files(CalibrateOptions(model="arm.urdf", log="log.csv", loop=["weld:frame=tool0"],
                                           out="calibrated.urdf", report="report.json"))
    print(run.verdict.describe())

1. **Check** the output paths before any work (`io.files.check_outputs`).
2. **Load** the model (`model.robot.RobotModel.from_file`), the loops and the log (`closedloop.run.inputs`).
3. **Calibrate** (`calibration.pipeline.calibrate`: the problem built once, the fit judged by the
   options' `VerdictRules`).
4. **Predict** the calibrated robot's accuracy over the workspace (`analysis.accuracy`, `run.accuracy`).
5. **Validate**: k-fold held-out refits (`validation.kfold.cross_validate`), whole regions of joint space
   held out (`validation.regions`) and, where the loops form several fixtures, leave-one-fixture-out
   (`validation.fixtures.leave_one_fixture_out`).
6. **Judge** the fit with the held-out evidence (`calibration.verdict.judge`), every piece of the fit's
   own judgement kept, and the prediction against the nominal model and the accuracy target
   (`calibration.verdict.judge_workspace`, `judge_accuracy`).
7. **Write** the model (unless the verdict is failed and not forced), its sensor file, the report, the
   HTML page and figures, published whole (`io.files.OutputSet`; `folder` publishes a whole folder).

Nothing is printed: progress goes to the reporter given (`closedloop.progress.ProgressReporter`,
``progress(task, done, total, note)``; its ``close()`` is called between steps where it has one), and
what the user should read is in the returned `RunResult`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from closedloop.errors import ClosedLoopError, InputError
from closedloop.run.options import CalibrateOptions

#: the record a run published as a whole folder writes last (`calibrate_files`)
DONE = "done.json"


@dataclass(frozen=True)
class RunResult:
    """What one run did: the calibration (its final verdict included), the report written, the log read,
    the files written, and what the run has to say beyond the report (`messages`)."""

    result: Any  # closedloop.records.CalibrationResult
    report: dict
    log: Any  # closedloop.io.logs.JointLog
    seconds: float
    model_written: bool = False
    sensors: Path | None = None
    figures: list[Path] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)

    @property
    def verdict(self):
        return self.result.verdict


def calibrate_files(
    options: CalibrateOptions,
    progress=None,
    *,
    folder: str | Path | None = None,
    done: Callable[[RunResult], dict] | None = None,
) -> RunResult:
    """The run of the module doc.  `folder` (every output inside it) is published whole: written into a
    hidden temporary folder beside it and renamed onto it (`io.files.OutputSet`), with ``done.json``
    (`DONE`: the JSON record `done` makes of the run) written last inside."""
    from closedloop.calibration.pipeline import calibrate
    from closedloop.calibration.verdict import judge_accuracy, judge_workspace
    from closedloop.output.report import build_report
    from closedloop.records import AccuracyRecord
    from closedloop.run.accuracy import (
        check_workspace,
        next_poses,
        parse_accuracy,
        parse_prior,
        predicted_accuracy,
        region_validation,
        workspace_readings,
    )
    from closedloop.run.inputs import load_inputs

    o = options
    prog = progress or _silent
    check_run_outputs(o)
    prog("reading", 0)  # a long log takes seconds to read
    inp = load_inputs(o)  # the robot, its loops, the log, the folds, the fit's options
    _done(prog)
    robot, lg, loops = inp.robot, inp.log, inp.loops
    if o.workspace:
        check_workspace(o.workspace)  # refused now, not after the fit
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate(robot, lg, loops, inp.fit, progress=prog)
    _done(prog)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    prog("predicting accuracy", 0)  # an evaluation of every row with its Jacobian
    workspace = workspace_readings(o, robot, res.problem.joints)  # where the accuracy is predicted
    prior = parse_prior(o.prior_tolerance) if o.prior_tolerance else None  # the nominal model's tolerance
    accuracy = predicted_accuracy(res, *workspace, prior=prior)  # over the workspace (closedloop.analysis.accuracy)
    _done(prog)
    if inp.weighting_note:
        res.notes.append(inp.weighting_note)
    res.notes.extend(inp.geometry)
    inputs = _input_record(o.readings, inp.fit.weighting, lg, res)  # readings, weighting, where the torques come from
    if inputs["torques"] == "gravity":
        res.notes.append("joint torques: gravity from the model's inertials (the log has no tau:<joint> columns)")
    t1, c1 = time.perf_counter(), time.process_time()
    cv, cv_record = fold_validation(robot, lg, loops, inp.fit, inp.folds, o.cv is not None, res, prog)
    lofo = fixture_validation(robot, lg, loops, inp.fit, o.lofo, res, prog)
    regions = region_validation(robot, lg, loops, inp.fit, o, res, prog)  # whole regions of joint space held out
    verdict = judge_workspace(final_verdict(res, cv, lofo, o.rules), accuracy)  # no better than nominal: failed
    target = None
    if o.accuracy:  # ok only where the prediction meets the target
        verdict, target = judge_accuracy(verdict, accuracy, *parse_accuracy(o.accuracy))
    res = replace(res, verdict=verdict, accuracy=AccuracyRecord(workspace=accuracy, regions=regions, target=target))
    report = build_report(res, o.model, inp.log_name, row_name=lg.where)
    suggested = next_poses(o, res, accuracy, report)  # the configurations to record next
    report["inputs"] = inputs
    # the fit's time, and the held-out refits' (k-fold and fixtures): with the fit's, the work of the run
    report["solver"] |= {"seconds": elapsed, "cpu_seconds": cpu}
    report["solver"] |= {
        "validation_seconds": time.perf_counter() - t1,
        "validation_cpu_seconds": time.process_time() - c1,
    }
    if cv_record is not None:
        report["validation"] = cv_record
    if lofo is not None:
        report["fixture_validation"] = lofo
    return _write(o, robot, res, report, lg, elapsed, inp.messages, folder, done, accuracy, suggested)


def check_run_outputs(o: CalibrateOptions) -> None:
    """The output paths, before any work (`io.files.check_outputs`); the figure library where figures
    are asked for."""
    from closedloop.errors import require
    from closedloop.io.files import check_outputs

    check_outputs({"--out": o.out, "--report": o.report, "--html": o.html, "--suggest": o.suggest}, [o.model, o.log])
    if o.plots:
        check_outputs({"--plots": o.plots}, [o.model, o.log], directory=True)
    if o.html or o.plots:
        require("matplotlib", f"--{'html' if o.html else 'plots'}", "report")  # refused now, not after the fit


def fold_validation(
    robot, lg, loops: list, opts, k: int, given: bool, res, progress=None
) -> tuple[dict | None, dict | None]:
    """K-fold held-out validation (`validation.kfold.cross_validate`) of a converged fit: (the folds, the
    report's ``validation`` record); the rows `res` rejected as outliers are not judged (they stay in the
    refits' data).

    A training fold the refit cannot use (too few rows for the parameters) ends the validation: with the
    default K it is skipped with a note (no folds), with K `given` it is an input error naming the folds.
    """
    from closedloop.validation.kfold import cross_validate

    if not k or not res.converged:
        return None, None
    prog = progress or _silent
    prog("validating", 0, k)
    try:
        cv = cross_validate(
            robot,
            lg,
            loops,
            opts,
            k=k,
            progress=prog,
            exclude=[rj.row - 1 for rj in res.outliers.rejected],
        )
    except ClosedLoopError as exc:
        _done(prog)
        n_train = len(lg) - -(-len(lg) // k)
        why = f"{k}-fold validation refits on {n_train} of the {len(lg)} rows, and one failed: {exc}"
        if given:
            raise InputError(f"--cv {k}: {why} (fewer folds, or --cv 0)") from None
        res.notes.append(f"k-fold validation skipped: {why}")
        return None, {"k": k, "skipped": why}
    record = {
        "k": k,
        "excluded_rows": [i + 1 for i in cv["excluded"]],
        "test": cv["test"],
        "train": cv["train"],
        "test_whitened_rms": cv.get("test_whitened_rms"),
        "parameter_spread": cv.get("parameter_spread"),
        "inconsistent": cv.get("inconsistent"),
        "folds_converged": [f["converged"] for f in cv["folds"]],
    }
    _done(prog)
    return cv, record


def fixture_validation(robot, lg, loops: list, opts, lofo: str, res, progress=None) -> dict | None:
    """Leave-one-fixture-out validation of a converged fit (`lofo` 'auto': when the loops form several
    fixtures): the report's ``fixture_validation`` record (`validation.fixtures.leave_one_fixture_out`)."""
    from closedloop.validation.fixtures import fixture_groups, leave_one_fixture_out

    if not res.converged or lofo == "off" or lg.loop is None or len(fixture_groups(loops)) < 2:
        return None
    prog = progress or _silent
    prog("validating fixtures", 0)
    out = leave_one_fixture_out(robot, lg, loops, opts)
    _done(prog)
    return out


def final_verdict(res, cv: dict | None, fixtures: dict | None, rules=None):
    """The fit's verdict with the held-out evidence (`calibration.verdict.judge` on the fit, its k-fold
    folds and its held-out fixtures); what the fit's own judgement found beyond the rules (a known length
    left out of the fit, `calibration.solve.length_guard`) is kept, reasons and evidence alike."""
    from closedloop.calibration.verdict import judge
    from closedloop.records import Verdict

    if cv is None and fixtures is None:
        return res.verdict
    v = judge(res, cv, rules=rules, fixtures=fixtures)
    own = res.verdict
    if own is None:
        return v
    kept = Verdict(v.status, list(v.reasons), {**own.evidence, **v.evidence})
    for reason in own.reasons:
        if reason not in kept.reasons:
            status, _, why = reason.partition(": ")
            if status in ("suspect", "failed"):
                kept.add(status, why)
            else:
                kept.reasons.append(reason)
    return kept


def _write(
    o: CalibrateOptions, robot, res, report: dict, lg, elapsed, messages, folder, done, accuracy=None, suggested=None
) -> RunResult:
    import json

    from closedloop.io.files import OutputSet, atomic_write_text
    from closedloop.output.report import sensors_path, write_report, write_sensors
    from closedloop.output.urdf import model_frames, write_model

    failed = res.verdict.status == "failed"
    model_out = o.out if o.out and (not failed or o.force) else None
    report["outputs"] = {"model": model_out}  # `closedloop evaluate --calibration`
    sensors = sensors_path(model_out) if model_out else None  # what the model file cannot carry, beside it
    run = RunResult(res, report, lg, elapsed, model_out is not None, sensors, [], messages)
    marker = Path(folder) / DONE if folder is not None and done is not None else None
    suggest = o.suggest if suggested else None
    with OutputSet(order=[model_out, sensors, suggest, o.report, marker], folder=folder):  # model first
        if suggest:
            atomic_write_text(suggest, suggested)
        if o.report:
            write_report(report, o.report)
        if model_out:
            write_model(robot, res.as_dict(), model_out, frames=model_frames(res))  # with tool points and fixtures
            if write_sensors(res, model_out, robot.kind) is None:
                run = replace(run, sensors=None)
        if marker is not None and done is not None:
            atomic_write_text(marker, json.dumps(done(run), indent=1) + "\n")
    if o.html or o.plots:  # the figures, once the model and the report are out
        from closedloop.output.html import write_html, write_plots

        if o.html:
            write_html(res, report, o.html, o.snr, row_name=lg.where, accuracy=accuracy)
        if o.plots:
            run = replace(run, figures=[Path(p) for p in write_plots(res, report, o.plots, o.snr, accuracy)])
    return run


def _input_record(readings: str, weighting: str, lg, res=None) -> dict:
    """What the report says about the inputs: whether the readings are measured or commanded, the weighting
    that follows, and where the joint torques the compliance model used come from ('log', 'gravity': the
    model's inertials at the readings; null when no compliance was used)."""
    used = res is None or any(
        p.kind == "compliance" and (res.fit.status[k] == "estimated" or res.fit.values[k] != 0.0)
        for k, p in enumerate(res.problem.params)
    )
    return {
        "readings": readings,
        "weighting": weighting,
        "torques": getattr(lg, "torque_source", None) if used else None,
    }


def _silent(task: str, done: int, total: int | None = None, note: str = "") -> None:
    """No progress display."""


def _done(progress) -> None:
    close = getattr(progress, "close", None)
    if close is not None:
        close()
