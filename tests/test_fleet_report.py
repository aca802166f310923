"""The fleet report (`closedloop fleet-report`): per robot the latest verdict, the drift since the previous
calibration, the predicted workspace accuracy when the report has it, the robots needing attention first.

A real batch (ten simulated Pandas on two dates, two of them with joint 4's offset jumped by 800 urad,
~13 standard errors of a change) names the two drifted robots first; a synthetic summary of 100 robots
checks the order of the groups and the page."""

from __future__ import annotations

import base64
import csv
import json
import re
from pathlib import Path

import pytest

from closedloop.cli.main import main
from closedloop.fleet.batch import COLUMNS
from closedloop.fleet.report import fleet_report, read_summary
from closedloop.studies.fleet import FleetDrift, FleetSpec, configurations, robot_name, write_fleet

DATES = ["2026-03-02", "2026-03-09"]


def synthetic_summary(path: Path, robots: int = 100) -> Path:
    """A batch summary as `closedloop batch` writes it: two dates per robot; robot 17 drifted (z 9.5),
    robot 64 too (z 14.2, its previous calibration held a contradicted value), robot 5's second log could
    not be read, robot 30's verdict is suspect, every other second calibration drifted |z| < 3."""
    rows = []
    for i in range(robots):
        name = robot_name(i)
        for d, date in enumerate(DATES):
            row = {c: "" for c in COLUMNS}
            row.update(name=f"{name}-{date}", robot=name, date=date, status="ok", verdict="ok", out=str(path.parent))
            row.update(rms_after_mm="0.1", resumed="no")
            if d == 1:
                row.update(drift_from=f"{name}-{DATES[0]}", drift_max_z=f"{1.0 + (i % 19) / 10:.2f}")
                if i == 17:
                    row.update(drift_max_z="9.5", drift_flagged="panda_joint4.offset z=+9.5")
                if i == 64:
                    row.update(drift_max_z="14.2", drift_flagged="panda_joint2.offset z=-14.2; * z=+20.1")
                if i == 5:
                    row.update(status="failed", verdict="n/a", error="LogError: log.csv: row 3: 'n/a' is not a number")
                    row.update(drift_from="", drift_max_z="")
                if i == 30:
                    row.update(verdict="suspect", verdict_reasons="size hangs on held values")
            rows.append(row)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, COLUMNS)
        w.writeheader()
        w.writerows(rows)
    return path


def test_the_robots_that_need_attention_come_first(tmp_path, capsys):
    summary = synthetic_summary(tmp_path / "fleet.summary.csv")
    report = fleet_report(read_summary(summary))
    assert report["robots_total"] == 100 and report["jobs_total"] == 200
    order = [r["robot"] for r in report["robots"]]
    assert order[:4] == [robot_name(5), robot_name(64), robot_name(17), robot_name(30)]
    assert report["needs_attention"] == order[:4]
    assert report["attention"] == {"not calibrated": 1, "drifted": 2, "suspect": 1, "ok": 96}
    first = report["robots"][0]
    assert first["error"].startswith("LogError: log.csv: row 3") and first["drift"]["max_z"] is None
    assert report["robots"][1]["drift"]["flagged"] == ["panda_joint2.offset z=-14.2", "* z=+20.1"]
    zs = [r["drift"]["max_z"] for r in report["robots"][4:]]
    assert zs == sorted(zs, reverse=True)  # the rest by drift, largest first
    assert (
        main(["fleet-report", str(summary), "--json", str(tmp_path / "f.json"), "--html", str(tmp_path / "f.html")])
        == 0
    )
    out = capsys.readouterr().out
    assert out.index(robot_name(5)) < out.index(robot_name(64)) < out.index(robot_name(17))
    assert json.loads((tmp_path / "f.json").read_text())["needs_attention"][:3] == order[:3]
    page = (tmp_path / "f.html").read_text()
    png = base64.b64decode(re.search(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page).group(1))
    assert png.startswith(b"\x89PNG")
    assert page.index(robot_name(64)) < page.index(robot_name(17)) < page.index(robot_name(30))


def test_a_summary_that_is_not_one_is_refused(tmp_path):
    bad = tmp_path / "x.csv"
    bad.write_text("a,b\n1,2\n")
    assert main(["fleet-report", str(bad), "--json", str(tmp_path / "f.json")]) == 2
    assert not (tmp_path / "f.json").exists()


@pytest.mark.slow
def test_a_real_batch_names_the_two_drifted_robots_first(tmp_path):
    drifted = [robot_name(3), robot_name(7)]
    spec = FleetSpec(robots=10, dates=DATES, seed=11, drift=[FleetDrift(r, "panda_joint4", 800e-6) for r in drifted])
    manifest = write_fleet(tmp_path, spec, configurations(40))
    assert main(["batch", str(manifest), "--jobs", "1", "--quiet"]) == 0
    # the calibration reports carry the predicted workspace accuracy: read into the fleet report
    rep = tmp_path / "calibrated" / f"{robot_name(0)}-{DATES[1]}" / "report.json"
    frames = json.loads(rep.read_text())["accuracy"]["workspace"]["frames"]
    predicted = {f"{f['loop']}: {f['frame']}": f["predicted_rms_m"] for f in frames}
    assert predicted and all(v > 0 for v in predicted.values())
    summary = tmp_path / "fleet.summary.csv"
    assert (
        main(["fleet-report", str(summary), "--json", str(tmp_path / "f.json"), "--html", str(tmp_path / "f.html")])
        == 0
    )
    report = json.loads((tmp_path / "f.json").read_text())
    assert sorted(report["needs_attention"][:2]) == drifted
    for r in report["robots"][:2]:
        assert r["attention"] == "drifted" and any(
            f.startswith("panda_joint4.offset z=+") for f in r["drift"]["flagged"]
        )
        assert r["drift"]["max_z"] > 6.0
    assert all(r["drift"]["max_z"] < 6.0 for r in report["robots"][2:])
    acc = {r["robot"]: r["accuracy_m"] for r in report["robots"]}
    assert acc[robot_name(0)] == predicted and acc[robot_name(1)] != {}
    page = (tmp_path / "f.html").read_text()
    assert max(page.index(d) for d in drifted) < page.index(robot_name(0))
