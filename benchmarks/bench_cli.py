"""Benchmark: the command line's start-up and I/O beside the work of a calibration.

Two figures, with the machine, the load and the BLAS threads beside them:

* `closedloop calibrate` on the README's main-job data (`closedloop simulate panda_weld --n 200
  --seed 1`, simulated once into a temporary folder or read from `--data DIR`): the wall time of
  the whole command, the work (`report.json`: the fit's `solver.seconds` plus the held-out refits'
  `solver.validation_seconds`), and the difference: imports, parsing, reading the log, the report
  and the URDF; target: wall - work <= 0.5 s.  Run with the default options and with `--cv 0`.
  On a loaded machine the wall times measure the wait for a core as much as the command: the CPU
  seconds of the command less those of the work (`solver.cpu_seconds` + `validation_cpu_seconds`)
  are the start-up's own cost, whatever the load.
* `python -X importtime -c "import closedloop.cli.main"`: the cumulative import time of the command
  line, and the plain wall time of `python -c "import closedloop.cli.main"` beside that of
  `python -c pass` (the interpreter's own start).

Thread modes: `1` runs the commands with OPENBLAS_NUM_THREADS=OMP_NUM_THREADS=1, `default` with
the environment unchanged.  `--loaded` repeats everything while one busy process per CPU keeps
the cores busy (bounded in time, killed afterwards).

    python benchmarks/bench_cli.py                       # idle, both thread modes
    python benchmarks/bench_cli.py --threads 1 --repeat 5
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import add_arguments, condition, conditions, header  # benchmarks/machine.py

CLI = [sys.executable, "-m", "closedloop.cli.main"]
LOOP = "weld:frame=panda_hand_tcp,name=fixture"


def _env(mode: str) -> dict[str, str]:
    """The children's environment: BLAS threads per `mode`, and bytecode cached (as pip's install compiles
    it; an environment with PYTHONDONTWRITEBYTECODE would compile every module at every start)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    if mode != "default":
        env.update(OPENBLAS_NUM_THREADS=mode, OMP_NUM_THREADS=mode, MKL_NUM_THREADS=mode)
    return env


def _run(cmd: list[str], env: dict[str, str]) -> tuple[subprocess.CompletedProcess, float, float]:
    """(process, wall seconds, CPU seconds of the child) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr}")
    return out, wall, cpu


def simulate(out: Path) -> Path:
    """The README's main-job data (200 configurations of panda_weld, seed 1)."""
    _run(CLI + ["simulate", "panda_weld", "--n", "200", "--seed", "1", "--out", str(out)], _env("default"))
    return out


def calibrate_once(data: Path, work: Path, mode: str, cv: bool) -> tuple[float, float, float, float]:
    """(wall, work seconds: the fit and the held-out refits, child CPU, the work's CPU) of one
    `closedloop calibrate` of the main job."""
    cmd = CLI + [
        "calibrate",
        str(data / "nominal.urdf"),
        str(data / "log.csv"),
        "--loop",
        LOOP,
        "--out",
        str(work / "calibrated.urdf"),
        "--report",
        str(work / "report.json"),
        "--quiet",
    ]
    _, wall, cpu = _run(cmd + ([] if cv else ["--cv", "0"]), _env(mode))
    solver = json.loads((work / "report.json").read_text())["solver"]
    work_s = float(solver["seconds"]) + float(solver.get("validation_seconds", 0.0))
    work_cpu = float(solver.get("cpu_seconds", np.nan)) + float(solver.get("validation_cpu_seconds", 0.0))
    return wall, work_s, cpu, work_cpu


def import_time(mode: str) -> float:
    """Cumulative `-X importtime` of the command line (closedloop.cli.main and what it imports), seconds."""
    out, _, _ = _run([sys.executable, "-X", "importtime", "-c", "import closedloop.cli.main"], _env(mode))
    last = [ln for ln in out.stderr.splitlines() if re.search(r"\|\s+closedloop\.cli\.main$", ln)][-1]
    return int(last.split("|")[1]) * 1e-6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="a `closedloop simulate panda_weld --n 200 --seed 1` folder")
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure (median and best reported)")
    add_arguments(ap)
    args = ap.parse_args()
    modes = [m for m in args.threads if m in ("1", "2", "4", "default")]
    print(header())
    where = _run([sys.executable, "-c", "import closedloop; print(closedloop.__file__)"], _env("default"))[0]
    root = Path(where.stdout.strip()).parents[1]
    rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    print(f"code: {root} ({rev.stdout.strip() or 'not a git checkout'})")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        data = args.data or simulate(work / "sim")
        calibrate_once(data, work, "default", cv=False)  # warm-up (bytecode caches)
        for cond in conditions(args.loaded):
            with condition(cond) as cdesc:
                print(f"\n[{cdesc}]  median (best) of {args.repeat}; seconds")
                print(
                    f"{'threads':>8} {'command':>22} {'wall':>13} {'work':>13} {'wall - work':>13} {'cpu':>6} "
                    f"{'cpu - work cpu':>15}"
                )
                for mode in modes:
                    for cv in (True, False):
                        runs = np.array([calibrate_once(data, work, mode, cv) for _ in range(args.repeat)])
                        w, f, c, fc = runs[:, 0], runs[:, 1], runs[:, 2], runs[:, 3]
                        label = "calibrate" + ("" if cv else " --cv 0")
                        print(
                            f"{mode:>8} {label:>22} {np.median(w):>6.2f} ({w.min():.2f}) {np.median(f):>6.2f} "
                            f"({f.min():.2f}) {np.median(w - f):>6.2f} ({(w - f).min():.2f}) {np.median(c):>6.2f} "
                            f"{np.median(c - fc):>7.2f} ({(c - fc).min():.2f})",
                            flush=True,
                        )
                    imp = np.array([import_time(mode) for _ in range(args.repeat)])
                    plain = np.array(
                        [
                            _run([sys.executable, "-c", "import closedloop.cli.main"], _env(mode))[1:]
                            for _ in range(args.repeat)
                        ]
                    )
                    bare = np.array([_run([sys.executable, "-c", "pass"], _env(mode))[1] for _ in range(args.repeat)])
                    print(
                        f"{mode:>8} {'-X importtime':>22} closedloop.cli.main cumulative {np.median(imp):.3f} "
                        f"({imp.min():.3f}); python -c 'import closedloop.cli.main' wall {np.median(plain[:, 0]):.3f} "
                        f"({plain[:, 0].min():.3f}) cpu {np.median(plain[:, 1]):.3f}; python -c pass "
                        f"{np.median(bare):.3f}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
