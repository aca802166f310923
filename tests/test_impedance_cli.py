"""`closedloop impedance simulate|identify` end to end, its one-line errors, and records a lab may have."""

from __future__ import annotations

import errno
import json
import os
import sys

import numpy as np
import pytest

from closedloop.cli.main import main
from closedloop.impedance.data import read_record, record_bytes


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("imp") / "sim"
    args = ["impedance", "simulate", "--out", str(out), "--cycles", "40", "--engine", "rk4"]
    assert main(args + ["--stiffness", "dip:20,0.4,0.15", "--seed", "3", "--postures"]) == 0
    return out


@pytest.mark.slow
def test_simulate_identify_round_trip(sim_dir, tmp_path, capsys):
    out = sim_dir
    res, figs = tmp_path / "res.json", tmp_path / "figs"
    argv = ["impedance", "identify", str(out / "data.csv"), "--truth", str(out / "truth.csv"), "--bootstrap", "50"]
    argv += ["--folds", "3", "--posture", str(out / "posture_0.csv"), "--out", str(res), "--plots", str(figs)]
    assert main(argv) == 0
    doc = json.loads(res.read_text())
    s = doc["summary"]
    assert s["cycles"] == 40 and s["vaf_free_run"] > 99.0
    assert max(s["errors_vs_truth_percent"].values()) < 3.0
    assert abs(s["posture"]["posture_0"][2] / 16.84 - 1) < 0.03
    assert len(doc["table"]["K"]) == 1200 and "K_lo" in doc["table"]
    assert 6.0 <= s["prefilter_hz"] <= 20.0 and set(s["expected_error_percent"]) == {"I", "B", "K"}
    assert (figs / "impedance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "free-run VAF" in text and "expected error (bootstrap std)" in text


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
    for args, words in (
        (["--shoulder", "0.5,5000,75"], "--case robot"),  # the forearm has no shoulder
        (["--case", "robot", "--shoulder", "0.5,5000"], "ANGLE,K,B"),
        (["--case", "robot", "--shoulder", "0.5,-1,75"], "--shoulder stiffness"),
    ):
        assert main(["impedance", "simulate", "--out", str(tmp_path / "y")] + args) == 2
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, err
    assert not (tmp_path / "y").exists()  # refused before any work


@pytest.mark.slow
@pytest.mark.parametrize(
    "extra, words",
    [
        (["--prefilter", "nan"], ["--prefilter nan", "finite"]),
        (["--prefilter", "-5"], ["--prefilter -5", "> 0"]),
        (["--prefilter", "400"], ["pre-filter 400", "Nyquist"]),
        (["--pool-ms", "nan"], ["--pool-ms nan", "finite"]),
        (["--smooth-ms", "-1"], ["--smooth-ms -1", ">= 0"]),
        (["--period", "0"], ["--period 0", "> 0"]),
        (["--lag-ms", "-20"], ["--lag-ms -20", "> 0"]),
        (["--seed", "-1"], ["--seed -1", ">= 0"]),
        (["--folds", "1"], ["--folds 1"]),
        (["--columns", "torque"], ["--columns torque", "NAME=COLUMN"]),
        (["--columns", "force=tau"], ["'force'"]),
        (["--segment", "sideways"], ["--segment sideways"]),
    ],
)
def test_identify_options_checked_before_work(sim_dir, capsys, extra, words):
    assert main(["impedance", "identify", str(sim_dir / "data.csv"), "--bootstrap", "0", "--folds", "0"] + extra) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and all(w in err for w in words), err


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--seed", "-1"], ["--seed -1", ">= 0"]),
        (["--stiffness", "constant:nan"], ["constant:nan", "finite"]),
        (["--damping", "constant:-1"], ["damping", "unstable"]),
        (["--stiffness", "dip:20,1.5,0.1"], ["K(t) must stay positive"]),
        (["--cycles", "0"], ["--cycles 0"]),
        (["--noise", "nan"], ["--noise nan"]),
    ],
)
def test_simulate_options_checked_before_work(tmp_path, capsys, extra, words):
    out = tmp_path / "o"
    assert main(["impedance", "simulate", "--out", str(out), "--engine", "rk4", "--cycles", "2"] + extra) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and all(w in err for w in words), err
    assert not out.exists()


def test_outputs_never_replace_inputs(sim_dir, tmp_path, capsys):
    """--out onto the data, the truth or a hard link to the data: refused before any work, inputs intact."""
    data, truth = sim_dir / "data.csv", sim_dir / "truth.csv"
    before = {p: p.read_bytes() for p in (data, truth)}
    link = tmp_path / "link.csv"
    os.link(data, link)
    for target in (data, truth, link):
        assert main(["impedance", "identify", str(data), "--truth", str(truth), "--out", str(target)]) == 2
        assert "refusing to overwrite an input" in capsys.readouterr().err
    onsets = tmp_path / "on.csv"
    onsets.write_text("onset\n1\n3\n5\n")
    assert main(["impedance", "identify", str(data), "--segment", f"onsets:{onsets}", "--out", str(onsets)]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err and onsets.read_text() == "onset\n1\n3\n5\n"
    assert all(p.read_bytes() == b for p, b in before.items())


def test_full_disk_leaves_no_partial_file(sim_dir, tmp_path, monkeypatch, capsys):
    """A write that fails half-way (ENOSPC): exit 2, one line, no results file, no temporary left."""
    import closedloop.io.files as files

    def full(fd, data):
        os.write(fd, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files, "_write_all", full)
    res = tmp_path / "res.json"
    argv = ["impedance", "identify", str(sim_dir / "data.csv"), "--bootstrap", "10", "--folds", "0"]
    assert main(argv + ["--out", str(res)]) == 2
    assert "No space left" in capsys.readouterr().err
    out = tmp_path / "sim"
    assert main(["impedance", "simulate", "--out", str(out), "--engine", "rk4", "--cycles", "2"]) == 2
    assert not res.exists() and list(tmp_path.iterdir()) in ([], [out]) and not any(out.glob("*"))


def test_missing_extras_refused_before_work(sim_dir, tmp_path, monkeypatch, capsys):
    for name in ("h5py", "matplotlib"):
        monkeypatch.setitem(sys.modules, name, None)  # `import name` raises ImportError
    argv = ["impedance", "identify", str(sim_dir / "data.csv"), "--bootstrap", "0"]
    assert main(argv + ["--plots", str(tmp_path / "f")]) == 2
    assert "--plots: needs matplotlib" in capsys.readouterr().err
    assert main(["impedance", "simulate", "--out", str(tmp_path / "h"), "--format", "h5", "--cycles", "2"]) == 2
    err = capsys.readouterr().err
    assert "--format h5: needs h5py" in err and 'pip install "closedloop[impedance]"' in err


def _write(path, rec):
    path.write_bytes(record_bytes(rec))
    return path


def test_reversed_torque_sign_is_refused_with_the_cause(sim_dir, tmp_path, capsys):
    rec = read_record(sim_dir / "data.csv")
    rec.torque = -rec.torque
    bad = _write(tmp_path / "rev.csv", rec)
    assert main(["impedance", "identify", str(bad), "--bootstrap", "0", "--folds", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "torque sign reversed" in err and "--torque-sign -1" in err
    res = tmp_path / "r.json"
    argv = ["impedance", "identify", str(bad), "--torque-sign", "-1", "--truth", str(sim_dir / "truth.csv")]
    assert main(argv + ["--bootstrap", "0", "--folds", "0", "--out", str(res)]) == 0
    assert max(json.loads(res.read_text())["summary"]["errors_vs_truth_percent"].values()) < 3.0


def test_gaps_and_nan_blocks_give_a_right_result_with_a_note(sim_dir, tmp_path, capsys):
    rec = read_record(sim_dir / "data.csv")
    keep = np.ones(len(rec.time), bool)
    for c in (2, 5, 8, 15, 18, 25, 28, 35, 38):  # 0.1 s of rows deleted in 9 cycles
        keep[c * 1200 + 300 : c * 1200 + 360] = False
    rec.angle[20 * 1200 + 500 : 20 * 1200 + 560] = np.nan  # and a NaN block
    for k in ("time", "angle", "torque", "command", "event", "block"):
        setattr(rec, k, getattr(rec, k)[keep])
    rec.valid = None
    path = _write(tmp_path / "gappy.csv", rec)
    res = tmp_path / "r.json"
    argv = ["impedance", "identify", str(path), "--truth", str(sim_dir / "truth.csv"), "--bootstrap", "0"]
    assert main(argv + ["--folds", "0", "--out", str(res)]) == 0
    s = json.loads(res.read_text())["summary"]
    assert s["cycles"] <= 40 - 7 and max(s["errors_vs_truth_percent"].values()) < 4.0
    assert any("gaps in time" in n for n in s["notes"]) and any("non-finite" in n for n in s["notes"])
    assert "note: " in capsys.readouterr().out


def test_onsets_file_with_header_and_segment_auto(sim_dir, tmp_path, capsys):
    rec = read_record(sim_dir / "data.csv")
    from closedloop.impedance.data import onsets_from_events

    on = onsets_from_events(rec)
    times = [rec.time[rec.block == b][i] for b, i in on]
    f = tmp_path / "onsets.csv"
    f.write_text("cycle,onset\n" + "".join(f"{k},{t:.6f}\n" for k, t in enumerate(times)))
    truth = str(sim_dir / "truth.csv")
    base = ["impedance", "identify", "--bootstrap", "0", "--folds", "0", "--truth", truth]
    res = tmp_path / "a.json"
    assert main(base + [str(sim_dir / "data.csv"), "--segment", f"onsets:{f}", "--out", str(res)]) == 0
    assert json.loads(res.read_text())["summary"]["cycles"] == 40
    plain = tmp_path / "plain.txt"
    plain.write_text("".join(f"{t:.6f}\n" for t in times))
    assert main(base + [str(sim_dir / "data.csv"), "--segment", f"onsets:{plain}", "--out", str(res)]) == 0
    bad = tmp_path / "bad.csv"
    bad.write_text("cycle,when\n1,2\n")
    assert main(base + [str(sim_dir / "data.csv"), "--segment", f"onsets:{bad}"]) == 2
    assert "no onset column" in capsys.readouterr().err
    rec.event = None  # no event column: segment auto cuts by peak velocity and says so
    path = _write(tmp_path / "noev.csv", rec)
    assert main(base + [str(path), "--out", str(res)]) == 0
    s = json.loads(res.read_text())["summary"]
    assert any("peak velocity, period 2 s" in n for n in s["notes"]) and s["cycles"] >= 35


def test_each_warning_printed_once(sim_dir, capsys):
    argv = ["impedance", "identify", str(sim_dir / "data.csv"), "--bootstrap", "0", "--folds", "0"]
    assert main(argv + ["--align", "peak-velocity+rms"]) == 0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines and len(lines) == len(set(lines)), err
    assert all(ln.startswith("  warning: ") for ln in lines), err


def test_too_few_cycles_state_the_expected_error(tmp_path, capsys):
    out = tmp_path / "few"
    assert main(["impedance", "simulate", "--out", str(out), "--engine", "rk4", "--cycles", "12", "--seed", "4"]) == 0
    res = tmp_path / "r.json"
    argv = ["impedance", "identify", str(out / "data.csv"), "--truth", str(out / "truth.csv"), "--folds", "0"]
    assert main(argv + ["--out", str(res)]) == 0
    s = json.loads(res.read_text())["summary"]
    worst = max(s["expected_error_percent"].values())
    assert worst > 2.0 and any("12 cycles give an expected error" in w for w in s["warnings"])
    # the stated expected error is the right size: the actual errors are of the same order
    assert 0.3 * worst < max(s["errors_vs_truth_percent"].values()) < 2.0 * worst
    assert "about" in capsys.readouterr().err


@pytest.mark.parametrize("opt", [["--voluntary", "0.5"], ["--postures"]])
def test_robot_case_refuses_what_it_does_not_simulate(tmp_path, capsys, opt):
    assert main(["impedance", "simulate", "--case", "robot", "--out", str(tmp_path / "r"), *opt]) == 2
    assert f"{opt[0]}: the robot case does not simulate it" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
