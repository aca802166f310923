"""Loop parameters shared by name across loops.

One ball on the flange pressed into six sockets is one tool point, not six; a
marker seen by two cameras is one marker.  A loop parameter is shared by
naming a group for one of the loop's *share keys*:

    point:frame=ball,name=front_a,tip=@ball        the tip of this loop is the group 'ball'
    point:frame=ball,name=front_b,tip=@ball        ... and this one's too: one tip, three columns
    plane:frame=stylus,name=day1,normal=@table     one plane touched on several days
    measured_point:frame=tool,name=a,base=@tracker one tracker placement for several recordings
    camera:frame=marker,to=cam_l,name=L,tip=@marker

``KEY=@GROUP`` means: the loop's parameters of KEY are unknown and are the
parameters ``GROUP.<field>`` (``ball.tip_x``, ``ball.tip_y``, ``ball.tip_z``)
that every loop naming the same group uses.  In the API:
``share(loop, "tip", "ball")``.  The share keys (`SHARE_KEYS`): ``tip``,
``point``, ``normal`` (a plane's nrx, nry, d), ``closure`` (a weld's pose),
``base`` and ``tool`` (a measured loop's poses), ``hinge``, and ``camK``
(every parameter of camera K of a camera loop: pose, intrinsics, distortion).

In `CalibrationProblem` a shared parameter is one column: each loop reads
its values through an index map (`loop_columns`), its Jacobian columns land
in the same place (the stacked least squares sums the loops' normal
equations), and identifiability, the gauge, the report and the written
result see one parameter.  Its starting value is the mean of the loops' own
initial estimates (`initial_shared`), after which each loop's other
unknowns are refitted with the shared ones held (a Gauss-Newton on the
loop's own residual, `loops.common.refine_own`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import LoopError

if TYPE_CHECKING:
    from closedloop.loops.base import Loop
    from closedloop.model.parameters import Parameter
    from closedloop.problem.problem import CalibrationProblem


def parameter_name(loop: Loop, p: Parameter) -> str:
    """The name of a loop parameter in the problem: its group's when shared, else its own."""
    return (getattr(loop, "shared", None) or {}).get(p.field, p.name)


def loop_columns(loops: list[Loop], start: int, existing: list[str]) -> tuple[list[np.ndarray], list[Parameter]]:
    """Index maps of the loops' parameters into one vector (after `start` robot columns), and the new records.

    A field mapped by `loop.shared` to a name already present reuses that
    column (the group, or another loop's parameter such as a distance's
    ``front_a.px``); otherwise a column is added (named by the group for a
    shared field).  Shared parameters must agree in unit.
    """
    from dataclasses import replace

    index = {n: i for i, n in enumerate(existing)}
    new: list[Parameter] = []
    cols: list[np.ndarray] = []
    own = {lp.name for lp in loops}
    for lp in loops:
        idx = []
        for p in lp.parameters():
            name = parameter_name(lp, p)
            if name != p.name and name.split(".", 1)[0] in own and not getattr(lp, "parameter_only", False):
                raise LoopError(f"shared group '{name.split('.', 1)[0]}' has the name of a loop")
            if name in index:
                k = index[name]
                q = new[k - start] if k >= start else None
                if q is not None and q.unit != p.unit:
                    raise LoopError(f"loop '{lp.name}': {p.field} ({p.unit}) cannot share '{name}' ({q.unit})")
                if q is not None and name != p.name:  # the widest prior of the loops sharing it
                    new[k - start] = replace(q, prior=max(q.prior, p.prior))
            else:
                k = start + len(new)
                index[name] = k
                owner = name.split(".", 1)[0]
                new.append(p if name == p.name else replace(p, name=name, owner=owner))
            idx.append(k)
        cols.append(np.array(idx, dtype=int))
    return cols, new


def is_shared(problem: CalibrationProblem) -> np.ndarray:
    """(P,) True for the columns more than one loop reads."""
    count = np.zeros(len(problem.params), dtype=int)
    for c in problem.loop_columns:
        count[c] += 1
    return count > 1


def initial_shared(problem: CalibrationProblem, x0: np.ndarray, inits: list[np.ndarray | None]) -> np.ndarray:
    """x0 with each loop's initial estimate, shared columns at the mean over the loops, the rest refitted.

    `inits`: each loop's own initial vector (its `initialize_frames`, or None: nominal).
    """
    x = x0.copy()
    total = np.zeros(len(x))
    count = np.zeros(len(x))
    for cols, init in zip(problem.loop_columns, inits):
        if init is not None and cols.size:
            total[cols] += init
            count[cols] += 1
    hit = count > 0
    x[hit] = total[hit] / count[hit]
    return refine_unheld(problem, x, is_shared(problem))


def refine_unheld(problem: CalibrationProblem, x: np.ndarray, held: np.ndarray) -> np.ndarray:
    """`x` with each loop's unknowns that are not `held` (a mask over the problem's parameters) refitted on the
    loop's own residual with the held ones fixed (`loops.common.refine_own`): a start on a shared or given
    value, not on the loop's own guess of it.  Loops with no held parameter, or only held ones, keep theirs."""
    from closedloop.loops.common import refine_own

    x = np.array(x, dtype=float)
    for bi, (b, cols) in enumerate(zip(problem.blocks, problem.loop_columns)):
        mine = held[cols]
        if not mine.any() or mine.all() or b.theta.shape[0] == 0:
            continue
        Ts = problem.loop_frame_poses(x, bi)
        lp = b.loop
        p = refine_own(
            lambda q: lp.evaluate_frames(Ts, q, b.meas),
            lambda q: lp.residual_frames(Ts, q, b.meas),
            lp.normalize,
            x[cols].copy(),
            np.flatnonzero(~mine),
        )
        x[cols[~mine]] = p[~mine]
    return x
