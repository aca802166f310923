"""closedloop: closed-loop kinematic calibration of robots.

The method is Bennett & Hollerbach's (1991): when a robot closes a kinematic
loop with its task, the loop-closure equations identify its kinematic
parameters from its own joint readings.  See the README for the workflow.
"""

from closedloop.calibration.pipeline import CalibrationOptions, CalibrationResult, calibrate  # noqa: E402
from closedloop.calibration.verdict import judge
from closedloop.errors import CalibrationError, ClosedLoopError, InputError  # noqa: E402
from closedloop.io.logs import JointLog, read_log  # noqa: E402
from closedloop.loops import HingeLoop, Loop, MeasuredPointLoop, MeasuredPoseLoop, PlaneLoop, PointLoop, WeldLoop  # noqa: E402
from closedloop.loops.spec import parse_loop  # noqa: E402
from closedloop.model.robot import RobotModel  # noqa: E402
from closedloop.records import Verdict
from closedloop.version import __version__  # noqa: E402

__all__ = [
    "CalibrationOptions",
    "CalibrationResult",
    "calibrate",
    "JointLog",
    "read_log",
    "ClosedLoopError",
    "InputError",
    "Loop",
    "WeldLoop",
    "PointLoop",
    "PlaneLoop",
    "HingeLoop",
    "MeasuredPointLoop",
    "MeasuredPoseLoop",
    "parse_loop",
    "RobotModel",
    "Verdict",
    "judge",
    "write_model",
    "build_report",
    "write_report",
    "cross_validate",
    "CalibrationError",
    "__version__",
]


def __getattr__(name: str):
    """Output writers and validation load on first use (they import what `import closedloop` need not)."""
    if name == "write_model":
        from closedloop.output.urdf import write_model

        return write_model
    if name in ("build_report", "write_report"):
        from closedloop.output import report

        return getattr(report, name)
    if name == "cross_validate":
        from closedloop.validation.kfold import cross_validate

        return cross_validate
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
