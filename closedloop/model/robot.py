"""A robot model on Pinocchio, read from URDF, MJCF or a D-H table.

`RobotModel` knows the movable one-degree-of-freedom joints (revolute,
continuous, prismatic), maps joint readings to Pinocchio configurations and
finds frames by name.  Every later feature works on it whatever the source.
"""

from __future__ import annotations

import difflib
import logging
import re
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import pinocchio as pin

from closedloop.errors import ModelError
from closedloop.model.dh import DHTable, dh_table
from closedloop.model.stacked import StackedKinematics

log = logging.getLogger(__name__)

WORLD_FRAMES = ("universe", "world")
#: the model file suffixes a calibrated model is written with, for each input kind (`RobotModel.check_output`)
MODEL_SUFFIXES = {"urdf": (".urdf",), "dh": (".yaml", ".yml"), "mjcf": (".xml", ".mjcf")}


@dataclass(frozen=True)
class JointInfo:
    """A movable one-DOF joint.

    `axis` is the motion axis in the joint frame (angular for revolute joints,
    linear for prismatic ones); `continuous` joints use (cos, sin) in q.
    """

    name: str
    jid: int
    idx_q: int
    idx_v: int
    kind: str  # 'revolute' | 'continuous' | 'prismatic'
    axis: np.ndarray
    lower: float
    upper: float

    @property
    def unit(self) -> str:
        return "m" if self.kind == "prismatic" else "rad"


def limit_margins(lower, upper, margin: float, fraction: float = 0.1) -> np.ndarray:
    """Per-joint distances to keep from the joint limits: `margin` (radians, for a revolute joint's
    range of a few radians), but at most `fraction` of each joint's range, so that a short range in
    its own unit (a 4 cm prismatic finger, in metres) keeps most of its travel; an unlimited joint
    (an infinite range) gets `margin`."""
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    span = np.where(np.isfinite(hi - lo), np.maximum(hi - lo, 0.0), np.inf)
    return np.minimum(margin, fraction * span)


def find_frame(model: pin.Model, name: str) -> int:
    """The id of frame `name` in a Pinocchio model; where a joint and a link share the name (URDF allows it:
    Pinocchio then has a joint frame and a body frame of that name), the link's (a loop's frame is a link)."""
    ids = [i for i, f in enumerate(model.frames) if f.name == name]
    if len(ids) > 1:
        bodies = [i for i in ids if model.frames[i].type == pin.FrameType.BODY]
        return bodies[0] if bodies else ids[0]
    return model.getFrameId(name)


class RobotModel:
    """The nominal kinematic model of a robot."""

    def __init__(self, model: pin.Model, source: Path | None = None, kind: str = "urdf", dh: DHTable | None = None):
        self.model = model
        self.source = source
        self.kind = kind
        self.dh = dh
        self.joints: dict[str, JointInfo] = {}
        self._unsupported: dict[str, str] = {}
        self.mimic: dict[str, str] = {}  # URDF <mimic>: joint -> the joint it follows (see supporting_joints)
        self.mimic_coupling: dict[str, tuple[float, float]] = {}  # joint -> (multiplier, offset)
        self.urdf_tree: dict[str, tuple[str, str]] = {}  # URDF joint -> (parent link, child link)
        self.held: frozenset[str] = frozenset()  # URDF joints `closedloop simulate --robot` held fixed
        # a calibrated URDF's joints: the change (4x4, right-multiplied) from each joint's origin back to the one
        # of the model it was calibrated from (`io.robot_files.NOMINAL_ORIGIN`), where the structure of a
        # recalibration is read
        self.calibrated_from: dict[str, np.ndarray] = {}
        data = model.createData()
        q0 = pin.neutral(model)
        pin.computeJointJacobians(model, data, q0)
        for jid in range(1, model.njoints):
            jm = model.joints[jid]
            name = model.names[jid]
            short = jm.shortname()
            if jm.nv != 1:
                self._unsupported[name] = short
                continue
            # (a one-column Jacobian comes back as a 1-D array: reshape)
            J = np.asarray(pin.getJointJacobian(model, data, jid, pin.LOCAL)).reshape(6, model.nv)
            S = J[:, jm.idx_v]
            if "Prismatic" in short or short.startswith("JointModelP"):
                kind_j, axis = "prismatic", S[:3]
            else:
                kind_j, axis = ("continuous" if jm.nq == 2 else "revolute"), S[3:]
            if not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-9:
                raise ModelError(
                    f"{source or model.name}: joint '{name}' has a zero or invalid axis "
                    f"{np.round(axis, 6).tolist()}; give a nonzero <axis xyz=...>"
                )
            lo, hi = (
                (-np.pi, np.pi)
                if jm.nq == 2
                else (model.lowerPositionLimit[jm.idx_q], model.upperPositionLimit[jm.idx_q])
            )
            self.joints[name] = JointInfo(name, jid, jm.idx_q, jm.idx_v, kind_j, axis.copy(), float(lo), float(hi))

    @cached_property
    def stacked(self) -> StackedKinematics:
        """Forward kinematics of many configurations at once for this joint tree (`model.stacked`)."""
        return StackedKinematics(self.model)

    def calibrated_from_model(self) -> "RobotModel":
        """This robot with the joints of `calibrated_from` put back at the origins of the model it was calibrated
        from (self where there are none): the same joints, frames and names, at the nominal geometry."""
        if not self.calibrated_from:
            return self
        model = self.model.copy()
        for name, back in self.calibrated_from.items():
            if name in self.joints:
                jid = self.joints[name].jid
                model.jointPlacements[jid] = model.jointPlacements[jid] * pin.SE3(back[:3, :3], back[:3, 3])
        robot = RobotModel(model, self.source, self.kind, self.dh)
        robot.mimic, robot.mimic_coupling = dict(self.mimic), dict(self.mimic_coupling)
        return robot

    # ----------------------------------------------------------------- loading
    @classmethod
    def from_file(cls, path: str | Path) -> "RobotModel":
        """Load a URDF (.urdf), MJCF (.xml/.mjcf) or D-H table (.yaml/.yml): the file read and checked once
        (`closedloop.io.robot_files.read_model_file`), then the model built from it."""
        from closedloop.io.robot_files import read_model_file

        src = read_model_file(path)
        path = src.path
        if src.dh is not None:
            table = dh_table(src.dh, path)
            return cls(table.build_model(), path, "dh", table)
        build = pin.buildModelFromUrdf if src.kind == "urdf" else pin.buildModelFromMJCF
        with _captured_stderr() as log_lines:
            try:
                model = build(str(path))
            except Exception as exc:  # Pinocchio raises plain ValueError/RuntimeError
                text = " ".join(str(exc).split()) or type(exc).__name__
                said = " ".join(log_lines()[:1])
                raise ModelError(f"{path}: Pinocchio cannot parse this model ({said or text})"[:400]) from None
        robot = cls(model, path, src.kind)
        if src.urdf is not None:
            urdf = src.urdf
            robot.mimic = {j: f for j, (f, _, _) in urdf.mimics.items()}
            robot.mimic_coupling = {j: (m, o) for j, (_, m, o) in urdf.mimics.items()}
            robot.urdf_tree, robot.held, robot.calibrated_from = urdf.tree, urdf.held, urdf.calibrated_from
        return robot

    # ------------------------------------------------------------------ lookup
    @property
    def joint_names(self) -> list[str]:
        return list(self.joints)

    @property
    def urdf_path(self) -> Path | None:
        return self.source if self.kind == "urdf" else None

    def joint(self, name: str) -> JointInfo:
        try:
            return self.joints[name]
        except KeyError:
            if name in self._unsupported:
                raise ModelError(
                    f"joint '{name}' is a {self._unsupported[name]} joint; only 1-DOF "
                    "revolute, continuous and prismatic joints can be calibrated"
                ) from None
            raise ModelError(f"unknown joint '{name}'{_suggest(name, self.joint_names)}") from None

    def frame_id(self, name: str) -> int:
        """Pinocchio frame id of `name`; 'world' and 'universe' are the base frame."""
        if name in WORLD_FRAMES:
            return 0
        known = self.__dict__.setdefault("_frame_ids", {})  # name -> (model, its frame count, id): a lookup
        hit = known.get(name)  # per evaluation scans every frame of a large model
        if hit is not None and hit[0] is self.model and hit[1] == self.model.nframes:
            return hit[2]
        if not self.model.existFrame(name):
            names = [f.name for f in self.model.frames]
            raise ModelError(f"unknown frame '{name}'{_suggest(name, names)}")
        fid = find_frame(self.model, name)
        known[name] = (self.model, self.model.nframes, fid)
        return fid

    def supporting_joints(self, frame: str) -> list[str]:
        """Movable joints between the base and `frame`, base first; a coupled joint (URDF ``<mimic>``) is
        replaced by the joint it follows (its reading moves it: `configurations`)."""
        fid = self.frame_id(frame)
        if fid == 0:
            return []
        jid = self.model.frames[fid].parentJoint
        support = [self.model.names[j] for j in self.model.supports[jid]]
        out: list[str] = []
        for j in support:
            if j in self.mimic:
                j = self.followed(j, frame)
            if j in self.joints and j not in out:
                out.append(j)
        return out

    def followed(self, joint: str, frame: str = "") -> str:
        """The joint a coupled joint follows (URDF ``<mimic joint=...>``); a ModelError when that joint is
        not a movable joint of the model or is itself coupled."""
        f = self.mimic[joint]
        where = f" (between the base and frame '{frame}')" if frame else ""
        if f not in self.joints or f in self.mimic:
            raise ModelError(
                f"joint '{joint}'{where} mimics joint '{f}' (URDF <mimic>), which is "
                + ("itself coupled: a chain of mimics is not supported" if f in self.mimic else "not a movable joint")
            )
        return f

    def coupled(self, joint_names: list[str]) -> list[tuple[str, str, float, float]]:
        """The coupled joints that follow one of `joint_names`: (joint, followed, multiplier, offset)."""
        return [
            (j, f, *self.mimic_coupling.get(j, (1.0, 0.0)))
            for j, f in self.mimic.items()
            if f in joint_names and j not in joint_names and j in self.joints
        ]

    # ----------------------------------------------------------- configurations
    def configurations(
        self, angles: np.ndarray, joint_names: list[str], multipliers: dict[str, float] | None = None
    ) -> np.ndarray:
        """Pinocchio configurations (N, nq) from joint angles (N, len(joint_names)).

        Joints not listed stay at their neutral value, but a coupled joint (URDF ``<mimic>``) whose
        followed joint is listed takes ``multiplier * angle + offset`` of it (`multipliers`: coupled
        joint -> a multiplier other than the file's).  Continuous joints get (cos, sin) coordinates.
        """
        angles = np.atleast_2d(angles)
        q = np.tile(pin.neutral(self.model), (angles.shape[0], 1))
        for col, name in enumerate(joint_names):
            j = self.joints[name]
            if j.kind == "continuous":
                q[:, j.idx_q] = np.cos(angles[:, col])
                q[:, j.idx_q + 1] = np.sin(angles[:, col])
            else:
                q[:, j.idx_q] = angles[:, col]
        for name, f, mult, off in self.coupled(joint_names):
            mult = (multipliers or {}).get(name, mult)
            q[:, self.joints[name].idx_q] = mult * angles[:, joint_names.index(f)] + off
        return q

    @property
    def has_inertias(self) -> bool:
        """Whether the model carries real masses (a URDF's or MJCF's inertials; a D-H table has none)."""
        return self.kind != "dh" and float(sum(self.model.inertias[j].mass for j in range(1, self.model.njoints))) > 0.0

    def held_on_chain(self, frames: list[str]) -> list[str]:
        """The joints `closedloop simulate --robot` held fixed (`held`: marked
        `closedloop.io.robot_files.HELD` in the URDF) on the loop through `frames` (links or joints of the
        URDF): between the root and one frame, or between two (their common ancestors left out), root
        first; empty when the model marks none."""
        if not self.held:
            return []
        by_child = {child: j for j, (_, child) in self.urdf_tree.items()}
        chains: list[list[str]] = []
        for frame in frames:
            j = frame if frame in self.urdf_tree else by_child.get(frame)
            chain: list[str] = []
            while j is not None and j not in chain:  # a cycle is check_urdf's to refuse
                chain.append(j)
                j = by_child.get(self.urdf_tree[j][0])
            chains.append(chain[::-1])
        common = set(chains[0]).intersection(*chains[1:]) if len(chains) > 1 else set()
        out = [j for chain in chains for j in chain if j in self.held and j not in common]
        return list(dict.fromkeys(out))

    def check_output(self, out: str | Path | None) -> None:
        """The calibrated model is written in this model's own format (`closedloop.output.urdf.model_text`):
        the output's suffix must say so (`MODEL_SUFFIXES`); refused before any work."""
        from closedloop.errors import InputError

        if out is None:
            return
        suffixes = MODEL_SUFFIXES.get(self.kind)
        if not suffixes:
            raise InputError(
                f"--out {out}: no calibrated model can be written for {self.kind} input {self.source or ''} "
                "(the report holds the parameters); drop --out"
            )
        if Path(out).suffix.lower() not in suffixes:
            raise InputError(
                f"--out {out}: a {self.kind} input gives a calibrated {self.kind} model; name it *{' or *'.join(suffixes)}"
            )

    def with_gravity_torques(self, lg):
        """The log `lg` (`closedloop.io.logs.JointLog`) with ``tau:<joint>`` columns from the model's
        inertials (`gravity_torques`) when it carries none and the model has masses; otherwise as it is.
        The compliance model (theta' = k theta + theta_off - c tau) then needs no torque logging on a robot
        that carries only itself; logged torques always win.  Its `torque_source` says which: 'log',
        'gravity' or None."""
        present = [j for j in self.joint_names if f"tau:{j}" in lg.extra]
        if present or not self.has_inertias:
            lg.torque_source = "log" if present else None
            return lg
        known = [j for j in self.joint_names if j in lg.joints]
        tau = self.gravity_torques(lg.columns(known), known)
        lg.extra.update({f"tau:{j}": tau[:, k] for k, j in enumerate(known)})
        lg.torque_source = "gravity"
        return lg

    def gravity_torques(self, angles: np.ndarray, joint_names: list[str]) -> np.ndarray:
        """Joint torques that hold the robot still against gravity at each configuration (N, len(joint_names)).

        The generalized gravity g(q) of the model's inertials (Pinocchio's RNEA at zero velocity and
        acceleration, ``pin.computeGeneralizedGravity``): the actuator torque of a static arm carrying
        only itself.  Contact or payload forces are not in it.  Joints not listed stay at their neutral
        value.
        """
        model, data, gravity = self.model, self.model.createData(), pin.computeGeneralizedGravity
        q = self.configurations(angles, joint_names)
        idx = [self.joints[n].idx_v for n in joint_names]
        if not q.shape[0]:
            return np.empty((0, len(joint_names)))
        stacked = self.stacked.gravity(model, q)  # every configuration at once (`model.stacked`)
        if stacked is not None:
            return stacked[:, idx]
        # a list comprehension gathers the rows fastest (a Pinocchio call per configuration)
        return np.array([gravity(model, data, qi) for qi in q])[:, idx]

    def describe(self) -> dict:
        """Joints and frames, for `closedloop inspect`."""
        return {
            "source": str(self.source) if self.source else None,
            "kind": self.kind,
            "joints": [
                {"name": j.name, "type": j.kind, "axis": j.axis.round(6).tolist(), "lower": j.lower, "upper": j.upper}
                for j in self.joints.values()
            ],
            "unsupported_joints": self._unsupported,
            "mimic_joints": dict(self.mimic),
            "frames": [f.name for f in self.model.frames if f.name != "universe"],
        }


@contextmanager
def _captured_stderr():
    """Hold what C++ code writes to the process's stderr (urdfdom logs its refusals there, several lines
    each) during the block; yields a function returning those lines, stripped of their log prefixes."""
    import os
    import sys
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real stderr (embedded): nothing to capture
        yield lambda: []
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)

        def lines() -> list[str]:
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
            out = [re.sub(r"^\s*(\x1b\[[0-9;]*m)*(Error|Warning):\s*", "", ln).strip() for ln in text.splitlines()]
            return [re.sub(r"\x1b\[[0-9;]*m", "", ln) for ln in out if ln and not ln.startswith("at line")]

        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _suggest(name: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(name, choices, n=3)
    return f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""
