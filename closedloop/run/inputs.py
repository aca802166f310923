"""A run's inputs: the robot's loops, the joint log (a CSV, a ROS bag, or each loop's own file) with its
torques, and the known distances, blocks and lengths of a rig; how the readings are weighted.

Used by `closedloop.run.calibrate` and by ``closedloop evaluate`` (which reads its log alike).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from closedloop.errors import InputError


def read_inputs(
    log_path: str | None,
    robot,
    loops: list,
    degrees: bool = False,
    order: list[str] | None = None,
    notes: list[str] | None = None,
):
    """The joint log: the positional file (CSV or bag), or each loop's own ``log=`` file (one per fixture);
    refused where most readings of a joint lie far beyond its limits (`io.logs.check_angle_units`) or
    where its ``loop`` column names no loop given (`io.logs.check_loop_column`); with the model's gravity
    torques where it logs none (`with_gravity_torques`).  A bag's extraction is said in `notes`."""
    from closedloop.io.logs import check_angle_units, check_loop_column

    lg = _read(log_path, robot, loops, degrees, order, notes if notes is not None else [])
    check_angle_units(lg, robot, degrees)
    check_loop_column(lg, [lp.name for lp in loops])
    return with_gravity_torques(lg, robot)


def with_gravity_torques(lg, robot):
    """The log with ``tau:<joint>`` columns from the model's inertials (`RobotModel.gravity_torques`) when it
    carries none and the model has masses; otherwise as it is.  The compliance model (theta' = k theta +
    theta_off - c tau) then needs no torque logging on a robot that carries only itself; logged torques
    always win.  `torque_source` says which: 'log', 'gravity' or None."""
    present = [j for j in robot.joint_names if f"tau:{j}" in lg.extra]
    if present or not robot.has_inertias:
        lg.torque_source = "log" if present else None
        return lg
    known = [j for j in robot.joint_names if j in lg.joints]
    tau = robot.gravity_torques(lg.columns(known), known)
    lg.extra.update({f"tau:{j}": tau[:, k] for k, j in enumerate(known)})
    lg.torque_source = "gravity"
    return lg


def _read(log_path: str | None, robot, loops: list, degrees: bool, order: list[str] | None, notes: list[str]):
    from closedloop.io.logs import read_log, read_loop_logs

    linear = [j for j, info in robot.joints.items() if info.kind == "prismatic"]
    real = [lp for lp in loops if not getattr(lp, "parameter_only", False)]
    own = [lp for lp in real if getattr(lp, "log_path", None)]
    if own:
        if len(own) != len(real):
            missing = [lp.name for lp in real if not getattr(lp, "log_path", None)]
            raise InputError(
                f"loop(s) {', '.join(missing)} have no log=FILE while others have: give every loop "
                "its file, or one log with a 'loop' column"
            )
        if log_path:
            raise InputError(f"{log_path}: the loops name their own log files (log=...); give no log besides")
        return read_loop_logs([(lp.name, lp.log_path) for lp in own], robot.joint_names, degrees, linear, order)
    if not log_path:
        raise InputError("no log given: name the CSV log (or each loop's file with --loop ...,log=FILE)")
    if order:
        return read_log(log_path, robot.joint_names, degrees, linear, order)
    if Path(log_path).suffix.lower() != ".csv":  # the bag reader is not loaded for a CSV log
        from closedloop.io.bags import extract, is_bag

        if is_bag(log_path):
            lg, samples = extract(log_path, robot.joint_names)
            notes.append(f"{log_path}: {len(samples)} standstills extracted")
            return lg
    return read_log(log_path, robot.joint_names, degrees=degrees, linear=linear)


@dataclass(frozen=True)
class RunInputs:
    """What a run reads before its fit: the robot, its loops (with the rig's known distances, blocks and
    lengths), the log and its name, the k-fold count for its rows, and the fit's options."""

    robot: Any  # closedloop.model.robot.RobotModel
    loops: list
    log: Any  # closedloop.io.logs.JointLog
    log_name: str
    folds: int
    fit: Any  # closedloop.records.CalibrationOptions
    weighting_note: str | None = None
    messages: list[str] = field(default_factory=list)  # what the reading has to say (a bag's standstills)
    geometry: list[str] = field(default_factory=list)  # warnings on the loops' geometry (`check_loop_geometry`)


def load_inputs(o) -> RunInputs:
    """The run's inputs (`RunInputs`) from its options (`closedloop.run.options.CalibrateOptions`): the
    model and the calibrated model's format, the loops, the log and its loop column, the k-fold count
    (`cv`, or 5, fewer on a shorter log), the weighting, the fit's options."""
    from closedloop.calibration.pipeline import CalibrationOptions
    from closedloop.calibration.verdict import VerdictRules
    from closedloop.model.parameters import fix_values
    from closedloop.model.robot import RobotModel
    from closedloop.output.urdf import check_model_output

    weights, note = weighting(o)  # what the options alone decide, first
    fit = CalibrationOptions(
        identify=o.identify,
        fix=fix_values(o.fix),
        noise=o.noise,
        weighting=weights,
        max_iter=o.max_iter,
        snr=o.snr,
        bounds=dict(o.bound),
        robust=None if o.robust == "off" else o.robust,
        threads=o.threads,
        rules=o.rules if o.rules is not None else VerdictRules(),
    )
    robot = RobotModel.from_file(o.model)
    check_model_output(robot.kind, o.out, o.model)
    loops = run_loops(o, robot)
    messages: list[str] = []
    lg = read_inputs(o.log, robot, loops, o.degrees, o.joints, messages)
    geometry = check_loop_geometry(o.model, robot, lg, loops, o.loop)  # before any work
    messages += [f"warning: {w}" for w in geometry]
    log_name = o.log or str(lg.source)
    k = o.folds
    if k > len(lg):
        if o.cv is not None:
            raise InputError(f"--cv {k}: more folds than the {len(lg)} rows of {log_name}")
        k = len(lg) if len(lg) >= 2 else 0
    return RunInputs(robot, loops, lg, log_name, k, fit, note, messages, geometry)


def run_loops(options, robot) -> list:
    """The loops of `options.loop` (or the model's own, a D-H table that closes) and the rig's known
    distances, blocks and lengths (`problem.distances`, `problem.lengths`)."""
    from closedloop.loops.spec import default_loops, parse_loop
    from closedloop.problem.distances import parse_blocks, parse_distances
    from closedloop.problem.lengths import parse_lengths

    loops = [parse_loop(s, robot) for s in options.loop] or default_loops(robot)
    if not loops:
        raise InputError("no --loop given: say how the chain is closed, e.g. --loop weld:frame=<tool frame>")
    return (
        loops
        + parse_distances(options.distance, loops)
        + parse_blocks(options.block, loops)
        + parse_lengths(options.length, robot)
    )


#: the note when commanded readings are fitted by plain least squares (`weighting`)
COMMANDED = (
    "readings are commanded setpoints (--readings commanded): the residual is model and servo "
    "error, not reading noise; fitted by plain least squares (--weighting none)"
)
COMMANDED_AS_NOISE = (
    "readings are commanded setpoints, yet --weighting noise treats the residual as reading noise: "
    "its noise estimate stands for model and servo error"
)


def weighting(options) -> tuple[str, str | None]:
    """(the weighting, the note to make): `weighting` as given, else plain least squares ('none') for
    commanded readings (the errors-in-variables weighting models reading noise, which a setpoint does not
    have), else 'noise'."""
    commanded = options.readings == "commanded"
    if options.weighting is None:
        return ("none", COMMANDED) if commanded else ("noise", None)
    return options.weighting, COMMANDED_AS_NOISE if commanded and options.weighting == "noise" else None


def check_loop_geometry(model_path, robot, lg, loops: list, specs: list[str] | None = None) -> list[str]:
    """Before any work: refuse a loop through joints ``closedloop simulate --robot`` held fixed
    (`closedloop.io.robot_files.HELD`: the log has no readings of them, the model calls them rigid),
    one line naming them; return a warning for each point loop whose contact point lies on the last
    joint's axis (`closedloop.loops.point.contact_on_axis`: that joint cannot move the point, its
    parameters are not seen and the fit is degenerate), naming the joint and the fix.

    A contact on the axis is named, not refused: the fit still calibrates the joints that move the
    point (the UR5 socket scenario's stylus lies on the flange axis), but a stylus off the axis sees
    the last joint too.  `specs`: the ``--loop`` texts of `loops`, for the messages.
    """
    import numpy as np

    from closedloop.io.robot_files import held_on_chain
    from closedloop.loops.point import PointLoop, contact_on_axis
    from closedloop.model.axes import point_on_axis_message

    warnings = []
    for k, lp in enumerate(loops):
        frames = [f for f in (lp.frame_a, lp.frame_b) if f not in ("universe", "world")]
        held = held_on_chain(model_path, frames) if robot.kind == "urdf" else []
        if held:
            raise InputError(
                f"{model_path}: loop '{lp.name}' passes joint(s) {', '.join(held)}, which the simulation held "
                "fixed (not driven: the log has no readings of them); simulate this loop "
                f"(closedloop simulate --robot ROBOT --loop {specs[k] if specs and k < len(specs) else '...'}), "
                "or calibrate the loop that was simulated"
            )
        if isinstance(lp, PointLoop):
            joints = robot.supporting_joints(lp.frame_a)
            rows = np.ones(len(lg), bool) if lg.loop is None else lg.loop == lp.name
            blind = contact_on_axis(robot, lp, lg.columns(joints)[rows], joints)
            if blind:
                warnings.append(
                    point_on_axis_message(
                        f"loop '{lp.name}' on {lp.frame_a}",
                        lp.frame_a,
                        blind,
                        lp.tip is not None,
                        "its parameters are left to the model; to calibrate it, hold a stylus off the axis "
                        '(its tip, if measured: tip="x y z" in the frame)',
                    )
                )
    return warnings
