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
``scenario_files``; every named scenario: `scenario_catalog`), ``loop_types`` (one class per type of the
loop registry ``closedloop.loops.spec.LOOP_TYPES``, registered with `simulates` into `SIM_LOOPS`), ``true_robot``
(the draw of the truth), ``environment`` and ``scene`` (the MuJoCo scene), ``driver`` and ``qp`` (the
nominal planner), ``tracking`` (driving and recording), ``outputs`` (the dataset's files), ``dataset``
(`simulate`, step by step), ``selection`` (pose selection), ``robot_scenario`` (a user's robot file),
``camera_scene`` (the head-camera scenarios).  The parameters a calibration can tell apart, read off the
structure of the nominal robot (no fit), are `closedloop.studies.identifiable`'s.  The public names load on
first use.
"""

from importlib import import_module
from typing import Any

#: the public names and the module of each, loaded on first use (PEP 562): the scenario catalog
#: (``simulate --help``) reads the scenario files without loading the simulator
_PUBLIC = {
    "SimResult": "closedloop.sims.dataset",
    "sensor_readings": "closedloop.sims.dataset",
    "simulate": "closedloop.sims.dataset",
    "SIM_LOOPS": "closedloop.sims.loop_types",
    "SimLoop": "closedloop.sims.loop_types",
    "simulates": "closedloop.sims.loop_types",
    "load_scenario": "closedloop.sims.scenario_files",
    "SCENARIOS": "closedloop.sims.scenario_files",  # the registry with the shipped scenario files in it
    "DoorGeometry": "closedloop.sims.scenarios",
    "PlaneGeometry": "closedloop.sims.scenarios",
    "Scenario": "closedloop.sims.scenarios",
    "SimSettings": "closedloop.sims.scenarios",
    "TrackerGeometry": "closedloop.sims.scenarios",
    "scenario_catalog": "closedloop.sims.scenarios",
    "draw_errors": "closedloop.sims.true_robot",
    "perturbable_parameters": "closedloop.sims.true_robot",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(_PUBLIC[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
