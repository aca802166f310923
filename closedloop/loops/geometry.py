"""A run's loops checked on its model and log before any work: no loop through joints the simulation held
fixed, and a named warning for each point contact on a joint's axis (`check_loop_geometry`)."""

from __future__ import annotations

from closedloop.errors import InputError


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

    from closedloop.loops.point import PointLoop, contact_on_axis
    from closedloop.model.axes import point_on_axis_message

    warnings = []
    for k, lp in enumerate(loops):
        frames = [f for f in (lp.frame_a, lp.frame_b) if f not in ("universe", "world")]
        held = robot.held_on_chain(frames)
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
