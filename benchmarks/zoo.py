"""The full robot zoo: every arm x loop type x seed x start, judged against the truth.

Data from `tests/zoo.py` (a generator independent of closedloop's parametrization); each case is
calibrated with the defaults of `closedloop.calibrate`, given the verdict `closedloop calibrate` gives
on the command line (the fit's, with the size's predicted error stated where a short length holds the
size: `closedloop.calibration.verdict.judge_size`; the fit's own verdict is kept beside it), and its
calibrated URDF judged by what the robot does (tool forward kinematics against the truth after the best base/tool transforms, the
scale fitted only for loops blind to it).  A case is *right* (within `Case.tolerances()`; counted
as *flagged* too when its verdict is 'suspect' or 'failed': a false alarm), *refused* (wrong, and
the verdict is 'suspect' or 'failed', or a user-facing error), *wrong, foretold* (wrong, verdict ok,
and every figure outside tolerance foretold by the calibration's own workspace prediction, as
`closedloop check` judges it: `closedloop.validation.check.unforetold`, see `judged_rows`),
*wrong, foretold by the 95 % bound* (foretold only by the prediction's 95 % bound of the largest error,
the expected error being within tolerance: counted apart), *confidently wrong* (wrong, verdict ok, a
figure outside tolerance the prediction did not foretell),
or a *crash* (an exception that is not a closedloop error).

    python benchmarks/zoo.py                      # everything (slow: hinge loops take seconds each)
    python benchmarks/zoo.py --seeds 1 --loops weld,point --variants exact
    python benchmarks/zoo.py --robots ur5,panda --json out/zoo.json
    python benchmarks/zoo.py --first-seed 21 --seeds 2     # seeds 21 and 22

Variants: exact (2 mm / 2 mrad / 0.02 rad errors, noise-free), rough (10x the errors), noisy (joint
noise 1e-5 rad; judged against 5x the tool error the noise alone leaves, zoo_judge.predicted_std),
rows10 (10 % of the rows replaced by random readings), cell (one cell = 1e6).
Loops: weld for the redundant (7-DOF) arms only; point, plane, hinge, measured_point for all.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))  # zoo_judge, after sys.modules['zoo']
from machine import machine, tests_zoo  # noqa: E402

zoo = tests_zoo()

VARIANTS = {
    "exact": {},
    "rough": {"err_m": 2e-2, "err_rad": 2e-2, "offset_rad": 0.2},
    "noisy": {"sigma": 1e-5},
    "rows10": {"corrupt_rows": 0.10},
    "cell": {"corrupt_cells": 1, "cell_value": 1e6},
}
LOOPS = ["weld", "point", "plane", "hinge", "measured_point"]
N = {"weld": 60, "point": 60, "plane": 100, "hinge": 40, "measured_point": 60}


def dof(robot: str) -> int:
    import pinocchio as pin

    return zoo.joint_info(pin.buildModelFromXML(zoo.chain_urdf(zoo.ZOO[robot])))[0].__len__()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default=",".join(zoo.ZOO))
    ap.add_argument("--loops", default=",".join(LOOPS))
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--seeds", type=int, default=3, help="how many seeds")
    ap.add_argument("--first-seed", type=int, default=0, help="the first seed (seeds never run before: a fresh draw)")
    ap.add_argument("--json", default=None, help="write every case's outcome here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    rows, t0 = [], time.perf_counter()
    print(f"# machine: {machine()}", flush=True)
    for robot in args.robots.split(","):
        d = dof(robot)
        for loop in args.loops.split(","):
            if loop == "weld" and d < 7:
                continue
            for variant in args.variants.split(","):
                for seed in range(args.first_seed, args.first_seed + args.seeds):
                    kw = dict(VARIANTS[variant])
                    if loop == "measured_point" and kw.get("sigma"):
                        kw["sigma_t"] = 1e-5
                    try:
                        case = zoo.make_case(robot, loop, n=N[loop], seed=seed, tag=variant, **kw)
                    except RuntimeError as exc:
                        print(f"{robot}/{loop}/s{seed}/{variant}: no data ({exc})", flush=True)
                        continue
                    cpu = time.process_time()
                    fit = zoo.run_case(case)  # the verdict of the fit (the API's)
                    cpu = time.process_time() - cpu  # the case's own CPU: the wall time depends on the load
                    ws = workspace(fit)
                    o = as_command_line(fit, ws)
                    outcome = classify(o, case, ws)
                    print(o.line(outcome.upper() if outcome.startswith("wrong, fore") else None), flush=True)
                    rows.append(
                        {
                            "robot": robot,
                            "dof": d,
                            "loop": loop,
                            "variant": variant,
                            "seed": seed,
                            "flagged": bool(o.right and o.refused),
                            "flagged_fit_verdict": bool(fit.right and fit.refused),
                            "outcome": outcome,
                            "verdict": o.status,
                            # the fit's verdict alone, with a size held by a short length flagging it on the length
                            "outcome_fit_verdict": classify(fit, case, ws),
                            "fit_verdict": fit.status,
                            "reasons": list(getattr(getattr(o.result, "verdict", None), "reasons", []) or []),
                            "size_measured": (getattr(getattr(o.result, "verdict", None), "evidence", None) or {}).get(
                                "size_measured"
                            ),
                            "converged": o.converged,
                            "seconds": o.seconds,
                            "cpu_seconds": cpu,  # the case's: calibration and judging
                            "calibrate_cpu_seconds": fit.cpu_seconds,  # the calibration's alone (nan: it raised)
                            "error": o.error,
                            "judgement": vars(o.judgement) if o.judgement else None,
                            "notes": list(getattr(o.result, "notes", []) or []),
                        }
                    )
                    if args.json:  # after every case: a run stopped early keeps what it did
                        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
                        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    print(f"\n{len(rows)} cases in {time.perf_counter() - t0:.0f} s\n")
    print(table(rows, "loop"))
    print()
    print(table(rows, "variant"))
    print()
    print("With the fit's verdict alone (a size held by a short length flagging it on the length):\n")
    print(table(rows, "variant", fit_verdict=True))
    print()
    print(findings(rows))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


def workspace(o):
    """The calibration's predicted accuracy over the workspace (`closedloop.analysis.accuracy`), or None."""
    from closedloop.analysis.accuracy import predict_from_result

    return predict_from_result(o.result) if o.result is not None else None


def as_command_line(o, ws):
    """The outcome with the verdict `closedloop calibrate` gives on the command line, where the workspace
    prediction states the size's predicted error (`closedloop.calibration.verdict.judge_size`)."""
    import dataclasses

    from closedloop.calibration.verdict import judge_size

    v = getattr(o.result, "verdict", None)
    if v is None or ws is None:
        return o
    judged = judge_size(v, o.result, None, ws)
    if judged is v:
        return o
    return dataclasses.replace(o, status=judged.status, result=dataclasses.replace(o.result, verdict=judged))


def judged_rows(o, case, ws=None) -> list[dict]:
    """The judge's figures as `closedloop check` rows (error, predicted, bound, tol, result) beside the
    calibration's predicted accuracy over the workspace (`closedloop.analysis.accuracy.predict_from_result`:
    the expected largest error and its 95 % bound): the tool's largest position and rotation error, a
    relative motion's (which carries two configurations' errors: twice the predicted position error plus,
    for a pose, twice the reach times the rotation error) and the size."""
    j, tol = o.judgement, case.tolerances()
    ws = ws if ws is not None else workspace(o)

    def both(m: float | None, r: float | None) -> tuple[float | None, float | None, float | None]:
        rel = None if m is None else 2.0 * m + (2.0 * case.reach * r if r is not None else 0.0)
        return m, r, rel

    pm, pr, rel = both(ws.max_m if ws else None, ws.max_rad if ws else None)
    rad95 = [f.max95_rad for f in ws.frames if f.max95_rad is not None] if ws else []
    bm, br, brel = both(max((f.max95_m for f in ws.frames), default=None) if ws else None, max(rad95, default=None))
    figures = [
        ("position", j.pos_max, pm, bm, tol["pos"]),
        ("rotation", j.rot_max, pr, br, tol["rot"]),
        ("relative position", j.rel_pos_max, rel, brel, tol["rel_pos"]),
        (
            "relative rotation",
            j.rel_rot_max,
            None if pr is None else 2.0 * pr,
            None if br is None else 2.0 * br,
            2.0 * tol["rot"],
        ),
    ]
    if not case.scale_visible:
        size95 = 1.96 * ws.size_std if ws and ws.size_std is not None else None  # as the report's predicted95
        figures.append(("size", abs(j.scale - 1.0), ws.size_predicted if ws else None, size95, tol["scale"]))
    return [
        {"name": n, "error": e, "predicted": p, "bound": b, "tol": t, "result": "ok" if e < t else "FAIL"}
        for n, e, p, b, t in figures
    ]


def classify(o, case, ws=None) -> str:
    """right / refused / crash / wrong, foretold (by the 95 % bound alone) / confidently wrong (module
    docstring); `ws` the case's workspace prediction where computed already."""
    from closedloop.validation.check import unforetold, within_bound_only

    if o.right:
        return "right"
    if o.refused:
        return "refused"
    if o.status == "crash" or o.judgement is None:
        return "crash"
    rows = judged_rows(o, case, ws)
    if unforetold(rows):
        return "confidently wrong"
    return BOUND if within_bound_only(rows) else "wrong, foretold"


#: the class of a wrong answer foretold by the prediction's 95 % bound alone (`check.within_bound_only`)
BOUND = "wrong, foretold by the 95 % bound"


def findings(rows: list[dict]) -> str:
    """Per finding of a flagged verdict (`robot_sweep.FINDINGS`), how many right and wrong answers it flagged."""
    from robot_sweep import FINDINGS

    lines = ["| finding | flags right answers | flags wrong answers |", "|---|---:|---:|"]
    for what, words in FINDINGS.items():
        hit = [r for r in rows if r["verdict"] in ("suspect", "failed") and any(words in x for x in r["reasons"])]
        right = sum(r["outcome"] == "right" for r in hit)
        if hit:
            lines.append(f"| {what} | {right} | {len(hit) - right} |")
    return "\n".join(lines)


def table(rows: list[dict], by: str, fit_verdict: bool = False) -> str:
    """Markdown table per `by` and in total: cases, right (and how many of those the verdict flags:
    false alarms), refused (wrong, verdict not ok), wrong and foretold (verdict ok; of which by the 95 % bound
    alone), confidently wrong (wrong, verdict ok, not foretold), crashes;
    `fit_verdict`: classified by the fit's own verdict instead of the command line's."""
    key, flag = ("outcome_fit_verdict", "flagged_fit_verdict") if fit_verdict else ("outcome", "flagged")
    keys = sorted({r[by] for r in rows}, key=lambda k: (LOOPS + list(VARIANTS)).index(k))
    out = [
        f"| {by} | cases | right | of which flagged | refused | wrong, foretold | of which by the 95 % bound "
        "| confidently wrong | crash | slowest (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k in keys + ["total"]:
        sel = [r for r in rows if k == "total" or r[by] == k]
        c = Counter(r.get(key, r["outcome"]) for r in sel)
        flagged = sum(bool(r.get(flag, r.get("flagged"))) for r in sel)
        out.append(
            f"| {k} | {len(sel)} | {c['right']} | {flagged} | {c['refused']} | {c['wrong, foretold'] + c[BOUND]} | "
            f"{c[BOUND]} | {c['confidently wrong']} | {c['crash']} | "
            f"{max((r['seconds'] for r in sel), default=0.0):.1f} |"
        )
    return "\n".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
