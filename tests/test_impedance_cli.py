"""`closedloop impedance simulate|identify` end to end and its one-line errors."""

from __future__ import annotations

import json

from closedloop.cli.main import main


def test_simulate_identify_round_trip(tmp_path, capsys):
    out = tmp_path / "sim"
    assert (
        main(
            [
                "impedance",
                "simulate",
                "--out",
                str(out),
                "--cycles",
                "40",
                "--engine",
                "rk4",
                "--stiffness",
                "dip:20,0.4,0.15",
                "--seed",
                "3",
                "--postures",
            ]
        )
        == 0
    )
    res, fig = tmp_path / "res.json", tmp_path / "fig.svg"
    assert (
        main(
            [
                "impedance",
                "identify",
                str(out / "data.csv"),
                "--truth",
                str(out / "truth.csv"),
                "--bootstrap",
                "50",
                "--folds",
                "3",
                "--posture",
                str(out / "posture_0.csv"),
                "--out",
                str(res),
                "--plot",
                str(fig),
            ]
        )
        == 0
    )
    doc = json.loads(res.read_text())
    s = doc["summary"]
    assert s["cycles"] == 40 and s["vaf_free_run"] > 99.0
    assert max(s["errors_vs_truth_percent"].values()) < 6.0
    assert abs(s["posture"]["posture_0"][2] / 16.84 - 1) < 0.03
    assert len(doc["table"]["K"]) == 1200 and "K_lo" in doc["table"]
    assert fig.read_text().lstrip().startswith("<?xml")
    assert "free-run VAF" in capsys.readouterr().out


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    assert main(["impedance", "identify", str(tmp_path / "missing.csv")]) == 2
    assert "no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("time,angle,torque\n0,0,0\n")
    assert main(["impedance", "identify", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and err.count("\n") == 1
    assert main(["impedance", "simulate", "--out", str(tmp_path / "x"), "--stiffness", "wobble:3"]) == 2
    assert "stiffness" in capsys.readouterr().err
