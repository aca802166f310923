"""MuJoCo dataset generator for closed-loop kinematic calibration (``closedloop.sims``).

A scenario draws a *true* robot (nominal + random joint placement errors and
sensor offsets), closes its kinematic loop in MuJoCo with an equality
constraint (weld to a fixture, ball socket, or a hinged door's handle), drives
the robot with its *nominal* model along the nominal loop's self-motion (QP
differential IK), and records joint readings at quasi-static points, as in
Bennett & Hollerbach (1991), thesis ch. 3.5.

Public API::

    from closedloop.sims import SCENARIOS, simulate
    result = simulate("panda_weld", n=200, seed=0, out_dir=Path("out"))

See :func:`simulate` for the outputs and :class:`SimSettings` for the settings.
"""

from .dataset import SimResult, sensor_readings, simulate
from .scenarios import SCENARIOS, DoorGeometry, Scenario, SimSettings, draw_errors, perturbable_parameters

__all__ = [
    "SCENARIOS",
    "DoorGeometry",
    "Scenario",
    "SimResult",
    "SimSettings",
    "draw_errors",
    "perturbable_parameters",
    "sensor_readings",
    "simulate",
]
