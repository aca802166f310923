"""A run's inputs (`load_inputs`): the model, the robot's loops and the known distances, blocks and lengths
of a rig, the joint log (`closedloop.io.joint_log`: a CSV, a ROS bag, or each loop's own file) with its
torques, the loops' geometry on it; how the readings are weighted.  Used by `closedloop.run.calibrate`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from closedloop.errors import InputError


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
    geometry: list[str] = field(
        default_factory=list
    )  # warnings on the loops' geometry (`loops.geometry.check_loop_geometry`)


def load_inputs(o) -> RunInputs:
    """The run's inputs (`RunInputs`) from its options (`closedloop.run.options.CalibrateOptions`): the
    model and the calibrated model's format, the loops (`loops.spec.parse_loops`) and the rig's known
    distances, blocks and lengths (read first, `problem.rig`; made loops by `problem.distances`,
    `problem.lengths`), the log and its loop column,
    the loops' geometry on it (`loops.geometry.check_loop_geometry`), the k-fold count (`cv`, or 5, fewer on
    a shorter log), the weighting, the fit's options."""
    from closedloop.calibration.pipeline import CalibrationOptions
    from closedloop.io.joint_log import read_joint_log
    from closedloop.loops.geometry import check_loop_geometry
    from closedloop.loops.spec import parse_loops
    from closedloop.model.parameters import fix_values
    from closedloop.model.robot import RobotModel
    from closedloop.problem.distances import distance_loops
    from closedloop.problem.lengths import length_loops_on
    from closedloop.problem.rig import parse_rig

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
        rules=o.rules,
    )
    rig = parse_rig(o.distance, o.block, o.length)  # the rig's known distances, blocks and lengths, as records
    robot = RobotModel.from_file(o.model)
    robot.check_output(o.out)
    loops = parse_loops(o.loop, robot)  # or the model's own (a D-H table that closes)
    loops += [*distance_loops(rig.distances, loops), *length_loops_on(robot, rig.lengths)]
    messages: list[str] = []
    lg = read_joint_log(o.log, robot, loops, o.degrees, o.joints, messages)
    lg = robot.with_gravity_torques(lg)  # where the log has no torques
    geometry = check_loop_geometry(o.model, robot, lg, loops, o.loop)  # before any work
    messages += [f"warning: {w}" for w in geometry]
    log_name = o.log or str(lg.source)
    k = o.folds
    if k > len(lg):
        if o.cv is not None:
            raise InputError(f"--cv {k}: more folds than the {len(lg)} rows of {log_name}")
        k = len(lg) if len(lg) >= 2 else 0
    return RunInputs(robot, loops, lg, log_name, k, fit, note, messages, geometry)


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
