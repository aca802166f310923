"""One calibration run, from files to files: load -> check -> calibrate -> validate -> judge -> write.

`calibrate_files` is what ``closedloop calibrate`` and each job of ``closedloop batch`` run, and what a
script calls to do the same from Python::

    from closedloop.run import CalibrateOptions, calibrate_files
    run = calibrate_files(CalibrateOptions(model="arm.urdf", log="log.csv", loop=["weld:frame=tool0"],
                                           out="calibrated.urdf", report="report.json"))
    print(run.verdict.describe())

The run goes down the layers once and comes back up with its result:

1. **Check** the output paths before any work (`io.files.check_outputs`).
2. **Load** (`closedloop.run.inputs.load_inputs`): the model (`model.robot.RobotModel.from_file`, whose
   format the output must keep: `RobotModel.check_output`), the loops (`loops.spec.parse_loops`) and the
   rig's known distances and lengths, the log with its torques, and the loops' geometry on it
   (`loops.geometry.check_loop_geometry`); ``--workspace`` and ``--accuracy`` read (`run.accuracy`).
3. **Calibrate** (`calibration.pipeline.calibrate`: the problem built once, the fit judged by the
   options' `VerdictRules`).
4. **Predict** the calibrated robot's accuracy over the workspace, and the poses to record next
   (`run.accuracy.predict_workspace`: `analysis.accuracy`, `design.next_poses`).
5. **Validate** (`validate`): k-fold held-out refits (`validation.kfold.cross_validate`), whole regions
   of joint space held out (`validation.regions`) and, where the loops form several fixtures,
   leave-one-fixture-out (`validation.fixtures.leave_one_fixture_out`).
6. **Judge** once (`calibration.verdict.judge_run`): the fit with the held-out evidence, every piece of
   the fit's own judgement kept, the prediction against the nominal model and the accuracy target.
7. **Write**: the report (`output.report.build_report`) and each file made whole as text by its writer
   in `closedloop.output` (model, sensor file, report, suggestions), then published as one set
   (`io.files.publish`; `folder` publishes a whole folder); the HTML page and figures after them.

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


#: packages the run imports late, about 0.5 s of one core (SciPy's spatial and cluster packages: the
#: model-error test's k-d tree, the regions' k-means), imported on a thread of their own while the fit starts
#: (`_prefetch`; after the inputs are read, so that a refused input is not kept waiting for it)
PREFETCH = ("scipy.spatial", "scipy.cluster.vq")


def _prefetch(modules: tuple[str, ...]) -> None:
    """Import `modules` on a thread of their own (not a daemon: an early exit waits for it, never leaves an
    import half done).  A module that fails to import is imported again, and fails, where it is used."""
    import importlib
    import sys
    import threading

    todo = [m for m in modules if m not in sys.modules]

    def load() -> None:
        for m in todo:
            try:
                importlib.import_module(m)
            except Exception:  # said where it is used
                return

    if todo:
        threading.Thread(target=load, name="closedloop-prefetch").start()


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
    from closedloop.calibration.verdict import judge_run
    from closedloop.records import AccuracyRecord
    from closedloop.run.accuracy import predict_workspace, workspace_request
    from closedloop.run.inputs import load_inputs

    o = options
    prog = progress or _silent
    check_run_outputs(o)
    prog("reading", 0)  # a long log takes seconds to read
    inp = load_inputs(o)  # the robot, its loops, the log, the folds, the fit's options
    _done(prog)
    _prefetch(PREFETCH)  # the inputs hold: the run goes on
    robot, lg, loops = inp.robot, inp.log, inp.loops
    request = workspace_request(o)  # --workspace, --accuracy and --prior-tolerance refused now, not after the fit
    t0, c0 = time.perf_counter(), time.process_time()
    res = calibrate(robot, lg, loops, inp.fit, progress=prog)
    _done(prog)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    prog("predicting accuracy", 0)  # an evaluation of every row with its Jacobian
    predicted = predict_workspace(o, robot, res, request)  # the accuracy over the workspace, the poses to record next
    _done(prog)
    if inp.weighting_note:
        res.notes.append(inp.weighting_note)
    res.notes.extend(inp.geometry)
    inputs = _input_record(o.readings, inp.fit.weighting, lg, res)  # readings, weighting, where the torques come from
    if inputs["torques"] == "gravity":
        res.notes.append("joint torques: gravity from the model's inertials (the log has no tau:<joint> columns)")
    t1, c1 = time.perf_counter(), time.process_time()
    held = validate(robot, lg, loops, inp.fit, inp.folds, o, res, prog, predicted.accuracy)
    _done(prog)
    if predicted.note:
        res.notes.append(predicted.note)
    verdict, met = judge_run(res, held.cv, held.fixtures, o.rules, predicted.accuracy, request.target)
    res = replace(
        res, verdict=verdict, accuracy=AccuracyRecord(workspace=predicted.accuracy, regions=held.regions, target=met)
    )
    model_out = o.out if o.out and (verdict.status != "failed" or o.force) else None
    sections = {
        "inputs": inputs,
        # the fit's time, and the held-out refits' (k-fold and fixtures): with the fit's, the work of the run
        "timing": {
            "seconds": elapsed,
            "cpu_seconds": cpu,
            "validation_seconds": time.perf_counter() - t1,
            "validation_cpu_seconds": time.process_time() - c1,
        },
        "validation": held.cv_record,
        "fixture_validation": held.fixtures,
        "outputs": {"model": model_out},  # `closedloop evaluate --calibration`
        "next_poses": predicted.next_poses,
    }
    run = RunResult(res, {}, lg, elapsed, model_out is not None, None, [], inp.messages)
    return _write(o, robot, run, inp.log_name, sections, folder, done, predicted)


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


@dataclass(frozen=True)
class HeldOut:
    """What a run held out of its fit and refitted without: the k-fold folds (`validation.kfold.cross_validate`)
    and the report's record of them, the fixtures (`validation.fixtures.leave_one_fixture_out`), whole
    regions of joint space (`validation.regions.region_validate`); None where not run."""

    cv: dict | None = None
    cv_record: dict | None = None
    fixtures: dict | None = None
    regions: dict | None = None


def validate(robot, lg, loops: list, opts, k: int, o: CalibrateOptions, res, progress=None, workspace=None) -> HeldOut:
    """The held-out validation of a converged fit, every kind the options ask for (`HeldOut`); the rows `res`
    rejected as outliers are not judged, nor trained on: the refits reuse the fit's outlier screen
    (`kfold.cross_validate`'s `train_without_excluded`) instead of screening again.

    A fit already failed (its own verdict, or its `workspace` prediction no better than the nominal model:
    `calibration.verdict.judge_workspace`) is not validated: a held-out finding can only add to a failed
    verdict, and each refit repeats the fit's work on a problem that failed (a many-jointed hand whose
    finger barely moves: nine refits, over 90 % of the run), so the records say why and the run ends.

    K-fold (`k` folds): a training fold the refit cannot use (too few rows for the parameters) ends it:
    with the default K it is skipped with a note, with ``--cv`` given it is an input error naming the folds.
    Leave-one-fixture-out (``--lofo`` 'auto'): when the loops form several fixtures.  Regions
    (``--regions K``): a region the refit cannot do without is a note, not an error; too few rows for K
    regions are said in the record, not run.  Each kind is its own task of `progress` (a new task replaces
    the last one's display); the caller closes the display after the step.
    """
    from closedloop.calibration.verdict import judge_workspace
    from closedloop.records import FAILED
    from closedloop.validation.fixtures import fixture_groups, leave_one_fixture_out
    from closedloop.validation.kfold import cross_validate
    from closedloop.validation.regions import region_validate

    if not res.converged:
        return HeldOut()
    if res.verdict is not None and judge_workspace(res.verdict, workspace).status == FAILED:
        why = "the fit failed (its verdict): refits of held-out rows cannot make it right"
        res.notes.append(f"held-out validation not run: {why}")
        n = int(o.regions or 0)
        return HeldOut(
            cv_record={"k": k, "skipped": why} if k else None,
            regions={"k": n, "skipped": why} if n >= 2 else None,
        )
    prog = progress or _silent
    exclude = [rj.row - 1 for rj in res.outliers.rejected]
    cv = cv_record = fixtures = regions = None
    if k:
        prog("validating", 0, k)
        try:
            cv = cross_validate(
                robot, lg, loops, opts, k=k, progress=prog, exclude=exclude, train_without_excluded=True, result=res
            )
        except ClosedLoopError as exc:
            n_train = len(lg) - -(-len(lg) // k)
            why = f"{k}-fold validation refits on {n_train} of the {len(lg)} rows, and one failed: {exc}"
            if o.cv is not None:
                raise InputError(f"--cv {k}: {why} (fewer folds, or --cv 0)") from None
            res.notes.append(f"k-fold validation skipped: {why}")
            cv_record = {"k": k, "skipped": why}
        else:
            cv_record = {
                "k": k,
                "excluded_rows": [i + 1 for i in cv["excluded"]],
                "test": cv["test"],
                "train": cv["train"],
                "test_whitened_rms": cv.get("test_whitened_rms"),
                "parameter_spread": cv.get("parameter_spread"),
                "inconsistent": cv.get("inconsistent"),
                "folds_converged": [f["converged"] for f in cv["folds"]],
                **_refit_rows(cv["folds"]),
            }
    if o.lofo != "off" and lg.loop is not None and len(fixture_groups(loops)) >= 2:
        prog("validating fixtures", 0)
        fixtures = leave_one_fixture_out(robot, lg, loops, opts, result=res)
    n = int(o.regions or 0)
    if n >= 2 and len(lg) < 4 * n:  # regions of a few rows each say nothing of extrapolation: not run, said
        regions = {"k": n, "skipped": f"{len(lg)} rows: too few for {n} regions (at least {4 * n})"}
    elif n >= 2:
        prog("validating regions", 0, n)
        try:
            rv = region_validate(
                robot,
                lg,
                loops,
                res.problem.joints,
                opts,
                k=n,
                exclude=exclude,
                progress=lambda task, done, total=None, note="": prog("validating regions", done, total, note),
                result=res,
            )
        except ClosedLoopError as exc:
            why = str(exc).splitlines()[0]
            res.notes.append(f"region validation skipped: {why}")
            regions = {"k": n, "skipped": why}
        else:
            regions = {
                "k": rv["k"],
                "rows": [len(r) for r in rv["regions"]],
                "test": rv["test"],
                "train": rv["train"],
                "folds_converged": [f["converged"] for f in rv["folds"]],
                **_refit_rows(rv["folds"]),
            }
    return HeldOut(cv, cv_record, fixtures, regions)


def _refit_rows(folds: list[dict]) -> dict:
    """The report's record of what each held-out refit used: the rows it was trained on and judged on (on a
    long log an even sample: `validation.kfold.validation_rows`) and whether it started at the calibration's
    solution (`validation.kfold`'s warm refit)."""
    return {
        "train_rows": [f["n_train"] for f in folds],
        "test_rows": [f["n_test"] for f in folds],
        "folds_warm": [f["warm"] for f in folds],
    }


def _write(
    o: CalibrateOptions, robot, run: RunResult, log_name: str, sections: dict, folder, done, predicted
) -> RunResult:
    """The run's report (`output.report.build_report`, with the run's `sections`) and files, each made
    whole as text by its writer in `closedloop.output`, then published as one set (`io.files.publish`: the
    model first, the report and the completion record last); the HTML page and the figures, once the model
    and the report are out, as a second set."""
    import json

    from closedloop.io.files import publish
    from closedloop.output.report import build_report, report_text, sensors_path, sensors_text
    from closedloop.output.urdf import model_frames, model_text

    res = run.result
    report = build_report(res, o.model, log_name, row_name=run.log.where, **sections)
    model_out = sections["outputs"]["model"]
    run = replace(run, report=report)
    sensors = sensors_path(model_out) if model_out else None  # what the model file cannot carry, beside it
    sensor_file = sensors_text(res, model_out, robot.kind) if model_out else None
    files: dict[str | Path, str | bytes] = {}
    if o.suggest and predicted.suggested:
        files[o.suggest] = predicted.suggested
    if o.report:
        files[o.report] = report_text(report)
    if model_out:
        files[model_out] = model_text(
            robot, res.as_dict(), model_out, model_frames(res)
        )  # with tool points and fixtures
    if sensors is not None and sensor_file is not None:
        files[sensors] = sensor_file
        run = replace(run, sensors=sensors)
    marker = Path(folder) / DONE if folder is not None and done is not None else None
    if marker is not None and done is not None:
        files[marker] = json.dumps(done(run), indent=1) + "\n"
    publish(files, order=[model_out, sensors, o.suggest, o.report, marker], folder=folder)  # model first
    if o.html or o.plots:  # the figures, once the model and the report are out
        from closedloop.output.html import figures, plot_files, render_html

        figs = figures(res, report, o.snr, predicted.accuracy)  # drawn once, for the page and the files
        pages: dict[str | Path, str | bytes] = {}
        if o.html:
            pages[o.html] = render_html(
                res, report, o.snr, row_name=run.log.where, accuracy=predicted.accuracy, figs=figs
            )
        if o.plots:
            plots = plot_files(res, report, o.plots, o.snr, predicted.accuracy, figs=figs)
            pages.update({path: data for path, data in plots.items()})
            run = replace(run, figures=list(plots))
        publish(pages)
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
