"""Scenarios as small YAML files: the shipped ones (``scenarios/*.yaml``) and a user's.

A scenario file names a robot (a key of :data:`closedloop.assets.catalog.ROBOTS`, or a URDF/MJCF file
relative to the YAML), a loop in the syntax of ``calibrate --loop`` (``TYPE:frame=A[,to=B][,name=N]``;
TYPE a loop type of the registry ``closedloop.loops.spec.LOOP_TYPES`` that the simulator simulates,
:func:`closedloop.sims.loop_types.simulated_types`), the grasp configuration
``q0`` (automatic for a robot file), ``settings:`` (any :class:`~closedloop.sims.scenarios.SimSettings`
field), the loop geometry (``door:``, ``plane:``, ``tracker:``), and for a robot file ``tool:`` (a stylus
link on the loop frame) and ``joints:`` (the driven joints), see :mod:`closedloop.sims.robot_scenario`.
Importing this module registers the shipped files in :data:`~closedloop.sims.scenarios.SCENARIOS`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from closedloop.errors import InputError
from closedloop.sims.loop_types import sim_loop
from closedloop.sims.scenarios import (
    SCENARIO_DIR,
    SCENARIOS,
    DoorGeometry,
    PlaneGeometry,
    Scenario,
    SimSettings,
    TrackerGeometry,
)

__all__ = ["SCENARIO_DIR", "parse_sim_loop", "scenario_from_dict", "load_scenario"]

_SCENARIO_KEYS = {
    "description",
    "robot",
    "loop",
    "q0",
    "settings",
    "door",
    "plane",
    "tracker",
    "min_joint_range",
    "tool",
    "joints",
    "name",
}


def parse_sim_loop(spec: str) -> tuple[str, str, str | None, str]:
    """``TYPE:frame=A[,to=B][,name=N]`` (the syntax of ``calibrate --loop``) -> (type, frame, to, name).

    TYPE is a name of the loop registry (``closedloop.loops.spec.LOOP_TYPES``), refused as ``calibrate``
    refuses it when unknown, and in one line naming the simulated types when the simulator lacks it.
    """
    kind, _, rest = spec.partition(":")
    kind = kind.strip()
    try:
        sim = sim_loop(kind)
    except InputError as exc:
        raise InputError(f"--loop {spec}: {exc}") from None
    kw: dict[str, str] = {}
    for item in (t for t in rest.split(",") if t.strip()):
        key, eq, val = (x.strip() for x in item.partition("="))
        if not eq or key not in ("frame", "to", "name"):
            raise InputError(
                f"--loop {spec}: the simulator takes frame=, to= (weld only) and name= "
                f"(got '{item}'); the loop's unknowns are what calibrate estimates"
            )
        kw[key] = val
    if "frame" not in kw:
        raise InputError(f"--loop {spec}: say which frame closes the loop, e.g. {kind}:frame=tool0")
    if "to" in kw and not sim.two_chains:
        raise InputError(
            f"--loop {spec}: only a weld closes two chains of one robot (to=); a {kind} loop closes on the world"
        )
    return kind, kw["frame"], kw.get("to"), kw.get("name", sim.default_name)


def _settings(data: dict | None, where: str, loop_type: str) -> SimSettings:
    names = {f.name for f in dataclasses.fields(SimSettings)}
    bad = sorted(set(data or {}) - names)
    if bad:
        raise InputError(f"{where}: unknown setting(s) {', '.join(bad)} (known: {', '.join(sorted(names))})")
    # the settings the loop type needs whatever the robot (`SimLoop.settings`); a scenario's own win
    merged = {**sim_loop(loop_type).settings, **(data or {})}
    values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in merged.items()}
    return SimSettings(**values)


def scenario_from_dict(data: dict, name: str, where: str, base_dir: Path | None = None) -> Scenario:
    """A :class:`Scenario` from a YAML mapping (see ``closedloop/sims/scenarios/*.yaml``).

    ``robot`` is a key of :data:`closedloop.assets.catalog.ROBOTS` or a robot file (URDF; relative paths
    from ``base_dir``); for a file, ``q0`` may be left out (a well-conditioned grasp pose is
    chosen), and ``tool: {xyz: [x, y, z]}`` adds a stylus link on the loop frame and ``joints:``
    lists the driven joints (:mod:`closedloop.sims.robot_scenario`).
    """
    from closedloop.assets.catalog import ROBOTS

    bad = sorted(set(data) - _SCENARIO_KEYS)
    if bad:
        raise InputError(f"{where}: unknown key(s) {', '.join(bad)} (known: {', '.join(sorted(_SCENARIO_KEYS))})")
    for key in ("robot", "loop"):
        if key not in data:
            raise InputError(f"{where}: a scenario needs '{key}:'")
    loop_type, frame, to, loop_name = parse_sim_loop(str(data["loop"]))
    settings = _settings(data.get("settings"), where, loop_type)
    robot, q0 = str(data["robot"]), data.get("q0")
    if robot not in ROBOTS or "tool" in data or "joints" in data:
        from closedloop.sims.robot_scenario import prepare_robot

        path = Path(robot) if robot not in ROBOTS else ROBOTS[robot].path
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        prepared = prepare_robot(
            path, loop_type, frame, to, tool=data.get("tool"), joints=data.get("joints"), q0=q0, where=where
        )
        robot, frame, q0 = prepared.key, prepared.frame, prepared.q0
    elif q0 is None:
        raise InputError(f"{where}: give q0 for the built-in robot '{robot}' (or its URDF path for an automatic one)")
    geom = {"door": DoorGeometry, "plane": PlaneGeometry, "tracker": TrackerGeometry}
    parts = {
        k: cls(**{a: tuple(v) if isinstance(v, list) else v for a, v in (data.get(k) or {}).items()})
        for k, cls in geom.items()
        if k in data
    }
    own = sim_loop(loop_type).geometry  # the loop type's geometry, its defaults when not given
    if own is not None and own[0] not in parts:
        parts[own[0]] = own[1]()
    return Scenario(
        name=str(data.get("name", name)),
        description=str(data.get("description", "")),
        robot=robot,
        loop_type=loop_type,
        loop_name=loop_name,
        tool_frame=frame,
        target_frame=to,
        q0=tuple(float(v) for v in q0),
        settings=settings,
        min_joint_range=float(data.get("min_joint_range", 0.1)),
        **parts,
    )


def load_scenario(path: str | Path) -> Scenario:
    """A scenario YAML file (registered in :data:`SCENARIOS` under its file name)."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read scenario ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: a scenario is a mapping (robot:, loop:, q0:, settings: ...)")
    sc = scenario_from_dict(data, path.stem, str(path), path.parent)
    SCENARIOS[sc.name] = sc
    return sc


def load_builtin() -> None:
    """Register the shipped scenario files."""
    for f in sorted(SCENARIO_DIR.glob("*.yaml")):
        load_scenario(f)


load_builtin()
