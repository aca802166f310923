"""A rig's known geometry as the options give it, read into records before the model is: the distances
between loop points (``--distance A.point B.point METRES [SIGMA]``), the points of a block at known
positions in its own frame (``--block NAME A.point=X,Y,Z B.point=X,Y,Z ... [sigma=S]``: its pairwise
distances), the lengths between two frames of the robot (``--length FRAME_A FRAME_B METRES [SIGMA]``).

What the text alone decides is refused here, one line naming the option as given: the number of words, a
number that is not one (`closedloop.io.schemas.parse_number`), a block's points at one position, a length
that is not positive.  What needs the loops or the model is checked where they are made loops:
`closedloop.problem.distances.distance_loops` (the loops' points), `closedloop.problem.lengths.length_loops_on`
(the robot's frames and its nominal lengths).  In a ``--config`` file each occurrence may be one line of
words ("A B 0.05", "[A, B, 0.05]").
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from closedloop.errors import LoopError
from closedloop.io.schemas import parse_number


@dataclass(frozen=True)
class KnownDistance:
    """A known distance between two loop points (``LOOP.point`` or ``LOOP.tip``), metres; `sigma` None for
    the default; `block` names the block it is a pairwise distance of."""

    a: str
    b: str
    distance: float
    sigma: float | None = None
    block: str | None = None


@dataclass(frozen=True)
class KnownLength:
    """A known length between two frames of the robot, metres; `sigma` None for the default; `given` is the
    option as it was given, for the messages."""

    frame_a: str
    frame_b: str
    length: float
    sigma: float | None = None
    given: str = ""


@dataclass(frozen=True)
class Rig:
    """A run's known geometry: the distances (``--distance``, then each ``--block``'s pairwise ones) and the
    lengths (``--length``), in the order given."""

    distances: tuple[KnownDistance, ...] = ()
    lengths: tuple[KnownLength, ...] = ()


def parse_rig(distances: list, blocks: list, lengths: list) -> Rig:
    """The `Rig` of the ``--distance``, ``--block`` and ``--length`` occurrences (lists of words or lines)."""
    return Rig(
        distances=(*known_distances(distances), *block_distances(blocks)),
        lengths=tuple(known_lengths(lengths)),
    )


def _words(item) -> list[str]:
    """An occurrence's words: a list as given, or a ``--config`` line split at spaces, commas and brackets."""
    if isinstance(item, str):
        return [t for t in re.split(r"[\s,\[\]'\"]+", item) if t]
    return [str(t) for t in item]


def known_distances(items: list) -> list[KnownDistance]:
    """``--distance A B D [SIGMA]`` occurrences -> records."""
    out = []
    for item in items:
        it = _words(item)
        if len(it) not in (3, 4):
            raise LoopError(
                f"--distance {' '.join(it)}: expected A B DISTANCE [SIGMA] (e.g. front_a.point front_b.point 0.050)"
            )
        nums = [parse_number(t, f"--distance {' '.join(it)}", LoopError) for t in it[2:]]
        out.append(KnownDistance(it[0], it[1], nums[0], nums[1] if len(nums) > 1 else None))
    return out


def block_distances(items: list) -> list[KnownDistance]:
    """``--block NAME A.point=X,Y,Z B.point=X,Y,Z ... [sigma=S]`` occurrences -> the pairwise distances of
    each block's points (positions in the block's own frame, metres; `closedloop.problem.distances`)."""
    out = []
    for item in items:
        it = item.split() if isinstance(item, str) else [str(t) for t in item]
        where = f"--block {' '.join(it)}"
        if len(it) < 3 or "=" in it[0]:
            raise LoopError(f"{where}: expected NAME A.point=X,Y,Z B.point=X,Y,Z ... [sigma=S] (two points or more)")
        sigma, pts = None, []
        for t in it[1:]:
            ref, eq, val = t.partition("=")
            if not eq:
                raise LoopError(f"{where}: '{t}' is not REF=X,Y,Z")
            if ref == "sigma":
                sigma = parse_number(val, where, LoopError)
                continue
            xyz = [parse_number(v, where, LoopError) for v in re.split(r"[,\s\[\]]+", val) if v]
            if len(xyz) != 3:
                raise LoopError(f"{where}: {ref} needs 3 coordinates X,Y,Z (m), got '{val}'")
            pts.append((ref, np.array(xyz, dtype=float)))
        if len(pts) < 2:
            raise LoopError(f"{where}: a block needs two points or more")
        for (ra, sa), (rb, sb) in combinations(pts, 2):
            d = float(np.linalg.norm(sa - sb))
            if d <= 0.0:
                raise LoopError(f"{where}: {ra} and {rb} are at the same position")
            out.append(KnownDistance(ra, rb, d, sigma, block=it[0]))
    return out


def known_lengths(items: list) -> list[KnownLength]:
    """``--length A B L [SIGMA]`` occurrences -> records; the length and its sigma positive."""
    out = []
    for item in items:
        it = _words(item)
        where = f"--length {' '.join(it)}"
        if len(it) not in (3, 4):
            raise LoopError(f"{where}: expected FRAME_A FRAME_B METRES [SIGMA] (e.g. panda_link3 panda_link4 0.0825)")
        nums = [parse_number(t, where, LoopError) for t in it[2:]]
        if nums[0] <= 0 or (len(nums) > 1 and nums[1] <= 0):
            raise LoopError(f"{where}: the length and its SIGMA must be positive (metres)")
        out.append(KnownLength(it[0], it[1], nums[0], nums[1] if len(nums) > 1 else None, given=where))
    return out
