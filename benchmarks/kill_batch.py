"""Kill `closedloop batch --jobs 2` at random moments: no process may be left 3 s later, no job folder
finished after the kill, none half written; SIGINT/SIGTERM end with one line and exit 130/143.

    python benchmarks/kill_batch.py [--kills 12] [--jobs 4]

Each round starts a fresh batch of `--jobs` 200-row weld calibrations (10 folds each) on a 2-worker
local pool and sends SIGKILL, SIGINT (to the process group, as Ctrl-C) or SIGTERM (to the batch) after
a delay drawn uniformly over 0.3-4 s after the start (pool starting, jobs running, jobs finishing).
Prints one line per round and the totals.

Measured (2-core VM, load 4-9, 4 jobs of ~2.5 s each): 12 rounds (4 each of SIGKILL, group SIGINT,
SIGTERM, 9 of them while jobs ran): 0 processes left 3 s later, 0 jobs finished after the kill, 0 half
written; every SIGINT/SIGTERM one line and exit 130/143.  (After a SIGKILL the multiprocessing resource
tracker, which outlives the batch by design, may print its 2-line "leaked semaphore" warning.)
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]

from machine import header  # noqa: E402

WELD = "weld:frame=panda_hand,name=fixture"


def _inputs(d: Path, n_jobs: int) -> Path:
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.loops import WeldLoop
    from closedloop.model.robot import RobotModel
    from closedloop.studies.truth import make_dataset

    (d / "panda.urdf").write_text(nominal_urdf("panda"))
    robot = RobotModel.from_file(d / "panda.urdf")
    ds = make_dataset(
        robot, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 200, np.random.default_rng(5)
    )
    ds.log().write_csv(d / "log.csv")
    doc = {
        "defaults": {"model": str(d / "panda.urdf"), "log": str(d / "log.csv"), "loops": [WELD], "cv": 10},
        "jobs": [{"name": f"j{i}", "out": f"out/j{i}"} for i in range(n_jobs)],
    }
    (d / "m.yaml").write_text(yaml.safe_dump(doc))
    return d / "m.yaml"


def _alive(pids: set[int]) -> list[int]:
    out = []
    for q in pids:
        try:
            if Path(f"/proc/{q}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                out.append(q)
        except OSError:
            pass
    return out


def one_round(manifest: Path, how: str, delay: float, work: Path) -> dict:
    from closedloop.fleet.batch import descendants

    (work / "m.yaml").write_text(manifest.read_text())
    with (work / "err.txt").open("w") as err:
        p = subprocess.Popen(
            [sys.executable, "-m", "closedloop.cli.main", "batch", str(work / "m.yaml"), "--jobs", "2", "--quiet"],
            stdout=subprocess.DEVNULL,
            stderr=err,
            cwd=work,
            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
            preexec_fn=lambda: (os.setpgid(0, 0), signal.signal(signal.SIGINT, signal.SIG_DFL)),
        )
        seen: set[int] = set()
        t0 = time.monotonic()
        while time.monotonic() - t0 < delay and p.poll() is None:
            seen |= set(descendants(p.pid))
            time.sleep(0.02)
        sig = {"SIGKILL": signal.SIGKILL, "SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM}[how]
        if p.poll() is None:
            os.killpg(p.pid, sig) if how == "SIGINT" else p.send_signal(sig)
        p.wait(timeout=60)
    out = work / "out"
    folders = sorted(q.name for q in out.iterdir()) if out.exists() else []
    time.sleep(3.0)
    after = sorted(q.name for q in out.iterdir()) if out.exists() else []
    lines = (work / "err.txt").read_text().strip().splitlines()
    return {
        "how": how,
        "delay": delay,
        "rc": p.returncode,
        "workers_seen": len(seen),
        "left": len(_alive(seen)),
        "finished_after_kill": len(set(after) - set(folders)),
        "half_written": sum(1 for f in folders if not f.startswith(".") and not (out / f / "done.json").exists()),
        "stderr_lines": len(lines),
        "done": sum(1 for f in folders if not f.startswith(".")),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=int, default=12)
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(header())
    rng = np.random.default_rng(args.seed)
    hows = ["SIGKILL", "SIGINT", "SIGTERM"]
    with tempfile.TemporaryDirectory(prefix="kill-batch-") as tmp:
        manifest = _inputs(Path(tmp), args.jobs)
        rows = []
        for k in range(args.kills):
            work = Path(tmp) / f"r{k}"
            work.mkdir()
            r = one_round(manifest, hows[k % 3], float(rng.uniform(0.3, 4.0)), work)
            rows.append(r)
            print(
                f"{r['how']:<8} after {r['delay']:4.1f} s: exit {r['rc']:>4}, {r['workers_seen']} processes seen, "
                f"{r['left']} left 3 s later, {r['done']} job(s) done, {r['finished_after_kill']} finished after the "
                f"kill, {r['half_written']} half written, {r['stderr_lines']} stderr line(s)",
                flush=True,
            )
    bad = [
        r
        for r in rows
        if r["left"]
        or r["finished_after_kill"]
        or r["half_written"]
        or (r["how"] != "SIGKILL" and r["rc"] != 0 and (r["stderr_lines"] != 1 or r["rc"] not in (130, 143)))
    ]
    print(f"{len(rows)} rounds, {len(bad)} with a process left, a late or half job, or a noisy interrupt")


if __name__ == "__main__":
    main()
