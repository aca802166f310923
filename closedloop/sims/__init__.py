"""MuJoCo dataset generator for closed-loop kinematic calibration (``closedloop.sims``).

A scenario draws a *true* robot (nominal + random joint placement errors and
sensor offsets), closes its kinematic loop in MuJoCo with an equality
constraint (weld to a fixture, ball socket, a hinged door's handle, or a puck
sliding on a plane), drives the robot with its *nominal* model along the
nominal loop's self-motion (QP differential IK), and records joint readings at
quasi-static points, as in Bennett & Hollerbach (1991), thesis ch. 3.5.  The
open-loop scenario (``ur5_tracker``, thesis 3.2) has no constraint: the robot
goes to random configurations and an external tracker measures its tool point.
With the setting ``select`` the samples are chosen by pose selection from a pool
of nominal self-motion configurations (:mod:`closedloop.sims.selection`).

Public API::

    from closedloop.sims import SCENARIOS, simulate
    result = simulate("panda_weld", n=200, seed=0, out_dir=Path("out"))

See :func:`simulate` for the outputs and :class:`SimSettings` for the settings.

Layout: ``scenarios`` (settings, geometries, the registry; scenarios are data: ``scenarios/*.yaml``,
``scenario_files``), ``loop_types`` (one class per loop type in one table, `SIM_LOOPS`), ``true_robot``
(the draw of the truth), ``environment`` and ``scene`` (the MuJoCo scene), ``driver`` and ``qp`` (the
nominal planner), ``tracking`` (driving and recording), ``outputs`` (the dataset's files), ``dataset``
(`simulate`, step by step), ``selection`` (pose selection), ``robot_scenario`` (a user's robot file),
``camera_scene`` (the head-camera scenarios).
"""

from closedloop.sims.dataset import SimResult, sensor_readings, simulate
from closedloop.sims.loop_types import SIM_LOOPS, SimLoop
from closedloop.sims.scenario_files import load_scenario  # registers the shipped scenario YAML files
from closedloop.sims.scenarios import SCENARIOS, DoorGeometry, PlaneGeometry, Scenario, SimSettings, TrackerGeometry
from closedloop.sims.true_robot import draw_errors, perturbable_parameters

__all__ = [
    "SCENARIOS",
    "SIM_LOOPS",
    "SimLoop",
    "DoorGeometry",
    "PlaneGeometry",
    "TrackerGeometry",
    "Scenario",
    "SimResult",
    "SimSettings",
    "draw_errors",
    "load_scenario",
    "perturbable_parameters",
    "sensor_readings",
    "simulate",
]
