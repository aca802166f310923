"""Denavit-Hartenberg tables (thesis eqs. 4.1 and 4.2) as Pinocchio models.

A D-H table is a YAML file::

    name: my_chain
    closes: true            # the last frame is the base frame (thesis Fig. 3-3)
    units: {length: m, angle: rad}   # optional; length may be m, mm or in
    joints:
      - {name: j1, theta_off: 0.0, s: 0.3, a: 0.0, alpha: 1.5708}
      - {name: j2, theta_off: 0.1, s: 0.0, a: 0.4, alpha: 0.0, convention: hayati}
      - {name: j3, theta_off: 0.0, s: 0.0, a: 0.2, alpha: 0.0, k: 0.95}

Row j is the link transform A_j from frame j to frame j-1:

* ``convention: dh`` (default, eq. 4.1):  A_j = Rot(z, th') Trans(z, s) Trans(x, a) Rot(x, alpha)
* ``convention: hayati`` (eq. 4.2):        A_j = Rot(z, th') Trans(x, s) Rot(x, a) Rot(y, alpha)

with th' = k * th + theta_off, the sensor model of eq. 4.4.  In the Hayati row
``a`` is an angle (rotation about x) and ``s`` a length along x, as in the thesis.

The Pinocchio model has one revolute-z joint per row.  Joint j's placement in
joint j-1's frame is the constant part of A_{j-1} (everything after the
rotation), and the constant part of the last row is the placement of the frame
``<name>_end``.  The joint rotation Rot(z, th') itself is the joint motion.
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
CONVENTIONS = ("dh", "hayati")


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

    def constant(self, s: float | None = None, a: float | None = None, alpha: float | None = None) -> pin.SE3:
        """The constant part of A_j (everything after Rot(z, th'))."""
        s = self.s if s is None else s
        a = self.a if a is None else a
        alpha = self.alpha if alpha is None else alpha
        if self.convention == "dh":
            return pin.SE3(np.eye(3), np.array([a, 0.0, s])) * pin.SE3(rot("x", alpha), np.zeros(3))
        return pin.SE3(np.eye(3), np.array([s, 0.0, 0.0])) * pin.SE3(rot("x", a) @ rot("y", alpha), np.zeros(3))


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
        return f"{self.name}_end"

    def build_model(self) -> pin.Model:
        """A Pinocchio model with one revolute-z joint per row (eq. 4.3: T_c = A_1 ... A_n)."""
        model = pin.Model()
        model.name = self.name
        parent = 0
        placement = pin.SE3.Identity()
        for row in self.rows:
            jid = model.addJoint(
                parent,
                pin.JointModelRZ(),
                placement,
                row.name,
                np.array([1e3]),
                np.array([1e3]),
                np.array([row.lower]),
                np.array([row.upper]),
            )
            model.appendBodyToJoint(jid, pin.Inertia.FromSphere(0.1, 0.01), pin.SE3.Identity())
            model.addFrame(pin.Frame(f"{row.name}_link", jid, 0, pin.SE3.Identity(), pin.FrameType.BODY))
            parent = jid
            placement = row.constant()
        model.addFrame(pin.Frame(self.end_frame, parent, 0, placement, pin.FrameType.OP_FRAME))
        return model


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
    """Read a D-H YAML file, validated by :data:`closedloop.io.schemas.DH_SCHEMA`; errors name file, row, field.

    Beyond the schema: unique row names, a row gives its geometry (not only a name), ``lower <= upper``,
    lengths within +/- 100 m and angles within +/- 1000 rad after unit conversion, 1e-6 <= |k| <= 1e3.
    """
    from closedloop.io.schemas import DH_SCHEMA, load_yaml, validate

    path = Path(path)
    doc = load_yaml(path, "D-H table", ModelError)
    if not isinstance(doc, dict) or "joints" not in doc:
        raise ModelError(f"{path}: a D-H table needs a non-empty 'joints' list")
    validate(doc, DH_SCHEMA, path, ModelError, rows="joints")
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
        a_scale = A if conv == "hayati" else L  # Hayati 'a' is an angle; D-H 'a' a length
        si = {
            "theta_off": vals["theta_off"] * A,
            "s": vals["s"] * L,
            "a": vals["a"] * a_scale,
            "alpha": vals["alpha"] * A,
            "lower": vals["lower"] * A,
            "upper": vals["upper"] * A,
        }
        for key, v in si.items():
            lim, unit = (MAX_LENGTH_M, "m") if key == "s" or (key == "a" and conv == "dh") else (MAX_ANGLE_RAD, "rad")
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
