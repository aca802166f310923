"""What a loop spec sets on a loop beyond its type's own keys: shared parameter groups and task noise.

* ``KEY=@GROUP`` (`share`): the loop's parameters of share key KEY are the group's, one column in the
  problem for every loop naming the group (`closedloop.problem.shared` builds the columns);
* ``sigma_task=LENGTH`` (`set_task_noise`): a task-space noise on the loop's translation rows, a
  variance component of the fit when ``auto`` (`closedloop.estimate.variance`).

Both are configuration, set once on the loop when it is made; what a calibration estimates goes to
the problem, not here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from closedloop.errors import LoopError, ParameterError

if TYPE_CHECKING:
    from closedloop.loops.base import Loop


#: share key -> the parameter fields it names (a key 'camK' names every field 'camK.*')
SHARE_KEYS: dict[str, tuple[str, ...]] = {
    "tip": ("tip_x", "tip_y", "tip_z"),
    "point": ("px", "py", "pz"),
    "normal": ("nrx", "nry", "d"),
    "closure": ("x", "y", "z", "rx", "ry", "rz"),
    "base": ("x", "y", "z", "rx", "ry", "rz"),
    "tool": ("tool_x", "tool_y", "tool_z", "tool_rx", "tool_ry", "tool_rz"),
    "hinge": ("hinge_x", "hinge_y", "hinge_rx", "hinge_ry", "radius", "height"),
}


def key_fields(loop: Loop, key: str) -> list[str]:
    """The fields of `loop`'s own parameters that share key `key` names (LoopError if none)."""
    fields = [p.field for p in loop.parameters()]
    if key.startswith("cam") and key[3:].isdigit():
        out = [f for f in fields if f.startswith(key + ".")]
    elif key in SHARE_KEYS:
        out = [f for f in fields if f in SHARE_KEYS[key]]
    else:
        raise LoopError(
            f"loop '{loop.name}': '{key}' cannot be shared (share keys: {', '.join(sorted(SHARE_KEYS))}, camK)"
        )
    if not out:
        raise LoopError(f"loop '{loop.name}': no unknown parameter for '{key}' to share (is it given?)")
    return out


def share(loop: Loop, key: str, group: str) -> Loop:
    """Make the parameters of `key` of `loop` the shared group `group` (returns the loop)."""
    group = group.strip().lstrip("@")
    if not group or not all(c.isalnum() or c in "_-" for c in group):
        raise LoopError(f"loop '{loop.name}': shared group name '{group}' must be letters, digits, '_' or '-'")
    shared = dict(getattr(loop, "shared", None) or {})
    for f in key_fields(loop, key):
        shared[f] = f"{group}.{f}"
    loop.shared = shared
    return loop


def parse_sigma(text: str) -> float | np.ndarray | str:
    """'0.2mm' / '200um' / '2e-4' (m) / '0.1/0.1/0.3mm' (per axis) / 'auto' -> metres or 'estimate'."""
    t = str(text).strip().lower().replace(" ", "")
    if t in ("auto", "estimate", "estimated"):
        return "estimate"
    if "/" in t:  # per axis, one unit at the end: 0.1/0.1/0.3mm
        unit = t.lstrip("0123456789.e+-/")
        parts = t[: len(t) - len(unit)].split("/")
        return np.array([parse_sigma(p + unit) for p in parts])
    for unit, f in (("mm", 1e-3), ("um", 1e-6), ("µm", 1e-6), ("cm", 1e-2), ("m", 1.0)):
        if t.endswith(unit):
            t, factor = t[: -len(unit)], f
            break
    else:
        factor = 1.0
    try:
        v = float(t) * factor
    except ValueError:
        raise ParameterError(f"sigma_task={text}: expected a length (0.2mm, 2e-4) or 'auto'") from None
    if not np.isfinite(v) or v < 0 or v > 1.0:
        raise ParameterError(f"sigma_task={text}: expected a length between 0 and 1 m")
    return v


def set_task_noise(loop: Loop, value) -> Loop:
    """Give `loop` a task-space noise: a length (m; per-axis: three), 'estimate'/'auto', or 0 (none).

    The loop's measurement covariance becomes its own (a tracker's, if any)
    plus sigma_task^2 on its translation rows; 'estimate' makes sigma_task a
    variance component estimated with the joint noise (`variance_components`).
    Configuration, set once on the loop: ``loop.own_cov`` keeps the covariance
    without the task term, ``loop.task_var`` the given variance (what a
    calibration estimates goes to the problem's `BlockNoise`, not here).
    """
    if isinstance(value, str):
        value = parse_sigma(value)
    if not hasattr(loop, "own_cov"):
        loop.own_cov = loop.measurement_cov
    rows = list(loop.translation_rows)
    if not rows:
        raise ParameterError(f"loop '{loop.name}': sigma_task needs a loop with translation rows")
    if isinstance(value, str):
        loop.task_noise = "estimate"
        return loop
    sig = np.asarray(value, dtype=float).reshape(-1)
    if sig.size not in (1, len(rows)):
        raise ParameterError(f"loop '{loop.name}': sigma_task has {sig.size} values for {len(rows)} translation rows")
    sig = np.broadcast_to(sig, (len(rows),)).copy()
    if np.any(~np.isfinite(sig)) or np.any(sig < 0):
        raise ParameterError(f"loop '{loop.name}': sigma_task must be finite and >= 0")
    loop.task_noise = sig
    if not np.any(sig):  # sigma_task=0: no task-space noise (the joint noise alone)
        loop.measurement_cov, loop.task_var = loop.own_cov, None
        return loop
    _apply_task(loop, sig**2)
    return loop


def task_matrix(loop: Loop) -> np.ndarray:
    T = np.zeros((loop.dim, loop.dim))
    rows = list(loop.translation_rows)
    T[rows, rows] = 1.0
    return T


def _apply_task(loop: Loop, var: np.ndarray | float) -> None:
    """measurement_cov = the loop's own covariance + diag(var) on its translation rows."""
    base = getattr(loop, "own_cov", None)
    T = task_matrix(loop)
    T[T > 0] = np.broadcast_to(np.asarray(var, dtype=float), (int(T.sum()),))
    loop.measurement_cov = T if base is None else base + T
    loop.task_var = var
