"""closedloop: closed-loop kinematic calibration of robots.

The method is Bennett & Hollerbach's (1991): when a robot closes a kinematic
loop with its task, the loop-closure equations identify its kinematic
parameters from its own joint readings.  See the README for the workflow.

The public names load on first use (``from closedloop import calibrate`` imports the calibrator then):
`import closedloop` itself is instant, so that the command line can take over Ctrl-C before the
numerical libraries load.
"""

from __future__ import annotations

import importlib

from closedloop.errors import CalibrationError, ClosedLoopError, InputError
from closedloop.version import __version__

#: public name -> the module that defines it
_LAZY = {
    "CalibrateOptions": "closedloop.run",
    "calibrate_files": "closedloop.run",
    "RunResult": "closedloop.run",
    "CalibrationOptions": "closedloop.calibration.pipeline",
    "CalibrationResult": "closedloop.calibration.pipeline",
    "calibrate": "closedloop.calibration.pipeline",
    "judge": "closedloop.calibration.verdict",
    "JointLog": "closedloop.io.logs",
    "read_log": "closedloop.io.logs",
    "Loop": "closedloop.loops",
    "WeldLoop": "closedloop.loops",
    "PointLoop": "closedloop.loops",
    "PlaneLoop": "closedloop.loops",
    "HingeLoop": "closedloop.loops",
    "MeasuredPointLoop": "closedloop.loops",
    "MeasuredPoseLoop": "closedloop.loops",
    "parse_loop": "closedloop.loops.spec",
    "RobotModel": "closedloop.model.robot",
    "Verdict": "closedloop.calibration.verdict",
    "VerdictRules": "closedloop.records",
    "write_model": "closedloop.output.urdf",
    "build_report": "closedloop.output.report",
    "write_report": "closedloop.output.report",
    "cross_validate": "closedloop.validation.kfold",
    "predict_from_result": "closedloop.analysis.accuracy",
    "PriorTolerance": "closedloop.analysis.accuracy",
    "WorkspaceAccuracy": "closedloop.analysis.accuracy",
    "region_validate": "closedloop.validation.regions",
}

__all__ = [
    "CalibrateOptions",
    "calibrate_files",
    "RunResult",
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
    "VerdictRules",
    "judge",
    "write_model",
    "build_report",
    "write_report",
    "cross_validate",
    "predict_from_result",
    "PriorTolerance",
    "WorkspaceAccuracy",
    "region_validate",
    "CalibrationError",
    "__version__",
]


def __getattr__(name: str):
    """The public names of `_LAZY`, imported from their module on first use."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
