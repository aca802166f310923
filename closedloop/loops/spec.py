"""Loop specifications from the command line: ``TYPE:key=value,key=value``.

    weld:frame=panda_hand                       tool welded to an unknown world pose
    weld:frame=tip,to=base,closure=identity     known closure (a chain that closes on itself)
    weld:frame=l_hand,to=r_hand,name=grasp      two branches of one model, unknown grasp
    weld:frame=tool,closure="0.5 0 0.3 0 0 0"   known closure pose (x y z rx ry rz)

Every loop has a name (default: its type) used to name its parameters.

Keys every loop type takes:

    tip=@ball              ``KEY=@GROUP``: the loop's unknowns of KEY are the shared group GROUP's
                           (one tool at many fixtures; ``closedloop.problem.shared``; keys tip, point, normal,
                           closure, base, tool, hinge, camK)
    fixture=place1         the fixture the loop belongs to (leave-one-fixture-out validation groups by it)
    log=place1_a.csv       this loop's own log file (header-less with --joints): one file per fixture
    sigma_task=0.2mm       the loop's own task-space noise (contact play, tracker noise) on its
                           translation rows, isotropic or per axis (0.1/0.1/0.3mm), added to the joint
                           noise; ``sigma_task=auto`` estimates it (a variance component),
                           ``sigma_task=0`` turns it off (``closedloop.estimate.variance``)

Vectors may be written without spaces or quotes: ``tip=[0.01,0,0.1]`` (commas inside brackets do not
split the spec) as well as ``tip="0.01 0 0.1"``.
"""

from __future__ import annotations

from importlib import import_module
from typing import Callable

from closedloop.errors import InputError, LoopError
from closedloop.loops.base import Loop
from closedloop.model.robot import RobotModel

LoopFactory = Callable[[dict[str, str], RobotModel], Loop]

#: Every loop type, in one table (as qpsolvers keeps its solvers): type name -> the module that
#: defines it (relative to this package, or absolute), where its factory is registered with its keys
#: (`register`).  The parser (`parse_loop`), ``closedloop loops`` and ``calibrate --help``
#: (`all_loop_types`) and the simulator read it: a simulator class registers under one of these names
#: (`closedloop.sims.loop_types.simulates`), and ``simulate`` takes exactly these names.  A type's
#: module is imported on first use (``import closedloop`` pays for no camera code).  Adding a loop type
#: is its own module, one entry here and, to simulate it, its simulator class
#: (docs/architecture/adding-a-loop-type.md).
LOOP_TYPES: dict[str, str] = {
    "weld": ".weld",
    "point": ".point",
    "plane": ".plane",
    "sphere": ".sphere",
    "face": ".face",
    "hinge": ".hinge",
    "passive": ".passive",
    "measured_pose": ".measured",
    "measured_point": ".measured",
    "camera": ".camera.spec",
}
#: the factories and keys of the types whose modules are loaded (filled by `register`)
REGISTRY: dict[str, tuple[LoopFactory, set[str]]] = {}
GENERIC_KEYS = {"sigma_task", "fixture", "log"}  # keys every loop type takes (module docstring)


def register(kind: str, keys: set[str]):
    """Register the factory of loop type `kind` (which must have its entry in `LOOP_TYPES`) and its keys."""
    if kind not in LOOP_TYPES:
        raise LoopError(f"loop type '{kind}' has no entry in closedloop.loops.spec.LOOP_TYPES (add it there)")

    def deco(fn: LoopFactory) -> LoopFactory:
        REGISTRY[kind] = (fn, keys | {"name"})
        return fn

    return deco


def loop_type(kind: str) -> tuple[LoopFactory, set[str]]:
    """The factory and keys of loop type `kind` (its module loaded on first use); LoopError if unknown."""
    if kind not in REGISTRY and kind in LOOP_TYPES:
        import_module(LOOP_TYPES[kind], __package__)  # registers the type
    if kind not in REGISTRY:
        raise LoopError(f"unknown loop type '{kind}' (known: {', '.join(sorted(LOOP_TYPES))})")
    return REGISTRY[kind]


def all_loop_types() -> dict[str, tuple[LoopFactory, set[str]]]:
    """Every loop type of `LOOP_TYPES` with its factory and keys (loads every loop module)."""
    return {kind: loop_type(kind) for kind in LOOP_TYPES}


def parse_loop(spec: str, robot: RobotModel) -> Loop:
    """A loop from ``TYPE:key=value,...``; errors name the spec and the bad key."""
    kind, _, rest = spec.partition(":")
    kind = kind.strip()
    try:
        factory, keys = loop_type(kind)
    except LoopError as exc:
        raise LoopError(f"--loop {spec}: {exc}") from None
    kw: dict[str, str] = {}
    shares: dict[str, str] = {}
    generic: dict[str, str] = {}
    task = None
    for item in _split(rest):
        if not item:
            continue
        key, eq, val = item.partition("=")
        if not eq:
            raise LoopError(f"--loop {spec}: expected key=value, got '{item}'")
        key = key.strip()
        val = val.strip().strip('"').strip("'")
        if val.startswith("@"):  # a shared group (closedloop.problem.shared); checked on the loop below
            shares[key] = val[1:]
            continue
        if key == "sigma_task":
            task = val
            continue
        if key in ("fixture", "log"):  # generic: kept on the loop (closedloop.validation.fixtures, data.read_loop_logs)
            generic[key] = val
            continue
        if key not in keys:
            raise LoopError(
                f"--loop {spec}: unknown key '{key}' for {kind} (keys: {', '.join(sorted(keys | GENERIC_KEYS))})"
            )
        if val.startswith("[") and val.endswith("]"):
            val = val[1:-1]
        kw[key] = val
    loop = factory(kw, robot)
    if "fixture" in generic:
        loop.fixture = generic["fixture"]
    if "log" in generic:
        loop.log_path = generic["log"]
    if shares or task is not None:
        from closedloop.loops.settings import set_task_noise, share

        try:
            for key, group in shares.items():
                share(loop, key, group)
            if task is not None:
                set_task_noise(loop, task)
        except InputError as exc:
            raise LoopError(f"--loop {spec}: {exc}") from None
    for f in loop.frames:
        try:
            robot.frame_id(f)
        except Exception as exc:
            raise LoopError(f"--loop {spec}: {exc}") from None
    return loop


def parse_loops(specs: list[str], robot: RobotModel) -> list[Loop]:
    """The loops of the ``--loop`` texts `specs` (`parse_loop`), or the model's own (`default_loops`);
    refused when there is none."""
    loops = default_loops(robot) if not specs else [parse_loop(s, robot) for s in specs]
    if not loops:
        raise InputError("no --loop given: say how the chain is closed, e.g. --loop weld:frame=<tool frame>")
    return loops


def default_loops(robot: RobotModel) -> list[Loop]:
    """Loops implied by the model itself: a D-H table with ``closes: true``."""
    if robot.kind == "dh" and robot.dh is not None and robot.dh.closes:
        weld, _ = loop_type("weld")  # the chain closes on itself: the identity closure
        return [weld({"name": "closure", "frame": robot.dh.end_frame, "to": "universe", "closure": "identity"}, robot)]
    return []


def _split(text: str) -> list[str]:
    """Split on commas outside quotes."""
    out, cur, quote, depth = [], "", "", 0
    for ch in text:
        if ch in "\"'" and (not quote or quote == ch):
            quote = "" if quote else ch
        if not quote and ch in "[]":
            depth += 1 if ch == "[" else -1
        if ch == "," and not quote and depth <= 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return out
