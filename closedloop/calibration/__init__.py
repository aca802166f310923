"""The calibration pipeline: staged fits, the outlier screen, the re-check at the solution, the verdict.

`calibrate` (in `pipeline`) runs the whole of it on a robot, its loops and a joint log; `judge` (in
`verdict`) gives the verdict from the evidence the result carries; `staged` holds the stages (a coarse
fit on the identifiable parameters, then the full one).
"""

from closedloop.calibration.pipeline import calibrate
from closedloop.calibration.verdict import judge
from closedloop.records import CalibrationOptions, CalibrationResult

__all__ = ["calibrate", "judge", "CalibrationOptions", "CalibrationResult"]
