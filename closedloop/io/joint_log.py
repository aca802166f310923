"""A run's joint log, whichever file holds it: the positional file (a CSV log, or a ROS bag's standstills),
or each loop's own ``log=`` file (one per fixture); checked against the robot and the loops before any
work (`read_joint_log`)."""

from __future__ import annotations

from pathlib import Path

from closedloop.errors import InputError
from closedloop.io.logs import JointLog, check_angle_units, check_loop_column, read_log, read_loop_logs


def read_joint_log(
    log_path: str | None,
    robot,
    loops: list,
    degrees: bool = False,
    order: list[str] | None = None,
    notes: list[str] | None = None,
) -> JointLog:
    """The joint log of `robot` (`closedloop.model.robot.RobotModel`) and its `loops`: the positional file
    `log_path` (CSV or bag), or each loop's own ``log=`` file; refused where most readings of a joint lie
    far beyond its limits (`check_angle_units`) or where its ``loop`` column names no loop given
    (`check_loop_column`).  A bag's extraction is said in `notes`."""
    lg = _read(log_path, robot, loops, degrees, order, notes if notes is not None else [])
    check_angle_units(lg, robot, degrees)
    check_loop_column(lg, [lp.name for lp in loops])
    return lg


def _read(log_path: str | None, robot, loops: list, degrees: bool, order: list[str] | None, notes: list[str]):
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
