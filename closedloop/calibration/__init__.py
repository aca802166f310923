"""The calibration pipeline: the outlier screen, the solve, the re-check at the solution, the verdict.

`calibrate` (in `pipeline`) runs the whole of it on a robot, its loops and a joint log; `solve` decides how
the reduced problem is solved (which stages of `closedloop.estimate.residual` from which starts, restarts,
valley starts, the re-check at the solution, the known-length guard); `judge` (in `verdict`) gives the
verdict from the evidence the result carries, by the thresholds of `VerdictRules`.
"""

from closedloop.calibration.pipeline import calibrate
from closedloop.calibration.verdict import judge
from closedloop.records import CalibrationOptions, CalibrationResult

__all__ = ["calibrate", "judge", "CalibrationOptions", "CalibrationResult"]
