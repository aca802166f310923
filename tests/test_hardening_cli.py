"""The malformed-input matrix as a table: one row per case, the input, the exit code, the words.

Every bad input gives exit 2 and ONE line on stderr naming the file / option / field (never a
traceback); inputs that are fine give exit 0.  Cases run in-process (`main([...])`), except the
real Ctrl-C, which needs a process to signal.  `{urdf}`, `{log}` are a mesh-free Panda and a
30-row weld log; `{tmp}` the case's directory; other `{name}` are the case's own files.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from closedloop.cli.main import main

WELD = "weld:frame=panda_hand,name=fixture"
DH = """name: chain
closes: false
units: {length: m, angle: rad}
joints:
  - {name: j1, theta_off: 0.0, s: 0.3, a: 0.0, alpha: 1.5708}
  - {name: j2, theta_off: 0.1, s: 0.0, a: 0.4, alpha: 0.0}
  - {name: j3, theta_off: 0.0, s: 0.0, a: 0.2, alpha: 0.0, k: 0.95}
"""
TRUTH = {"parameters": {"j1.x": 0.001, "fixture.x": 0.5}}
REPORT = {
    "parameters": [
        {"name": "j1.x", "kind": "placement", "unit": "m", "initial": 0.0, "calibrated": 0.0011, "status": "estimated"},
        {"name": "fixture.x", "kind": "loop", "unit": "m", "initial": 0.4, "calibrated": 0.5, "status": "estimated"},
    ]
}
ZERO_AXIS = """<robot name="z"><link name="base"/><link name="l1"/><link name="l2"/>
 <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><axis xyz="0 0 1"/>
  <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
 <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.1 0 0"/><axis xyz="0 0 0"/>
  <limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>"""
MIMIC = ZERO_AXIS.replace('<axis xyz="0 0 0"/>', '<axis xyz="0 0 1"/><mimic joint="j1" multiplier="2"/>')


def dh(**rows) -> str:
    """The D-H table with text substitutions old=new given as keyword pairs (see the cases)."""
    text = DH
    for old, new in rows.values():
        text = text.replace(old, new)
    return text


def report(**changes) -> str:
    r = json.loads(json.dumps(REPORT))
    r["parameters"][0].update(changes)
    return json.dumps(r)


@dataclass
class Case:
    id: str
    argv: list[str]
    rc: int
    words: list[str]
    files: dict[str, str | bytes] = field(default_factory=dict)


def calib(*extra: str, log: str = "{log}", model: str = "{urdf}") -> list[str]:
    return ["calibrate", model, log, "--loop", WELD, *extra]  # the summary is what some cases read


def log_edit(fn) -> str:
    """A marker: the case's log.csv is the fixture log passed through `fn` (applied in the test)."""
    return ("LOG", fn)  # type: ignore[return-value]


CASES = [
    # ---------------------------------------------------------------- D-H tables (were tracebacks)
    Case(
        "dh-units-not-mapping",
        ["inspect", "{t.yaml}"],
        2,
        ["t.yaml", "field 'units'", "expected a mapping"],
        {"t.yaml": dh(u=("units: {length: m, angle: rad}", "units: metres"))},
    ),
    Case(
        "dh-units-list-value",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'units', field 'length'", "expected one of"],
        {"t.yaml": dh(u=("{length: m, angle: rad}", "{length: [m], angle: rad}"))},
    ),
    Case(
        "dh-units-mapping-value",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'angle'", "expected one of"],
        {"t.yaml": dh(u=("angle: rad}", "angle: {a: 1}}"))},
    ),
    Case(
        "dh-units-unknown",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'length'", "'furlong'"],
        {"t.yaml": dh(u=("length: m", "length: furlong"))},
    ),
    Case(
        "dh-s-1e308",
        ["inspect", "{t.yaml}"],
        2,
        ["joints row 1 ('j1'), field 's'", "out of range"],
        {"t.yaml": dh(u=("s: 0.3", "s: 1e308"))},
    ),
    Case(
        "dh-k-1e308",
        ["inspect", "{t.yaml}"],
        2,
        ["joints row 3 ('j3'), field 'k'", "out of range"],
        {"t.yaml": dh(u=("k: 0.95", "k: 1e308"))},
    ),
    Case("dh-k-zero", ["inspect", "{t.yaml}"], 2, ["field 'k'", "out of range"], {"t.yaml": dh(u=("k: 0.95", "k: 0"))}),
    Case(
        "dh-length-1e5-m",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'a'", "|a| <= 100 m"],
        {"t.yaml": dh(u=("a: 0.4", "a: 100000"))},
    ),
    Case(
        "dh-s-nan",
        ["inspect", "{t.yaml}"],
        2,
        ["field 's'", "finite number", "nan"],
        {"t.yaml": dh(u=("s: 0.3", "s: .nan"))},
    ),
    # ---------------------------------------------------------------- D-H: accepted but wrong
    Case(
        "dh-closes-quoted-no",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'closes'", "true or false", "'no'"],
        {"t.yaml": dh(u=("closes: false", "closes: 'no'"))},
    ),
    Case(
        "dh-closes-bare-no",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'closes'", "true or false", "'no'"],
        {"t.yaml": dh(u=("closes: false", "closes: no"))},
    ),
    Case(
        "dh-s-true",
        ["inspect", "{t.yaml}"],
        2,
        ["row 1 ('j1'), field 's'", "got true (a boolean)"],
        {"t.yaml": dh(u=("s: 0.3", "s: true"))},
    ),
    Case(
        "dh-lower-above-upper",
        ["inspect", "{t.yaml}"],
        2,
        ["row 2 ('j2')", "lower 1.0 exceeds upper -1.0"],
        {"t.yaml": dh(u=("alpha: 0.0}\n  - {name: j3", "alpha: 0.0, lower: 1.0, upper: -1.0}\n  - {name: j3"))},
    ),
    Case(
        "dh-name-list",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'name'", "expected a string, got a list"],
        {"t.yaml": dh(u=("name: chain", "name: [a, b]"))},
    ),
    Case(
        "dh-row-name-list",
        ["inspect", "{t.yaml}"],
        2,
        ["joints row 2, field 'name'", "expected a string"],
        {"t.yaml": dh(u=("name: j2", "name: [j2]"))},
    ),
    Case(
        "dh-row-name-dotted",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'name'", "not a valid name"],
        {"t.yaml": dh(u=("name: j2", "name: j.2"))},
    ),
    Case(
        "dh-row-only-name",
        ["inspect", "{t.yaml}"],
        2,
        ["joints row 3 ('j3')", "gives only a name"],
        {"t.yaml": dh(u=("{name: j3, theta_off: 0.0, s: 0.0, a: 0.2, alpha: 0.0, k: 0.95}", "{name: j3}"))},
    ),
    Case(
        "dh-underscore-number",
        ["inspect", "{t.yaml}"],
        2,
        ["field 's'", "expected a finite number, got '1_000'"],
        {"t.yaml": dh(u=("s: 0.3", "s: 1_000"))},
    ),
    Case(
        "dh-duplicate-key",
        ["inspect", "{t.yaml}"],
        2,
        ["t.yaml", "not valid YAML line", "duplicate key 's'"],
        {"t.yaml": dh(u=("s: 0.3,", "s: 0.3, s: 0.4,"))},
    ),
    Case(
        "dh-duplicate-row",
        ["inspect", "{t.yaml}"],
        2,
        ["row 2 ('j1')", "duplicate name 'j1'"],
        {"t.yaml": dh(u=("name: j2", "name: j1"))},
    ),
    Case(
        "dh-unknown-top-field",
        ["inspect", "{t.yaml}"],
        2,
        ["unknown field(s) 'close'"],
        {"t.yaml": dh(u=("closes: false", "close: true"))},
    ),
    Case(
        "dh-unknown-row-field",
        ["inspect", "{t.yaml}"],
        2,
        ["row 1 ('j1')", "unknown field(s) 'd'"],
        {"t.yaml": dh(u=("s: 0.3", "d: 0.3"))},
    ),
    Case(
        "dh-bad-convention",
        ["inspect", "{t.yaml}"],
        2,
        ["row 2 ('j2'), field 'convention'", "dh, hayati"],
        {"t.yaml": dh(u=("{name: j2,", "{name: j2, convention: hartenberg,"))},
    ),
    Case("dh-not-yaml", ["inspect", "{t.yaml}"], 2, ["not valid YAML line"], {"t.yaml": "joints: [ {name: j1"}),
    Case("dh-empty-joints", ["inspect", "{t.yaml}"], 2, ["field 'joints'", "at least"], {"t.yaml": "joints: []\n"}),
    Case("dh-not-a-mapping", ["inspect", "{t.yaml}"], 2, ["needs a non-empty 'joints' list"], {"t.yaml": "- 1\n"}),
    Case("dh-bom-ok", ["inspect", "{t.yaml}"], 0, ["3 movable joints"], {"t.yaml": "\ufeff" + DH}),
    Case(
        "dh-deg-huge-angle",
        ["inspect", "{t.yaml}"],
        2,
        ["field 'alpha'", "out of range"],
        {"t.yaml": dh(u=("angle: rad", "angle: deg"), v=("alpha: 1.5708", "alpha: 900000"))},
    ),
    Case("dh-ok", ["inspect", "{t.yaml}"], 0, ["3 movable joints", "chain_end"], {"t.yaml": DH}),
    # ---------------------------------------------------------------- models
    Case(
        "urdf-zero-axis",
        ["inspect", "{z.urdf}"],
        2,
        ["joint 'j2'", "is zero; give a nonzero axis"],
        {"z.urdf": ZERO_AXIS},
    ),
    Case("urdf-mimic-listed", ["inspect", "{m.urdf}"], 0, ["j2", "mimics j1"], {"m.urdf": MIMIC}),
    Case(
        "urdf-mimic-in-loop",
        ["calibrate", "{m.urdf}", "{m.csv}", "--loop", "weld:frame=l2", "--quiet"],
        2,
        ["joint 'j2' (between the base and frame 'l2') mimics joint 'nope'", "not a movable joint"],
        {
            "m.urdf": MIMIC.replace('joint="j1" multiplier', 'joint="nope" multiplier'),
            "m.csv": "j1,j2\n0.1,0.2\n0.2,0.4\n",
        },
    ),
    Case("mjcf-door-shipped", ["inspect", "closedloop/assets/door.xml"], 0, ["1 movable joints", "hinge"]),
    Case("model-missing", calib(model="{tmp}/nope.urdf"), 2, ["nope.urdf", "no such model file"]),
    Case("model-unknown-suffix", ["inspect", "{x.txt}"], 2, ["unknown model type '.txt'"], {"x.txt": "hello"}),
    Case("urdf-garbage", ["inspect", "{g.urdf}"], 2, ["g.urdf", "not valid XML (line 1"], {"g.urdf": "<robot"}),
    # ---------------------------------------------------------------- logs
    Case(
        "log-underscore-number",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 3, column 'panda_joint1'", "'1_000'"],
        {"l.csv": log_edit(lambda t: _cell(t, 2, 0, "1_000"))},
    ),
    Case(
        "log-bom-accepted",
        calib("--cv", "0", "--regions", "0", log="{l.csv}"),
        0,
        ["calibrated", "converged"],
        {"l.csv": log_edit(lambda t: "\ufeff" + t)},
    ),
    Case(
        "log-loop-misspelled",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 2, column 'loop'", "no loop named 'fixtrue'", "did you mean 'fixture'"],
        {"l.csv": log_edit(lambda t: _add_loop_column(t, lambda i: "fixtrue" if i % 3 == 0 else "fixture"))},
    ),
    Case(
        "log-loop-empty-cell",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 3, column 'loop': empty"],
        {"l.csv": log_edit(lambda t: _add_loop_column(t, lambda i: "" if i == 1 else "fixture"))},
    ),
    Case(
        "log-huge-reading",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 4, column 'panda_joint2'", "out of range"],
        {"l.csv": log_edit(lambda t: _cell(t, 3, 1, "1e300"))},
    ),
    Case(
        "log-inf",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 2, column 'panda_joint1'", "value is inf"],
        {"l.csv": log_edit(lambda t: _cell(t, 1, 0, "inf"))},
    ),
    Case(
        "log-hex",
        calib(log="{l.csv}"),
        2,
        ["'0x10' is not a number"],
        {"l.csv": log_edit(lambda t: _cell(t, 4, 2, "0x10"))},
    ),
    Case(
        "log-short-row",
        calib(log="{l.csv}"),
        2,
        ["l.csv line 2 has 2 fields"],
        {"l.csv": log_edit(lambda t: t.replace("\n", "\n1,2\n", 1))},
    ),
    Case(
        "log-header-only",
        calib(log="{l.csv}"),
        2,
        ["no data rows"],
        {"l.csv": log_edit(lambda t: t.split("\n")[0] + "\n")},
    ),
    Case("log-empty", calib(log="{l.csv}"), 2, ["empty log"], {"l.csv": ""}),
    Case("log-not-utf8", calib(log="{l.csv}"), 2, ["not a UTF-8 text CSV"], {"l.csv": b"\xff\xfe\x00j\x00"}),
    Case("log-nul-byte", calib(log="{l.csv}"), 2, ["l.csv"], {"l.csv": log_edit(lambda t: t.replace(",", "\x00,", 1))}),
    Case("log-is-directory", calib(log="{tmp}"), 2, ["is a directory, not a CSV log"]),
    Case("log-missing", calib(log="{tmp}/none.csv"), 2, ["none.csv", "cannot read"]),
    Case("log-no-joint-column", calib(log="{l.csv}"), 2, ["no column names a joint"], {"l.csv": "a,b\n1,2\n"}),
    Case(
        "log-duplicate-column",
        calib(log="{l.csv}"),
        2,
        ["duplicate column(s) panda_joint1"],
        {"l.csv": log_edit(lambda t: t.replace("panda_joint2", "panda_joint1", 1))},
    ),
    Case(
        "log-in-degrees",
        calib(log="{l.csv}"),
        2,
        ["l.csv", "readings of joint 'panda_joint", "beyond its limits", "a log in degrees? (give --degrees)"],
        {
            "l.csv": log_edit(
                lambda t: "\n".join(
                    t.splitlines()[:1]
                    + [
                        ",".join(repr(float(v) * 57.29577951308232) for v in line.split(","))
                        for line in t.splitlines()[1:]
                        if line
                    ]
                )
            )
        },
    ),
    # one cell far beyond its joint's limits is a corrupted row for the outlier screen, not a unit error
    Case(
        "log-one-cell-beyond-limits",
        calib("--cv", "0", "--regions", "0", log="{l.csv}"),
        0,
        ["rejected: ", "l.csv line 5 (loop fixture)"],
        {"l.csv": log_edit(lambda t: _cell(t, 4, 3, "100.0"))},
    ),
    # ---------------------------------------------------------------- calibrate options
    Case("cv-1", calib("--cv", "1"), 2, ["--cv 1", "K >= 2"]),
    Case("cv-negative", calib("--cv", "-3"), 2, ["--cv -3", ">= 0"]),
    Case("cv-more-than-rows", calib("--cv", "100"), 2, ["--cv 100", "more folds than the 30 rows"]),
    Case("cv-not-int", calib("--cv", "2.5"), 2, ["--cv", "whole number"]),
    # 5 rows determine the 27 parameters; a training fold's 4 do not: the default validation is skipped with
    # a note, a K given is an input error naming the folds (was: a training fold's message as the log's)
    Case(
        "cv-folds-too-short-default",
        calib(log="{l.csv}"),
        0,
        ["k-fold validation skipped", "refits on 4 of the 5 rows"],
        {"l.csv": log_edit(lambda t: "\n".join(t.splitlines()[:6]) + "\n")},
    ),
    Case(
        "cv-folds-too-short-given",
        calib("--cv", "5", log="{l.csv}"),
        2,
        ["--cv 5", "refits on 4 of the 5 rows", "--cv 0"],
        {"l.csv": log_edit(lambda t: "\n".join(t.splitlines()[:6]) + "\n")},
    ),
    Case("snr-negative", calib("--snr", "-1"), 2, ["--snr -1", "must be > 0"]),
    Case("snr-nan", calib("--snr", "nan"), 2, ["--snr", "nan", "finite number"]),
    Case("snr-underscore", calib("--snr", "1_000"), 2, ["--snr", "'1_000' is not a number"]),
    Case("noise-negative-sci", calib("--noise", "-1e-4"), 2, ["--noise -1e-4", "must be > 0"]),
    Case("noise-zero", calib("--noise", "0"), 2, ["--noise 0", "must be > 0"]),
    Case(
        "noise-joint-bad",
        calib("--noise", "panda_joint1=abc"),
        2,
        ["--noise panda_joint1=abc", "'abc' is not a number"],
    ),
    Case("noise-joint-nan", calib("--noise", "panda_joint1=nan"), 2, ["--noise panda_joint1=nan", "finite"]),
    Case(
        "bound-reversed", calib("--bound", "fixture.x=1:-1"), 2, ["--bound fixture.x=1:-1", "exceeds the upper bound"]
    ),
    Case("bound-no-colon", calib("--bound", "fixture.x=1"), 2, ["--bound fixture.x=1", "NAME=LOW:HIGH"]),
    Case("bound-not-number", calib("--bound", "fixture.x=a:b"), 2, ["--bound fixture.x=a:b", "'a' is not a number"]),
    Case("max-iter-zero", calib("--max-iter", "0"), 2, ["--max-iter 0", ">= 1"]),
    Case(
        "loop-closure-1e308",
        ["calibrate", "{urdf}", "{log}", "--loop", 'weld:frame=panda_hand,closure="1e308 0 0 0 0 0"', "--quiet"],
        2,
        ["--loop", "1e308 is out of range"],
    ),
    Case(
        "loop-closure-nan",
        ["calibrate", "{urdf}", "{log}", "--loop", 'weld:frame=panda_hand,closure="nan 0 0 0 0 0"', "--quiet"],
        2,
        ["--loop", "value is nan"],
    ),
    Case(
        "loop-closure-underscore",
        ["calibrate", "{urdf}", "{log}", "--loop", 'weld:frame=panda_hand,closure="1_0 0 0 0 0 0"', "--quiet"],
        2,
        ["--loop", "'1_0' is not a number"],
    ),
    Case(
        "loop-unknown-frame",
        ["calibrate", "{urdf}", "{log}", "--loop", "weld:frame=panda_hnd"],
        2,
        ["unknown frame 'panda_hnd'"],
    ),
    Case("no-loop", ["calibrate", "{urdf}", "{log}"], 2, ["no --loop given"]),
    Case("unknown-option", calib("--frobnicate"), 2, ["unrecognized arguments: --frobnicate"]),
    Case("no-command", [], 2, ["required: command"]),
    Case("missing-positional", ["calibrate", "{urdf}"], 2, ["required: log"]),
    Case("bad-choice", calib("--weighting", "maybe"), 2, ["--weighting", "invalid choice"]),
    Case(
        "config-bad-number",
        calib("--config", "{c.yaml}"),
        2,
        ["c.yaml", "option 'snr'", "'abc' is not valid"],
        {"c.yaml": "snr: abc\n"},
    ),
    Case("config-snr-negative", calib("--config", "{c.yaml}"), 2, ["--snr -1", "must be > 0"], {"c.yaml": "snr: -1\n"}),
    # ---------------------------------------------------------------- output paths, checked before any work
    Case(
        "out-equals-report",
        calib("--out", "{tmp}/p.urdf", "--report", "{tmp}/p.urdf"),
        2,
        ["--report", "the same file as --out"],
    ),
    Case("out-is-directory", calib("--out", "{tmp}"), 2, ["--out", "is a directory"]),
    Case(
        "report-below-file",
        calib("--report", "{f.txt}/r.json"),
        2,
        ["f.txt' is a file, not a directory"],
        {"f.txt": "x"},
    ),
    Case("report-readonly-dir", calib("--report", "{ro}/r.json"), 2, ["cannot write in"]),
    Case("out-yaml-for-urdf", calib("--out", "{tmp}/cal.yaml"), 2, ["--out", "calibrated urdf model", "*.urdf"]),
    Case("out-overwrites-input", calib("--out", "{urdf}"), 2, ["refusing to overwrite an input"]),
    Case(
        "out-urdf-for-dh",
        ["calibrate", "{t.yaml}", "{log}", "--out", "{tmp}/c.urdf"],
        2,
        ["*.yaml or *.yml"],
        {"t.yaml": DH},
    ),
    Case(
        "out-urdf-for-mjcf",
        ["calibrate", "closedloop/assets/door.xml", "{log}", "--out", "{tmp}/c.urdf"],
        2,
        ["calibrated mjcf model", "*.xml or *.mjcf"],
    ),
    # ---------------------------------------------------------------- batch, extract, impedance (were exit 70 or accepted)
    Case(
        "batch-csv-unquoted-comma",
        ["batch", "{m.csv}"],
        2,
        ["m.csv", "line 2", "8 cells", "the header has 7", "quote"],
        {"m.csv": "name,robot,date,model,log,loops,out\nj1,a,2026-01-01,m.urdf,l.csv,weld:frame=a,name=b,o1\n"},
    ),
    Case(
        "extract-a-csv",
        ["extract", "{log}", "--model", "{urdf}", "--out", "{tmp}/x.csv"],
        2,
        ["not a ROS bag", "a CSV log goes straight to calibrate"],
    ),
    Case(
        "extract-threshold-negative",
        ["extract", "{tmp}/b.bag", "--joints", "j1", "--out", "{tmp}/x.csv", "--threshold", "-1"],
        2,
        ["--threshold -1", "must be > 0"],
    ),
    Case(
        "extract-window-without-split",
        ["extract", "{tmp}/b.bag", "--joints", "j1", "--out", "{tmp}/x.csv", "--window", "a=0:10"],
        2,
        ["--window is for --split window"],
    ),
    Case(
        "extract-window-reversed",
        [
            "extract",
            "{tmp}/b.bag",
            "--joints",
            "j1",
            "--out",
            "{tmp}/x.csv",
            "--split",
            "window",
            "--window",
            "a=50:10",
        ],
        2,
        ["a=50:10", "below T1"],
    ),
    Case(
        "impedance-bootstrap-negative",
        ["impedance", "identify", "{tmp}/d.csv", "--bootstrap", "-1"],
        2,
        ["--bootstrap -1", ">= 0"],
    ),
    Case(
        "impedance-max-shift-negative",
        ["impedance", "identify", "{tmp}/d.csv", "--max-shift-ms", "-5"],
        2,
        ["--max-shift-ms -5", ">= 0"],
    ),
    Case(
        "impedance-noise-negative",
        ["impedance", "simulate", "--noise", "-1", "--out", "{tmp}/o"],
        2,
        ["--noise -1", ">= 0"],
    ),
    # ---------------------------------------------------------------- check
    Case(
        "check-ok",
        ["check", "{t.json}", "{r.json}"],
        0,
        ["2 within tolerance"],
        {"t.json": json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-bom-ok",
        ["check", "{t.json}", "{r.json}"],
        0,
        ["2 within tolerance"],
        {"t.json": "\ufeff" + json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-outside",
        ["check", "{t.json}", "{r.json}", "--tol-m", "1e-6"],
        1,
        ["1 outside"],
        {"t.json": json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    # another robot's truth: refused (was a table of the report's parameters against 0)
    Case(
        "check-other-robots-joints",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["r.json", "calibrates joints j1", "truth of joints joint1", "not the same"],
        {
            "t.json": json.dumps(TRUTH | {"joint_names": ["joint1", "joint2"]}),
            "r.json": json.dumps(REPORT | {"joints": ["j1", "j2", "j3"]}),
        },
    ),
    Case(
        "check-no-parameter-in-common",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["none of the 2 parameters"],
        {"t.json": '{"parameters": {"joint1.x": 0.001, "socket.px": 0.5}}', "r.json": json.dumps(REPORT)},
    ),
    # another dataset of the same robot (a loop between two fingertips, the report's a fingertip in a socket):
    # its true robot is another draw; refused (was a table of errors 21 times the tolerance)
    Case(
        "check-other-datasets-loop",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["r.json: its loops close tip_a and the world", "truth of a loop between tip_a and tip_b", "another dataset"],
        {
            "t.json": json.dumps(TRUTH | {"loop": {"type": "weld", "frame": "tip_a", "to": "tip_b", "name": "pinch"}}),
            "r.json": json.dumps(REPORT | {"loops": [{"name": "fixture", "frame_a": "tip_a", "frame_b": "universe"}]}),
        },
    ),
    Case(
        "check-same-datasets-loop",
        ["check", "{t.json}", "{r.json}"],
        0,
        ["2 within tolerance"],
        {
            "t.json": json.dumps(TRUTH | {"loop": {"type": "weld", "frame": "tip_a", "name": "fixture"}}),
            "r.json": json.dumps(REPORT | {"loops": [{"name": "fixture", "frame_a": "tip_a", "frame_b": "universe"}]}),
        },
    ),
    Case(
        "check-notes-a-failed-verdict",
        ["check", "{t.json}", "{r.json}"],
        0,
        ["2 within tolerance", "verdict is failed: the fit stalled"],
        {
            "t.json": json.dumps(TRUTH),
            "r.json": json.dumps(REPORT | {"verdict": {"status": "failed", "reasons": ["the fit stalled"]}}),
        },
    ),
    Case(
        "check-tol-negative",
        ["check", "{t.json}", "{r.json}", "--tol-m", "-1"],
        2,
        ["--tol-m -1", "> 0"],
        {"t.json": json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-tol-nan",
        ["check", "{t.json}", "{r.json}", "--tol-rad", "nan"],
        2,
        ["--tol-rad", "finite"],
        {"t.json": json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-tol-zero",
        ["check", "{t.json}", "{r.json}", "--tol-px", "0"],
        2,
        ["--tol-px 0", "> 0"],
        {"t.json": json.dumps(TRUTH), "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-params-list",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["t.json", "field 'parameters'", "expected a mapping"],
        {"t.json": '{"parameters": [1, 2]}', "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-value-string",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'j1.x'", "got '0.001'"],
        {"t.json": '{"parameters": {"j1.x": "0.001"}}', "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-value-bool",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'j1.x'", "boolean"],
        {"t.json": '{"parameters": {"j1.x": true}}', "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-nan",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["t.json", "NaN is not a JSON number"],
        {"t.json": '{"parameters": {"j1.x": NaN}}', "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-not-object",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["t.json", "expected a 'parameters'"],
        {"t.json": "[1]", "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-empty-file",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["t.json", "not valid JSON (line 1"],
        {"t.json": "", "r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-truth-missing",
        ["check", "{tmp}/none.json", "{r.json}"],
        2,
        ["none.json", "cannot read truth file"],
        {"r.json": json.dumps(REPORT)},
    ),
    Case(
        "check-report-no-kind",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["parameters row 1 ('j1.x')", "missing field 'kind'"],
        {
            "t.json": json.dumps(TRUTH),
            "r.json": json.dumps(
                {"parameters": [{"name": "j1.x", "unit": "m", "calibrated": 0, "status": "estimated"}]}
            ),
        },
    ),
    Case(
        "check-report-calibrated-list",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'calibrated'", "expected a finite number"],
        {"t.json": json.dumps(TRUTH), "r.json": report(calibrated=[1, 2, 3])},
    ),
    Case(
        "check-report-rot-string",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'calibrated'", "got 'x'"],
        {
            "t.json": json.dumps({"parameters": {"f.rx": 0.1, "f.ry": 0, "f.rz": 0}}),
            "r.json": json.dumps(
                {
                    "parameters": [
                        {
                            "name": f"f.r{a}",
                            "kind": "loop",
                            "unit": "rad",
                            "initial": 0,
                            "calibrated": "x" if a == "y" else 0.1,
                            "status": "estimated",
                        }
                        for a in "xyz"
                    ]
                }
            ),
        },
    ),
    Case(
        "check-report-params-dict",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'parameters'", "expected a list"],
        {"t.json": json.dumps(TRUTH), "r.json": '{"parameters": {"a": 1}}'},
    ),
    Case(
        "check-report-duplicate",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["duplicate parameter 'j1.x'"],
        {
            "t.json": json.dumps(TRUTH),
            "r.json": json.dumps({"parameters": REPORT["parameters"] + REPORT["parameters"][:1]}),
        },
    ),
    Case(
        "check-report-huge",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["field 'calibrated'", "out of range"],
        {"t.json": json.dumps(TRUTH), "r.json": report(calibrated=1e308)},
    ),
    Case(
        "check-report-dh-no-initial",
        ["check", "{t.json}", "{r.json}"],
        2,
        ["missing field 'initial'"],
        {
            "t.json": json.dumps(TRUTH),
            "r.json": json.dumps(
                {"parameters": [{"name": "j9.s", "kind": "dh", "unit": "m", "calibrated": 0.1, "status": "estimated"}]}
            ),
        },
    ),
    # ---------------------------------------------------------------- simulate (all refused before simulating)
    Case(
        "sim-select-bogus",
        ["simulate", "panda_weld", "--n", "2", "--out", "{tmp}/o", "--set", "select=bogus"],
        2,
        ["field 'select'", "greedy", "'bogus'"],
    ),
    Case("sim-seed-negative", ["simulate", "panda_weld", "--seed", "-1", "--out", "{tmp}/o"], 2, ["--seed -1", ">= 0"]),
    Case(
        "sim-out-is-file",
        ["simulate", "panda_weld", "--out", "{f.txt}"],
        2,
        ["--out", "is a file; give a directory"],
        {"f.txt": "x"},
    ),
    Case(
        "sim-out-below-file", ["simulate", "panda_weld", "--out", "{f.txt}/d"], 2, ["f.txt' is a file"], {"f.txt": "x"}
    ),
    Case("sim-out-readonly", ["simulate", "panda_weld", "--out", "{ro}/d"], 2, ["cannot write in"]),
    Case(
        "sim-out-holds-dataset",
        ["simulate", "panda_weld", "--out", "{tmp}"],
        2,
        ["holds another dataset (truth.json)", "--replace"],
        {"truth.json": "{}"},
    ),
    Case(
        "sim-kp-negative",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "kp=-5"],
        2,
        ["--set kp=-5: field 'kp'", "out of range (must be > 0"],
    ),
    Case(
        "sim-kp-1e308",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "kp=1e308"],
        2,
        ["field 'kp'", "out of range"],
    ),
    Case(
        "sim-timestep-zero",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "timestep=0"],
        2,
        ["field 'timestep'", "out of range"],
    ),
    Case(
        "sim-noise-negative",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "noise=-1"],
        2,
        ["--set noise=-1: field 'noise'", "out of range (must be >= 0"],
    ),
    Case(
        "sim-solimp-order",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "solimp=[0.9,0.5,0.001,0.5,2]"],
        2,
        ["solimp dmin 0.9 exceeds dmax 0.5"],
    ),
    Case(
        "sim-min-above-max",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "min_steps=500"],
        2,
        ["min_steps 500 exceeds max_steps 300"],
    ),
    Case("sim-n-zero", ["simulate", "panda_weld", "--n", "0", "--out", "{tmp}/o"], 2, ["--n 0", ">= 1"]),
    Case("sim-seed-float", ["simulate", "panda_weld", "--seed", "1.5", "--out", "{tmp}/o"], 2, ["whole number"]),
    Case("sim-unknown-scenario", ["simulate", "panda_wled", "--out", "{tmp}/o"], 2, ["unknown scenario 'panda_wled'"]),
    Case(
        "sim-unknown-setting",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "kq=1"],
        2,
        ["unknown setting 'kq'"],
    ),
    Case(
        "sim-gravity-maybe",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "gravity=maybe"],
        2,
        ["'gravity' takes true or false"],
    ),
    Case(
        "sim-integrator-bad",
        ["simulate", "panda_weld", "--out", "{tmp}/o", "--set", "integrator=leapfrog"],
        2,
        ["field 'integrator'", "'leapfrog'"],
    ),
]


def _cell(text: str, row: int, col: int, value: str) -> str:
    lines = text.split("\n")
    cells = lines[row].split(",")
    cells[col] = value
    lines[row] = ",".join(cells)
    return "\n".join(lines)


def _add_loop_column(text: str, name) -> str:
    lines = [ln for ln in text.split("\n") if ln]
    return "\n".join([lines[0] + ",loop"] + [f"{ln},{name(i)}" for i, ln in enumerate(lines[1:])]) + "\n"


@pytest.fixture(scope="module")
def panda_files(tmp_path_factory):
    """A mesh-free Panda and 30 exact weld configurations (two perturbed parameters)."""
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.loops import WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    d = tmp_path_factory.mktemp("panda")
    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(d / "panda.urdf")
    ds = make_dataset(
        robot,
        WeldLoop("fixture", "panda_hand"),
        [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8],
        30,
        np.random.default_rng(5),
        perturb=["panda_joint2.x", "panda_joint3.offset"],
    )
    ds.log().write_csv(d / "log.csv")
    return d / "panda.urdf", d / "log.csv"


@pytest.fixture()
def readonly_dir(tmp_path):
    """A directory no file can be created in: chmod 555, or (as root, who ignores modes) sysfs."""
    if os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        yield d
        d.chmod(0o755)
    else:
        yield Path("/sys")


def _materialize(case: Case, tmp: Path, panda_files, ro: Path) -> list[str]:
    urdf, log = panda_files
    names = {"urdf": str(urdf), "log": str(log), "tmp": str(tmp), "ro": str(ro)}
    for name, content in case.files.items():
        p = tmp / name
        if isinstance(content, tuple):  # log_edit
            content = content[1](log.read_text())
        if isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content, encoding="utf-8")
        names[name] = str(p)
    out = []
    for a in case.argv:
        for k, v in names.items():
            a = a.replace("{" + k + "}", v)
        out.append(a)
    return out


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(case: Case, tmp_path, panda_files, readonly_dir, capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # shipped models by relative path
    argv = _materialize(case, tmp_path, panda_files, readonly_dir)
    before = {p: p.read_bytes() for p in map(Path, panda_files)}
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == case.rc, f"exit {rc}, expected {case.rc}\nstdout: {out}\nstderr: {err}"
    text = err if rc == 2 else out
    for w in case.words:
        assert w in text, f"'{w}' not in: {text}"
    assert "Traceback" not in err
    if rc == 2:
        assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), err
        assert "calibrated" not in out  # refused before any work
    assert all(p.read_bytes() == b for p, b in before.items())  # the inputs are never touched
    assert not list(tmp_path.rglob(".closedloop-*"))  # no temporary left


def test_every_listed_issue_case_is_in_the_table():
    ids = {c.id for c in CASES}
    listed = {
        "dh-units-not-mapping",
        "dh-units-list-value",
        "dh-units-mapping-value",
        "dh-s-1e308",
        "dh-k-1e308",
        "urdf-zero-axis",
        "loop-closure-1e308",
        "cv-1",
        "cv-negative",
        "cv-more-than-rows",
        "report-readonly-dir",
        "out-is-directory",
        "report-below-file",
        "check-truth-params-list",
        "check-report-calibrated-list",
        "check-report-rot-string",
        "sim-select-bogus",
        "sim-seed-negative",
        "sim-out-is-file",
        "mjcf-door-shipped",
        "dh-closes-quoted-no",
        "dh-s-true",
        "dh-lower-above-upper",
        "dh-name-list",
        "dh-row-only-name",
        "log-underscore-number",
        "log-loop-misspelled",
        "urdf-mimic-in-loop",
        "bound-reversed",
        "snr-negative",
        "snr-nan",
        "check-tol-negative",
        "check-tol-nan",
        "out-equals-report",
        "out-yaml-for-urdf",
        "sim-kp-negative",
        "sim-kp-1e308",
        "sim-timestep-zero",
        "sim-noise-negative",
        "log-bom-accepted",
        "noise-negative-sci",
    }
    assert listed <= ids, sorted(listed - ids)
    assert len(ids) == len(CASES)


def test_outputs_written_as_a_set_model_before_report(panda_files, tmp_path, monkeypatch):
    """A good run writes model, its sensor file and report; the model is published first, the report last."""
    urdf, log = panda_files
    order = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (order.append(Path(b).name), real(a, b)))
    rc = main(
        [
            "calibrate",
            str(urdf),
            str(log),
            "--loop",
            WELD,
            "--quiet",
            "--cv",
            "0",
            "--regions",
            "0",
            "--out",
            str(tmp_path / "sub" / "cal.urdf"),
            "--report",
            str(tmp_path / "rep.json"),
        ]
    )
    assert rc == 0
    assert order == ["cal.urdf", "cal.sensors.yaml", "rep.json"]  # the model's sensor file with it
    assert json.loads((tmp_path / "rep.json").read_text())["solver"]["status"] == "converged"
    assert "<robot" in (tmp_path / "sub" / "cal.urdf").read_text()
    assert not list(tmp_path.rglob(".closedloop-*"))


def test_keyboard_interrupt_in_calibrate_and_simulate_exit_130(panda_files, tmp_path, monkeypatch, capsys):
    import closedloop.calibration.pipeline
    import closedloop.sims

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    urdf, log = panda_files
    monkeypatch.setattr(closedloop.calibration.pipeline, "calibrate", interrupt)
    rc = main(["calibrate", str(urdf), str(log), "--loop", WELD, "--quiet", "--report", str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert rc == 130 and err.strip() == "interrupted; outputs not yet published were discarded"
    assert not (tmp_path / "r.json").exists()
    monkeypatch.setattr(closedloop.sims, "simulate", interrupt)
    rc = main(["simulate", "panda_weld", "--n", "2", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 130 and len(err.strip().splitlines()) == 1 and "interrupted" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_real_ctrl_c_in_simulate_one_line_exit_130(tmp_path):
    """SIGINT to a running `closedloop simulate`: one line, exit 130, nothing written.

    The child is given SIGINT's default disposition: started from a process that ignores SIGINT (a script's
    background job, nohup), it would inherit that, and Python then installs no KeyboardInterrupt handler
    (the command rightly runs on there, as any program would)."""
    from closedloop.io.marker import RUNNING_MARKER

    out, marker = tmp_path / "o", tmp_path / "running"
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "closedloop.cli.main",
            "simulate",
            "panda_weld",
            "--n",
            "20000",
            "--out",
            str(out),
            "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, RUNNING_MARKER: str(marker)},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    t0 = time.monotonic()  # until the simulation drives the robot (`closedloop.io.marker`), never a fixed time
    while not (marker.exists() and "simulate" in marker.read_text().split()):
        assert p.poll() is None, p.communicate()
        assert time.monotonic() - t0 < 300, "the simulation never started"
        time.sleep(0.002)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert err.strip().splitlines() == ["interrupted; outputs not yet published were discarded"]
    assert not out.exists() or not any(out.iterdir())


def test_internal_error_is_one_line_exit_70(panda_files, monkeypatch, capsys):
    """A bug (an unexpected exception) is still one line, with its type, and exit 70."""
    import closedloop.calibration.pipeline

    def boom(*a, **k):
        raise ZeroDivisionError("float division by zero")

    urdf, log = panda_files
    monkeypatch.setattr(closedloop.calibration.pipeline, "calibrate", boom)
    rc = main(["calibrate", str(urdf), str(log), "--loop", WELD, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 70 and len(err.strip().splitlines()) == 1
    assert "internal error (ZeroDivisionError: float division by zero)" in err


@pytest.mark.parametrize("unnamed", [True, False], ids=["o_tmpfile", "staging-dir"])
def test_output_set_publishes_whole_or_nothing(tmp_path, monkeypatch, unnamed):
    """Both staging paths (O_TMPFILE and the hidden staging directory) publish in order or leave nothing."""
    import closedloop.io.files as ex

    if not unnamed:
        monkeypatch.setattr(ex, "_unnamed", lambda d: None)
    (tmp_path / "r.json").write_text("old report")
    order = []
    real = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (order.append(Path(b).name), real(a, b)))
    with ex.OutputSet(order=[tmp_path / "m" / "cal.urdf", tmp_path / "r.json"]):
        ex.atomic_write_text(tmp_path / "r.json", "new report")
        ex.atomic_write_text(tmp_path / "m" / "cal.urdf", "<robot/>")
        assert (tmp_path / "r.json").read_text() == "old report"  # nothing published inside the block
    assert order == ["cal.urdf", "r.json"]
    assert (tmp_path / "r.json").read_text() == "new report" and (tmp_path / "m" / "cal.urdf").exists()
    with pytest.raises(RuntimeError):
        with ex.OutputSet():
            ex.atomic_write_text(tmp_path / "r.json", "newer")
            raise RuntimeError("failed half-way")
    assert (tmp_path / "r.json").read_text() == "new report"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["cal.urdf", "m", "r.json"]
