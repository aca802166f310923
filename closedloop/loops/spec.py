"""Loop specifications from the command line: ``TYPE:key=value,key=value``.

    weld:frame=panda_hand                       tool welded to an unknown world pose
    weld:frame=tip,to=base,closure=identity     known closure (a chain that closes on itself)
    weld:frame=l_hand,to=r_hand,name=grasp      two branches of one model, unknown grasp
    weld:frame=tool,closure="0.5 0 0.3 0 0 0"   known closure pose (x y z rx ry rz)

Every loop has a name (default: its type) used to name its parameters.
"""

from __future__ import annotations

from importlib import import_module
from typing import Callable

from ..errors import LoopError
from ..robot import RobotModel
from .base import Loop
from .weld import WeldLoop, parse_pose

LoopFactory = Callable[[dict[str, str], RobotModel], Loop]
REGISTRY: dict[str, tuple[LoopFactory, set[str]]] = {}
# loop types whose modules are imported on first use (kind -> module in this package)
LAZY_KINDS = {"camera": ".camera"}


def register(kind: str, keys: set[str]):
    def deco(fn: LoopFactory) -> LoopFactory:
        REGISTRY[kind] = (fn, keys | {"name"})
        return fn
    return deco


@register("weld", {"frame", "to", "closure"})
def _weld(kw: dict[str, str], robot: RobotModel) -> Loop:
    if "frame" not in kw:
        raise LoopError("weld loop needs frame=<tool frame>")
    closure = kw.get("closure", "unknown")
    known = None
    if closure == "identity":
        known = parse_pose("0 0 0 0 0 0")
    elif closure != "unknown":
        known = parse_pose(closure)
    return WeldLoop(kw.get("name", "weld"), kw["frame"], kw.get("to", "universe"), closure=known)


def parse_loop(spec: str, robot: RobotModel) -> Loop:
    """A loop from ``TYPE:key=value,...``; errors name the spec and the bad key."""
    kind, _, rest = spec.partition(":")
    kind = kind.strip()
    if kind not in REGISTRY and kind in LAZY_KINDS:
        import_module(LAZY_KINDS[kind], __package__)  # registers the type
    if kind not in REGISTRY:
        known = ", ".join(sorted(set(REGISTRY) | set(LAZY_KINDS)))
        raise LoopError(f"--loop {spec}: unknown loop type '{kind}' (known: {known})")
    factory, keys = REGISTRY[kind]
    kw: dict[str, str] = {}
    for item in _split(rest):
        if not item:
            continue
        key, eq, val = item.partition("=")
        if not eq:
            raise LoopError(f"--loop {spec}: expected key=value, got '{item}'")
        key = key.strip()
        if key not in keys:
            raise LoopError(f"--loop {spec}: unknown key '{key}' for {kind} (keys: {', '.join(sorted(keys))})")
        kw[key] = val.strip().strip('"').strip("'")
    loop = factory(kw, robot)
    for f in loop.frames:
        try:
            robot.frame_id(f)
        except Exception as exc:
            raise LoopError(f"--loop {spec}: {exc}") from None
    return loop


def default_loops(robot: RobotModel) -> list[Loop]:
    """Loops implied by the model itself: a D-H table with ``closes: true``."""
    if robot.kind == "dh" and robot.dh.closes:
        return [WeldLoop("closure", robot.dh.end_frame, "universe", closure=parse_pose("0 0 0 0 0 0"))]
    return []


def _split(text: str) -> list[str]:
    """Split on commas outside quotes."""
    out, cur, quote = [], "", ""
    for ch in text:
        if ch in "\"'" and (not quote or quote == ch):
            quote = "" if quote else ch
        if ch == "," and not quote:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return out
