"""A model on data: closure and loop-point spread with the robot untouched.

Any model (the nominal URDF, a calibrated one, another tool's) is judged on
any data the same way: the robot's parameters are held, the loops' own
unknowns (contact points, tool points, closures; shared ones once) are
fitted by plain least squares on the loop-closure residual (eq. 3.8), and
the closure that remains is reported per loop:

* ``rms_m`` / ``rms_rad``: RMS of the translation / rotation closure norms;
* ``mean_m``: the mean translation closure norm (for a point loop with its
  point fitted, the mean distance of the tool point to its mean: the spread
  a ball-and-socket rig quotes);
* ``max_m``; ``rms_px`` for camera loops (image-point error).

Known distances (`constraints.DistanceLoop`) are left out: they are not
closures of the robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "rms_m": self.rms_m,
            "mean_m": self.mean_m,
            "rms_rad": self.rms_rad,
            "loops": self.loops,
            "loop_parameters": self.values,
        }


def evaluate_model(
    robot: RobotModel,
    log_: JointLog,
    loops: list[Loop],
    values: dict[str, float] | None = None,
    label: str = "model",
    max_iter: int = 100,
) -> Evaluation:
    """Closure of `robot` (its parameters set from `values` by name, e.g. a calibration's) on `log_`.

    Only the loops' own unknowns are fitted (unweighted), the robot is held.
    """
    from closedloop.calibration.pipeline import build_problem
    from closedloop.estimate.lm import SolverOptions
    from closedloop.estimate.stages import plain_stage
    from closedloop.problem.shared import initial_shared

    loops = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    problem = build_problem(robot, log_, loops)
    x = problem.nominal
    for k, name in enumerate(problem.names[: problem.n_robot]):
        if values and name in values:
            x[k] = values[name]
    inits = [problem.initialize_loop(x, bi) if cols.size else None for bi, cols in enumerate(problem.loop_columns)]
    x = initial_shared(problem, x, inits)
    est = sorted({int(k) for c in problem.loop_columns for k in c})
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
    )


def evaluate_result(result, log_: JointLog, loops: list[Loop], label: str = "calibrated") -> Evaluation:
    """`evaluate_model` with a calibration's robot parameters."""
    prob = result.problem
    values = {n: float(v) for n, v in zip(prob.names[: prob.n_robot], result.values[: prob.n_robot])}
    return evaluate_model(prob.robot, log_, loops, values, label)


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
        tot = f"{e.mean_m * 1e3:.3f}/{e.rms_m * 1e3:.3f} mm" if e.rms_m is not None else ""
        lines.append(f"{e.model:<{width}}  " + "  ".join(f"{c:>14}" for c in cells) + f"  {tot:>16}")
    return "\n".join(lines)
