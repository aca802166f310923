"""`closedloop fleet-report SUMMARY`: one report for a fleet calibrated by `closedloop batch`
(:mod:`closedloop.fleet.report`): per robot the verdict, the drift since the previous calibration, the
predicted workspace accuracy, the robots that need attention first; JSON and an HTML page."""

from __future__ import annotations

from pathlib import Path


def cmd_fleet_report(args) -> int:
    from closedloop.errors import InputError
    from closedloop.fleet.report import fleet_report, read_summary, write_fleet_report
    from closedloop.io.files import check_outputs
    from closedloop.run.options import check_number

    if not args.json and not args.html:
        raise InputError("fleet-report: give --json FILE and/or --html FILE")
    z = check_number("--drift-z", args.drift_z, 0.0, 1e6, lo_open=True)
    outputs = {k: Path(v) for k, v in (("--json", args.json), ("--html", args.html)) if v}
    check_outputs(outputs, [args.summary])
    report = fleet_report(read_summary(args.summary), z)
    write_fleet_report(report, args.json, args.html)
    counts = ", ".join(f"{n} {a}" for a, n in report["attention"].items() if n)
    print(f"{report['robots_total']} robots, {report['jobs_total']} calibrations: {counts}")
    for r in [r for r in report["robots"] if r["attention"] != "ok"][: args.top]:
        z_txt = "" if r["drift"]["max_z"] is None else f", drift max |z| {r['drift']['max_z']:.1f}"
        why = r["error"] or "; ".join(r["drift"]["flagged"]) or r["verdict_reasons"]
        print(
            f"  {r['robot']}: {r['attention']} ({r['job']}, verdict {r['verdict']}{z_txt}){': ' + why if why else ''}"
        )
    for path in outputs.values():
        print(f"  wrote {path}")
    return 0


def add_parser(sub) -> None:
    """The `fleet-report` subcommand."""
    f = sub.add_parser(
        "fleet-report",
        help="one report of a fleet calibrated by `batch`: verdicts, drift, accuracy, who needs attention",
    )
    f.add_argument("summary", help="the batch's summary CSV (MANIFEST.summary.csv)")
    f.add_argument("--json", metavar="FILE", help="write the report as JSON")
    f.add_argument("--html", metavar="FILE", help="write the report as one HTML page with the fleet's drift plot")
    f.add_argument("--drift-z", default=3.0, help="the threshold the batch flagged drift at (the plot's line)")
    f.add_argument("--top", type=int, default=10, help="robots needing attention printed (default 10)")
    f.set_defaults(func=cmd_fleet_report)
