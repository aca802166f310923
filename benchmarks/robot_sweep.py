"""The robot sweep: every robot file of example-robot-data through the command line, as a user would.

For every URDF of the installed ``example-robot-data`` (``--robots`` filters by folder or file name),
the script picks up to ``--chains`` chains from the root to a far link (the leaves with the most
movable joints, at least ``--min-joints``, on different branches) and builds the cases

* ``point``: a stylus ``--tool "0.03 0.02 0.05"`` on the chain's last link, in a ball socket;
* ``weld``: the chain's last link welded to a fixture;
* ``weld2``: the two longest chains' last links welded to each other (two hands, where there are two);

each exact and with 1e-5 rad of joint noise, each on its own seed (``--seed``: the first).  A case runs
``closedloop simulate --robot`` -> ``calibrate`` (the command ``simulate`` prints) -> ``check``, each
command under the case's time limit (``--timeout``), and is classified:

========================  ====================================================================
right                     check within tolerance, verdict ``ok``
right, flagged            check within tolerance, verdict ``suspect`` or ``failed`` (a false alarm)
wrong, flagged            check outside tolerance (or calibrate failed, exit 3), verdict not ``ok``
wrong, foretold           check outside tolerance, verdict ``ok``, and every row outside tolerance foretold by
                          the report's prediction (`closedloop.validation.check.unforetold`: its 95 % bound of
                          the largest error above the tolerance, observed at most 3x the expected): an honest
                          answer, the expected largest error above the tolerance
wrong, foretold by bound  the same, a row foretold by the 95 % bound alone (the expected largest error within
                          the tolerance: `check.within_bound_only`), counted apart
confidently wrong         check outside tolerance, verdict ``ok``, a row outside tolerance the prediction did
                          not foretell (none, a 95 % bound within the tolerance, or observed above 3x the
                          expected)
clean refusal             simulate or calibrate exits 2 with one ``error:`` line
empty                     simulate recorded fewer configurations than asked (exit 3)
internal error            a traceback, ``internal error`` or an unknown exit code
timeout                   a command ran past the time limit
========================  ====================================================================

    nice python benchmarks/robot_sweep.py --robots panda,ur5 --out out/sweep
    nice python benchmarks/robot_sweep.py --json out/sweep.json --markdown docs/benchmarks/robot-sweep.md

The machine is shared: the cases run one at a time (``--jobs`` runs more), every command of a case
under ``--timeout`` seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import load, machine  # noqa: E402

MOVABLE = ("revolute", "continuous", "prismatic")
CLASSES = (
    "right",
    "right, flagged",
    "wrong, flagged",
    "wrong, foretold",
    "wrong, foretold by the 95 % bound",
    "confidently wrong",
    "clean refusal",
    "empty",
    "internal error",
    "timeout",
)
STYLUS = "0.03 0.02 0.05"


@dataclass(frozen=True)
class Case:
    """One simulate -> calibrate -> check run."""

    robot: str  # the URDF's path relative to the robots directory
    loop: str  # the --loop of simulate
    kind: str  # point / weld / weld2
    noise: float
    seed: int
    tool: str | None = None
    truth: str = "identifiable"  # simulate's draw of the true robot (``--set truth=...``): identifiable or all


@dataclass
class Outcome:
    case: Case
    cls: str
    seconds: float
    verdict: str = ""
    detail: str = ""
    steps: list[str] = field(default_factory=list)
    cpu: float = 0.0  # CPU seconds of the case's commands (their own: the wall time depends on the load)
    rows: list[dict] = field(default_factory=list)  # check's rows: name, error, predicted, bound, tol, result
    reasons: list[str] = field(default_factory=list)  # the verdict's reasons (what flagged it)


def _observed(r: dict) -> str:
    p = "none" if r.get("predicted") is None else f"{r['predicted']:.3g}"
    b = f" (95 % bound {r['bound']:.3g})" if r.get("bound") is not None else ""
    return f"{r['name']}: {r['error']:.3g} observed, {p} predicted{b}, tolerance {r['tol']:g}"


def classify(verdict: str, rows: list[dict]) -> str:
    """The class of a case that ran to `check` (module docstring), from its verdict and check's rows."""
    from closedloop.validation.check import unforetold, within_bound_only

    if all(r.get("result") != "FAIL" for r in rows):
        return "right" if verdict == "ok" else "right, flagged"
    if verdict != "ok":
        return "wrong, flagged"
    if unforetold(rows):
        return "confidently wrong"
    return BOUND if within_bound_only(rows) else "wrong, foretold"


#: the class of a wrong answer foretold by the report's 95 % bound alone (`classify`)
BOUND = "wrong, foretold by the 95 % bound"
#: the classes of a wrong answer with an ``ok`` verdict
WRONG_OK = ("wrong, foretold", BOUND, "confidently wrong")

#: the words of the short-length finding (`closedloop.analysis.gauge.short_gauge_warning`)
SHORT = "stands for a length of only"


def short_length_alone(cls: str, reasons: list[str]) -> str:
    """The class a case had when a size held by a short length flagged the verdict on the length alone (the
    rule before the command line stated the size's predicted error instead, `closedloop.calibration.verdict.
    judge_size`): an ``ok`` verdict whose reasons carry that finding as a note was ``suspect`` then."""
    if not any(r.startswith("note: ") and SHORT in r for r in reasons):
        return cls
    if cls == "right":
        return "right, flagged"
    return "wrong, flagged" if cls in WRONG_OK else cls


def under_predicted(rows: list[dict]) -> bool:
    """Whether a row's observed error is above FORETOLD times its prediction (within tolerance or not)."""
    from closedloop.validation.check import FORETOLD

    return any(r.get("predicted") and abs(r.get("error") or 0.0) > FORETOLD * r["predicted"] for r in rows)


def _tree(path: Path):
    """(parent link of each link with its joint, children of each link) of a URDF, or None when unreadable."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError:
        return None
    parent: dict[str, tuple[str, ET.Element]] = {}
    for j in root.findall("joint"):
        p, c = j.find("parent"), j.find("child")
        if p is not None and c is not None:
            parent[c.get("link", "")] = (p.get("link", ""), j)
    links = [lk.get("name", "") for lk in root.findall("link")]
    return links, parent


def _chain(link: str, parent) -> list[ET.Element]:
    out = []
    while link in parent:
        link, j = parent[link]
        out.append(j)
    return out[::-1]


def chains(path: Path, n_chains: int, min_joints: int) -> list[tuple[str, int]]:
    """Up to `n_chains` far links on different branches, with the number of movable joints above them."""
    tree = _tree(path)
    if tree is None:
        return []
    links, parent = tree
    has_child = {p for p, _ in parent.values()}
    scored = []
    for link in links:
        if link in has_child and any(
            parent.get(c, ("", None))[0] == link and parent[c][1].get("type") in MOVABLE for c in links
        ):
            continue  # a link something still moves below: not far
        joints = _chain(link, parent)
        movable = [j for j in joints if j.get("type") in MOVABLE and j.find("mimic") is None]
        if len(movable) >= min_joints:
            scored.append((len(movable), len(joints), link, movable))
    scored.sort(key=lambda t: (-t[0], -t[1], t[2]))
    picked: list[tuple[str, int]] = []
    used: list[set[str]] = []
    for nm, _, link, movable in scored:
        own = {j.get("name", "") for j in movable[-min_joints:]}  # the distal joints: a branch of its own
        if any(own & u for u in used):
            continue
        # the link nearest the end of the distal movable joint's child chain with a fixed tip is fine as is
        picked.append((link, nm))
        used.append(own)
        if len(picked) == n_chains:
            break
    return picked


def robot_files(base: Path, only: list[str], per_folder: int = 0) -> list[Path]:
    """The URDFs under `base` (paths containing one of `only`; at most `per_folder` per robot folder)."""
    files = sorted(p for p in base.rglob("*.urdf") if p.is_file())
    if only:
        files = [p for p in files if any(o in str(p.relative_to(base)) for o in only)]
    if per_folder:
        seen: Counter = Counter()
        kept = []
        for p in files:
            folder = p.relative_to(base).parts[0]
            if seen[folder] < per_folder:
                kept.append(p)
                seen[folder] += 1
        files = kept
    return files


def cases(base: Path, files: list[Path], n_chains: int, min_joints: int, seed: int, truth: str = "all") -> list[Case]:
    out: list[Case] = []
    for f in files:
        rel = str(f.relative_to(base))
        ch = chains(f, max(n_chains, 2), min_joints)
        specs: list[tuple[str, str, str | None]] = []
        for link, _ in ch[:n_chains]:
            specs.append(("point", f"point:frame={link},name=socket", STYLUS))
            specs.append(("weld", f"weld:frame={link},name=fixture", None))
        if len(ch) >= 2:  # the two longest chains' ends welded to each other (two hands)
            specs.append(("weld2", f"weld:frame={ch[0][0]},to={ch[1][0]},name=grasp", None))
        for kind, loop, tool in specs:
            for noise in (0.0, 1e-5):
                out.append(Case(rel, loop, kind, noise, seed + len(out), tool, truth))
    return out


def interleaved(todo: list[Case]) -> list[Case]:
    """The cases robot by robot in turn (the first case of every robot, then the second, ...): a run
    stopped early has seen as many robots as it could."""
    by_robot: dict[str, list[Case]] = {}
    for c in todo:
        by_robot.setdefault(c.robot, []).append(c)
    out = []
    for k in range(max((len(v) for v in by_robot.values()), default=0)):
        out += [v[k] for v in by_robot.values() if k < len(v)]
    return out


def read_outcomes(paths: list[str]) -> list[Outcome]:
    """Outcomes appended by ``--json`` (one JSON object a line), for ``--from-json``."""
    out = []
    for path in paths:
        for line in Path(path).read_text().splitlines():
            d = json.loads(line)
            d["case"] = Case(**d["case"])
            o = Outcome(**d)
            if o.rows:  # classified again: the rule is `classify`'s, whatever the run's was
                o.cls = classify(o.verdict, o.rows)
            out.append(o)
    return out


def _run(cmd: list[str], timeout: float) -> tuple[int | None, str, str, float, float]:
    """(exit code or None past `timeout`, stdout, stderr, wall seconds, CPU seconds): the CPU time is the
    command's own (user + system, its children included) from `os.wait4` on its process id, so commands
    running side by side (``--jobs``) are each counted once."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen(cmd, stdout=out, stderr=err, text=True)
        timer = threading.Timer(timeout, p.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(p.pid, 0)
        finally:
            timer.cancel()
        p.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
        wall, cpu = time.perf_counter() - t0, usage.ru_utime + usage.ru_stime
        if wall >= timeout and p.returncode < 0:  # killed by the timer
            return None, "", "", wall, cpu
        out.seek(0)
        err.seek(0)
        return p.returncode, out.read(), err.read(), wall, cpu


def _error_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    return lines[-1][:300] if lines else stderr.strip().splitlines()[-1][:300] if stderr.strip() else ""


def _internal(rc: int | None, stderr: str) -> bool:
    return rc not in (0, 1, 2, 3, None) or "Traceback" in stderr or "internal error" in stderr


def run_case(case: Case, base: Path, work: Path, n: int, timeout: float, cli: list[str]) -> Outcome:
    """One case's commands (module docstring), with their wall and CPU seconds."""
    cpu = [0.0]

    def run(cmd: list[str]) -> tuple[int | None, str, str, float]:
        rc, so, se, wall, used = _run(cmd, timeout)
        cpu[0] += used
        return rc, so, se, wall

    o = _case(case, base, work, n, cli, run)
    o.cpu = cpu[0]
    return o


def _case(case: Case, base: Path, work: Path, n: int, cli: list[str], run) -> Outcome:
    out = work / f"case{case.seed}"
    shutil.rmtree(out, ignore_errors=True)
    sim = cli + ["simulate", "--robot", str(base / case.robot), "--loop", case.loop, "--n", str(n)]
    sim += ["--seed", str(case.seed), "--out", str(out / "sim"), "--replace"]
    if case.tool:
        sim += ["--tool", case.tool]
    if case.noise:
        sim += ["--set", f"noise={case.noise}"]
    if case.truth != "identifiable":
        sim += ["--set", f"truth={case.truth}"]
    total = 0.0
    rc, so, se, dt = run(sim)
    total += dt
    steps = [f"simulate rc={rc} {dt:.1f}s"]
    if rc is None:
        return Outcome(case, "timeout", total, detail="simulate", steps=steps)
    if _internal(rc, se):
        return Outcome(case, "internal error", total, detail=_error_line(se), steps=steps)
    if rc == 2:
        return Outcome(case, "clean refusal", total, detail=_error_line(se), steps=steps)
    log_csv = out / "sim" / "log.csv"
    rows = max(0, len(log_csv.read_text().splitlines()) - 1) if log_csv.is_file() else 0
    if rc == 3 or rows < n:  # fewer configurations than asked (exit 3 says so; files written when some were)
        said = _error_line(se) or (so.strip().splitlines() or [""])[0]
        return Outcome(case, "empty", total, detail=f"{rows} of {n} recorded (rc {rc}): {said[:200]}", steps=steps)
    truth = json.loads((out / "sim" / "truth.json").read_text())
    from closedloop.sims.outputs import next_commands  # the commands simulate prints

    calibrate = next_commands(out / "sim", truth)[0].split()[1:]
    cal = cli + calibrate + ["--quiet"]
    rc, so, se, dt = run(cal)
    total += dt
    steps.append(f"calibrate rc={rc} {dt:.1f}s")
    if rc is None:
        return Outcome(case, "timeout", total, detail="calibrate", steps=steps)
    if _internal(rc, se):
        return Outcome(case, "internal error", total, detail=_error_line(se), steps=steps)
    if rc == 2:
        return Outcome(case, "clean refusal", total, detail=_error_line(se), steps=steps)
    report = out / "sim" / "report.json"
    verdict, reasons = "", []
    if report.is_file():
        try:
            v = json.loads(report.read_text()).get("verdict", {})
            verdict, reasons = str(v.get("status", "")), [str(r) for r in v.get("reasons", [])]
        except (ValueError, AttributeError):
            verdict = ""
    if rc == 3:
        return Outcome(case, "wrong, flagged", total, verdict or "failed", _error_line(se), steps, reasons=reasons)
    chk = cli + ["check", str(out / "sim" / "truth.json"), str(report), "--json", str(out / "check.json")]
    rc, so, se, dt = run(chk)
    total += dt
    steps.append(f"check rc={rc} {dt:.1f}s")
    if rc is None:
        return Outcome(case, "timeout", total, verdict, "check", steps)
    if _internal(rc, se) or rc not in (0, 1):
        return Outcome(case, "internal error", total, verdict, _error_line(se), steps)
    said = [ln for ln in so.strip().splitlines() if ln.startswith("note: the report's verdict")]
    worst = (said or so.strip().splitlines() or [""])[-1]
    keep = ("name", "error", "predicted", "bound", "tol", "result")
    rows = [{k: r.get(k) for k in keep} for r in json.loads((out / "check.json").read_text())["rows"]]
    if verdict == "ok" and any(r["result"] == "FAIL" for r in rows):  # what check observed against the prediction
        worst = "; ".join(_observed(r) for r in rows if r["result"] == "FAIL")
    return Outcome(case, classify(verdict, rows), total, verdict, worst, steps, rows=rows, reasons=reasons)


def markdown(outcomes: list[Outcome], header: str, n: int, timeout: float) -> str:
    from closedloop.assets.catalog import example_robot_data_dir

    erd = f"{example_robot_data_dir()}/"
    by_robot: dict[str, Counter] = {}
    for o in outcomes:
        by_robot.setdefault(o.case.robot, Counter())[o.cls] += 1
    cols = list(CLASSES)
    lines = [
        "| robot file | cases | " + " | ".join(cols) + " | slowest: wall (s) | CPU (s) |",
        "|---|---:|" + "---:|" * len(cols) + "---:|---:|",
    ]
    for robot, c in sorted(by_robot.items()):
        slow = max((o for o in outcomes if o.case.robot == robot), key=lambda o: o.seconds)
        counts = " | ".join(str(c[k]) for k in cols)
        lines.append(f"| `{robot}` | {sum(c.values())} | {counts} | {slow.seconds:.0f} | {slow.cpu:.0f} |")
    tot = Counter(o.cls for o in outcomes)
    slowest_all = max(outcomes, key=lambda o: o.seconds)
    lines.append(
        f"| **all ({len(by_robot)} files)** | {len(outcomes)} | "
        + " | ".join(str(tot[k]) for k in cols)
        + f" | {slowest_all.seconds:.0f} | {slowest_all.cpu:.0f} |"
    )
    right = tot["right"] + tot["right, flagged"]
    text = [
        f"{header}; {n} configurations per case, each command at most {timeout:g} s.",
        "",
        "\n".join(lines),
        "",
        f"Right answers flagged: {tot['right, flagged']} of {right}"
        + (f" ({100 * tot['right, flagged'] / right:.0f} %)" if right else "")
        + "; "
        + "; ".join(_flagged_share(outcomes, noise, what) for noise, what in ((0.0, "exact"), (1e-5, "noisy")))
        + ".",
        "",
        "Had a size held by a short length flagged the verdict on the length alone (the rule before the "
        "report's predicted size error was stated in its place): "
        + "; ".join(
            _flagged_share(outcomes, noise, what, short_length_alone)
            for noise, what in ((0.0, "exact"), (1e-5, "noisy"))
        )
        + ".",
        "",
        "Had a row been foretold only by an expected largest error above the tolerance (the rule before the "
        "report's 95 % bound was read): "
        + "; ".join(
            f"{what}: {sum(o.cls in ('confidently wrong', BOUND) for o in outcomes if o.case.noise == noise)} "
            "confidently wrong"
            for noise, what in ((0.0, "exact"), (1e-5, "noisy"))
        )
        + ".",
        "",
        "Right answers whose error is above 3x the predicted one (within tolerance: not misleading at it): "
        f"{sum(o.cls.startswith('right') and under_predicted(o.rows) for o in outcomes)}.",
        "",
        "What flagged the verdicts (from the reports' verdict reasons):",
        "",
        warning_table(outcomes),
        "",
        "Every case that is not right (the line each gave):",
        "",
        "| robot file | loop | noise | class | verdict | what it said |",
        "|---|---|---:|---|---|---|",
    ]
    for o in outcomes:
        if o.cls != "right":
            det = o.detail.replace(erd, "").replace("|", "/")[:200]
            text.append(f"| `{o.case.robot}` | `{o.case.loop}` | {o.case.noise:g} | {o.cls} | {o.verdict} | {det} |")
    slowest = sorted(outcomes, key=lambda o: -o.seconds)[:5]
    text += ["", "Slowest cases:", ""]
    text += [
        f"* `{o.case.robot}` `{o.case.loop}` noise {o.case.noise:g}: {o.seconds:.0f} s wall, {o.cpu:.0f} s CPU "
        f"({', '.join(o.steps)})"
        for o in slowest
    ]
    return "\n".join(text) + "\n"


#: the findings a verdict is flagged by, as the words that name them (`warning_table`)
FINDINGS = {
    "size held by a short length": SHORT,
    "joints move less than 0.05 rad": "move less than",
    "the size changed": "overall size changed",
    "error bars not reliable": "error bars are not reliable",
    "held-out fold": "validation fold",
    "no single length holds the size": "no single length",
    "size held in part": "does not hold the length scale alone",
    "not better than nominal": "does not make the robot more accurate",
    "corrections no calibration makes": "corrections no calibration makes",
    "implausibly large corrections": "implausibly large corrections",
    "outliers rejected": "rejected as outliers",
    "not a minimum": "minimum",
}


def warning_table(outcomes: list[Outcome]) -> str:
    """Per finding, how many right and how many wrong answers it flagged (a case may carry several)."""
    lines = ["| finding | flags right answers | flags wrong answers |", "|---|---:|---:|"]
    for what, words in FINDINGS.items():
        right = sum(o.cls == "right, flagged" and any(words in r for r in o.reasons) for o in outcomes)
        wrong = sum(o.cls == "wrong, flagged" and any(words in r for r in o.reasons) for o in outcomes)
        if right or wrong:
            lines.append(f"| {what} | {right} | {wrong} |")
    return "\n".join(lines)


def _flagged_share(outcomes: list[Outcome], noise: float, what: str, rule=None) -> str:
    """Right answers flagged, confident wrong answers and wrong answers foretold by the 95 % bound alone at one
    noise level (`rule`: the class under another
    rule, from the class and the verdict's reasons)."""
    cls = [(o, rule(o.cls, o.reasons) if rule else o.cls) for o in outcomes if o.case.noise == noise]
    right = [c for _, c in cls if c in ("right", "right, flagged")]
    flagged = sum(c == "right, flagged" for c in right)
    cw = sum(c == "confidently wrong" for _, c in cls)
    bound = sum(c == BOUND for _, c in cls)
    share = f" ({100 * flagged / len(right):.0f} %)" if right else ""
    return f"{what}: {flagged} of {len(right)}{share} flagged, {cw} confidently wrong, {bound} foretold by the 95 % bound alone"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="", help="comma-separated parts of robot file paths (default: all)")
    ap.add_argument("--per-folder", type=int, default=0, help="at most this many files per robot folder (0: all)")
    ap.add_argument("--chains", type=int, default=2, help="chains per robot file (1-3)")
    ap.add_argument("--min-joints", type=int, default=4)
    ap.add_argument("--n", type=int, default=100, help="configurations per case")
    ap.add_argument("--seed", type=int, default=7001, help="the first case's seed (each case its own)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per command of a case")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--kinds", default="point,weld,weld2")
    ap.add_argument("--noise", default="0,1e-5", help="noise levels to run (of 0 and 1e-5)")
    ap.add_argument(
        "--truth",
        choices=("all", "identifiable"),
        default="all",
        help="simulate's true robot: every joint origin off (default: the held lengths too, so a size can be "
        "wrong) or only what a calibration identifies (--set truth=...)",
    )
    ap.add_argument("--out", default="out/robot_sweep", help="scratch folder for the datasets")
    ap.add_argument("--json", default=None, help="append every outcome here as one JSON line")
    ap.add_argument("--markdown", default=None, help="write the results table here")
    ap.add_argument("--list", action="store_true", help="list the cases and stop")
    ap.add_argument(
        "--order",
        choices=("robots", "interleaved"),
        default="interleaved",
        help="robot after robot, or one case of each robot in turn (default: a run stopped early has seen every robot)",
    )
    ap.add_argument("--from-json", default=None, help="no run: the table of the outcomes in these --json files")
    ap.add_argument("--header", default=None, help="with --from-json: the machine line above the table")
    args = ap.parse_args(argv)

    from closedloop.assets.catalog import example_robot_data_dir

    base = example_robot_data_dir()
    files = robot_files(base, [r for r in args.robots.split(",") if r], args.per_folder)
    kinds = set(args.kinds.split(","))
    levels = {float(v) for v in args.noise.split(",")}
    todo = [
        c
        for c in cases(base, files, args.chains, args.min_joints, args.seed, args.truth)
        if c.kind in kinds and c.noise in levels
    ]
    if args.from_json:
        outcomes = read_outcomes(args.from_json.split(","))
        text = markdown(outcomes, args.header or "from " + args.from_json, args.n, args.timeout)
        if args.markdown:
            Path(args.markdown).write_text(text)
        else:
            print(text)
        return 0
    if args.order == "interleaved":
        todo = interleaved(todo)
    if args.list:
        for c in todo:
            print(c.robot, c.loop, c.noise, c.seed)
        print(f"{len(todo)} cases on {len({c.robot for c in todo})} robot files ({len(files)} files)")
        return 0
    cli = [sys.executable, "-m", "closedloop.cli"]
    work = Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    header = f"{machine()}; {load()} at the start; nice {os.nice(0)}"
    print(header, flush=True)
    outcomes: list[Outcome] = []
    t0 = time.perf_counter()

    def one(c: Case) -> Outcome:
        return run_case(c, base, work, args.n, args.timeout, cli)

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for o in pool.map(one, todo):
            outcomes.append(o)
            print(
                f"{o.cls:18s} {o.seconds:6.1f}s {o.verdict:8s} {o.case.robot} {o.case.loop} "
                f"noise={o.case.noise:g}: {o.detail[:140]}",
                flush=True,
            )
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps({**asdict(o), "case": asdict(o.case)}) + "\n")
    print(f"{len(outcomes)} cases in {time.perf_counter() - t0:.0f} s: {dict(Counter(o.cls for o in outcomes))}")
    if args.markdown:
        Path(args.markdown).write_text(markdown(outcomes, header, args.n, args.timeout))
    return 0


if __name__ == "__main__":
    sys.exit(main())
