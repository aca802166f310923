"""Named kinematic parameters and how they act on a Pinocchio model.

Every parameter has a stable name ``<owner>.<field>``:

* URDF/MJCF joints: ``j.x j.y j.z j.rx j.ry j.rz`` -- the placement error of
  the joint frame, a twist in the joint's OWN frame:  M_j = M0_j * exp6(p).
  Using the joint frame (not the parent's) makes the structural redundancies
  single components when the axis is a frame axis: ``j.rz`` duplicates
  ``j.offset`` and ``j.z`` is absorbed by the next joint (thesis 3.2, 4 of 6).
* ``j.offset`` and ``j.scale``: the sensor model of eq. 4.4,
  theta' = k * theta + theta_off, with nominal 0 and 1.
* ``j.compliance`` (opt-in): joint compliance c = 1/K (rad per N m).  Under
  actuator torque tau the link lags the motor-side reading by c * tau, so the
  full sensor model is  theta' = k * theta + theta_off - c * tau  (torques
  from the log's ``tau:<joint>`` columns).
* D-H rows: ``j.theta_off j.s j.a j.alpha j.k`` (eqs. 4.1, 4.2, 4.4).
* ``m.mimic`` (opt-in): the multiplier of a coupled joint m (URDF ``<mimic>``), whose angle is
  ``mimic * theta'_f + offset`` of the joint f it follows.
* Loop parameters (closure transforms, contact points) belong to the loops.

The derivative of a frame pose with respect to a geometric parameter is
written as a *generator*: the right-perturbation twist delta of the joint
placement that the parameter moves (M_j <- M_j exp6(delta dp)).  Pinocchio's
frame kinematic regressor (LOCAL) maps such twists to the frame's own
variation, so every geometric column of the calibration Jacobian is
``regressor @ G`` (the columns of eqs. 4.11-4.14, without writing them by hand).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from closedloop.errors import ModelError, ParameterError
from closedloop.model.dh import DHTable
from closedloop.model.robot import RobotModel

PLACEMENT_FIELDS = ("x", "y", "z", "rx", "ry", "rz")

# Default expected error magnitudes: used to scale Jacobian columns and to
# decide whether the data determine a direction better than this prior.
DEFAULT_PRIORS = {
    "m": 0.01,
    "rad": 0.01,
    "offset": 0.05,
    "scale": 0.05,
    "loop_m": 1.0,
    "loop_rad": 1.0,
    "compliance": 1e-4,
}


@dataclass
class Parameter:
    """One scalar kinematic parameter."""

    name: str
    kind: str  # 'placement' | 'offset' | 'scale' | 'dh' | 'loop'
    owner: str
    field: str
    nominal: float
    unit: str  # 'm', 'rad' or '1'
    prior: float
    scales_with_length: float = 0.0  # d(value)/d(eps) under lengths -> (1+eps) lengths
    priority: int = 3  # lower is kept first when parameters are redundant
    order: int = 0


@dataclass
class RobotState:
    """The robot at one parameter vector: a Pinocchio model and the sensor model."""

    model: pin.Model
    data: pin.Data
    offset: np.ndarray  # per joint of `joints`
    scale: np.ndarray
    compliance: np.ndarray
    G: np.ndarray  # (6*(njoints-1), P) right-twist generators of joint placements
    G_frames: dict[int, np.ndarray] = field(default_factory=dict)  # frame id -> (6, P)
    mimic: dict[str, float] = field(default_factory=dict)  # coupled joint -> its multiplier (URDF <mimic>)


def _dh_table(robot: RobotModel) -> DHTable:
    """The D-H table of a robot of kind "dh" (`RobotModel.from_file` builds every such robot with its table)."""
    if robot.dh is None:
        raise ModelError(f"robot '{robot.source}': a D-H robot without its D-H table")
    return robot.dh


class RobotParameters:
    """The robot-owned parameters of a set of joints.

    `joints` lists the joints to parameterize (the joints of the loops);
    values are the absolute parameter values (not errors).
    """

    def __init__(self, robot: RobotModel, joints: list[str], priors: dict | None = None):
        self.robot = robot
        self.joints = list(joints)
        pri = {**DEFAULT_PRIORS, **(priors or {})}
        self.params: list[Parameter] = []
        nominal_model = robot.model
        for order, name in enumerate(self.joints):
            j = robot.joint(name)
            ang = j.unit  # offset unit follows the joint type
            if robot.kind == "dh":
                row = _dh_table(robot).rows[j.jid - 1]
                for fld in ("s", "a", "alpha"):
                    unit = "rad" if fld == "alpha" or (fld == "a" and row.convention == "hayati") else "m"
                    val = getattr(row, fld)
                    self.params.append(
                        Parameter(
                            f"{name}.{fld}",
                            "dh",
                            name,
                            fld,
                            val,
                            unit,
                            pri[unit],
                            scales_with_length=val if unit == "m" else 0.0,
                            priority=4,
                            order=order,
                        )
                    )
                self.params.append(
                    Parameter(
                        f"{name}.theta_off",
                        "offset",
                        name,
                        "theta_off",
                        row.theta_off,
                        "rad",
                        pri["offset"],
                        priority=2,
                        order=order,
                    )
                )
                self.params.append(
                    Parameter(f"{name}.k", "scale", name, "k", row.k, "1", pri["scale"], priority=3, order=order)
                )
                self.params.append(
                    Parameter(
                        f"{name}.compliance",
                        "compliance",
                        name,
                        "compliance",
                        0.0,
                        "rad/Nm",
                        pri["compliance"],
                        priority=3,
                        order=order,
                    )
                )
            else:
                M0 = nominal_model.jointPlacements[j.jid]
                t_local = M0.rotation.T @ M0.translation  # scale direction in the joint frame
                for k, fld in enumerate(PLACEMENT_FIELDS):
                    unit = "m" if k < 3 else "rad"
                    self.params.append(
                        Parameter(
                            f"{name}.{fld}",
                            "placement",
                            name,
                            fld,
                            0.0,
                            unit,
                            pri[unit],
                            scales_with_length=float(t_local[k]) if k < 3 else 0.0,
                            priority=4,
                            order=order,
                        )
                    )
                self.params.append(
                    Parameter(
                        f"{name}.offset",
                        "offset",
                        name,
                        "offset",
                        0.0,
                        ang,
                        pri["offset"] if ang == "rad" else pri["m"],
                        priority=2,
                        order=order,
                    )
                )
                self.params.append(
                    Parameter(f"{name}.scale", "scale", name, "scale", 1.0, "1", pri["scale"], priority=3, order=order)
                )
                self.params.append(
                    Parameter(
                        f"{name}.compliance",
                        "compliance",
                        name,
                        "compliance",
                        0.0,
                        "rad/Nm" if ang == "rad" else "m/N",
                        pri["compliance"],
                        priority=3,
                        order=order,
                    )
                )
        for m, f, mult, _ in robot.coupled(self.joints):  # a coupled joint's multiplier (URDF <mimic>)
            self.params.append(
                Parameter(
                    f"{m}.mimic", "mimic", m, "mimic", mult, "1", pri["scale"], priority=3, order=self.joints.index(f)
                )
            )
        self.index = {p.name: i for i, p in enumerate(self.params)}
        self._mimic = [(m, self.index[f"{m}.mimic"]) for m, _, _, _ in robot.coupled(self.joints)]
        self._joint_pos = {n: i for i, n in enumerate(self.joints)}
        self._off_idx = np.array([self.index[self.sensor_name(n, "offset")] for n in self.joints], dtype=int)
        self._scale_idx = np.array([self.index[self.sensor_name(n, "scale")] for n in self.joints], dtype=int)
        self._comp_idx = np.array([self.index[f"{n}.compliance"] for n in self.joints], dtype=int)

    def sensor_name(self, joint: str, what: str) -> str:
        if self.robot.kind == "dh":
            return f"{joint}.{'theta_off' if what == 'offset' else 'k'}"
        return f"{joint}.{what}"

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.params])

    def offset_index(self) -> np.ndarray:
        return self._off_idx

    def scale_index(self) -> np.ndarray:
        return self._scale_idx

    def compliance_index(self) -> np.ndarray:
        return self._comp_idx

    # ------------------------------------------------------------------ apply
    def apply(self, values: np.ndarray) -> RobotState:
        """The model at `values` with its generator matrix.

        URDF joints:  M_j = M0_j exp6(p_j);  exp6(p + dp) = exp6(p) exp6(Jexp6(p) dp),
        so the generator block of joint j is Jexp6(p_j) (Pinocchio's right Jacobian).
        D-H rows: each of s, a, alpha moves the constant part C of A_j along a
        one-parameter subgroup, so its generator is exact at any value.

        The last state is kept and given again for the same values (a walk evaluates one configuration at a
        time at one model: a model copy per call was an eighth of its time); callers read it, and its `data`
        is Pinocchio's scratch.
        """
        values = np.asarray(values, dtype=float)
        key = values.tobytes()
        kept = self.__dict__.get("_applied")
        if kept is not None and kept[0] == key:
            return kept[1]
        state = self._apply(values)
        self.__dict__["_applied"] = (key, state)
        return state

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_applied"}  # a model and its data: not sent

    def _apply(self, values: np.ndarray) -> RobotState:
        """`apply`, computed."""
        robot = self.robot
        model = robot.model.copy()
        P = len(self.params)
        G = np.zeros((6 * (model.njoints - 1), P))
        G_frames: dict[int, np.ndarray] = {}
        if robot.kind == "dh":  # each row's s, a, alpha move its tail and its own head (`DHTable.placements`)
            geo = {n: tuple(values[self.index[f"{n}.{f}"]] for f in ("s", "a", "alpha")) for n in self.joints}
            cols = {n: [self.index[f"{n}.{f}"] for f in ("s", "a", "alpha")] for n in self.joints}
            G, G_frames = _dh_table(robot).placements(model, geo, P, cols)
        else:
            for name in self.joints:
                j = robot.joint(name)
                i0 = self.index[f"{name}.x"]
                p = values[i0 : i0 + 6]
                model.jointPlacements[j.jid] = robot.model.jointPlacements[j.jid] * pin.exp6(p)
                G[6 * (j.jid - 1) : 6 * j.jid, i0 : i0 + 6] = pin.Jexp6(p)
        return RobotState(
            model,
            model.createData(),
            values[self._off_idx].copy(),
            values[self._scale_idx].copy(),
            values[self._comp_idx].copy(),
            G,
            G_frames,
            {m: float(values[k]) for m, k in self._mimic},
        )

    def placement_errors(self, values: np.ndarray) -> dict[str, pin.SE3]:
        """Joint name -> calibrated joint placement (Pinocchio joint frame in its parent)."""
        state = self.apply(values)
        return {n: state.model.jointPlacements[self.robot.joint(n).jid] for n in self.joints}


def match(names: list[str], patterns: list[str]) -> list[str]:
    """Names matching any of the glob patterns, e.g. ``*.offset`` or ``panda_joint[2-7].*``.

    A pattern without a dot matches a whole kind: ``offset`` == ``*.offset``,
    ``placement`` == every placement component.
    """
    out = []
    for n in names:
        for pat in patterns:
            if pat == "placement":
                pat_list = [f"*.{f}" for f in PLACEMENT_FIELDS]
            elif "." not in pat and "*" not in pat:
                pat_list = [f"*.{pat}"]
            else:
                pat_list = [pat]
            if any(fnmatch.fnmatchcase(n, p) for p in pat_list):
                out.append(n)
                break
    return out


def fix_values(spec: list[str]) -> dict[str, float | None]:
    """``--fix j3.s`` / ``--fix j3.s=1.0`` items (comma-separated within one) as pattern -> value (None
    keeps the current value); the patterns are matched against a problem's names by `expand_fix`."""
    fixed: dict[str, float | None] = {}
    for item in spec:
        for part in item.split(","):
            part = part.strip()
            if not part:
                continue
            key, _, val = part.partition("=")
            value: float | None = None
            if val:
                from closedloop.io.schemas import parse_number  # strict: no 1_000, no nan

                value = parse_number(val, f"--fix {part}", ParameterError)
            fixed[key.strip()] = value
    return fixed


def expand_fix(fix: dict[str, float | None], names: list[str]) -> dict[str, float | None]:
    """Fixed parameters by pattern (`match`) -> by name; a pattern that names no parameter is refused."""
    out: dict[str, float | None] = {}
    for key, value in fix.items():
        matched = match(names, [key])
        if not matched:
            raise ParameterError(f"--fix {key}: no parameter named '{key}'")
        for m in matched:
            out[m] = value
    return out


def parse_fix(spec: list[str], names: list[str]) -> dict[str, float | None]:
    """Parse ``--fix j3.s`` / ``--fix j3.s=1.0`` (patterns allowed without a value) against `names`."""
    return expand_fix(fix_values(spec), names)
