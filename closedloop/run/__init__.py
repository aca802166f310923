"""One calibration run from files to files (`calibrate_files`) and its options, defined once
(`CalibrateOptions`): what ``closedloop calibrate``, ``closedloop batch`` and a script run alike."""

from __future__ import annotations

from closedloop.run.calibrate import RunResult, calibrate_files
from closedloop.run.options import CalibrateOptions

__all__ = ["CalibrateOptions", "RunResult", "calibrate_files"]
