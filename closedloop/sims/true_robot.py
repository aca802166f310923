"""The draw of the true robot: which parameters are perturbed, and by how much.

Truth model (:func:`perturbable_parameters`, :func:`draw_errors`): the true
robot equals the nominal one plus uniform random errors, per parameter kind

* ``translation`` (``<joint>.x .y .z``) U(-m, m) metres, default m = 2 mm;
* ``rotation`` (``<joint>.rx .ry .rz``) U(-m, m) rad, default m = 2 mrad;
* ``offset`` (``<joint>.offset``) U(-m, m) rad, default m = 0.02 rad;
* ``scale`` (``<joint>.scale``) 1 + U(-m, m), default m = 0 (not perturbed).

Which parameters are drawn (the setting ``truth``): ``identifiable`` (:func:`identifiable_parameters`,
what a calibration of the loop estimates) or ``all`` (:func:`all_parameters`, every joint origin of the
driven chain, the lengths a calibration must hold at their nominal values included, as a real robot
file's errors are).

A joint placement error is a right twist in the joint's own frame:
``M = M0 * exp6([x, y, z, rx, ry, rz])``.  Sensor model (thesis eq. 4.4):
``theta_true = scale * reading + offset``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.sims.loop_types import sim_loop
from closedloop.sims.scenarios import Scenario

__all__ = ["perturbable_parameters", "identifiable_parameters", "all_parameters", "draw_errors"]

_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")


def _axis_component(axis: np.ndarray) -> int | None:
    """Index 0/1/2 of the coordinate axis a unit joint axis is aligned with, else None."""
    a = np.abs(np.asarray(axis, dtype=float))
    i = int(np.argmax(a))
    return i if a[i] > 1.0 - 1e-9 else None


def perturbable_parameters(model: pin.Model, joint_names: list[str], scale: bool = False) -> list[str]:
    """Names of the parameters that are perturbed in the true robot.

    The fixed rule for a serial chain of revolute joints welded to an unknown
    fixture (the core's automatic reduction may replace it):

    * the first joint's placement is not perturbed (base gauge, absorbed by the
      unknown closure) and neither is its offset;
    * for every other joint, the placement components along the joint axis are
      not perturbed: rotation about the axis (duplicates the offset) and
      translation along it (absorbed by the next joint).  For axis z these are
      ``.rz`` and ``.z``; for an axis along x or y, ``.rx``/``.x`` or ``.ry``/``.y``;
    * fixed joints (tool, flanges) are never perturbed;
    * offsets of all joints but the first are perturbed; scales of all joints
      only when ``scale`` is true.

    Args:
        model: nominal Pinocchio model.
        joint_names: the movable 1-DOF joints of the chain, in Pinocchio order.
        scale: include ``<joint>.scale`` parameters.
    """
    names: list[str] = []
    for k, jn in enumerate(joint_names):
        jid = model.getJointId(jn)
        jm = model.joints[jid]
        short = jm.shortname()
        if short in ("JointModelRX", "JointModelRY", "JointModelRZ"):
            skip_axis: int | None = "XYZ".index(short[-1])
        elif short == "JointModelRevoluteUnaligned":
            skip_axis = _axis_component(jm.axis)
        else:
            skip_axis = None
        if k > 0:
            for c, comp in enumerate(_COMPONENTS):
                if skip_axis is not None and c % 3 == skip_axis:
                    continue
                names.append(f"{jn}.{comp}")
            names.append(f"{jn}.offset")
        if scale:
            names.append(f"{jn}.scale")
    return names


# identifiable_parameters' answers in this process, by nominal robot file's text, scenario, joints and `scale`
_IDENTIFIABLE: dict[tuple[str, str, tuple[str, ...], bool], tuple[str, ...]] = {}
_IDENTIFIABLE_KEPT = 64


def identifiable_parameters(nominal_path, sc: Scenario, joint_names: list[str], scale: bool = False) -> list[str]:
    """The parameters to perturb: those a calibration of the scenario's loop estimates.

    Errors in structurally redundant parameters are indistinguishable from errors in the
    parameters that absorb them, so a truth that ``closedloop check`` can compare parameter by
    parameter is drawn in the identifiable set, read off the nominal robot's structure
    (:mod:`closedloop.studies.identifiable`: self-motion through the grasp configuration for a closed
    loop, random configurations for a measured one).  Loop types with no loop class in the
    calibration core fall back to :func:`perturbable_parameters`.

    The answer depends on the nominal file, the scenario and the joints alone (its walk has a fixed seed):
    kept for the process (the last 64), so that another dataset of the same scenario (another seed, size
    or setting) does not walk the nominal robot's self-motion again.
    """
    key = (Path(nominal_path).read_text(), repr(sc), tuple(joint_names), bool(scale))
    names = _IDENTIFIABLE.get(key)
    if names is None:
        names = tuple(_identifiable_parameters(nominal_path, sc, joint_names, scale))
        if len(_IDENTIFIABLE) >= _IDENTIFIABLE_KEPT:
            del _IDENTIFIABLE[next(iter(_IDENTIFIABLE))]
        _IDENTIFIABLE[key] = names
    return list(names)


def _identifiable_parameters(nominal_path, sc: Scenario, joint_names: list[str], scale: bool) -> list[str]:
    """`identifiable_parameters`, computed."""
    from closedloop.model.robot import RobotModel
    from closedloop.studies.identifiable import DEFAULT_IDENTIFY, identifiable_names, measured_identifiable_names

    kind = sim_loop(sc.loop_type)
    loop = kind.core_loop(sc, nominal_path)
    if loop is None:
        model = pin.buildModelFromUrdf(str(nominal_path))
        return perturbable_parameters(model, joint_names, scale=scale)
    robot = RobotModel.from_file(nominal_path)
    identify = DEFAULT_IDENTIFY + (("scale",) if scale else ())
    if not kind.closed:
        names = measured_identifiable_names(robot, loop, identify)
    else:
        names = identifiable_names(robot, [loop], np.asarray(sc.q0, dtype=float)[None, :], identify)
    return [n for n in names if n.rsplit(".", 1)[0] in joint_names]


def all_parameters(joint_names: list[str], scale: bool = False) -> list[str]:
    """Every placement component (x, y, z, rx, ry, rz) and the offset of every driven joint (its scale too
    with `scale`): the truth of a robot file whose every joint origin is off, the first joint's and the
    components along each axis included.  Those a calibration cannot see are absorbed by the base, by a
    neighbour or by the length it holds: the overall size of the true robot differs from the nominal one
    by what the held length is off."""
    names: list[str] = []
    for jn in joint_names:
        names += [f"{jn}.{c}" for c in _COMPONENTS] + [f"{jn}.offset"]
        if scale:
            names.append(f"{jn}.scale")
    return names


def _kind(name: str) -> str:
    comp = name.rsplit(".", 1)[1]
    if comp in ("x", "y", "z"):
        return "translation"
    if comp in ("rx", "ry", "rz"):
        return "rotation"
    return comp  # offset / scale


def draw_errors(names: list[str], rng: np.random.Generator, magnitudes: dict[str, float]) -> dict[str, float]:
    """Draw true parameter values: uniform in +/- magnitude per kind; scale = 1 + U(-m, m).

    Args:
        names: parameter names (see :func:`perturbable_parameters`).
        rng: random generator (one uniform draw per name, in order).
        magnitudes: magnitude per kind (``translation``, ``rotation``, ``offset``, ``scale``).
    """
    out: dict[str, float] = {}
    for name in names:
        kind = _kind(name)
        m = float(magnitudes.get(kind, 0.0))
        u = float(rng.uniform(-1.0, 1.0))
        out[name] = (1.0 + m * u) if kind == "scale" else m * u
    return out
