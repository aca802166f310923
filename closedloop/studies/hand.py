"""The hand procedure of thesis chapter 4 (Utah-MIT hand, thumb opposed to a finger).

Two pieces, both independent of the particular hand:

* `staged_calibration` -- 4.2.6: "The poorly known parameters (base and tip
  transformations) are first estimated by assuming that the finger parameters
  are correct.  Then all parameters are allowed to freely vary."  Each stage is
  an ordinary `calibrate` call whose `CalibrationOptions.initial` is the
  previous stage's values.  `thesis_stages` builds the two stages of the
  thesis for the 8-row thumb-finger table (``assets/dh/utah_mit_thumb_finger.yaml``):
  stage 1 frees the parameters marked ~ in Table 4.1 (palm link j3, tip link
  j7, the hard-to-measure offsets) with the rest held at the table's values,
  stage 2 frees every theta_off, s, a, alpha and k; both hold s_0 = -1.3 in
  (the length scale, 4.2.2) and k_7 = 1.0 (the k = 0 trivial solution).

* `palm_frame_parameters` -- 4.5: the identified loop table (rows j0..j7,
  base frame on the thumb's distal axis) re-expressed as two open chains
  from the palm frame 2' (frame 2 after the rotation theta_3' of the thumb's
  proximal joint), Tables 4.3 and 4.4.

What can and cannot be converted (4.5):

* The FINGER chain is rows p+1.. of the loop, preceded by the constant part
  of row p (the palm link, "row -1" of Table 4.3: no joint, no k).  Exact.
* The THUMB chain runs the loop backwards from the palm: each loop row j
  (j = p .. 1) contributes Rz(-theta_j') followed by the inverse of the
  constant part of row j-1.  The inverse of a D-H constant part,
  (Tz(s) Tx(a) Rx(alpha))^-1 = Tx(-a) Rx(-alpha) Tz(-s), is a D-H row
  (s = 0, a = -a, alpha = -alpha) plus a translation -s along the NEXT joint
  axis; that translation is merged into the next row's s when the next row is
  D-H, and otherwise becomes an extra pure translation row (``translation_z``),
  the s'_1 = -0.1604 in of Table 4.4.  The inverse of a Hayati constant part is
  a Hayati row with the order reversed (eq. 4.18, ``hayati_reversed``:
  Rz(theta') Ry(alpha) Rx(a) Tx(s)) and negated values.
* Thumb readings are negated ("the joint angles for the thumb are negated",
  4.3): with reading' = -reading the reversed joint has theta_off -> -theta_off
  and the same k.  (Table 4.4 prints every thumb k one row too low -- e.g. 0.9336,
  the k of joint 2, on the row carrying theta_3 -- our rows carry the k of the
  joint whose rotation they contain.)
* NOT convertible: the fingertip transformations.  The loop only identifies
  the composite "effective endpoint link" (finger distal axis -> plate ->
  thumb distal axis, the constant part of the last row, 4.2.3); how it splits
  into a finger tip, the plate and a thumb tip is invisible to a rigid grasp.
  Both chains therefore end with their distal joint's rotation and a tip marked
  unknown (the '?' rows); the composite link is returned as ``closing_link``.
  The thesis takes theta_off = 0, s = 0, a = 0.735 in, alpha = 0 for practical
  purposes (`NOMINAL_TIP`).
* The palm frame is only defined up to a rotation about and a translation
  along the thumb's proximal axis z_2 when the procedure is repeated with other
  fingers; relating two such palm frames needs one extra fixed-thumb
  measurement (4.5), which is outside these functions.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from closedloop.calibration.pipeline import CalibrationOptions, CalibrationResult, calibrate
from closedloop.errors import ModelError, OptionError, ParameterError, SimulationError
from closedloop.io.logs import JointLog
from closedloop.loops.base import Loop
from closedloop.model.dh import LENGTH_UNITS, rot
from closedloop.model.robot import RobotModel

INCH = LENGTH_UNITS["in"]

# Table 4.1 "~": difficult to measure (guessed for link 7, roughly calculated otherwise).
TABLE_4_1_POORLY_KNOWN = [
    "j0.theta_off",
    "j3.theta_off",
    "j3.s",
    "j3.a",
    "j3.alpha",
    "j4.theta_off",
    "j4.s",
    "j4.a",
    "j5.theta_off",
    "j7.theta_off",
    "j7.s",
    "j7.a",
    "j7.alpha",
]
# 4.2.2 / 4.3: the two fixed parameters of the thesis.
TABLE_4_1_FIXED = {"j0.s": -1.3 * INCH, "j7.k": 1.0}
# 4.5: tip D-H parameters taken "for practical purposes" [57] (metres, radians).
NOMINAL_TIP = {"theta_off": 0.0, "s": 0.0, "a": 0.735 * INCH, "alpha": 0.0}


# --------------------------------------------------------------------------- staged calibration
def staged_calibration(
    robot: RobotModel, log: JointLog, loops: list[Loop], stages: list[CalibrationOptions]
) -> list[CalibrationResult]:
    """Run `calibrate` once per stage, each starting from the previous stage's values (4.2.6).

    A stage's own ``initial`` entries win over the carried-over values; its
    ``fix`` values win over both (as in `calibrate`).  Returns one result per
    stage; the last is the calibration.
    """
    if not stages:
        raise OptionError("staged_calibration needs at least one stage (a list of CalibrationOptions)")
    results: list[CalibrationResult] = []
    carried: dict[str, float] = {}
    for opt in stages:
        stage = replace(opt, initial={**carried, **opt.initial}, fix=dict(opt.fix))
        res = calibrate(robot, log, loops, stage)
        results.append(res)
        carried = res.as_dict()
    return results


def thesis_stages(
    robot: RobotModel,
    poorly_known: list[str] | None = None,
    fixed: dict[str, float | None] | None = None,
    noise=None,
    scale_factors: bool = True,
    **common,
) -> list[CalibrationOptions]:
    """The two stages of 4.2.6 for a thumb-finger D-H table.

    Stage 1: only `poorly_known` (default: the ~ entries of Table 4.1) are
    free; everything else keeps its current value.  Stage 2: every D-H
    parameter (and every k if `scale_factors`).  Both stages fix `fixed`
    (default s_0 = -1.3 in, k_7 = 1.0).
    """
    poorly = list(TABLE_4_1_POORLY_KNOWN if poorly_known is None else poorly_known)
    fix = dict(TABLE_4_1_FIXED if fixed is None else fixed)
    fix = {n: v for n, v in fix.items() if n.rsplit(".", 1)[0] in robot.joint_names}
    common.setdefault("weighting", "none")
    stage1 = CalibrationOptions(identify=[p for p in poorly if p not in fix], fix=fix, noise=noise, **common)
    kinds = ["theta_off", "s", "a", "alpha"] + (["k"] if scale_factors else [])
    stage2 = CalibrationOptions(identify=kinds, fix=fix, noise=noise, **common)
    return [stage1, stage2]


# --------------------------------------------------------------------------- palm frame (4.5)
@dataclass
class PalmRow:
    """One row of a palm-frame chain (Tables 4.3, 4.4), metres and radians.

    convention: 'dh' (eq. 4.1), 'hayati' (eq. 4.2), 'hayati_reversed' (eq. 4.18:
    Rz(th') Ry(alpha) Rx(a) Tx(s)), 'translation_z' (Tz(s) only, the s'_1 row),
    'constant' (no joint: the constant part of a 'hayati'/'dh' row, Table 4.3 row -1).
    joint: the loop joint whose reading drives the row (None: no joint);
    sign: reading multiplier (+1 finger, -1 thumb: the thumb readings are negated).
    unknown: the tip transformation is not identified (Tables 4.3/4.4 '?').
    """

    label: str
    convention: str
    theta_off: float = 0.0
    s: float = 0.0
    a: float = 0.0
    alpha: float = 0.0
    k: float | None = None
    joint: str | None = None
    sign: float = 1.0
    base: str = "dh"  # for 'constant' rows: the convention of the constant part
    unknown: bool = False

    def transform(self, reading: float = 0.0) -> np.ndarray:
        """4x4 transform of the row at a reading (the joint's own, un-negated reading)."""
        th = 0.0
        if self.joint is not None:
            th = (self.k if self.k is not None else 1.0) * self.sign * reading + self.theta_off
        T = _hom(rot("z", th), np.zeros(3))
        if self.unknown:
            return T
        conv = self.base if self.convention == "constant" else self.convention
        if conv == "dh":
            C = _hom(np.eye(3), [self.a, 0, self.s]) @ _hom(rot("x", self.alpha), np.zeros(3))
        elif conv == "hayati":
            C = _hom(np.eye(3), [self.s, 0, 0]) @ _hom(rot("x", self.a) @ rot("y", self.alpha), np.zeros(3))
        elif conv == "hayati_reversed":
            C = _hom(rot("y", self.alpha) @ rot("x", self.a), np.zeros(3)) @ _hom(np.eye(3), [self.s, 0, 0])
        elif conv == "translation_z":
            C = _hom(np.eye(3), [0, 0, self.s])
        else:
            raise OptionError(
                f"row {self.label}: unknown convention '{conv}' (known: dh, hayati, hayati_reversed, translation_z)"
            )
        return T @ C

    def in_units(self, length: float = INCH) -> dict:
        """The row as printed in the thesis (lengths in `length` metres, e.g. inches)."""
        ang_a = (
            self.convention in ("hayati", "hayati_reversed") or self.base == "hayati" and self.convention == "constant"
        )
        return {
            "label": self.label,
            "convention": self.convention,
            "theta_off": None if self.unknown else self.theta_off,
            "s": None if self.unknown else self.s / length,
            "a": None if self.unknown else (self.a if ang_a else self.a / length),
            "alpha": None if self.unknown else self.alpha,
            "k": self.k,
        }


@dataclass
class PalmFrameParameters:
    finger: list[PalmRow]
    thumb: list[PalmRow]
    closing_link: PalmRow  # the identified composite tip link (finger distal axis -> thumb distal axis)
    notes: list[str]

    @staticmethod
    def chain(rows: list[PalmRow], readings: dict[str, float]) -> np.ndarray:
        T = np.eye(4)
        for r in rows:
            T = T @ r.transform(readings.get(r.joint, 0.0) if r.joint else 0.0)
        return T


def palm_frame_parameters(
    robot: RobotModel, values: dict[str, float] | None = None, palm_joint: str = "j3"
) -> PalmFrameParameters:
    """Finger and thumb parameters relative to the palm frame 2' (thesis 4.5, Tables 4.3 and 4.4).

    robot: the loop's D-H model (rows thumb-distal .. palm .. finger-distal);
    values: identified values by name (``res.as_dict()``; missing names take
    the table's values); palm_joint: the row whose rotated frame is the palm
    frame (the thumb's proximal joint, j3 for the thumb-finger table).
    See the module docstring for what is and is not convertible.
    """
    if robot.kind != "dh":
        raise ModelError(
            f"{robot.source}: palm_frame_parameters needs the loop's D-H table (a .yaml model), "
            f"not a {robot.kind} model"
        )
    values = values or {}
    assert robot.dh is not None  # kind 'dh'
    rows = robot.dh.rows
    names = [r.name for r in rows]
    if palm_joint not in names:
        raise ParameterError(f"unknown palm joint '{palm_joint}' (rows: {names})")
    p = names.index(palm_joint)
    if p == 0 or p == len(rows) - 1:
        raise ParameterError(f"palm joint '{palm_joint}': it must have thumb rows before it and finger rows after it")

    def g(i: int, f: str) -> float:
        return float(values.get(f"{names[i]}.{f}", getattr(rows[i], f)))

    notes = []
    # Finger: row -1 = constant part of row p, then rows p+1 .. n-1; the last row's constant part is the tip.
    finger = [
        PalmRow("-1", "constant", 0.0, g(p, "s"), g(p, "a"), g(p, "alpha"), None, None, 1.0, base=rows[p].convention)
    ]
    for m, i in enumerate(range(p + 1, len(rows))):
        last = i == len(rows) - 1
        finger.append(
            PalmRow(
                str(m),
                rows[i].convention,
                g(i, "theta_off"),
                g(i, "s"),
                g(i, "a"),
                g(i, "alpha"),
                g(i, "k"),
                names[i],
                1.0,
                unknown=last,
            )
        )
    end = len(rows) - 1
    closing = PalmRow(
        "closing", "constant", 0.0, g(end, "s"), g(end, "a"), g(end, "alpha"), None, None, base=rows[end].convention
    )
    notes.append(
        "finger tip transformation not identified: the loop sees only the composite link "
        f"{names[end]} (finger distal axis -> thumb distal axis), returned as closing_link"
    )

    # Thumb: backwards from the palm.  Row m carries Rz(-theta_j') (j = p - m) and inv(C_{j-1}).
    thumb: list[PalmRow] = []
    carry_s = 0.0  # translation along the current z left over from an inverted D-H constant part
    for m, j in enumerate(range(p, 0, -1)):
        c = j - 1  # constant part inverted in this row
        th = -g(j, "theta_off")
        if rows[c].convention == "dh":
            row = PalmRow(str(m), "dh", th, carry_s, -g(c, "a"), -g(c, "alpha"), g(j, "k"), names[j], -1.0)
            carry_s = -g(c, "s")
        else:
            if abs(carry_s) > 0:
                thumb.append(PalmRow(f"{m}'", "translation_z", 0.0, carry_s, 0.0, 0.0, None, None))
                notes.append(
                    f"thumb row {m}': extra translation s' = {carry_s / INCH:.4f} in along the "
                    f"axis of {names[j]} (the s of the inverted D-H row {names[c]}; Table 4.4's s'_1)"
                )
                carry_s = 0.0
            row = PalmRow(
                str(m), "hayati_reversed", th, -g(c, "s"), -g(c, "a"), -g(c, "alpha"), g(j, "k"), names[j], -1.0
            )
        thumb.append(row)
    tip = PalmRow(str(p), "dh", -g(0, "theta_off"), carry_s, 0.0, 0.0, g(0, "k"), names[0], -1.0, unknown=True)
    if abs(carry_s) > 0:
        notes.append(
            f"thumb tip row also carries s = {carry_s / INCH:.4f} in (not representable once the tip is unknown)"
        )
    thumb.append(tip)
    notes.append(
        "thumb tip transformation not identified: the base frame on the thumb's distal axis is a "
        "choice of the loop, not the physical tip (Table 4.4 '?')"
    )
    notes.append(
        "thumb readings are negated (reading' = -reading): reversed rows have theta_off -> -theta_off "
        "and keep the joint's k"
    )
    notes.append(
        "repeating with another finger gives a palm frame 2' displaced along / rotated about the "
        "thumb's proximal axis z_2; relate them with one fixed-thumb endpoint measurement (4.5)"
    )
    return PalmFrameParameters(finger, thumb, closing, notes)


def _hom(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# --------------------------------------------------------------------------- a simulated thesis hand
#: Table 4.2: the thesis's calibrated hand, per row (theta_off rad, s in, a in or rad (Hayati), alpha rad, k).
TABLE_4_2 = [
    (0.2380, -1.3000, 0.0069, 0.0668, 0.9508),
    (0.0850, -1.5085, -0.1515, -0.0480, 0.8596),
    (-0.0943, 0.1604, -0.3097, 1.6207, 0.9336),
    (-1.7824, 1.8050, 0.5755, 0.2890, 0.9579),
    (0.1389, 1.7151, 1.3356, -1.5836, 1.0125),
    (0.5464, 1.6307, 0.0292, 0.0737, 0.8577),
    (-0.0425, 1.1474, 0.1745, 0.1260, 0.9350),
    (3.7552, -0.8322, -1.4377, -0.5631, 1.0000),
]
_FIELDS = ("theta_off", "s", "a", "alpha", "k")


def table_4_1_path():
    """The nominal thumb-finger D-H table shipped with the package (Table 4.1)."""
    from closedloop.assets.catalog import model_file

    return model_file("dh/utah_mit_thumb_finger.yaml")


def _loop_problem(robot: RobotModel):
    from closedloop.loops.spec import default_loops
    from closedloop.problem.problem import CalibrationProblem, LoopBlock

    n = len(robot.joint_names)
    return CalibrationProblem(
        robot, robot.joint_names, [LoopBlock(default_loops(robot)[0], np.zeros((1, n)), np.arange(1))]
    )


def close_readings(problem, readings: np.ndarray, iters: int = 200) -> tuple[np.ndarray, float]:
    """Damped Gauss-Newton on the readings (1, n) until the problem's (nominal-valued) loop closes: the
    readings and the largest closure residual."""
    th, err = close_many(problem, readings, iters)
    return th, float(err[0])


def close_many(problem, starts: np.ndarray, iters: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Damped Gauss-Newton on the readings from each row of `starts` (k, n) until the problem's
    (nominal-valued) loop closes or `iters` steps: the readings (k, n) and each row's largest closure
    residual.  The rows still open are evaluated together (one evaluation of 40 rows costs 4 of one row)."""
    x = problem.nominal
    th = np.array(np.atleast_2d(starts), dtype=float)
    open_rows = np.arange(th.shape[0])
    for _ in range(iters):
        if not open_rows.size:
            break
        ev = problem.evaluate(x, True, [th[open_rows]], columns=[])[0]  # Jq alone
        still = []
        for k, i in enumerate(open_rows):
            if np.abs(ev.r[k]).max() < 1e-13:
                continue
            J = ev.Jq[k]
            th[i] = th[i] - np.linalg.solve(J.T @ J + 1e-6 * np.eye(J.shape[1]), J.T @ ev.r[k])
            still.append(i)
        open_rows = np.array(still, dtype=int)
    return th, np.abs(problem.evaluate(x, False, [th])[0].r).max(axis=1)


def nominal_closed_pose(robot: RobotModel, seed: int = 100) -> np.ndarray:
    """A closed configuration of the D-H chain `robot` with the smallest readings (model angles wrapped)."""
    prob = _loop_problem(robot)
    off = prob.nominal[prob.rp.offset_index()]
    rng = np.random.default_rng(seed)
    best = None
    closed, errs = close_many(prob, rng.uniform(-1.2, 1.2, (40, len(robot.joint_names))))  # 40 starts
    for th, err in zip(closed[:, None, :], errs):
        if err > 1e-12:
            continue
        th = ((th + off + np.pi) % (2 * np.pi) - np.pi) - off
        if best is None or np.abs(th).max() < np.abs(best).max():
            best = th
    if best is None:
        raise SimulationError(f"{robot.source}: no closed configuration found from 40 starts")
    return best


def thesis_hand_dataset(
    out_dir, n: int = 100, seed: int = 5, offset_clip: float = 0.5, k_range: tuple[float, float] = (0.85, 1.0)
):
    """A TRUE thumb-finger hand and exact readings along its self-motion (a 2-DOF loop).

    The true hand is Table 4.2 (the thesis's calibrated hand) with offset errors
    clipped to +/-`offset_clip` rad and scale factors to `k_range`: errors of the
    size the thesis found on the real hand, relative to the nominal Table 4.1.
    Writes ``true_hand.yaml`` to `out_dir`; returns (truth values by parameter
    name, readings (n, 8), the true robot).
    """
    from pathlib import Path

    import yaml

    from closedloop.studies.synthetic import self_motion

    table = table_4_1_path()
    doc = yaml.safe_load(Path(table).read_text())
    nominal = RobotModel.from_file(table)
    rows = []
    for raw, vals in zip(doc["joints"], TABLE_4_2):
        row = dict(raw, **dict(zip(_FIELDS, vals)))
        row["theta_off"] = raw["theta_off"] + float(
            np.clip(row["theta_off"] - raw["theta_off"], -offset_clip, offset_clip)
        )
        row["k"] = float(np.clip(row["k"], *k_range))
        rows.append(row)
    path = Path(out_dir) / "true_hand.yaml"
    path.write_text(yaml.safe_dump({**doc, "joints": rows}))
    prob = _loop_problem(RobotModel.from_file(path))
    th0, err = close_readings(prob, nominal_closed_pose(nominal))
    if err > 1e-12:
        raise SimulationError(
            f"{path}: the true hand does not close near the nominal's closed pose (closure error {err:.3g})"
        )
    angles = th0[0] * prob.nominal[prob.rp.scale_index()] + prob.nominal[prob.rp.offset_index()]
    for row, q in zip(rows, angles):  # keep the walk within 0.8 rad of its start
        row["lower"], row["upper"] = float(q - 0.8), float(q + 0.8)
    path.write_text(yaml.safe_dump({**doc, "joints": rows}))
    truth_robot = RobotModel.from_file(path)
    prob = _loop_problem(truth_robot)
    readings = self_motion(prob, prob.nominal, th0, n, np.random.default_rng(seed), step=0.05)
    return dict(zip(prob.names, prob.nominal)), readings, truth_robot
