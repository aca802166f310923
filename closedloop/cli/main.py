"""The `closedloop` command line: the parser, the dispatch and the exit codes.  Printing happens in the
modules of `closedloop.cli` and only there (`calibrate`, `simulate`, `evaluate`, `extract`, `loops`;
`config` for ``--config``; option values: `parse`).

User mistakes (`InputError`) print one line and exit with code 2.  Nothing heavy is imported before
`main` has taken over the signals: Ctrl-C while the numerical libraries load is one line and exit 130 too.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable

from closedloop.cli.parse import float_arg, int_arg, join_negative_numbers
from closedloop.errors import (
    EXIT_FAILED,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_PIPE,
    CalibrationError,
    ClosedLoopError,
    InputError,
)

__all__ = [
    "EXIT_FAILED",
    "EXIT_INPUT",
    "EXIT_INTERNAL",
    "build_parser",
    "cmd_check",
    "cmd_inspect",
    "main",
]


# --------------------------------------------------------------------------- commands
def cmd_inspect(args) -> int:
    from closedloop.model.parameters import RobotParameters
    from closedloop.model.robot import RobotModel

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
        print(f"  {n:<24} mimics {m} (URDF <mimic>: moves with it)")
    print(f"frames: {', '.join(info['frames'])}")
    first = info["joints"][0]["name"] if info["joints"] else ""
    fields = [p.split(".", 1)[1] for p in info["parameters"] if p.split(".", 1)[0] == first]
    print(f"parameters per joint (<joint>.<field>): {', '.join(fields)}")
    return 0


def cmd_check(args) -> int:
    from closedloop.run.options import check_number
    from closedloop.validation.check import check_parameters, check_report

    tols = {
        o: check_number(f"--{o.replace('_', '-')}", getattr(args, o), 0.0, 1e6, lo_open=True)
        for o in ("tol_m", "tol_rad", "tol_scale", "tol_px")
    }
    if args.json:  # refused before any work where it would overwrite an input
        from closedloop.io.files import check_outputs

        check_outputs({"--json": args.json}, [args.truth, args.report])
    truth = _load_json(args.truth, "truth file")
    report = _load_json(args.report, "report file")
    _refuse_swapped(truth, report, args.truth, args.report)
    src = {"truth_source": args.truth, "report_source": args.report}
    view = "parameters" if args.parameters else "auto"
    rows, ok = check_report(truth, report, **tols, **src, model=args.model, view=view, truth_model=args.truth_model)
    kinematic = bool(rows) and rows[0].get("view") == "kinematics"
    if kinematic:
        print(
            "what the robots do: largest error over 200 random readings within the joint ranges "
            "(m, rad; size as a ratio), base, tool and unmeasured size removed:"
        )
        _print_rows(rows, "loop / quantity")
        from closedloop.validation.check import prediction_finding

        finding = prediction_finding(rows)
        if finding:
            print(finding)
        if args.show_parameters:
            print("\nthe parameter table (a second view: a correct robot in another parametrization may differ here):")
            _print_rows(check_parameters(truth, report, **tols, **src)[0], "parameter")
    else:
        _print_rows(rows, "parameter")
        if not args.parameters:  # the kinematic view could not be had: say why
            from pathlib import Path

            model = args.model or report.get("model")
            why = (
                "the report names no robot model (give --model FILE)"
                if not model
                else f"the robot model {model} is not found (give --model FILE)"
                if not Path(model).is_file()
                else "no loop of the report has robot frames to follow"
            )
            print(f"note: compared by parameters, not by what the robots do: {why}")
    verdict = report.get("verdict") if isinstance(report.get("verdict"), dict) else {}
    if args.json:  # the rows for a script: observed, predicted and tolerance per row, and the verdict
        from closedloop.io.files import atomic_write_text

        doc = {"verdict": verdict.get("status"), "pass": bool(ok), "rows": rows}
        atomic_write_text(args.json, json.dumps(doc, indent=1, default=float) + "\n")
    if verdict.get("status") in ("suspect", "failed"):  # what the calibration said of itself
        own = f"{verdict['status']}: "
        reasons = [r[len(own) :] if str(r).startswith(own) else str(r) for r in verdict.get("reasons", [])]
        print(f"note: the report's verdict is {verdict['status']}: " + "; ".join(dict.fromkeys(reasons)))
    return 0 if ok else 1


def _print_rows(rows: list[dict], what: str) -> None:
    """The rows as a table; the predicted error and the ratio observed / predicted where the report has them."""
    predicted = any(r.get("predicted") is not None for r in rows)
    extra = f"{'predicted':>12}{'ratio':>8}" if predicted else ""
    width = max([40] + [len(r["name"]) + 2 for r in rows])  # a long loop or frame name widens the column
    print(f"{what:<{width}}{'true':>14}{'calibrated':>14}{'error':>12}{extra}{'tol':>10}  result")
    for r in rows:
        cal = "" if r["calibrated"] is None else f"{r['calibrated']:14.6g}"
        err = "" if r["error"] is None else f"{r['error']:12.3g}"
        tol = "" if r["tol"] is None else f"{r['tol']:10.3g}"
        true = "" if r["true"] is None else f"{r['true']:14.6g}"
        more = ""
        if predicted:
            p, q = r.get("predicted"), r.get("ratio")
            # a ratio of 1e4 or more (a prediction far off) in 3 digits, so that it keeps its 8 columns
            ratio = "" if q is None else f"{q:8.2f}" if abs(q) < 1e4 else f"{q:8.2g}"
            more = ("" if p is None else f"{p:12.3g}").rjust(12) + ratio.rjust(8)
        print(f"{r['name']:<{width}}{true:>14}{cal:>14}{err:>12}{more}{tol:>10}  {r['result']}")
    bad = sum(r["result"] == "FAIL" for r in rows)
    print(
        f"{sum(r['result'] == 'ok' for r in rows)} within tolerance, {bad} outside, "
        f"{sum(r['result'] not in ('ok', 'FAIL') for r in rows)} not compared"
    )


CHECK_ORDER = (
    "the order is: closedloop check TRUTH REPORT (truth.json of closedloop simulate, then calibrate's --report)"
)


def _refuse_swapped(truth, report, truth_path: str, report_path: str) -> None:
    """Refuse a calibration report given as `check`'s truth file, or a simulation's truth file given as its
    report, in one line saying which is which: a report's ``parameters`` is a list of named records
    (`closedloop.io.schemas.REPORT_SCHEMA`), a truth file's a mapping of names to values beside the
    scenario it was simulated from (`TRUTH_SCHEMA`).  Anything else is left to the schemas' messages."""
    params = truth.get("parameters") if isinstance(truth, dict) else None
    if isinstance(params, list) and params and all(isinstance(p, dict) and "name" in p for p in params):
        raise InputError(
            f"{truth_path}: a calibration report given as the truth file (the first argument); {CHECK_ORDER}"
        )
    if isinstance(report, dict) and isinstance(report.get("parameters"), dict) and "scenario" in report:
        raise InputError(
            f"{report_path}: a simulation's truth file given as the report (the second argument); {CHECK_ORDER}"
        )


def _load_json(path: str, what: str = "JSON file"):
    from closedloop.io.schemas import load_json

    return load_json(path, what)


# --------------------------------------------------------------------------- parser
def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `closedloop` parser; with `command`, only that subcommand gets its options (the others are
    named only), so that a run imports the option code of its own subcommand alone."""
    p = _Parser(prog="closedloop", description="Closed-loop kinematic calibration of robots.")
    p.add_argument("-v", "--verbose", action="store_true", help="log details")
    sub = p.add_subparsers(dest="command", required=True)
    for name, add in _SUBCOMMANDS.items():
        if command is None or name == command:
            add(sub)
        else:
            sub.add_parser(name)
    return p


def _add_inspect(sub) -> None:
    i = sub.add_parser("inspect", help="list a model's joints, frames and parameter names")
    i.add_argument("model", help="URDF, MJCF (.xml) or D-H table (.yaml)")
    i.add_argument("--json", action="store_true", help="print the description as JSON")
    i.set_defaults(func=cmd_inspect)


def _add_extract(sub) -> None:
    from closedloop.cli.extract import add_extract_parser

    add_extract_parser(sub)


def _add_batch(sub) -> None:
    from closedloop.cli.batch import add_parser as add_batch  # closedloop batch MANIFEST (many jobs, any executor)

    add_batch(sub)


def _add_fleet_report(sub) -> None:
    from closedloop.cli.fleet import add_parser as add_fleet_report  # closedloop fleet-report SUMMARY

    add_fleet_report(sub)


def _add_loops(sub) -> None:
    from closedloop.cli.loops import cmd_loops

    lp = sub.add_parser("loops", help="list the loop types, their keys and an example each")
    lp.set_defaults(func=cmd_loops)


def _add_impedance(sub) -> None:
    from closedloop.cli.impedance import add_parser as add_impedance  # closedloop impedance simulate|identify

    add_impedance(sub)


def _add_evaluate(sub) -> None:
    from closedloop.cli.evaluate import add_parser as add_evaluate  # closedloop evaluate MODEL... LOG --loop ...

    add_evaluate(sub)


def __getattr__(name: str):
    """`cmd_calibrate` and `cmd_simulate`, imported on first use (module doc)."""
    if name == "cmd_calibrate":
        from closedloop.cli.calibrate import cmd_calibrate

        return cmd_calibrate
    if name == "cmd_simulate":
        from closedloop.cli.simulate import cmd_simulate

        return cmd_simulate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _add_calibrate(sub) -> None:
    from closedloop.cli.calibrate import add_arguments, cmd_calibrate
    from closedloop.cli.loops import loop_help

    c = sub.add_parser(
        "calibrate",
        help="calibrate a model from a joint log",
        epilog=loop_help,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(c)  # derived from the run's options (closedloop.run.options)
    c.set_defaults(func=cmd_calibrate)


def _add_simulate(sub) -> None:
    from closedloop.cli.simulate import add_simulate_robot_options, cmd_simulate, scenario_help

    s = sub.add_parser(
        "simulate",
        help="generate a closed-chain dataset in MuJoCo",
        epilog=scenario_help,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    s.add_argument("scenario", nargs="?", help="a scenario name (below) or a scenario YAML file")
    add_simulate_robot_options(s)
    s.add_argument(
        "--n",
        type=int_arg,
        default=None,
        metavar="N",
        help="configurations to record (default 200; with --poses, the file's rows); fewer recorded: exit 3 and "
        "why (the files are written when some were)",
    )
    s.add_argument(
        "--seed", type=int_arg, default=0, help="random seed: the same seed gives the same dataset (default 0)"
    )
    s.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        help="dataset folder: nominal.urdf, scene.xml, log.csv, truth.json (refused if it holds another dataset)",
    )
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a scenario setting")
    s.add_argument("--replace", action="store_true", help="replace the dataset already in --out (refused otherwise)")
    s.add_argument("--quiet", action="store_true", help="no progress and no summary (errors and warnings only)")
    s.set_defaults(func=cmd_simulate)
    from closedloop.cli.sweep import add_sweep_options  # --seeds / --jobs / --ray: many datasets on the executor

    add_sweep_options(s)


def _add_check(sub) -> None:
    k = sub.add_parser(
        "check", help="compare a calibration report with simulation truth: by what the robots do (default)"
    )
    k.add_argument("truth", help="truth.json of a simulated dataset (closedloop simulate)")
    k.add_argument("report", help="JSON report of the calibration (calibrate --report)")
    k.add_argument("--tol-m", type=float_arg, default=1e-3, help="tolerance for lengths (m)")
    k.add_argument("--tol-rad", type=float_arg, default=5e-3, help="tolerance for angles (rad)")
    k.add_argument("--tol-scale", type=float_arg, default=5e-3, help="tolerance for scale factors")
    k.add_argument("--tol-px", type=float_arg, default=1.0, help="tolerance for camera intrinsics (px)")
    k.add_argument(
        "--model",
        default=None,
        help="the robot model the report calibrated (default: the report's 'model' field)",
    )
    k.add_argument(
        "--truth-model",
        default=None,
        help="the true robot's model where it is not the calibrated one's (default: the truth's 'model' field)",
    )
    k.add_argument(
        "--parameters",
        action="store_true",
        help="judge by the parameter table instead of what the robots do (parametrization-dependent)",
    )
    k.add_argument(
        "--json",
        default=None,
        metavar="FILE",
        help="also write the rows (observed error, predicted, tolerance, result) and the verdict as JSON",
    )
    k.add_argument(
        "--show-parameters",
        action="store_true",
        help="print the parameter table below the kinematic comparison",
    )
    k.set_defaults(func=cmd_check)


#: the subcommands in the order `closedloop --help` lists them
_SUBCOMMANDS = {
    "calibrate": _add_calibrate,
    "inspect": _add_inspect,
    "simulate": _add_simulate,
    "check": _add_check,
    "extract": _add_extract,
    "batch": _add_batch,
    "fleet-report": _add_fleet_report,
    "loops": _add_loops,
    "impedance": _add_impedance,
    "evaluate": _add_evaluate,
}


def _command(argv: list[str]) -> str | None:
    """The subcommand an argument list runs (its first word that is not an option), if it names one."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in _SUBCOMMANDS else None


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (an `InputError`, exit 2) instead of a usage block, and no
    abbreviated options (`--degree` must not silently mean `--degrees`); subcommands parse alike.  An
    epilog may be given as a function, called where the epilog is read (the help printed, the docs built):
    calibrate's lists the loop types, which loads every loop module and Pinocchio, and a run parsing its
    arguments should not wait for them."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    @property
    def epilog(self) -> str | None:
        text = self._epilog
        return text() if callable(text) else text

    @epilog.setter
    def epilog(self, text: str | Callable[[], str] | None) -> None:
        self._epilog = text

    def error(self, message: str):
        raise InputError(f"{self.prog}: {message} (see {self.prog} --help)")


class _LogFormatter(logging.Formatter):
    """A library's ``note: ...`` reads as the command's own note line; anything else names its level and
    module (``WARNING closedloop.x: ...``)."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno < logging.ERROR and record.getMessage().startswith("note: "):
            return record.getMessage()
        return super().format(record)


class _Signal(KeyboardInterrupt):
    """SIGTERM / SIGHUP raised as an exception, so that every cleanup (temporary outputs) runs."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


_received: list[int] = []  # the signals received during this command (a library may swallow the exception)


def _raise_signal(signum, _frame):
    _received.append(signum)
    _note_signal(signum)
    raise _Signal(signum)


def _raise_interrupt(signum, _frame):
    """SIGINT as Python's own handler, remembered: numpy turns an interrupt in its C extension's import
    into an ImportError, which must still end as an interruption."""
    _received.append(signum)
    _note_signal(signum)
    raise KeyboardInterrupt


def _note_signal(signum: int) -> None:
    """No output is published after an interrupt, even one a library caught (`io.files.note_signal`)."""
    from closedloop.io.files import note_signal

    note_signal(signum)


#: glibc's allocator in the program's own process (`_keep_freed_arrays`): arrays up to this many bytes come
#: from the heap, and up to TRIM_THRESHOLD bytes of freed heap stay with the process
MMAP_THRESHOLD = 256 << 20
TRIM_THRESHOLD = 1 << 30


def _keep_freed_arrays() -> None:
    """Keep freed large arrays in the process for the next pass (glibc on Linux; elsewhere nothing).

    A long log's passes form arrays of tens to hundreds of megabytes (100,000 rows: J 130 MB, its
    whitening's roots 29 MB).  glibc maps each one fresh from the kernel above its mmap threshold (32 MB at
    most by its own adjustment) and gives it back when freed, so every pass pays the page faults of its
    arrays again.  With the heap serving up to `MMAP_THRESHOLD` and keeping `TRIM_THRESHOLD` of freed memory,
    a 100,000-row calibration spends 0.5 s less system time and 0.2 s less user time (1.2-1.7 s -> 0.8-0.9 s;
    2-core AMD EPYC, three runs each) for 60-120 MB more peak memory.  Thresholds the user set
    (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``) are left as set."""
    import os

    if not sys.platform.startswith("linux") or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    libc.mallopt(m_mmap_threshold, MMAP_THRESHOLD)
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        libc.mallopt(m_trim_threshold, TRIM_THRESHOLD)


#: the environment variables OpenBLAS reads for its thread count (`_numerical_defaults`)
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")


def _numerical_defaults() -> None:
    """Settings of the numerical libraries for the program's own process, made before they load; a setting the
    user made in the environment is left as it is.

    * OpenBLAS starts with one thread (``OPENBLAS_NUM_THREADS=1``, unless a thread count is set).  The
      calibration holds BLAS to one thread wherever it works (`estimate.threads`: its algebra is tall and
      thin, and its parallel work runs on threads of its own), but each OpenBLAS starts a worker per core
      when it loads, and those spin-wait for work that never comes: SciPy's copy, loaded on a thread while
      the fit runs, spun for 2 % of a 100,000-row calibration's CPU samples, numpy's for 2 % more, on the
      cores the fit's own threads need on a busy machine.  ``--threads N`` still raises the count where asked.
    * numpy does not ask the kernel for huge pages (``NUMPY_MADVISE_HUGEPAGE=0``).  Each of a long log's large
      arrays is then faulted in 2 MB pages, each zeroed whole at its first touch: at 100,000 rows 1.3-1.4 s
      of system time against 1.0-1.1 s in 4 kB pages, and 20-40 MB more peak memory (2-core AMD EPYC, four
      runs each).
    """
    import os

    if not any(v in os.environ for v in BLAS_THREAD_VARIABLES):
        os.environ["OPENBLAS_NUM_THREADS"] = "1"
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


def main(argv: list[str] | None = None) -> int:
    """Run one command.  Exit codes: 0 ok, 1 check outside tolerance, 2 a user's mistake (one line on
    stderr), 130 interrupted (Ctrl-C; 128 + signal number for SIGTERM/SIGHUP), 70 an internal error.

    Run as the program (`argv` None), the process then ends at once (`_exit_now`): the exit handlers run and
    the streams are flushed, the interpreter's teardown (a last garbage collection over every object, the
    modules emptied one by one: a quarter of a second after a long log's calibration) is skipped.  Not under
    a profiler or a tracer (``python -m cProfile``, coverage): they write what they saw once the program
    returns."""
    rc = _main(argv)
    if argv is None and sys.getprofile() is None and sys.gettrace() is None:
        _exit_now(rc)
    return rc


def _main(argv: list[str] | None) -> int:
    """`main`'s command, its exit code returned."""
    import signal
    import threading

    from closedloop.io.files import track_inputs

    own_process = argv is None  # run as the program (not called by a test or a script)
    if own_process:
        _keep_freed_arrays()
        _numerical_defaults()
    argv = join_negative_numbers(list(sys.argv[1:] if argv is None else argv))
    handlers = {}
    _received.clear()
    from closedloop.io.files import clear_signals

    clear_signals()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            handlers[sig] = signal.signal(sig, _raise_signal)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # (not where SIGINT is ignored)
            handlers[signal.SIGINT] = signal.signal(signal.SIGINT, _raise_interrupt)

    def interrupted(signum: int | None) -> int:
        print(
            ("\n" if sys.stderr.isatty() else "")
            + "interrupted"
            + (f" (signal {signum})" if signum and signum != signal.SIGINT else "")
            + "; outputs not yet published were discarded",
            file=sys.stderr,
        )
        code = 128 + signum if signum and signum != signal.SIGINT else 130
        if _received and not own_process:  # a real signal to a caller's process (a script, a test run): it stops
            raise _Signal(signum) if signum and signum != signal.SIGINT else KeyboardInterrupt()  # the caller too
        if own_process:  # the interpreter would kill itself with SIGINT at exit (exit -2) had the interrupt
            _exit_now(code)  # landed in a C extension's import; our cleanups have run: leave with the code
        return code

    verbose = "-v" in argv or "--verbose" in argv
    if verbose:  # accepted before or after the subcommand: the top-level flag
        argv = ["-v"] + [a for a in argv if a not in ("-v", "--verbose")]
    try:
        with track_inputs():  # every file a reader opens is an input no output may replace
            from closedloop.cli.config import parse_args  # (the heavy imports start here: inside the handlers)

            args = parse_args(build_parser(_command(argv)), argv)  # applies a subcommand's --config FILE
            handler = logging.StreamHandler()
            handler.setFormatter(_LogFormatter())
            logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
            rc = args.func(args)
            if _received:  # a library swallowed the interrupt and the command ran on: it still ends interrupted
                return interrupted(_received[0])
            return rc
    except SystemExit as exc:  # --help, --version, a --config loader that already printed its line
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(f"error: {exc.code}", file=sys.stderr)
        return EXIT_INPUT
    except CalibrationError as exc:  # the data cannot give a calibration (NotIdentifiable, Convergence): failed
        print(f"error: calibration failed: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except ClosedLoopError as exc:  # InputError and its kin: the user's mistake, one line
        if _received:
            return interrupted(_received[0])
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt as exc:
        return interrupted(getattr(exc, "signum", None))
    except BrokenPipeError:  # the reader went away (`| head`): quiet, as a tool killed by SIGPIPE
        import os

        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        except (OSError, ValueError):
            pass
        return EXIT_PIPE
    except OSError as exc:  # a file system refusal the checks could not foresee (disk full, ...)
        if _received:
            return interrupted(_received[0])
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT
    except MemoryError:
        print("error: out of memory (a smaller log or fewer parameters may fit)", file=sys.stderr)
        return EXIT_INPUT
    except Exception as exc:  # a bug: still one line, the traceback with -v
        if _received:  # an interrupt a library turned into another exception (numpy's import: ImportError)
            return interrupted(_received[0])
        if verbose:
            import traceback

            traceback.print_exc()
        print(
            f"error: internal error ({type(exc).__name__}: {_one_line(exc)}); this is a bug in closedloop, "
            "please report it (rerun with -v for the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    finally:
        if own_process and signal.SIGINT in handlers:
            # the command has ended, its outputs published or discarded: an interrupt while the interpreter
            # exits changes nothing, where Python's default would end the process by SIGINT (exit -2)
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            del handlers[signal.SIGINT]
        for sig, h in handlers.items():
            signal.signal(sig, h)


def _exit_now(code: int) -> None:
    """Run the exit handlers, flush the standard streams and end the process with `code`, without the
    interpreter's own finalization (which would also turn an interrupt seen during an import into SIGINT)."""
    import atexit
    import os

    try:
        atexit._run_exitfuncs()  # multiprocessing's finalizers: the pool's semaphores released
    except BaseException:  # noqa: BLE001 - leaving anyway
        pass

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 2000 else text[:1997] + "..."


if __name__ == "__main__":
    sys.exit(main())
