"""closedloop: closed-loop kinematic calibration of robots.

The method is Bennett & Hollerbach's (1991): when a robot closes a kinematic
loop with its task, the loop-closure equations identify its kinematic
parameters from its own joint readings.  See the README for the workflow.
"""

__version__ = "0.1.0"

from .calibration import CalibrationOptions, CalibrationResult, calibrate  # noqa: E402
from .data import JointLog, read_log  # noqa: E402
from .errors import ClosedLoopError, InputError  # noqa: E402
from .loops import Loop, WeldLoop  # noqa: E402
from .robot import RobotModel  # noqa: E402

__all__ = ["CalibrationOptions", "CalibrationResult", "calibrate", "JointLog", "read_log", "ClosedLoopError",
           "InputError", "Loop", "WeldLoop", "RobotModel", "__version__"]
