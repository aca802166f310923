"""Denavit-Hartenberg tables (thesis eqs. 4.1 and 4.2) as Pinocchio models.

A D-H table is a YAML file::

    name: my_chain
    closes: true            # the last frame is the base frame (thesis Fig. 3-3)
    units: {length: m, angle: rad}   # optional; length may be m, mm or in
    joints:
      - {name: j1, theta_off: 0.0, s: 0.3, a: 0.0, alpha: 1.5708}
      - {name: j2, theta_off: 0.1, s: 0.0, a: 0.4, alpha: 0.0, convention: hayati}
      - {name: j3, theta_off: 0.0, s: 0.0, a: 0.2, alpha: 0.0, k: 0.95}
      - {name: j4, s: 0.1, a: 0.05, alpha: -1.5708, convention: modified}

Row j is the link transform A_j from frame j to frame j-1:

* ``convention: dh`` (default, eq. 4.1):  A_j = Rot(z, th') Trans(z, s) Trans(x, a) Rot(x, alpha)
* ``convention: hayati`` (eq. 4.2):        A_j = Rot(z, th') Trans(x, s) Rot(x, a) Rot(y, alpha)
* ``convention: modified`` (Craig's):      A_j = Rot(x, alpha) Trans(x, a) Rot(z, th') Trans(z, s)

with th' = k * th + theta_off, the sensor model of eq. 4.4.  In the Hayati row
``a`` is an angle (rotation about x) and ``s`` a length along x, as in the thesis.
In Craig's modified row ``alpha`` and ``a`` are his alpha_{i-1} and a_{i-1} (the
link before the joint) and ``s`` his d_i; the conventions mix freely, row by row.

Trees (a torso with branches): a row's ``parent`` names the row it hangs on
(default: the row before it; ``base`` for a new branch from the base)::

      - {name: torso, s: 0.3, alpha: 1.5708}
      - {name: l1, parent: torso, a: 0.2, convention: modified}
      - {name: l2, a: 0.3}                       # on l1
      - {name: r1, parent: torso, a: -0.2, convention: modified}
      - {name: r2, a: 0.3}                       # on r1

The Pinocchio model has one revolute-z joint per row.  Each row's transform is
split at its rotation Rot(z, th') (the joint motion) into a head (before it: the
modified row's Rot(x, alpha) Trans(x, a) Trans(z, s), Trans(z, s) commuting with
the rotation; identity for the others) and a tail (after it: the D-H and Hayati
rows' constant part; identity for a modified row).  Joint j's placement in its
parent's frame is tail(parent) head(j).  Every row without children ends in a
frame at its tail: ``<name>_end`` for a serial chain, ``<row>_end`` for each
branch of a tree.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml

from closedloop.errors import ModelError

LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254}
ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}
CONVENTIONS = ("dh", "hayati", "modified")
#: a row's `parent` for a branch that starts at the base
BASE = "base"


@dataclass
class DHRow:
    """One row of a D-H table, in metres and radians."""

    name: str
    theta_off: float = 0.0
    s: float = 0.0
    a: float = 0.0
    alpha: float = 0.0
    k: float = 1.0
    convention: str = "dh"
    lower: float = -np.pi
    upper: float = np.pi
    parent: str | None = None  # the row this one hangs on: None for the row before it, BASE for the base

    def constant(self, s: float | None = None, a: float | None = None, alpha: float | None = None) -> pin.SE3:
        """The constant part of A_j after Rot(z, th') (the tail; identity for a modified row)."""
        s = self.s if s is None else s
        a = self.a if a is None else a
        alpha = self.alpha if alpha is None else alpha
        if self.convention == "modified":
            return pin.SE3.Identity()
        if self.convention == "dh":
            return pin.SE3(np.eye(3), np.array([a, 0.0, s])) * pin.SE3(rot("x", alpha), np.zeros(3))
        return pin.SE3(np.eye(3), np.array([s, 0.0, 0.0])) * pin.SE3(rot("x", a) @ rot("y", alpha), np.zeros(3))

    def head(self, s: float | None = None, a: float | None = None, alpha: float | None = None) -> pin.SE3:
        """The constant part of A_j before Rot(z, th'): Rot(x, alpha) Trans(x, a) Trans(z, s) for a modified
        row (Trans(z, s) commutes with the rotation), identity for the others."""
        if self.convention != "modified":
            return pin.SE3.Identity()
        s = self.s if s is None else s
        a = self.a if a is None else a
        alpha = self.alpha if alpha is None else alpha
        return pin.SE3(rot("x", alpha), np.zeros(3)) * pin.SE3(np.eye(3), np.array([a, 0.0, s]))

    def generators(self, s: float, a: float, alpha: float) -> np.ndarray:
        """(6, 3) right-perturbation twists (linear, angular) of the part of the row that s, a, alpha move
        (the tail, or a modified row's head), per d s, d a, d alpha; exact at any value.

        Modified head H = Rot(x, alpha) Trans(x, a) Trans(z, s): ds and da are right translations along z
        and x; dalpha a left rotation about x, the right twist Ad(H^-1) (0, e_x).  The tails: see
        `tail_generators`.
        """
        if self.convention != "modified":
            return tail_generators(self.convention, a, alpha, self.constant(s, a, alpha))
        g = np.zeros((6, 3))
        g[2, 0] = 1.0
        g[0, 1] = 1.0
        g[:, 2] = self.head(s, a, alpha).inverse().action @ np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
        return g


@dataclass
class DHTable:
    """A chain of D-H / Hayati rows; `closes` means the last frame is the base frame."""

    name: str
    rows: list[DHRow]
    closes: bool = False
    source: Path | None = None
    length_unit: str = "m"
    angle_unit: str = "rad"
    extra: dict = field(default_factory=dict)

    @property
    def end_frame(self) -> str:
        """The last row's end frame (the chain's ``<name>_end``)."""
        ends = self.end_frames()
        return ends.get(self.rows[-1].name, f"{self.name}_end")

    def parents(self) -> dict[str, str | None]:
        """Row name -> the row it hangs on (None: the base); a row without `parent` hangs on the row before."""
        out: dict[str, str | None] = {}
        for i, r in enumerate(self.rows):
            if r.parent == BASE or (r.parent is None and i == 0):
                out[r.name] = None
            else:
                out[r.name] = r.parent if r.parent is not None else self.rows[i - 1].name
        return out

    @property
    def is_tree(self) -> bool:
        """Whether some row does not hang on the row before it (branches)."""
        par = self.parents()
        return any(par[r.name] != prev.name for r, prev in zip(self.rows[1:], self.rows))

    def children(self) -> dict[str | None, list[str]]:
        """Row name (None: the base) -> the rows that hang on it, in table order."""
        out: dict[str | None, list[str]] = {None: []} | {r.name: [] for r in self.rows}
        for name, parent in self.parents().items():
            out[parent].append(name)
        return out

    def end_frames(self) -> dict[str, str]:
        """Leaf row -> its end frame: ``<name>_end`` for a serial chain, ``<row>_end`` for a tree's branches."""
        kids = self.children()
        leaves = [r.name for r in self.rows if not kids[r.name]]
        if len(leaves) == 1 and not self.is_tree:
            return {leaves[0]: f"{self.name}_end"}
        return {leaf: f"{leaf}_end" for leaf in leaves}

    def build_model(self) -> pin.Model:
        """A Pinocchio model with one revolute-z joint per row (eq. 4.3: T_c = A_1 ... A_n along a branch)."""
        model = pin.Model()
        model.name = self.name
        rows = {r.name: r for r in self.rows}
        par = self.parents()
        jid_of: dict[str | None, int] = {None: 0}
        for row in self.rows:
            parent_name = par[row.name]
            parent = rows[parent_name] if parent_name is not None else None
            placement = (parent.constant() if parent is not None else pin.SE3.Identity()) * row.head()
            jid = model.addJoint(
                jid_of[parent_name],
                pin.JointModelRZ(),
                placement,
                row.name,
                np.array([1e3]),
                np.array([1e3]),
                np.array([row.lower]),
                np.array([row.upper]),
            )
            jid_of[row.name] = jid
            model.appendBodyToJoint(jid, pin.Inertia.FromSphere(0.1, 0.01), pin.SE3.Identity())
            model.addFrame(pin.Frame(f"{row.name}_link", jid, 0, pin.SE3.Identity(), pin.FrameType.BODY))
        for leaf, frame in self.end_frames().items():
            model.addFrame(pin.Frame(frame, jid_of[leaf], 0, rows[leaf].constant(), pin.FrameType.OP_FRAME))
        return model

    def placements(
        self, model: pin.Model, values: dict[str, tuple[float, float, float]], P: int, cols: dict[str, list[int]]
    ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """Set `model`'s joint and end-frame placements at `values` (row -> (s, a, alpha); other rows
        nominal) and return the right-twist generators: (6 (njoints-1), P) for joint placements and
        frame id -> (6, P) for end frames, columns `cols` (row -> its s, a, alpha columns).

        Joint j's placement is tail(parent) head(j): a right twist xi of the head is one of the placement;
        a right twist xi of the parent's tail is Ad(head(j)^-1) xi of it.
        """
        rows = {r.name: r for r in self.rows}
        par = self.parents()
        G = np.zeros((6 * (model.njoints - 1), P))
        G_frames: dict[int, np.ndarray] = {}

        def geo(r: DHRow) -> tuple[float, float, float]:
            return values.get(r.name, (r.s, r.a, r.alpha))

        for jid, row in enumerate(self.rows, start=1):
            parent_name = par[row.name]
            parent = rows[parent_name] if parent_name is not None else None
            if row.name not in values and (parent is None or parent.name not in values):
                continue
            head = row.head(*geo(row))
            tail = parent.constant(*geo(parent)) if parent is not None else pin.SE3.Identity()
            model.jointPlacements[jid] = tail * head
            if row.name in values and row.convention == "modified":
                G[6 * (jid - 1) : 6 * jid, cols[row.name]] += row.generators(*geo(row))
            if parent is not None and parent.name in values and parent.convention != "modified":
                G[6 * (jid - 1) : 6 * jid, cols[parent.name]] += head.inverse().action @ parent.generators(*geo(parent))
        for leaf, frame in self.end_frames().items():
            row = rows[leaf]
            if leaf not in values:
                continue
            fid = model.getFrameId(frame)
            f = model.frames[fid]
            f.placement = row.constant(*geo(row))
            model.frames[fid] = f  # the Python binding hands out copies
            if row.convention != "modified":
                Gf = np.zeros((6, P))
                Gf[:, cols[leaf]] = row.generators(*geo(row))
                G_frames[fid] = Gf
        return G, G_frames


def tail_generators(convention: str, a: float, alpha: float, C: pin.SE3) -> np.ndarray:
    """Right-perturbation twists of the tail C for d s, d a, d alpha (columns), exact.

    D-H (eq. 4.1), C = Trans(z,s) Trans(x,a) Rot(x,alpha):
      ds: left translation along z;  da: left translation along x;  dalpha: right rotation about x.
    Hayati (eq. 4.2), C = Trans(x,s) Rot(x,a) Rot(y,alpha):
      ds: left translation along x;  da: right rotation about Ry(alpha)^T x;  dalpha: right rotation about y.
    A left twist xi becomes the right twist Ad(C^-1) xi.
    """
    Rt = C.rotation.T
    g = np.zeros((6, 3))
    ex, ey, ez = np.eye(3)
    if convention == "dh":
        g[:3, 0] = Rt @ ez
        g[:3, 1] = Rt @ ex
        g[3:, 2] = ex
    else:
        g[:3, 0] = Rt @ ex
        g[3:, 1] = rot("y", alpha).T @ ex
        g[3:, 2] = ey
    return g


def rot(axis: str, angle: float) -> np.ndarray:
    """Elementary rotation matrix Rot(axis, angle)."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


#: largest |length| (m) and |angle| (rad) of a D-H field after unit conversion, and the range of |k|
MAX_LENGTH_M = 100.0
MAX_ANGLE_RAD = 1e3
K_RANGE = (1e-6, 1e3)
GEOMETRY = ("theta_off", "s", "a", "alpha")


def load_dh(path: str | Path) -> DHTable:
    """Read a D-H YAML file (`closedloop.io.robot_files.read_model_file`) into its table (`dh_table`)."""
    from closedloop.io.robot_files import read_model_file

    src = read_model_file(path)
    if src.dh is None:
        raise ModelError(f"{path}: not a D-H table (.yaml or .yml)")
    return dh_table(src.dh, src.path)


def dh_table(doc: dict, path: Path) -> DHTable:
    """The table of a D-H document read from `path`, already validated by :data:`closedloop.io.schemas.DH_SCHEMA`
    (`closedloop.io.robot_files.read_model_file`); errors name file, row, field.

    Beyond the schema: unique row names, a row gives its geometry (not only a name), ``lower <= upper``,
    lengths within +/- 100 m and angles within +/- 1000 rad after unit conversion, 1e-6 <= |k| <= 1e3.
    """
    units = doc.get("units") or {}
    lu, au = units.get("length", "m"), units.get("angle", "rad")
    L, A = LENGTH_UNITS[lu], ANGLE_UNITS[au]
    rows: list[DHRow] = []
    seen: set[str] = set()
    for i, raw in enumerate(doc["joints"], start=1):
        name = raw["name"]
        where = f"{path}: joints row {i} ('{name}')"
        if name in seen:
            raise ModelError(f"{where}: duplicate name '{name}'")
        seen.add(name)
        if not any(f in raw for f in GEOMETRY):
            raise ModelError(f"{where}: gives only a name; give its geometry ({', '.join(GEOMETRY)}; 0 where zero)")
        conv = raw.get("convention", doc.get("convention", "dh"))
        vals = {
            key: float(raw.get(key, default))
            for key, default in (
                ("theta_off", 0.0),
                ("s", 0.0),
                ("a", 0.0),
                ("alpha", 0.0),
                ("k", 1.0),
                ("lower", -np.pi / A),
                ("upper", np.pi / A),
            )
        }
        parent = raw.get("parent")
        if parent is not None and parent != BASE and parent not in seen - {name}:
            raise ModelError(f"{where}: parent '{parent}' is not a row above this one (or '{BASE}')")
        a_scale = A if conv == "hayati" else L  # Hayati 'a' is an angle; D-H and modified 'a' a length
        si = {
            "theta_off": vals["theta_off"] * A,
            "s": vals["s"] * L,
            "a": vals["a"] * a_scale,
            "alpha": vals["alpha"] * A,
            "lower": vals["lower"] * A,
            "upper": vals["upper"] * A,
        }
        for key, v in si.items():
            lim, unit = (
                (MAX_LENGTH_M, "m") if key == "s" or (key == "a" and conv != "hayati") else (MAX_ANGLE_RAD, "rad")
            )
            if abs(v) > lim:
                raise ModelError(f"{where}, field '{key}': {raw.get(key)} is out of range (|{key}| <= {lim:g} {unit})")
        if not K_RANGE[0] <= abs(vals["k"]) <= K_RANGE[1]:
            raise ModelError(
                f"{where}, field 'k': {raw['k']} is out of range ({K_RANGE[0]:g} <= |k| <= {K_RANGE[1]:g})"
            )
        if si["lower"] > si["upper"]:
            raise ModelError(f"{where}: lower {raw.get('lower')} exceeds upper {raw.get('upper')}")
        rows.append(
            DHRow(
                name=name,
                theta_off=si["theta_off"],
                s=si["s"],
                a=si["a"],
                alpha=si["alpha"],
                k=vals["k"],
                convention=conv,
                lower=si["lower"],
                upper=si["upper"],
                parent=parent,
            )
        )
    return DHTable(
        name=doc.get("name", _stem_name(path)),
        rows=rows,
        closes=doc.get("closes", False),
        source=path,
        length_unit=lu,
        angle_unit=au,
    )


def _stem_name(path: Path) -> str:
    """The file's stem as a chain name (characters outside the name pattern become '_')."""
    import re

    name = re.sub(r"[^A-Za-z0-9_\-]", "_", path.stem) or "chain"
    return name if not name[0].isdigit() and name[0] != "-" else f"_{name}"


def dump_dh(table: DHTable, values: dict[str, float] | None = None) -> str:
    """The table as YAML, in the units it was read in; `values` overrides row fields by name."""
    values = values or {}
    L, A = LENGTH_UNITS[table.length_unit], ANGLE_UNITS[table.angle_unit]
    rows = []
    for row in table.rows:
        get = lambda f: values.get(f"{row.name}.{f}", getattr(row, f))  # noqa: E731
        a_scale = A if row.convention == "hayati" else L
        rows.append(
            {
                "name": row.name,
                **({"parent": row.parent} if row.parent is not None else {}),
                "convention": row.convention,
                "theta_off": round(get("theta_off") / A, 12),
                "s": round(get("s") / L, 12),
                "a": round(get("a") / a_scale, 12),
                "alpha": round(get("alpha") / A, 12),
                "k": round(get("k"), 12),
            }
        )
    doc = {
        "name": table.name,
        "closes": table.closes,
        "units": {"length": table.length_unit, "angle": table.angle_unit},
        "joints": rows,
    }
    return yaml.safe_dump(doc, sort_keys=False)
