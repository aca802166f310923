"""`closedloop batch MANIFEST`: the command line of `closedloop.fleet.batch` (its parser, its summary lines).

The jobs, their outputs and the drift are `fleet.batch`'s; this module parses, prints and exits.
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

from closedloop.errors import EXIT_FAILED
from closedloop.io.files import is_special
from closedloop.run.options import check_number


def cmd_batch(args) -> int:
    """closedloop batch MANIFEST [--jobs N | --ray auto|ADDRESS] [--job-timeout S] [--summary CSV]."""
    from closedloop.cli.progress import ProgressDisplay
    from closedloop.fleet.batch import (
        check_batch_outputs,
        drift_path,
        end_workers,
        read_manifest,
        run_batch,
        start_worker_server,
    )
    from closedloop.parallel.executor import engine_from_args

    jobs = read_manifest(args.manifest)
    summary = (
        Path(args.summary) if args.summary else Path(args.manifest).with_name(Path(args.manifest).stem + ".summary.csv")
    )
    args.drift_z = check_number("--drift-z", args.drift_z, 0.0, 1e6, lo_open=True)
    if args.job_timeout is not None:
        args.job_timeout = check_number("--job-timeout", args.job_timeout, 0.0, 1e7, lo_open=True)
    check_batch_outputs(args.manifest, jobs, summary)
    with engine_from_args(args) as eng, ProgressDisplay(args.quiet) as shown:
        if eng.name == "local":
            start_worker_server()
        try:
            res = run_batch(jobs, summary, eng, shown, args.drift_z)
        except KeyboardInterrupt:  # Ctrl-C, SIGTERM: no worker may run on (the shutdown would wait for them)
            end_workers()
            raise
    flagged = [d for d in res.drift if d.flagged]
    verdicts = Counter(str(r.get("verdict", "")) for r in res.rows if r["name"] not in res.failed)
    print(
        f"{len(res.ran)} job(s) run on {eng.name} ({eng.workers} worker(s)), {len(res.resumed)} finished "
        f"earlier (not redone), {len(res.failed)} failed -> {summary}"
    )
    if +verdicts:
        print("  verdicts: " + ", ".join(f"{verdicts[v]} {v}" for v in ("ok", "suspect", "failed") if verdicts[v]))
    for name in res.failed:
        print(f"  failed: {name}: {next(r['error'] for r in res.rows if r['name'] == name)}", file=sys.stderr)
    for r in res.rows:
        if r.get("verdict") == "failed" and r["name"] not in res.failed:
            print(f"  verdict failed: {r['name']}: {r.get('verdict_reasons', '')}", file=sys.stderr)
    if res.drift:
        print(
            f"  drift: {len(flagged)} of {sum(not d.note for d in res.drift)} parameter changes exceed "
            f"{args.drift_z:g} standard errors" + ("" if is_special(summary) else f" -> {drift_path(summary)}")
        )
    for d in res.drift:
        if d.note:
            print(f"    {d.robot} {d.before} -> {d.after}: {d.note}")
    for d in flagged:
        print(f"    {d.robot} {d.before} -> {d.after}: {d.parameter} {d.change:+.3g} (z = {d.z:+.1f})")
    # a job that could not run: 1; every job ran but a calibration's verdict is failed: 3, as calibrate's
    return 1 if res.failed else EXIT_FAILED if verdicts["failed"] else 0


def add_parser(sub) -> None:
    """The `batch` subcommand."""
    from closedloop.parallel.executor import add_arguments

    b = sub.add_parser("batch", help="calibrate many robots/logs from a manifest (YAML or CSV), resumable")
    b.add_argument("manifest", help="YAML (jobs: [...]) or CSV: model, log, loops, options, out[, robot, date, cv]")
    b.add_argument("--summary", help="summary CSV (default: MANIFEST.summary.csv beside the manifest)")
    b.add_argument("--drift-z", default=3.0, help="flag a parameter change above this many std. errors")
    add_arguments(b, timeout=True)
    b.add_argument("--quiet", action="store_true", help="no progress lines (the summary is still printed)")
    b.set_defaults(func=cmd_batch)
