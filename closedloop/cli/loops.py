"""``closedloop loops``: the loop types of :data:`closedloop.loops.spec.LOOP_TYPES` with their keys and an
example each (also the epilog of ``calibrate --help``)."""

from __future__ import annotations

import textwrap

#: An example per loop type (the registry gives the keys; a loop module's factory docstring the syntax).
LOOP_EXAMPLES = {
    "weld": "weld:frame=panda_hand_tcp,name=fixture   (tool clamped to a fixture at an unknown pose)",
    "point": "point:frame=stylus_tip,name=socket        (tip in a ball socket; tip and socket unknown)",
    "plane": "plane:frame=stylus_tip,name=table         (tip touching an unknown plane)",
    "sphere": "sphere:frame=l_hand,to=r_hand,name=touch,distance=0.08   (two spheres in contact, radii sum 8 cm)",
    "face": "face:frame=l_palm,to=table,name=palm   (a flat face of l_palm sliding flat on a face of table)",
    "hinge": "hinge:frame=tool0,name=door               (tool on a door handle, hinge unknown)",
    "passive": "passive:frame=tool0,task=door.urdf,task_frame=handle,name=door",
    "measured_pose": "measured_pose:frame=tool0,name=tracker,sigma_t=1e-4,sigma_r=1e-3   "
    "(log columns tracker:x .. tracker:rz)",
    "measured_point": "measured_point:frame=stylus_tip,name=tracker   (log columns tracker:x tracker:y tracker:z)",
    "camera": 'camera:frame=marker,cameras=2,K1="600 600 320 240",K2="600 600 320 240"   (log columns <name>:u1 ..)',
}


def _registry() -> dict:
    from closedloop.loops.spec import all_loop_types  # every type of the one table, spec.LOOP_TYPES

    return all_loop_types()


def loop_help(width: int = 100) -> str:
    """One paragraph per registered loop type: keys, syntax and an example."""
    lines = ["loop types (--loop TYPE:key=value,...; repeatable; 'closedloop loops' for details):"]
    for kind, (factory, keys) in sorted(_registry().items()):
        lines.append(f"  {kind:<15} keys: {', '.join(sorted(keys))}")
    return "\n".join(textwrap.fill(ln, width, subsequent_indent=" " * 18) if len(ln) > width else ln for ln in lines)


def cmd_loops(args) -> int:
    """Print every loop type with its keys, syntax and an example."""
    for kind, (factory, keys) in sorted(_registry().items()):
        print(f"{kind}")
        print(f"  keys:    {', '.join(sorted(keys))}")
        doc = (factory.__doc__ or "").strip().splitlines()
        if doc:
            print(f"  syntax:  {doc[0].strip()}")
        print(f"  example: --loop {LOOP_EXAMPLES.get(kind, kind + ':frame=<tool frame>')}")
    from closedloop.loops.spec import GENERIC_KEYS

    print(
        f"Every loop type also takes: {', '.join(sorted(GENERIC_KEYS))}, and KEY=@GROUP (an unknown shared "
        "by several loops)."
    )
    print("Frames are the model's frame names (closedloop inspect MODEL lists them); 'to' defaults to the world.")
    return 0
