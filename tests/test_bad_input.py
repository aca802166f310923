"""Bad input to every command added since the first hardening round, as one case table.

Each case runs the command in-process (`main([...])`) on files written here and checks: the exit code,
ONE line on stderr naming what is at fault, the inputs untouched, no temporary file left.  The table is
also the documentation: docs/reference/bad-input.md is generated from it with the lines the user
actually sees (`python tests/test_bad_input.py` rewrites it; `test_docs_table_is_current` fails when the
page and the commands disagree).
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from closedloop.cli.main import main

WELD = "weld:frame=panda_hand,name=fixture"
DOC = Path(__file__).resolve().parents[1] / "docs" / "reference" / "bad-input.md"

LINK = '<link name="{n}"/>'
JOINT = (
    '<joint name="{n}" type="revolute"><parent link="{p}"/><child link="{c}"/><origin xyz="{xyz}"/>'
    '<axis xyz="{axis}"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
)


def urdf(joints=(("j1", "base", "l1"), ("j2", "l1", "l2")), xyz="0.1 0 0", axis="0 0 1", extra="", links=None) -> str:
    """A small URDF: links base, l1, l2 (or `links`) and revolute joints (name, parent, child)."""
    names = links or ["base", "l1", "l2"]
    body = "".join(LINK.format(n=n) for n in names)
    body += "".join(JOINT.format(n=n, p=p, c=c, xyz=xyz, axis=axis) for n, p, c in joints)
    return f'<robot name="r">{body}{extra}</robot>'


def chain(n: int) -> str:
    return urdf(
        joints=[(f"j{i}", f"l{i - 1}", f"l{i}") for i in range(1, n + 1)], links=[f"l{i}" for i in range(n + 1)]
    )


MANIFEST = """defaults: {{model: panda.urdf, loops: ["{weld}"], cv: 0}}
jobs:
  - {{name: a, log: log.csv, out: out/a{a}}}
  - {{name: {b}, log: log.csv, out: out/b}}
"""


def manifest(a: str = "", b: str = "b") -> str:
    return MANIFEST.format(weld=WELD, a=a, b=b)


@dataclass
class Case:
    """One bad input: `argv` with `{name}` for the case's files (`files`) and `{tmp}`; `kind` for the docs."""

    id: str
    kind: str
    argv: list[str]
    words: list[str]
    files: dict[str, str | bytes] = field(default_factory=dict)
    rc: int = 2
    hide: tuple[str, ...] = ()  # optional modules made unimportable for this case

    @property
    def command(self) -> str:
        return self.argv[0]


def calib(*extra: str, log: str = "{log.csv}", model: str = "{panda.urdf}") -> list[str]:
    return ["calibrate", model, log, "--loop", WELD, "--quiet", "--cv", "0", *extra]


CASES = [
    # ------------------------------------------------------------------ outputs
    Case(
        "report-onto-log-hardlink",
        "output is an input",
        calib("--report", "{hard.csv}"),
        ["--report", "refusing to overwrite an input"],
        {"hard.csv": "HARDLINK log.csv"},
    ),
    Case(
        "out-onto-model-symlink",
        "output is an input",
        calib("--out", "{sym.urdf}"),
        ["--out", "refusing to overwrite an input"],
        {"sym.urdf": "SYMLINK panda.urdf"},
    ),
    Case(
        "batch-summary-onto-manifest",
        "output is an input",
        ["batch", "{m.yaml}", "--summary", "{m.yaml}"],
        ["--summary", "refusing to overwrite an input"],
        {"m.yaml": manifest()},
    ),
    Case(
        "batch-summary-onto-log",
        "output is an input",
        ["batch", "{m.yaml}", "--summary", "{log.csv}"],
        ["--summary", "refusing to overwrite an input"],
        {"m.yaml": manifest()},
    ),
    Case(
        "batch-out-onto-log",
        "output is an input",
        ["batch", "{m.yaml}"],
        ["job a", "is a file; give a folder"],
        {"m.yaml": manifest().replace("out: out/a", "out: log.csv")},
    ),
    Case(
        "extract-out-onto-bag",
        "output is an input",
        ["extract", "{b.bag}", "--joints", "a", "--out", "{b.bag}"],
        ["refusing to overwrite an input"],
        {"b.bag": b"#ROSBAG V2.0\n"},
    ),
    # ------------------------------------------------------------------ wrong loop type
    Case(
        "weld-on-point-contact-data",
        "wrong loop type",
        calib(log="{socket.csv}"),
        ["loop 'fixture' (weld on panda_hand)", "orientation is not fixed", "--loop point:frame=panda_hand"],
    ),
    Case(
        "loop-on-the-base",
        "wrong loop type",
        ["calibrate", "{panda.urdf}", "{log.csv}", "--loop", "weld:frame=panda_link0,name=fixture", "--cv", "0"],
        ["loop(s) 'fixture' (panda_link0, universe)", "no movable joint", "frame=<link>"],
    ),
    # ------------------------------------------------------------------ batch manifests
    Case(
        "batch-duplicate-names",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["job 1 (entry 1) and job 2 (entry 2)", "same name 'a'"],
        {"m.yaml": manifest(b="a")},
    ),
    Case(
        "batch-cv-1",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["job 1", "cv 1", "K >= 2"],
        {"m.yaml": manifest(a=", cv: 1")},
    ),
    Case(
        "batch-cv-true",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["job 1", "expected a whole number"],
        {"m.yaml": manifest(a=", cv: true")},
    ),
    Case(
        "batch-degrees-maybe",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'degrees'", "degrees 'maybe': expected true or false"],
        {"m.yaml": manifest(a=", degrees: maybe")},
    ),
    Case(
        "batch-snr-negative",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'snr'", "must be > 0"],
        {"m.yaml": manifest(a=", snr: -1")},
    ),
    Case(
        "batch-noise-nan",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'noise'", "nan"],
        {"m.yaml": manifest(a=", noise: .nan")},
    ),
    Case(
        "batch-robust-unknown",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'robust'", "expected one of auto, huber, cauchy, off"],
        {"m.yaml": manifest(a=", robust: maybe")},
    ),
    Case(
        "batch-max-iter-fraction",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'max_iter'", "whole number"],
        {"m.yaml": manifest(a=", max_iter: 1.5")},
    ),
    Case(
        "batch-bounds-reversed",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["option 'bounds'", "exceeds the upper bound"],
        {"m.yaml": manifest(a=', bounds: ["fixture.x=1:0"]')},
    ),
    Case(
        "batch-gap-unknown",
        "batch manifest",
        ["batch", "{m.yaml}"],
        ["unknown key(s) gap"],
        {"m.yaml": manifest(a=", gap: -3")},
    ),
    Case(
        "batch-csv-cv-1",
        "batch manifest",
        ["batch", "{m.csv}"],
        ["line 2", "cv 1"],
        {"m.csv": f'name,model,log,loops,out,cv\na,panda.urdf,log.csv,"{WELD}",out/a,1\n'},
    ),
    Case(
        "batch-drift-z-nan",
        "option value",
        ["batch", "{m.yaml}", "--drift-z", "nan"],
        ["--drift-z nan", "finite"],
        {"m.yaml": manifest()},
    ),
    Case(
        "batch-drift-z-negative",
        "option value",
        ["batch", "{m.yaml}", "--drift-z", "-1"],
        ["--drift-z -1", "> 0"],
        {"m.yaml": manifest()},
    ),
    Case(
        "noise-implausible",
        "option value",
        calib("--noise", "5"),
        ["--noise 5: the joint noise must be > 0 and <= 0.1"],
    ),
    Case(
        "log-in-radians-given-degrees",
        "option value",
        calib("--degrees"),
        ["with --degrees no revolute joint moves more than", "a log in radians? (leave out --degrees)"],
    ),
    # ------------------------------------------------------------------ configs
    Case(
        "config-report-true",
        "config value",
        calib("--config", "{c.yaml}"),
        ["option 'report' takes a text value", "true (a boolean)"],
        {"c.yaml": "report: true\n"},
    ),
    Case(
        "config-snr-list",
        "config value",
        calib("--config", "{c.yaml}"),
        ["option 'snr' takes a number, got a list"],
        {"c.yaml": "snr: [1, 2]\n"},
    ),
    Case(
        "config-extract-gap-negative",
        "config value",
        ["extract", "{b.bag}", "--joints", "a", "--out", "{tmp}/o.csv", "--config", "{c.yaml}"],
        ["--gap -3", "must be > 0"],
        {"c.yaml": "split: gap\ngap: -3\n", "b.bag": b"x"},
    ),
    # ------------------------------------------------------------------ robot files
    Case(
        "simulate-a-dh-table",
        "robot file",
        ["simulate", "--robot", "{arm.yaml}", "--loop", "point:frame=tool", "--out", "{tmp}/sim"],
        ["arm.yaml is a D-H table", "a URDF or MJCF", "closedloop calibrate TABLE LOG"],
        {"arm.yaml": "convention: modified\nunits: deg\nrows: []\n"},
    ),
    Case(
        "urdf-two-parents",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["link 'l2' is the child of two joints ('j2' and 'j3')"],
        {"r.urdf": urdf(joints=(("j1", "base", "l1"), ("j2", "l1", "l2"), ("j3", "base", "l2")))},
    ),
    Case(
        "urdf-cycle",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["the joints form a cycle"],
        {"r.urdf": urdf(joints=(("j1", "base", "l1"), ("j2", "l1", "l2"), ("j3", "l2", "base")))},
    ),
    Case(
        "urdf-two-roots",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["2 root links ('base', 'x')"],
        {"r.urdf": urdf(links=["base", "l1", "l2", "x"])},
    ),
    Case(
        "urdf-chain-1200",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["link 'l1001' lies 1001 links below the root 'l0'"],
        {"r.urdf": chain(1200)},
    ),
    Case(
        "simulate-urdf-type-typo",
        "robot file",
        ["simulate", "--robot", "{r.urdf}", "--loop", "point:frame=l2", "--out", "{tmp}/sim"],
        ["r.urdf: joint 'j1': type 'revolut' is not one of revolute"],
        {"r.urdf": urdf().replace('type="revolute"', 'type="revolut"', 1)},
    ),
    Case(
        "simulate-urdf-origin-typo",
        "robot file",
        ["simulate", "--robot", "{r.urdf}", "--loop", "point:frame=l2", "--out", "{tmp}/sim"],
        ["r.urdf: joint 'j1': <origin> xyz=\"0.1 0..0 0\": expected 3 finite number(s)"],
        {"r.urdf": urdf(xyz="0.1 0..0 0")},
    ),
    Case(
        "urdf-zero-axis",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["joint 'j1'", "is zero"],
        {"r.urdf": urdf(axis="0 0 0")},
    ),
    Case(
        "urdf-nan-origin",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["joint 'j1': <origin> xyz=\"nan 0 0\""],
        {"r.urdf": urdf(xyz="nan 0 0")},
    ),
    Case(
        "urdf-inf-origin",
        "robot file",
        ["inspect", "{r.urdf}"],
        ['<origin> xyz="0 inf 0"', "finite"],
        {"r.urdf": urdf(xyz="0 inf 0")},
    ),
    Case(
        "urdf-xacro-expression",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["this is a xacro file", "run xacro first"],
        {"r.urdf": urdf(xyz="${a7} 0 0")},
    ),
    Case(
        "urdf-xacro-element",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["this is a xacro file (element <property>)"],
        {"r.urdf": urdf(extra='<xacro:property xmlns:xacro="http://www.ros.org/wiki/xacro" name="a7" value="1"/>')},
    ),
    Case(
        "urdf-missing-child",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["joint 'j2': child link 'l9' is not defined"],
        {"r.urdf": urdf(joints=(("j1", "base", "l1"), ("j2", "l1", "l9")))},
    ),
    Case(
        "urdf-two-joints-one-name",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["two joints named 'j1'"],
        {"r.urdf": urdf(joints=(("j1", "base", "l1"), ("j1", "l1", "l2")))},
    ),
    Case(
        "urdf-no-limit",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["Pinocchio cannot parse this model", "does not specify limits"],
        {"r.urdf": re.sub(r"<limit[^>]*/>", "", urdf())},
    ),
    Case("urdf-not-xml", "robot file", ["inspect", "{r.urdf}"], ["not valid XML (line 1"], {"r.urdf": "<robot"}),
    Case(
        "urdf-misspelt-attribute",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["joint 'j1': <origin xzy=\"0.1 0 0\">: no such attribute (did you mean xyz?)"],
        {"r.urdf": urdf().replace("<origin xyz=", "<origin xzy=", 1)},
    ),
    Case(
        "urdf-misspelt-element",
        "robot file",
        ["inspect", "{r.urdf}"],
        ["joint 'j1': <orgin> is not a URDF element (did you mean <origin>?)"],
        {"r.urdf": urdf().replace("<origin ", "<orgin ", 1)},
    ),
    # ------------------------------------------------------------------ option values
    Case(
        "length-1000",
        "option value",
        calib("--length", "panda_link2", "panda_link4", "1000"),
        ["--length panda_link2 panda_link4 1000", "0.3266 m apart"],
    ),
    Case(
        "length-zero",
        "option value",
        calib("--length", "panda_link2", "panda_link4", "0"),
        ["the length and its SIGMA must be positive"],
    ),
    Case(
        "extract-gap-negative",
        "option value",
        ["extract", "{b.bag}", "--joints", "a", "--out", "{tmp}/o.csv", "--split", "gap", "--gap", "-1"],
        ["--gap -1", "must be > 0"],
        {"b.bag": b"x"},
    ),
    Case(
        "extract-gap-nan",
        "option value",
        ["extract", "{b.bag}", "--joints", "a", "--out", "{tmp}/o.csv", "--split", "gap", "--gap", "nan"],
        ["--gap nan", "finite"],
        {"b.bag": b"x"},
    ),
    Case(
        "check-arguments-swapped",
        "check files",
        ["check", "{report.json}", "{truth.json}"],
        ["report.json: a calibration report given as the truth file", "closedloop check TRUTH REPORT"],
        {
            "report.json": '{"parameters": [{"name": "j1.x", "calibrated": 0.1}], "verdict": {"status": "ok"}}',
            "truth.json": '{"scenario": "arm_point", "parameters": {"j1.x": 0.1}}',
        },
    ),
    Case(
        "check-truth-given-as-report",
        "check files",
        ["check", "{truth.json}", "{truth2.json}"],
        ["truth2.json: a simulation's truth file given as the report", "closedloop check TRUTH REPORT"],
        {
            "truth.json": '{"scenario": "arm_point", "parameters": {"j1.x": 0.1}}',
            "truth2.json": '{"scenario": "arm_point", "parameters": {"j1.x": 0.1}}',
        },
    ),
    Case(
        "simulate-tool-1e9",
        "option value",
        [
            "simulate",
            "--robot",
            "{panda.urdf}",
            "--loop",
            "weld:frame=panda_hand",
            "--tool",
            "1e9,0,0",
            "--out",
            "{tmp}/sim",
        ],
        ["--tool 1e9,0,0", "longer than 2 m"],
    ),
    Case(
        "simulate-poses-missing-joint",
        "log",
        ["simulate", "panda_weld", "--poses", "{next.csv}", "--out", "{tmp}/sim"],
        ["next.csv: no column for driven joint(s) panda_joint7"],
        {
            "next.csv": "panda_joint1,panda_joint2,panda_joint3,panda_joint4,panda_joint5,panda_joint6\n0,0,0,-1.5,0,1.5\n"
        },
    ),
    Case(
        "simulate-poses-and-n",
        "option value",
        ["simulate", "panda_weld", "--poses", "{next.csv}", "--n", "5", "--out", "{tmp}/sim"],
        ["--n 5 and --poses", "the poses file sets the configurations"],
        {"next.csv": "panda_joint1\n0\n"},
    ),
    Case(
        "simulate-tool-two-numbers",
        "option value",
        [
            "simulate",
            "--robot",
            "{panda.urdf}",
            "--loop",
            "weld:frame=panda_hand",
            "--tool",
            "0.1,0",
            "--out",
            "{tmp}/sim",
        ],
        ["expected 3 numbers"],
    ),
    Case(
        "html-without-matplotlib",
        "missing extra",
        calib("--html", "{tmp}/r.html"),
        ["--html: needs matplotlib", 'pip install "closedloop[report]"', 'pip install ".[report]"'],
        hide=("matplotlib",),
    ),
    # ------------------------------------------------------------------ bags
    Case(
        "ros1-bag-garbled",
        "garbled bag",
        ["extract", "{g.bag}", "--model", "{panda.urdf}", "--out", "{tmp}/o.csv"],
        ["g.bag: damaged message at byte"],
        {"g.bag": "GARBLED ros1"},
    ),
    Case(
        "mcap-bag-garbled",
        "garbled bag",
        ["extract", "{g.mcap}", "--model", "{panda.urdf}", "--out", "{tmp}/o.csv"],
        ["g.mcap: damaged", "byte"],
        {"g.mcap": "GARBLED mcap"},
    ),
    Case(
        "calibrate-garbled-bag",
        "garbled bag",
        calib(log="{g.bag}"),
        ["g.bag: damaged message at byte"],
        {"g.bag": "GARBLED ros1"},
    ),
]


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A mesh-free Panda, a 30-row weld log, and a ROS 1 and an MCAP bag of 8 standstills."""
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.loops import PointLoop, WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    d = tmp_path_factory.mktemp("bad-input")
    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(d / "panda.urdf")
    q0 = [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8]
    ds = make_dataset(robot, WeldLoop("fixture", "panda_hand"), q0, 30, np.random.default_rng(5))
    ds.log().write_csv(d / "log.csv")
    point = make_dataset(robot, PointLoop("socket", "panda_hand"), q0, 30, np.random.default_rng(6))
    point.log().write_csv(d / "socket.csv")  # a ball in a socket: the hand's orientation free
    bags = {}
    try:
        from test_bags import stream, write_bag

        rng = np.random.default_rng(1)
        for fmt in ("ros1", "mcap"):
            bag = write_bag(d / f"b_{fmt}", fmt, {"/joint_states": stream(ds.readings[:8], rng, False)}, ds.joints, rng)
            f = bag if bag.is_file() else next(bag.glob("*.mcap"))
            bags[fmt] = garble(f.read_bytes(), seed=0)
    except ImportError:  # rosbags missing: the bag cases say so in their own line (exit 2 all the same)
        pass
    return d, bags


def garble(data: bytes, seed: int, size: int = 4096) -> bytes:
    """`data` with `size` random bytes in the middle."""
    g = bytearray(data)
    mid = len(g) // 2
    g[mid : mid + size] = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    return bytes(g)


def _materialize(case: Case, tmp: Path, base) -> list[str]:
    import os

    d, bags = base
    names = {"tmp": str(tmp)}
    for name in ("panda.urdf", "log.csv", "socket.csv"):
        (tmp / name).write_bytes((d / name).read_bytes())
        names[name] = str(tmp / name)
    for name, content in case.files.items():
        p = tmp / name
        if isinstance(content, str) and content.startswith("HARDLINK "):
            os.link(tmp / content.split()[1], p)
        elif isinstance(content, str) and content.startswith("SYMLINK "):
            p.symlink_to(tmp / content.split()[1])
        elif isinstance(content, str) and content.startswith("GARBLED "):
            fmt = content.split()[1]
            if fmt not in bags:
                pytest.fail("rosbags is needed to write the bags (pip install rosbags)")
            p.write_bytes(bags[fmt])
        elif isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content)
        names[name] = str(p)
    out = []
    for a in case.argv:
        for k, v in names.items():
            a = a.replace("{" + k + "}", v)
        out.append(a)
    return out


def run_case(case: Case, tmp: Path, base, capsys, monkeypatch) -> tuple[int, str]:
    """Run one case; check the inputs are untouched and no temporary is left; (exit code, stderr)."""
    argv = _materialize(case, tmp, base)
    for mod in case.hide:
        monkeypatch.setitem(sys.modules, mod, None)  # `import mod` raises ImportError
    before = {p: p.read_bytes() for p in tmp.rglob("*") if p.is_file()}
    rc = main(argv)
    out, err = capsys.readouterr()
    for p, b in before.items():
        assert p.read_bytes() == b, f"{p.name} was changed"
    assert not [p for p in tmp.rglob("*") if p.name.startswith(".closedloop-") or ".tmp-" in p.name]
    return rc, err


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_case(case: Case, tmp_path, base, capsys, monkeypatch):
    rc, err = run_case(case, tmp_path, base, capsys, monkeypatch)
    assert rc == case.rc, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), err
    assert "Traceback" not in err and "internal error" not in err
    for w in case.words:
        assert w in err, f"'{w}' not in: {err}"


def test_case_ids_unique():
    assert len({c.id for c in CASES}) == len(CASES)


# ----------------------------------------------------------------------------- the docs page
def _seen(err: str, tmp: Path) -> str:
    """The line as the docs show it: the case's folder dropped from paths."""
    return err.strip().replace(str(tmp) + "/", "").replace(str(tmp), ".")


def render(rows: list[tuple[Case, str]]) -> str:
    """docs/reference/bad-input.md from (case, line seen) rows."""
    kinds = sorted({c.kind for c, _ in rows})
    commands = sorted({c.command for c, _ in rows})
    lines = [
        "# Bad input: what each command says",
        "",
        "Every command refuses a bad input before doing any work, in **one line** on stderr naming the file,",
        "row, element or option at fault, with exit code 2; it never overwrites an input and never leaves a",
        "partial file.  Ctrl-C (SIGINT) and SIGTERM print one line too (exit 130 and 143) and leave the",
        "previous outputs as they were.  This page is generated from the case table of",
        "`tests/test_bad_input.py`, which runs every case and fails when a line here differs from what the",
        "command prints (`python tests/test_bad_input.py` rewrites it).",
        "",
        "## Commands x kinds of bad input",
        "",
        "| kind of input | " + " | ".join(f"`{c}`" for c in commands) + " |",
        "|---|" + "---|" * len(commands),
    ]
    for k in kinds:
        cells = [str(sum(1 for c, _ in rows if c.kind == k and c.command == cmd) or "") for cmd in commands]
        lines.append(f"| {k} | " + " | ".join(f"{n} clean" if n else "" for n in cells) + " |")
    lines += ["", "Every case: exit 2, one line, inputs untouched, no temporary file left.", ""]
    for k in kinds:
        lines += [f"## {k[0].upper() + k[1:]}", "", "| case | command | what the user sees |", "|---|---|---|"]
        for c, seen in rows:
            if c.kind == k:
                cmd = " ".join(a if "{" not in a else a.replace("{", "").replace("}", "") for a in c.argv[:2])
                shown = seen.replace("|", "\\|")
                lines.append(f"| {c.id} | `closedloop {cmd} ...` | `{shown}` |")
        lines.append("")
    lines += [
        "## Signals",
        "",
        "| event | what the user sees | exit |",
        "|---|---|---|",
        "| Ctrl-C (SIGINT), while the libraries load or during the work | `interrupted; outputs not yet published were discarded` | 130 |",
        "| SIGTERM | `interrupted (signal 15); outputs not yet published were discarded` | 143 |",
        "| SIGKILL of `batch --jobs N` | (nothing: killed) workers end within milliseconds, no job folder half written | -9 |",
        "",
        "Within the first tenth of a second of a process (the Python interpreter starting, before any",
        "closedloop code runs) Ctrl-C is Python's own: a short KeyboardInterrupt traceback, nothing written.",
        "",
        "## Outputs",
        "",
        "* An output that is an input of the same run (the same inode, through a symbolic or hard link",
        "  too) is refused before any work, and again when the outputs are published.",
        "* An output that is a device or a named pipe (`--report /dev/stdout`, a FIFO) is written into in",
        "  place; it is never replaced by a regular file.  `batch --summary` on a pipe gets the final table.",
        "* Outputs are staged in unnamed files in the target's folder, fsynced, then renamed into place:",
        "  on a full disk the command ends with `error: FILE: No space left on device` (exit 2) and the",
        "  previous files stay as they were, with no partial file beside them (`tests/test_output_rule.py`,",
        "  on a 64 KiB tmpfs).",
        "",
    ]
    return "\n".join(lines)


def collect(tmp_root: Path, base, capsys, monkeypatch) -> list[tuple[Case, str]]:
    rows = []
    for k, case in enumerate(CASES):
        tmp = tmp_root / f"c{k}"
        tmp.mkdir()
        with monkeypatch.context() as m:
            _, err = run_case(case, tmp, base, capsys, m)
        rows.append((case, _seen(err, tmp)))
    return rows


def test_docs_table_is_current(tmp_path, base, capsys, monkeypatch):
    """The page shows exactly what the commands print (regenerate: python tests/test_bad_input.py)."""
    text = render(collect(tmp_path, base, capsys, monkeypatch))
    if os.environ.get("CLOSEDLOOP_WRITE_DOCS"):
        DOC.parent.mkdir(parents=True, exist_ok=True)
        DOC.write_text(text)
    assert DOC.exists() and DOC.read_text() == text, (
        "docs/reference/bad-input.md is stale: python tests/test_bad_input.py"
    )


if __name__ == "__main__":  # rewrite the docs page
    os.environ["CLOSEDLOOP_WRITE_DOCS"] = "1"
    sys.exit(pytest.main([__file__, "-q", "-p", "no:cacheprovider", "-k", "docs_table"]))
