"""A model on data: closure and loop-point spread with the robot untouched.

Any model (the nominal URDF, a calibrated one, another tool's) is judged on
any data the same way: the robot's parameters are held, and of the loops'
unknowns only what is new at each place is fitted, by plain least squares on
the loop-closure residual (eq. 3.8): a socket's position, a fixture's pose, a
plane, a hinge.  What a calibration estimated once for all data is predicted,
not refitted: a shared group's parameters (``tip=@ball``), tool points and
tool frames, a measuring instrument (a tracker's base, cameras) are held at
the calibration's values where it has them (`held_values`; ``refit=True``
fits every unknown, as a fresh fit would).  The closure that remains is
reported per loop:

* ``rms_m`` / ``rms_rad``: RMS of the translation / rotation closure norms;
* ``mean_m``: the mean translation closure norm (for a point loop with its
  point fitted, the mean distance of the tool point to its mean: the spread
  a ball-and-socket rig quotes);
* ``max_m``; ``rms_px`` for camera loops (image-point error).

Known distances (`problem.distances.DistanceLoop`) are left out: they are not
closures of the robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from closedloop.errors import ClosedLoopError
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel


@dataclass
class Evaluation:
    """A model's closure on a log."""

    model: str
    loops: list[dict]
    rms_m: float | None
    mean_m: float | None
    rms_rad: float | None
    values: dict = field(default_factory=dict)  # the fitted loop unknowns
    held: dict = field(default_factory=dict)  # the loop unknowns taken from the calibration (not fitted)
    residuals: list = field(default_factory=list)  # per loop, the closure residual (N, dim)

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "rms_m": self.rms_m,
            "mean_m": self.mean_m,
            "rms_rad": self.rms_rad,
            "loops": self.loops,
            "loop_parameters": self.values,
            "held_from_calibration": self.held,
        }


#: loop fields that describe the tool, not the place: held at a calibration's value (`held_values`)
TOOL_FIELD_PREFIXES = ("tip_", "tool_")


def predicted(loop: Loop, field_name: str, name: str) -> bool:
    """Whether a loop parameter is estimated once for all data (held at the calibration's value).

    A shared group's parameter (``tip=@ball``: its name is the group's), a tool point or tool frame,
    and every parameter of a measuring instrument (a measured loop's sensor base, a camera loop's
    cameras) are; what is new at each place (a socket's position, a fixture's pose, a plane, a
    hinge, a passive chain's placement) is not.
    """
    own = name == f"{loop.name}.{field_name}"
    if not own:
        return True
    if field_name.startswith(TOOL_FIELD_PREFIXES):
        return True
    kind = type(loop).__name__
    return kind.startswith("Measured") or kind.startswith("Camera")


def held_values(problem, calibration: dict[str, float] | None, places: bool = True) -> dict[str, float]:
    """The loop parameters of `problem` to hold at `calibration`'s values: the `predicted` ones it has,
    and with `places` False every one it has."""
    if not calibration:
        return {}
    out = {}
    for b, cols in zip(problem.blocks, problem.loop_columns):
        for k, p in zip(cols, b.loop.parameters()):
            name = problem.names[k]
            if name in calibration and (not places or predicted(b.loop, p.field, name)):
                out[name] = float(calibration[name])
    return out


def evaluate_model(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    values: dict[str, float] | None = None,
    label: str = "model",
    max_iter: int = 100,
    calibration: dict[str, float] | None = None,
    refit: bool = False,
    places: bool = True,
) -> Evaluation:
    """Closure of `robot` (its parameters set from `values` by name, e.g. a calibration's or a sensor
    file's ``<joint>.scale`` / ``<joint>.compliance``) on `log_`.

    The robot is held; of the loops' unknowns those a calibration estimated once for all data
    (`predicted`) are held at `calibration`'s values (name -> value, e.g. a report's parameters) and
    the others are fitted (unweighted); with `refit` every loop unknown is fitted; with `places`
    False every loop unknown `calibration` has is held (the calibration's own places, predicted).
    """
    from closedloop.calibration.pipeline import build_problem
    from closedloop.estimate.lm import SolverOptions
    from closedloop.estimate.residual import plain_stage
    from closedloop.problem.shared import initial_shared, refine_unheld

    loops = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    problem = build_problem(robot, log_, loops)
    x = problem.nominal
    for k, name in enumerate(problem.names[: problem.n_robot]):
        if values and name in values:
            x[k] = values[name]
    held = {} if refit else held_values(problem, calibration, places)
    inits = [problem.initialize_loop(x, bi) if cols.size else None for bi, cols in enumerate(problem.loop_columns)]
    x = initial_shared(problem, x, inits)
    for n, v in held.items():
        x[problem.index[n]] = v
    if held:
        x = refine_unheld(problem, x, np.array([n in held for n in problem.names], dtype=bool))
    est = sorted({int(k) for c in problem.loop_columns for k in c if problem.names[k] not in held})
    if est:
        scale = np.array([p.prior for p in problem.params])
        st = plain_stage(problem, x, x[est], est, scale, SolverOptions(max_iter=max_iter), None)
        x = st.fun.full(st.solution.x)
    evals = problem.evaluate(x, False)
    rows, t_all, w_all = [], [], []
    for b, ev in zip(problem.blocks, evals):
        lp = b.loop
        t = np.linalg.norm(ev.r[:, list(lp.translation_rows)], axis=1) if lp.translation_rows else None
        w = np.linalg.norm(ev.r[:, list(lp.rotation_rows)], axis=1) if lp.rotation_rows else None
        px = np.linalg.norm(ev.r[:, list(lp.pixel_rows)].reshape(-1, 2), axis=1) if lp.pixel_rows else None
        if px is not None and ev.valid is not None:
            px = px[ev.valid[:, list(lp.pixel_rows)].reshape(-1, 2).all(axis=1)]
        rows.append(
            {
                "loop": lp.name,
                "n": int(ev.r.shape[0]),
                "rms_m": None if t is None else float(np.sqrt(np.mean(t**2))),
                "mean_m": None if t is None else float(np.mean(t)),
                "max_m": None if t is None else float(np.max(t)),
                "rms_rad": None if w is None else float(np.sqrt(np.mean(w**2))),
                "rms_px": None if px is None or not px.size else float(np.sqrt(np.mean(px**2))),
            }
        )
        if t is not None:
            t_all.append(t)
        if w is not None:
            w_all.append(w)
    t = np.concatenate(t_all) if t_all else None
    w = np.concatenate(w_all) if w_all else None
    fitted = {problem.names[k]: float(x[k]) for k in est}
    return Evaluation(
        label,
        rows,
        None if t is None else float(np.sqrt(np.mean(t**2))),
        None if t is None else float(np.mean(t)),
        None if w is None else float(np.sqrt(np.mean(w**2))),
        fitted,
        held,
        [ev.r for ev in evals],
    )


def evaluate_result(
    result, log_: JointLog, loops: list[Loop], label: str = "calibrated", refit: bool = False
) -> Evaluation:
    """`evaluate_model` with a calibration's robot parameters; what it estimated once for all data
    (`predicted`: shared groups, tool points, instruments) is held at its values unless `refit`."""
    return evaluate_fitted(result.problem, result.fit.values, log_, loops, label, refit)


def evaluate_fitted(
    problem, x: np.ndarray, log_: JointLog, loops: list[Loop], label: str = "calibrated", refit: bool = False
) -> Evaluation:
    """`evaluate_result` for the values `x` of a calibration problem (a refit's, `validation.refit`)."""
    n = problem.n_robot
    values = {name: float(v) for name, v in zip(problem.names[:n], x[:n])}
    loop_values = {name: float(v) for name, v in zip(problem.names[n:], x[n:])}
    return evaluate_model(problem.robot, log_, loops, values, label, calibration=loop_values, refit=refit)


def table(evals: list[Evaluation]) -> str:
    """A plain-text table: one row per model, one column per loop (mean | RMS closure, mm)."""
    loops = [r["loop"] for r in evals[0].loops] if evals else []
    width = max([len(e.model) for e in evals] + [5])
    head = f"{'model':<{width}}  " + "  ".join(f"{lp:>14}" for lp in loops) + f"  {'all (mean/RMS)':>16}"
    lines = [head]
    for e in evals:
        cells = []
        for r in e.loops:
            if r["rms_m"] is not None:
                cells.append(f"{r['mean_m'] * 1e3:6.3f}/{r['rms_m'] * 1e3:6.3f}")
            elif r["rms_rad"] is not None:
                cells.append(f"{r['rms_rad'] * 1e3:9.4f} mrad")
            else:
                cells.append(f"{r['rms_px']:9.4f} px" if r["rms_px"] is not None else "-")
        tot = f"{e.mean_m * 1e3:.3f}/{e.rms_m * 1e3:.3f} mm" if e.rms_m is not None and e.mean_m is not None else ""
        lines.append(f"{e.model:<{width}}  " + "  ".join(f"{c:>14}" for c in cells) + f"  {tot:>16}")
    return "\n".join(lines)


#: an observed closure within this factor of the predicted one is "within prediction" (`compare_prediction`)
WITHIN = 2.0


def compare_prediction(
    ev: Evaluation, report: dict, robot: RobotModel, log_: JointLog, loops: list[Loop], values: dict | None = None
) -> list[dict]:
    """The calibration's prediction beside what `evaluate_model` observed on `log_`, per loop.

    The closure of a calibrated model on configurations it was not fitted to is, to first order, the
    model's error at them with the loop's place refitted, and the readings' noise.  The first is the
    report's parameter uncertainty (`accuracy.workspace.covariance`, the one its workspace prediction
    propagates) propagated to these configurations (`closedloop.analysis.accuracy.predict_closure`); the
    second the fit's own closure RMS (`residuals.after`): predicted RMS = sqrt(model^2 + fit^2), for
    positions and rotations.  Rows: loop, unit, observed and predicted RMS, their ratio; [] where the
    report has no prediction.

    The covariance is of the report's parameters, corrections of the model the calibration started from: it
    is propagated there, at the report's values (`_calibrated_from`), not on the written model's frames,
    where its columns turn by the folded corrections (a joint offset of 10 mrad turns the slides of its
    frame by as much) and the strong correlations of a weakly determined set no longer cancel (a tracker's
    closure: 4.9 um predicted there, 39 um on the written model's frames).
    """
    from closedloop.analysis.accuracy import predict_closure
    from closedloop.calibration.pipeline import build_problem

    acc = report.get("accuracy") if isinstance(report, dict) else None
    ws = acc.get("workspace") if isinstance(acc, dict) else None
    cov = ws.get("covariance") if isinstance(ws, dict) else None
    if not isinstance(cov, dict) or not cov.get("parameters"):
        return []
    loops = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    start, calibrated = _calibrated_from(report, robot)
    problem = build_problem(start, log_, loops)
    x = problem.nominal
    for name, v in {**calibrated, **(values or {}), **ev.values, **ev.held}.items():
        if name in problem.index:
            x[problem.index[name]] = float(v)
    model = {r["loop"]: r for r in predict_closure(problem, x, list(cov["parameters"]), np.array(cov["matrix"]))}
    after = {r.get("loop"): r for r in (report.get("residuals") or {}).get("after", []) if isinstance(r, dict)}
    out = []
    for lp in ev.loops:
        m, fit = model.get(lp["loop"]), after.get(lp["loop"], {})
        if m is None:
            continue
        for unit in ("m", "rad"):
            obs, part = lp.get(f"rms_{unit}"), m.get(f"rms_{unit}")
            if obs is None or part is None:
                continue
            p = float(np.hypot(part, fit.get(f"rms_{unit}") or 0.0))
            out.append(
                {
                    "loop": lp["loop"],
                    "unit": unit,
                    "observed_rms": float(obs),
                    "predicted_rms": p,
                    "ratio": float(obs) / p if p > 0 else None,
                }
            )
    return out


def _calibrated_from(report: dict, robot: RobotModel) -> tuple[RobotModel, dict[str, float]]:
    """The model a report's parameters are corrections of, and the report's calibrated values: its model file
    where it is still there, else the written model at the geometry it was calibrated from
    (`RobotModel.calibrated_from_model`, a calibrated URDF); else the written model itself, with no value."""
    from pathlib import Path

    values = {
        str(p["name"]): float(p["calibrated"])
        for p in report.get("parameters") or []
        if isinstance(p, dict) and isinstance(p.get("calibrated"), (int, float))
    }
    src = report.get("model")
    if isinstance(src, str) and Path(src).is_file():
        try:
            return RobotModel.from_file(src), values
        except ClosedLoopError:
            pass
    start = robot.calibrated_from_model()
    return (start, values) if start is not robot else (robot, {})


def prediction_lines(model: str, rows: list[dict]) -> list[str]:
    """The comparison of `compare_prediction` as lines, and the finding: within prediction or not."""
    if not rows:
        return []
    f = {"m": (1e3, "mm"), "rad": (1e3, "mrad")}
    lines = []
    for r in rows:
        k, u = f[r["unit"]]
        ratio = "" if r["ratio"] is None else f" (ratio {r['ratio']:.2f})"
        lines.append(
            f"  {model}: loop {r['loop']}: closure RMS {r['observed_rms'] * k:.4g} {u} observed, "
            f"{r['predicted_rms'] * k:.4g} {u} predicted by its calibration{ratio}"
        )
    out = [r for r in rows if r["ratio"] is not None and r["ratio"] > WITHIN]
    below = [r for r in rows if r["ratio"] is not None and r["ratio"] < 1.0 / WITHIN]
    if out:
        lines.append(
            f"  {model}: observed NOT within prediction: "
            + ", ".join(f"loop {r['loop']} {r['ratio']:.2g}x ({r['unit']})" for r in out)
        )
    elif below:  # an expected RMS, not a bound: a closure far under it says the prediction is loose here
        lines.append(
            f"  {model}: observed below prediction: "
            + ", ".join(f"loop {r['loop']} {r['ratio']:.2g}x ({r['unit']})" for r in below)
            + " (the calibration predicts more error at these configurations than they show: its error bars "
            "are wide here, or these configurations lie where the data it was fitted to already were)"
        )
    else:
        lines.append(f"  {model}: observed within prediction (within {WITHIN:g}x either way)")
    return lines
