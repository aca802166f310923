"""One report for a fleet: per robot its latest calibration's verdict, the drift since the calibration
before it (in one gauge, :mod:`closedloop.fleet.drift`), the predicted workspace accuracy where the
calibration report has it, and the robots that need attention first; as JSON and as one self-contained
HTML page with a plot of the fleet (each robot's drift against time, the outliers named).

It is read from what `closedloop batch` wrote: the summary (one row per job, the drift columns of each
robot's later calibrations filled) and each job's ``report.json`` (for the accuracy only, one at a
time), so a fleet of any size is reported without holding its calibrations.

Attention, first to last (`ATTENTION`):

1. ``not calibrated``: the job could not run (its one-line error) or its verdict is ``failed``;
2. ``drifted``: a parameter changed by more than the batch's `z` standard errors since the previous
   calibration (or the previous calibration held a value the new data contradict);
3. ``suspect``: the verdict is ``suspect``;
4. ``ok``.

Within a group, the larger drift (the largest |z| of the robot's parameter changes) first.  A robot's
drift is judged on the largest |z| of some 40 parameter changes: with no change at all it exceeds 3 about
one time in ten, so the ranking, not the flag alone, is what to read in a large fleet.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
from pathlib import Path
from typing import Any

from closedloop.errors import InputError, require
from closedloop.io.files import atomic_write_text

ATTENTION = ("not calibrated", "drifted", "suspect", "ok")


def _float(v: Any) -> float | None:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def read_summary(path: str | Path) -> list[dict]:
    """The rows of a batch summary CSV; a file that is not one is refused with one line."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            missing = {"name", "robot", "date", "status", "verdict", "out"} - set(reader.fieldnames or ())
            if missing:
                raise InputError(f"{path}: not a batch summary (no column {', '.join(sorted(missing))})")
            return list(reader)
    except OSError as exc:
        raise InputError(f"{path}: cannot read the batch summary ({exc.strerror})") from None


def workspace_accuracy(out: str | Path) -> dict[str, float]:
    """The predicted workspace accuracy (RMS, m) per followed frame of a job's ``report.json`` ('loop: frame'),
    when it has one (`accuracy.workspace.frames`)."""
    try:
        report = json.loads((Path(out) / "report.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    ws = (report.get("accuracy") or {}).get("workspace") or {}
    frames = ws.get("frames") if isinstance(ws, dict) else None
    acc = {}
    for rec in frames if isinstance(frames, list) else []:  # `accuracy.workspace.frames`: a row per loop frame
        v = _float(rec.get("predicted_rms_m")) if isinstance(rec, dict) else None
        if v is not None:
            acc[f"{rec.get('loop')}: {rec.get('frame')}"] = v
    return acc


def attention(latest: dict) -> str:
    """The attention group of a robot from its latest calibration's summary row (module docstring)."""
    if latest["status"] != "ok" or latest["verdict"] == "failed":
        return "not calibrated"
    if latest.get("drift_flagged"):
        return "drifted"
    if latest["verdict"] == "suspect":
        return "suspect"
    return "ok"


def fleet_report(rows: list[dict], z_max: float = 3.0) -> dict:
    """The fleet report of a batch's summary rows: per robot (its jobs ordered by date) the latest
    calibration, ranked by attention; every job's drift for the plot."""
    by_robot: dict[str, list[dict]] = {}
    for r in rows:
        by_robot.setdefault(r.get("robot") or r["name"], []).append(r)
    robots = []
    history = []
    for robot, jobs in by_robot.items():
        jobs.sort(key=lambda r: (r.get("date") or "", r["name"]))
        for r in jobs:
            z = _float(r.get("drift_max_z"))
            if z is not None or r.get("drift_flagged"):
                history.append({"robot": robot, "job": r["name"], "date": r.get("date") or "", "drift_max_z": z})
        latest = jobs[-1]
        flagged = latest.get("drift_flagged") or ""
        robots.append(
            {
                "robot": robot,
                "job": latest["name"],
                "date": latest.get("date") or "",
                "calibrations": len(jobs),
                "attention": attention(latest),
                "status": latest["status"],
                "verdict": latest["verdict"],
                "verdict_reasons": latest.get("verdict_reasons") or "",
                "error": latest.get("error") or "",
                "rms_after_mm": _float(latest.get("rms_after_mm")),
                "cv_test_mm": _float(latest.get("cv_test_mm")),
                "drift": {
                    "since": latest.get("drift_from") or "",
                    "max_z": _float(latest.get("drift_max_z")),
                    "flagged": [s.strip() for s in flagged.split(";") if s.strip()],
                },
                "accuracy_m": workspace_accuracy(latest["out"]) if latest["status"] == "ok" else {},
                "out": latest["out"],
            }
        )
    rank = {a: i for i, a in enumerate(ATTENTION)}
    robots.sort(key=lambda r: (rank[r["attention"]], -(r["drift"]["max_z"] or 0.0), r["robot"]))
    counts = {a: sum(r["attention"] == a for r in robots) for a in ATTENTION}
    return {
        "robots_total": len(robots),
        "jobs_total": len(rows),
        "z_max": z_max,
        "attention": counts,
        "needs_attention": [r["robot"] for r in robots if r["attention"] != "ok"],
        "robots": robots,
        "drift_history": history,
    }


# --------------------------------------------------------------------------- the plot and the page
def _plt():
    require("matplotlib", "--html", "report").use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fig_drift(report: dict, named: int = 10) -> bytes:
    """Each robot's drift (largest |z| since its previous calibration) against the date, one grey line a
    robot, the threshold dashed; the `named` robots that drifted most, in red with their names (PNG)."""
    import datetime as dt

    import numpy as np

    plt = _plt()  # (refuses a missing matplotlib in one line, before any of its modules is imported)
    from matplotlib.collections import LineCollection

    def day(s: str) -> float:
        try:
            return float(dt.date.fromisoformat(s[:10]).toordinal())
        except ValueError:
            return float("nan")

    dates = sorted({day(h["date"]) for h in report["drift_history"]})
    gaps = np.diff(dates)
    width = 0.35 * (float(np.min(gaps)) if len(gaps) else 1.0)  # each robot at its own offset within a date
    order = {r["robot"]: i for i, r in enumerate(sorted(report["robots"], key=lambda r: r["robot"]))}
    spread = {k: width * ((i * 0.618034) % 1.0 - 0.5) for k, i in order.items()}
    series: dict[str, list[tuple[float, float]]] = {}
    for h in report["drift_history"]:
        if h["drift_max_z"] is not None:
            series.setdefault(h["robot"], []).append((day(h["date"]) + spread.get(h["robot"], 0.0), h["drift_max_z"]))
    worst = [
        r["robot"]
        for r in report["robots"]
        if r["drift"]["max_z"] is not None and r["drift"]["max_z"] > report["z_max"]
    ][:named]
    fig, ax = plt.subplots(figsize=(8, 4.2))
    grey = [np.array(v) for k, v in series.items() if k not in worst]
    if grey:
        ax.add_collection(LineCollection(grey, colors="0.6", linewidths=0.8, alpha=0.6))
        pts = np.vstack(grey)
        ax.scatter(pts[:, 0], pts[:, 1], s=6, color="0.5", zorder=2)
    labels: list[float] = []  # label heights (log10) placed so far: names do not overlap
    for name in sorted(worst, key=lambda k: -series[k][-1][1] if series.get(k) else 0.0):
        v = np.array(series.get(name, []))
        if len(v):
            ax.plot(v[:, 0], v[:, 1], "-o", color="tab:red", ms=4, lw=1.2, zorder=3)
            y = np.log10(v[-1, 1])
            while any(abs(y - other) < 0.045 for other in labels):
                y -= 0.045
            labels.append(y)
            ax.annotate(
                name,
                (v[-1, 0], v[-1, 1]),
                xytext=(v[-1, 0] + 0.6 * width, 10**y),
                fontsize=8,
                color="tab:red",
                va="center",
                arrowprops={"arrowstyle": "-", "color": "tab:red", "lw": 0.5},
            )
    ax.axhline(report["z_max"], ls="--", color="k", lw=0.8)
    ax.set_yscale("log")
    ticks = [d for d in dates if np.isfinite(d)]
    if ticks:
        lo, hi = min(ticks), max(ticks)
        ax.set_xlim(lo - 2 * width - 0.05 * (hi - lo), hi + 3 * width + 0.1 * (hi - lo))
        step = max(1, len(ticks) // 8)
        ax.set_xticks(ticks[::step])
        ax.set_xticklabels([dt.date.fromordinal(int(t)).isoformat() for t in ticks[::step]], fontsize=8)
    ax.set_xlabel("date of the calibration")
    ax.set_ylabel("drift since the previous calibration: largest |z|")
    ax.set_title(f"{len(series)} robots; dashed: |z| = {report['z_max']:g}; red: the {len(worst)} that drifted most")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


_CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;font-size:.85em}td,th{border:1px solid #ddd;padding:3px 7px;text-align:left}
th{background:#f3f3f3}.n{text-align:right}.notcalibrated{background:#f8d7da}.drifted{background:#ffe5cc}
.suspect{background:#fff3cd}img{max-width:100%}.small{color:#666;font-size:.85em}"""


def _mm(v: float | None) -> str:
    return "" if v is None else f"{v * 1e3:.3g}"


def render_fleet_html(report: dict, figure: bytes | None = None) -> str:
    """The fleet report as one page: the counts, the plot (PNG, embedded), one table row per robot in
    attention order."""
    e = html.escape
    png = base64.b64encode(figure if figure is not None else fig_drift(report)).decode("ascii")
    counts = ", ".join(f"{n} {a}" for a, n in report["attention"].items() if n)
    first = report["needs_attention"][:10]
    lines = [
        f"<p>{report['robots_total']} robots, {report['jobs_total']} calibrations: {e(counts)}.</p>",
        "<p><b>Needs attention first:</b> " + (e(", ".join(first)) if first else "none") + "</p>",
        "<img alt='drift of every robot against time' src='data:image/png;base64," + png + "'>",
        "<h2>Robots, in order of attention</h2>",
        "<table><tr><th>robot</th><th>attention</th><th>latest calibration</th><th>verdict</th>"
        "<th>drift since</th><th class='n'>max |z|</th><th>flagged changes</th>"
        "<th class='n'>predicted accuracy [mm]</th><th class='n'>closure after [mm]</th><th>error or reasons</th></tr>",
    ]
    for r in report["robots"]:
        acc = "; ".join(f"{f}: {_mm(v)}" for f, v in r["accuracy_m"].items())
        z = r["drift"]["max_z"]
        after = r["rms_after_mm"]
        cls = r["attention"].replace(" ", "")
        lines.append(
            f"<tr class='{cls}'><td>{e(r['robot'])}</td><td>{e(r['attention'])}</td><td>{e(r['job'])} "
            f"({e(r['date'])})</td><td>{e(r['verdict'])}</td><td>{e(r['drift']['since'])}</td>"
            f"<td class='n'>{'' if z is None else f'{z:.2f}'}</td><td>{e('; '.join(r['drift']['flagged']))}</td>"
            f"<td class='n'>{e(acc)}</td><td class='n'>{'' if after is None else format(after, '.3g')}"
            f"</td><td>{e(r['error'] or r['verdict_reasons'])}</td></tr>"
        )
    lines.append("</table>")
    title = "closedloop fleet report"
    return (
        f"<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'><title>{title}</title>"
        f"<style>{_CSS}</style></head><body><h1>{title}</h1>\n" + "\n".join(lines) + "\n</body></html>\n"
    )


def write_fleet_report(report: dict, json_path: str | Path | None = None, html_path: str | Path | None = None) -> None:
    """Write the report as JSON and/or HTML, each file whole; the page is drawn first, so a page that cannot be
    drawn (matplotlib missing) leaves no file written."""
    page = render_fleet_html(report) if html_path is not None else None
    if json_path is not None:
        atomic_write_text(json_path, json.dumps(report, indent=1) + "\n")
    if html_path is not None and page is not None:
        atomic_write_text(html_path, page)
