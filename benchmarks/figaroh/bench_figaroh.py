"""Benchmark: closedloop vs FIGAROH on open-loop (tracker) calibration of a UR10.

One simulated dataset, built once with Pinocchio on a true UR10, is given to
both tools: a tool point on ``tool0`` measured in position by a tracker whose
frame is unknown, at random configurations within the joint limits.  Each tool
identifies its own parameter set (closedloop: joint placements, joint offsets,
tracker base, tool point; FIGAROH 1.0.2: ``full_params`` base parameters,
base frame, tool point) from 50 and 1,000 poses, then predicts the tracker
reading at 200 held-out configurations; the RMS of the prediction against the
noise-free truth is the held-out error.

FIGAROH runs in its own virtual environment (``--figaroh-python``, default
``/tmp/figaroh-venv/bin/python``; ``--make-venv`` creates it, see README.md),
in a separate process: this script calls itself there with ``--worker``, the
two processes exchange the dataset and the predictions as CSV/JSON files in
``--workdir``.

    python benchmarks/figaroh/bench_figaroh.py                 # table -> stdout and results.md
    python benchmarks/figaroh/bench_figaroh.py --make-venv     # first create the FIGAROH venv
    python benchmarks/figaroh/bench_figaroh.py --no-weld       # skip the weld-loop sizes

Not part of the test suite; nothing imports it.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
DEFAULT_VENV = Path("/tmp/figaroh-venv")
FIGAROH_VERSION = "1.0.2"
# FIGAROH's own imports (figaroh/__init__.py imports every subpackage); pin,
# numpy, scipy and PyYAML come from the project environment (--system-site-packages)
VENV_PACKAGES = ["pandas", "matplotlib", "meshcat", "numdifftools", "ndcurves", "picos", "rospkg"]

JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
TOOL = "tool0"
LOOP = "trk"
SIGMA_M = 1e-5  # tracker noise (m)
SIGMA_Q = 0.0  # joint-reading noise (rad)
TIP = [0.03, -0.02, 0.15]  # true tool point in tool0 (m)
ROUGH_TIP = [0.01, 0.01, 0.1]  # a rough user guess, off the wrist_3 axis
N_TRAIN = (50, 1000)
N_HELD = 200


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from machine import machine  # noqa: E402


def erd_robots() -> Path:
    import site

    for s in site.getsitepackages():
        p = Path(s) / "cmeel.prefix/share/example-robot-data/robots"
        if p.is_dir():
            return p
    raise SystemExit("example-robot-data not found")


# ---------------------------------------------------------------- dataset
def make_dataset(workdir: Path, seed: int = 0) -> dict:
    """True UR10 (nominal + random errors), readings, tracker measurements, held-out truth -> files."""
    import pinocchio as pin

    from closedloop.model.robot import RobotModel
    from closedloop.output.urdf import write_urdf

    rng = np.random.default_rng(seed)
    urdf = erd_robots() / "ur_description/urdf/ur10_robot.urdf"
    nominal = RobotModel.from_file(urdf)
    truth: dict[str, float] = {}
    for j in JOINTS:  # closedloop convention: joint origin O -> O * exp6(p)
        for f in ("x", "y", "z"):
            truth[f"{j}.{f}"] = float(rng.uniform(-2e-3, 2e-3))
        for f in ("rx", "ry", "rz"):
            truth[f"{j}.{f}"] = float(rng.uniform(-2e-3, 2e-3))
    offsets = rng.uniform(-0.02, 0.02, len(JOINTS))  # on the sensor: true angle = reading + offset
    true_urdf = workdir / "ur10_true.urdf"
    if true_urdf.exists():
        true_urdf.unlink()
    write_urdf(nominal, truth, true_urdf, fold_offsets=False)

    model = pin.buildModelFromUrdf(str(true_urdf))
    data = model.createData()
    fid = model.getFrameId(TOOL)
    iq = np.array([model.joints[model.getJointId(j)].idx_q for j in JOINTS])
    lo, hi = model.lowerPositionLimit[iq], model.upperPositionLimit[iq]
    X = pin.SE3(pin.exp3(np.array([0.3, -0.2, 2.5])), np.array([2.0, 0.5, 0.3]))  # tracker in the base frame
    tip = np.array(TIP)  # tool point in tool0

    def measure(readings: np.ndarray) -> np.ndarray:
        out = np.empty((len(readings), 3))
        for i, r in enumerate(readings):
            q = pin.neutral(model)
            q[iq] = r + offsets
            pin.framesForwardKinematics(model, data, q)
            out[i] = X.actInv(data.oMf[fid].act(tip))
        return out

    n = max(N_TRAIN)
    q_train = rng.uniform(lo, hi, (n, len(JOINTS)))
    m_train = measure(q_train) + rng.normal(0.0, SIGMA_M, (n, 3))
    r_train = q_train + (rng.normal(0.0, SIGMA_Q, q_train.shape) if SIGMA_Q else 0.0)
    q_held = rng.uniform(lo, hi, (N_HELD, len(JOINTS)))
    m_held = measure(q_held)  # noise-free truth

    write_csv(workdir / "train.csv", r_train, m_train)
    write_csv(workdir / "heldout.csv", q_held, m_held)
    json.dump(
        {
            "placement": truth,
            "offsets": dict(zip(JOINTS, offsets.tolist())),
            "tracker_in_base": {"translation": X.translation.tolist(), "rotvec": pin.log3(X.rotation).tolist()},
            "tip_in_tool0": tip.tolist(),
            "sigma_m": SIGMA_M,
            "sigma_q": SIGMA_Q,
            "seed": seed,
        },
        open(workdir / "truth.json", "w"),
        indent=1,
    )
    return {"urdf": urdf, "q_train": r_train, "m_train": m_train, "q_held": q_held, "m_held": m_held}


def write_csv(path: Path, q: np.ndarray, m: np.ndarray) -> None:
    """FIGAROH's layout (joint names, x1 y1 z1); closedloop reads the same arrays."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(JOINTS + ["x1", "y1", "z1"])
        for qi, mi in zip(q, m):
            w.writerow([repr(float(v)) for v in np.concatenate([qi, mi])])


def read_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    a = np.loadtxt(path, delimiter=",", skiprows=1)
    return a[:, :6], a[:, 6:9]


# ---------------------------------------------------------------- closedloop
def run_closedloop(
    urdf: Path, q: np.ndarray, m: np.ndarray, q_held: np.ndarray, initial_tip=None, options: dict | None = None
) -> dict:
    from closedloop.calibration.pipeline import CalibrationOptions, calibrate
    from closedloop.io.logs import JointLog
    from closedloop.loops import MeasuredPointLoop
    from closedloop.model.robot import RobotModel

    stages: dict[str, float] = {}

    def progress(stage, it, total=None, note=""):
        stages.setdefault(stage, time.perf_counter())

    t0 = time.perf_counter()
    robot = RobotModel.from_file(urdf)
    extra = {f"{LOOP}:{c}": m[:, k].copy() for k, c in enumerate("xyz")}
    log = JointLog(list(JOINTS), q, None, None, extra)
    res = calibrate(
        robot,
        log,
        [MeasuredPointLoop(LOOP, TOOL, sigma_t=SIGMA_M, initial_tip=initial_tip)],
        CalibrationOptions(**(options or {})),
        progress=progress,
    )
    t1 = time.perf_counter()
    prob = res.problem
    loop = prob.blocks[0].loop
    cols = [JOINTS.index(j) for j in prob.joints]
    # the held-out configurations with zero measurements: residual = prediction - 0 (loops hold no data)
    from closedloop.problem.problem import CalibrationProblem, LoopBlock

    held = CalibrationProblem(
        prob.robot,
        prob.joints,
        [LoopBlock(loop, q_held[:, cols], np.arange(1, len(q_held) + 1), None, np.zeros((len(q_held), 3)))],
        prob.priors,
    )
    pred = held.evaluate(res.fit.values, jacobian=False)[0].r
    return {
        "total": t1 - t0,
        "solve": t1 - stages.get("solving", t0),
        "params": len(res.fit.estimated),
        "pred": pred,
        "status": res.fit.solver_status,
        "iters": res.fit.iterations,
    }


# ---------------------------------------------------------------- FIGAROH (worker, in its venv)
def worker(workdir: Path, n: int, out: Path) -> None:
    """Runs inside the FIGAROH venv: calibrate on the first n rows of train.csv, predict heldout.csv."""
    import contextlib
    import io
    import logging

    import yaml

    t0 = time.perf_counter()
    import figaroh
    from figaroh.calibration.base_calibration import BaseCalibration
    from figaroh.calibration.calibration_tools import calc_updated_fkm
    from figaroh.tools.robot import Robot

    t_import = time.perf_counter() - t0
    logging.disable(logging.WARNING)

    class TrackerCalibration(BaseCalibration):
        """Cost as in figaroh-examples' UR10Calibration (SE(3) log-map residuals, body frame)."""

        def cost_function(self, var):
            PEEe = calc_updated_fkm(self.model, self.data, var, self.q_measured, self.calib_config)
            raw = self._compute_logmap_residuals(self.PEE_measured, PEEe)
            return self.apply_measurement_weighting(raw, pos_weight=1.0, orient_weight=0.5)

    run = workdir / f"figaroh_{n}_{os.environ.get('FIGAROH_METHOD', 'structural')}"
    run.mkdir(exist_ok=True)
    with open(workdir / "train.csv") as f:
        lines = f.readlines()
    (run / "train.csv").write_text("".join(lines[: n + 1]))
    cfg = yaml.safe_load(open(HERE / "ur10_point_tracker.yaml"))
    cfg["tasks"]["calibration"]["data"]["source_file"] = str(run / "train.csv")
    cfg["tasks"]["calibration"]["data"]["number_of_samples"] = n
    cfg["tasks"]["calibration"]["parameters"]["estimation"]["method"] = os.environ.get("FIGAROH_METHOD", "structural")
    yaml.safe_dump(cfg, open(run / "config.yaml", "w"))

    log = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(log):
        robot = Robot(
            str(erd_robots() / "ur_description/urdf/ur10_robot.urdf"), package_dirs=str(erd_robots().parent.parent)
        )
        calib = TrackerCalibration(robot, str(run / "config.yaml"))
        calib.calib_config["known_baseframe"] = False  # tracker frame unknown
        calib.calib_config["known_tipframe"] = False  # tool point unknown
        calib.initialize()
        t1 = time.perf_counter()
        result = calib.solve(enable_logging=False)
    t2 = time.perf_counter()
    (run / "figaroh_stdout.txt").write_text(log.getvalue())

    q_held, _ = read_csv(workdir / "heldout.csv")
    model = calib.model
    qh = np.tile(calib.calib_config["q0"], (len(q_held), 1))
    for k, j in enumerate(JOINTS):
        qh[:, model.joints[model.getJointId(j)].idx_q] = q_held[:, k]
    pcfg = dict(calib.calib_config, NbSample=len(q_held))
    pred = calc_updated_fkm(model, calib.data, result.x, qh, pcfg).reshape(3, len(q_held)).T
    json.dump(
        {
            "version": figaroh.__version__,
            "import": t_import,
            "setup": t1 - t0,
            "solve": t2 - t1,
            "total": t2 - t0,
            "params": len(result.x),
            "names": list(calib.calib_config["param_name"]),
            "success": bool(result.success),
            "nfev": int(result.nfev),
            "status": calib.STATUS,
            "outliers": list(map(int, getattr(calib, "outlier_indices", []))),
            "pred": pred.tolist(),
        },
        open(out, "w"),
    )


def run_figaroh(python: str, workdir: Path, n: int, method: str = "structural") -> dict:
    out = workdir / f"figaroh_{n}_{method}.json"
    if out.exists():
        out.unlink()
    t0 = time.perf_counter()
    p = subprocess.run(
        [python, str(Path(__file__).resolve()), "--worker", str(workdir), str(n), str(out)],
        capture_output=True,
        text=True,
        env=dict(os.environ, FIGAROH_METHOD=method),
    )
    wall = time.perf_counter() - t0
    if p.returncode != 0 or not out.exists():
        tail = (p.stderr or p.stdout).strip().splitlines()[-8:]
        return {"error": " | ".join(tail) or f"exit code {p.returncode}"}
    r = json.load(open(out))
    r["pred"] = np.array(r["pred"])
    r["process"] = wall
    return r


def make_venv(venv: Path) -> None:
    """A venv seeing the project's site-packages (pin 4.1, numpy, scipy); FIGAROH with --no-deps."""
    if not (venv / "bin/python").exists():
        subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)], check=True)
    pip = [str(venv / "bin/python"), "-m", "pip", "install", "-q"]
    subprocess.run(pip + ["--no-deps", f"figaroh=={FIGAROH_VERSION}"], check=True)
    subprocess.run(pip + VENV_PACKAGES, check=True)
    # --system-site-packages sees the *base* interpreter's packages: when the project itself runs in a
    # venv, give FIGAROH the same Pinocchio and robot files explicitly
    from importlib.metadata import version

    same = [f"{name}=={version(name)}" for name in ("pin", "example-robot-data", "numpy", "scipy")]
    subprocess.run(pip + same, check=True)


# ---------------------------------------------------------------- weld loop (closedloop alone)
def weld_table(sizes: list[int]) -> str:
    p = subprocess.run(
        [sys.executable, str(REPO / "benchmarks/bench_calibrate.py"), "--sizes", *map(str, sizes), "--repeat", "1"],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    if p.returncode != 0:
        return f"bench_calibrate.py failed: {(p.stderr or p.stdout).strip().splitlines()[-1:]}"
    return p.stdout.strip()


def rms(pred: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((pred - truth) ** 2, axis=1))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs=3, metavar=("WORKDIR", "N", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--figaroh-python", default=os.environ.get("FIGAROH_PYTHON", str(DEFAULT_VENV / "bin/python")))
    ap.add_argument("--make-venv", action="store_true", help=f"create {DEFAULT_VENV} first")
    ap.add_argument("--workdir", default="/tmp/closedloop_figaroh_bench")
    ap.add_argument("--no-weld", action="store_true", help="skip the 7-DOF weld-loop sizes")
    ap.add_argument("--weld-sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs per tool and size")
    ap.add_argument(
        "--figaroh-methods",
        nargs="+",
        default=["structural", "excitation"],
        help="FIGAROH estimation.method values (structural is its default; also map, map_cv, cv_subset)",
    )
    ap.add_argument("--output", default=str(HERE / "results.md"))
    args = ap.parse_args()
    if args.worker:
        worker(Path(args.worker[0]), int(args.worker[1]), Path(args.worker[2]))
        return
    if args.make_venv:
        make_venv(DEFAULT_VENV)

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    ds = make_dataset(workdir)
    t_data = time.perf_counter() - t

    rows = []
    notes = []
    for n in N_TRAIN:
        q, m = ds["q_train"][:n], ds["m_train"][:n]
        for label, tip, opts in (
            ("closedloop (defaults)", None, {}),
            ("closedloop (initial_tip, weighting='none')", ROUGH_TIP, {"weighting": "none"}),
        ):
            cl = min(
                (run_closedloop(ds["urdf"], q, m, ds["q_held"], tip, opts) for _ in range(args.repeat)),
                key=lambda r: r["total"],
            )
            note = f"{cl['status']}, {cl['iters']} iterations"
            if tip is not None:
                note += f"; initial_tip={ROUGH_TIP} (true tip {TIP}); joint noise is 0, so no EIV weighting"
            rows.append((label, n, cl["solve"], cl["total"], cl["params"], rms(cl["pred"], ds["m_held"]), note))
        if not Path(args.figaroh_python).exists():
            rows.append(("FIGAROH", n, None, None, None, None, f"no FIGAROH python at {args.figaroh_python}"))
            continue
        for method in args.figaroh_methods:
            runs = [run_figaroh(args.figaroh_python, workdir, n, method) for _ in range(args.repeat)]
            bad = [r for r in runs if "error" in r]
            if bad:
                rows.append((f"FIGAROH ({method})", n, None, None, None, None, "failed: " + bad[0]["error"][:300]))
                continue
            fg = min(runs, key=lambda r: r["total"])
            rows.append(
                (
                    f"FIGAROH {fg['version']} ({method})",
                    n,
                    fg["solve"],
                    fg["total"],
                    fg["params"],
                    rms(fg["pred"], ds["m_held"]),
                    f"{fg['status']}, scipy nfev {fg['nfev']}; import {fg['import']:.1f} s not counted",
                )
            )

    lines = [
        "# closedloop vs FIGAROH: UR10, tool point measured by a tracker in an unknown frame",
        "",
        f"Machine: {machine()}",
        "",
        "Truth: UR10 (example-robot-data) + uniform errors of +/-2 mm and +/-2 mrad on every joint placement, "
        f"+/-0.02 rad joint offsets; tracker noise {SIGMA_M:g} m, joint noise {SIGMA_Q:g} rad; random "
        f"configurations within the joint limits (dataset built in {t_data:.1f} s). Held-out error: RMS of the "
        f"predicted tracker reading on {N_HELD} held-out configurations against the noise-free truth. "
        "Total time includes loading the robot model and building the problem (FIGAROH: constructor, config "
        "parsing, `initialize()`); solve time is the least-squares solve (FIGAROH: `solve()`, its "
        "post-fit report included; closedloop: from the start of the solver stage).",
        "",
        "| tool | poses | solve [s] | total [s] | identified params | held-out RMS [mm] | notes |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for tool, n, s, tt, npar, err, note in rows:
        f = lambda v, fmt: "—" if v is None else format(v, fmt)
        lines.append(
            f"| {tool} | {n:,} | {f(s, '.3f')} | {f(tt, '.3f')} | {f(npar, 'd')} | "
            f"{'—' if err is None else f'{err * 1e3:.4f}'} | {note} |"
        )
    for n in N_TRAIN:
        for g in [r for r in rows if r[1] == n and r[0].startswith("FIGAROH") and r[2] is not None]:
            for c in [r for r in rows if r[1] == n and r[0].startswith("closedloop")]:
                notes.append(
                    f"- {n:,} poses, {c[0]} vs {g[0]}: {g[3] / c[3]:.1f}x faster in total, "
                    f"{g[2] / c[2]:.1f}x in the solve; held-out RMS {c[5] * 1e3:.4f} mm vs "
                    f"{g[5] * 1e3:.4f} mm."
                )
    lines += [""] + notes
    if not args.no_weld:
        lines += [
            "",
            "## closedloop alone: 7-DOF Panda weld loop (`benchmarks/bench_calibrate.py --repeat 1`)",
            "",
            "```",
            weld_table(args.weld_sizes),
            "```",
        ]
    text = "\n".join(lines) + "\n"
    print(text)
    Path(args.output).write_text(text)


if __name__ == "__main__":
    main()
