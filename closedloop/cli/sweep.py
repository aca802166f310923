"""`closedloop simulate --seeds 0-19 [--scenarios A,B] --jobs N | --ray ADDR --out DIR`: many datasets.

One dataset per (scenario, seed), each an independent job on ``closedloop.parallel.executor``: in
``DIR/seed_000/`` (one scenario) or ``DIR/SCENARIO/seed_000/`` (several).  Every dataset is
published whole by ``simulate`` (``sims.outputs.DATASET_FILES``, ``truth.json`` last), so a killed
sweep leaves whole datasets and no half one; run again, it skips the seeds whose ``truth.json``
names the same scenario, seed, size and ``--set`` values (resumable), simulates the rest, and refuses
(without ``--replace``) a folder holding another dataset.  A seed that fails is
recorded (``DIR/sweep.csv``, exit 1) and the others go on.  ``DIR/sweep.csv`` gets a row as each
dataset finishes and is rewritten whole, in (scenario, seed) order, at the end.  The results do not depend on the
engine: the seed of a dataset is its own (``simulate(scenario, n, seed)``), never a worker's.
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from closedloop.errors import InputError
from closedloop.progress import ProgressReporter

COLUMNS = ["scenario", "seed", "status", "configurations", "steps", "seconds", "configs_per_second", "error", "out"]


@dataclass
class SweepRow:
    """One dataset of a sweep: simulated now, found finished (resumed), or failed."""

    scenario: str
    seed: int
    status: str  # ok | resumed | failed
    configurations: int | None = None
    steps: int | None = None
    seconds: float | None = None
    configs_per_second: float | None = None
    error: str = ""
    out: str = ""


def parse_seeds(text: str) -> list[int]:
    """'0-19', '3,5,8', '0-4,10-12' -> the seeds, in order, without repeats."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not m:
            raise InputError(f"--seeds {text}: '{part}' is not a seed or a range A-B of whole numbers")
        a, b = int(m.group(1)), int(m.group(2) if m.group(2) is not None else m.group(1))
        if b < a:
            raise InputError(f"--seeds {text}: range '{part}' runs backwards")
        if b - a >= 100_000:
            raise InputError(f"--seeds {text}: range '{part}' has more than 100000 seeds")
        seeds.extend(s for s in range(a, b + 1) if s not in seeds)
    if not seeds:
        raise InputError(f"--seeds {text}: no seeds")
    return seeds


def dataset_dir(out: Path, scenario: str, seed: int, several: bool) -> Path:
    """Where the dataset of (scenario, seed) goes."""
    return (out / scenario if several else out) / f"seed_{seed:03d}"


def finished(
    folder: Path, scenario: str, seed: int, n: int | None = None, overrides: dict | None = None
) -> bool | None:
    """True when `folder` holds a whole dataset of this scenario, seed, size and settings (its truth.json,
    written last); None when it holds none; False when it holds another."""
    try:
        truth = json.loads((folder / "truth.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    same = truth.get("scenario") == scenario and truth.get("seed") == seed
    if n is not None:
        same = same and (truth.get("samples") or {}).get("recorded") == n
    settings = truth.get("settings") or {}
    norm = lambda v: json.loads(json.dumps(v))  # noqa: E731  (tuples as lists, as truth.json has them)
    return same and all(norm(v) == settings[k] for k, v in (overrides or {}).items() if k in settings)


def _sim_job(scenarios: dict, n: int, overrides: dict, payload: tuple[str, int, str]) -> dict:
    """One dataset (runs in a worker): register the scenario there (a YAML or --robot one), simulate."""
    from closedloop.sims import SCENARIOS, simulate

    name, seed, folder = payload
    SCENARIOS[name] = scenarios[name]
    res = simulate(name, n, seed, Path(folder), **overrides.get(name, {}))
    return {
        "configurations": len(res.readings),
        "steps": int(res.n_steps),
        "seconds": round(res.elapsed_s, 4),
        "configs_per_second": round(res.configs_per_second, 2),
    }


def run_sweep(
    scenarios: dict[str, Any],
    seeds: list[int],
    n: int,
    out: Path,
    overrides: dict | None = None,
    engine=None,
    progress: ProgressReporter | None = None,
    replace: bool = False,
) -> list[SweepRow]:
    """Simulate every (scenario, seed) not finished before, on `engine`; rows in (scenario, seed) order.

    scenarios: name -> ``sims.Scenario`` (sent to the workers, so YAML and --robot scenarios work
    there too); overrides: name -> ``SimSettings`` overrides.  With `replace`, finished datasets
    are simulated again.
    """
    from closedloop.parallel.executor import imap

    several = len(scenarios) > 1
    rows: dict[tuple[str, int], SweepRow] = {}
    todo: list[tuple[str, int, str]] = []
    for name in scenarios:
        for seed in seeds:
            folder = dataset_dir(out, name, seed, several)
            done = None if replace else finished(folder, name, seed, n, (overrides or {}).get(name))
            if done is False:
                raise InputError(
                    f"{folder}: holds another dataset (another scenario, seed, --n or --set); "
                    "give another --out or --replace to simulate it again"
                )
            if done:
                rows[name, seed] = SweepRow(name, seed, "resumed", out=str(folder))
            else:
                todo.append((name, seed, str(folder)))
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "sweep.csv", "w", newline="") as fh:  # streamed as datasets finish
        w = csv.DictWriter(fh, COLUMNS)
        w.writeheader()
        w.writerows(_csv_row(r) for r in rows.values())
        fh.flush()
        for o in imap(
            _sim_job, todo, engine, shared=(scenarios, int(n), overrides or {}), progress=progress, task="simulate"
        ):
            name, seed, job_out = todo[o.index]
            rows[name, seed] = (
                SweepRow(name, seed, "ok", out=job_out, **o.value)
                if o.ok
                else SweepRow(name, seed, "failed", error=o.error or "", seconds=round(o.seconds, 4), out=job_out)
            )
            w.writerow(_csv_row(rows[name, seed]))
            fh.flush()
    ordered = [rows[name, seed] for name in scenarios for seed in seeds]
    _write_summary(out / "sweep.csv", ordered)  # rewritten whole, in (scenario, seed) order
    return ordered


def _csv_row(r: SweepRow) -> dict:
    return {k: ("" if v is None else v) for k, v in asdict(r).items()}


def _write_summary(path: Path, rows: list[SweepRow]) -> None:
    from closedloop.io.files import atomic_write

    def writer(tmp: str) -> None:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, COLUMNS)
            w.writeheader()
            w.writerows(_csv_row(r) for r in rows)

    atomic_write(path, writer)


def add_sweep_options(s) -> None:
    """--seeds / --scenarios / --jobs / --ray on the `simulate` parser; a plain simulate without them."""
    from closedloop.parallel.executor import add_arguments

    s.add_argument(
        "--seeds",
        metavar="A-B[,C,...]",
        help="simulate one dataset per seed into OUT/seed_NNN/ (resumable; with --jobs / --ray in parallel)",
    )
    s.add_argument(
        "--scenarios",
        "--scenario",
        metavar="A,B,...",
        help="with --seeds: several scenarios, into OUT/SCENARIO/seed_NNN/",
    )
    add_arguments(s)
    s.set_defaults(func=cmd_simulate_sweep)


def cmd_simulate_sweep(args) -> int:
    """`simulate`, or a sweep when --seeds / --scenarios is given."""
    import sys

    from closedloop.cli.simulate import cmd_simulate

    several = [x for x in (getattr(args, "scenarios", None) or "").split(",") if x.strip()]
    if getattr(args, "seeds", None) is None and len(several) == 1 and not args.scenario:
        args.scenario, args.scenarios = several[0].strip(), None  # `--scenario X` (an abbreviation): one dataset
    if getattr(args, "seeds", None) is None and getattr(args, "scenarios", None) is None:
        if getattr(args, "jobs", None) is not None or getattr(args, "ray", None):
            raise InputError("simulate: --jobs / --ray run a sweep: give --seeds (e.g. --seeds 0-19)")
        return cmd_simulate(args)
    from closedloop.cli.progress import ProgressDisplay
    from closedloop.parallel.executor import engine_from_args
    from closedloop.run.options import check_number

    scenarios = _scenarios(args)
    seeds = parse_seeds(args.seeds if args.seeds is not None else str(args.seed))
    if getattr(args, "poses", None):
        raise InputError("simulate: --poses records one dataset's configurations: not with --seeds or --scenarios")
    n = check_number("--n", 200 if args.n is None else args.n, 1, 10**7, integer=True)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a folder")
    overrides = {name: _overrides(args, sc) for name, sc in scenarios.items()}
    with engine_from_args(args) as eng, ProgressDisplay(args.quiet) as shown:
        rows = run_sweep(scenarios, seeds, n, out, overrides, eng, shown, replace=getattr(args, "replace", False))
    ran = [r for r in rows if r.status == "ok"]
    failed = [r for r in rows if r.status == "failed"]
    rate = sum(r.configurations or 0 for r in ran) / max(sum(r.seconds or 0.0 for r in ran), 1e-9)
    if not args.quiet:
        print(
            f"{len(ran)} dataset(s) simulated on {eng.name} ({eng.workers} worker(s)), "
            f"{sum(r.status == 'resumed' for r in rows)} finished earlier (not redone), {len(failed)} failed; "
            f"{rate:.0f} configurations/s per job -> {out / 'sweep.csv'}"
        )
    for r in failed:
        print(f"  failed: {r.scenario} seed {r.seed}: {r.error}", file=sys.stderr)
    return 1 if failed else 0


def _scenarios(args) -> dict[str, Any]:
    """The scenarios of the sweep, by name: --scenarios A,B (names or YAML files) or the one of `simulate`."""
    from closedloop.cli.simulate import resolve_scenario
    from closedloop.sims import SCENARIOS
    from closedloop.sims.scenarios import CAMERA_SCENARIOS, unknown_scenario

    names = [s.strip() for s in args.scenarios.split(",") if s.strip()] if args.scenarios else [None]
    out: dict[str, Any] = {}
    for given in names:
        if given is not None:
            args.scenario = given
        name = resolve_scenario(args)
        if name in CAMERA_SCENARIOS:
            raise InputError(
                f"--scenarios: {name} is a head-camera scenario, simulated alone (closedloop simulate {name})"
            )
        if name not in SCENARIOS:
            raise unknown_scenario(name)
        out[name] = SCENARIOS[name]
    return out


def _overrides(args, sc) -> dict:
    from closedloop.cli.parse import sim_overrides

    return sim_overrides(args.set, sc.settings)
