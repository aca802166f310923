"""The thesis's chapter 3 simulations as D-H tables, with exact data generated independently.

The thesis's numbers (Tables 3.1-3.8) are withheld, so the geometry here is ours: plausible
anthropomorphic arms in the thesis's units (the fixed length is 1: ``s3 = 1``, or ``s2 = 1`` for
point contact), revolute joints whose consecutive axes are never parallel (D-H is well defined):

* ``example1`` (3.3.2): a 7-DOF arm whose end effector grasps the ground; the 7 joint axes of the
  closed chain at a home posture give a cyclic D-H table (``closes: true``; the last row is the
  hand plus the ground link); 40 configurations with theta_1 = 0 to 0.5 rad; ``s3`` fixed.
* ``example2`` (3.3.2): two 6-DOF arms rigidly grasping each other, a 12-joint closed chain;
  40 configurations with theta_1..theta_6 in 0 to 0.25 rad (the thesis's 0 to 0.5 takes our
  second arm through singularities); ``s3`` fixed.
* ``door`` (3.4.2): a 6-DOF arm grasping a handle that turns about an unknown hinge
  (``hinge`` loop, hinge left to the loop's own unknowns); 40 configurations, theta_1 = 0 to 0.5 rad.
* ``point`` (3.4.1): a 6-DOF arm pressing a tool point on a fixed point (``point`` loop, tip and
  point unknown); 30 configurations with the wrist joints theta_4..theta_6 in 0 to 0.5 rad and
  theta_1..3 keeping the tip on the point (the thesis drives theta_1..3, which a wrist 0.3 long
  cannot follow in our arm); ``s2`` fixed.

Data: the loop is closed with Pinocchio on the true table (our own model builder, not
closedloop's), by Newton on the joints the loop determines, to |residual| < 1e-12.  Starting
guesses are thesis-sized: lengths +-0.1, twists +-0.3 rad, offsets +-0.6 rad (uniform).

A start is *recovered* when the calibrated mechanism is the true one: for the closed chains
(no gauge once s3 is fixed) every table parameter within 1e-6; for the door and point contact
(whose base and tool frames are partly gauges) the tool frame / tool point forward kinematics
over random configurations within 1e-6 after the best rigid base (and tool) transform.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml
from scratch import scratch_dir

FIELDS = ("theta_off", "s", "a", "alpha")
TOL = 1e-6


# ----------------------------------------------------------------------------- D-H algebra
def rot(axis: str, t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def dh_const(s: float, a: float, alpha: float) -> pin.SE3:
    """Trans(z, s) Trans(x, a) Rot(x, alpha) (eq. 4.1 after the joint rotation)."""
    return pin.SE3(rot("x", alpha), np.array([a, 0.0, s]))


def dh_A(theta: float, s: float, a: float, alpha: float) -> pin.SE3:
    return pin.SE3(rot("z", theta), np.zeros(3)) * dh_const(s, a, alpha)


def open_frames(rows: np.ndarray, theta: np.ndarray) -> list[pin.SE3]:
    """F_0 = I, F_j = A_1 ... A_j for rows (n, 4) = (theta_off, s, a, alpha) and readings theta."""
    F = [pin.SE3.Identity()]
    for (off, s, a, al), th in zip(rows, theta):
        F.append(F[-1] * dh_A(th + off, s, a, al))
    return F


def common_normal(p1, u1, p2, u2) -> tuple[np.ndarray, np.ndarray]:
    """Feet (on line 1, on line 2) of the common normal of two non-parallel lines."""
    w = p1 - p2
    b, d, e = u1 @ u2, u1 @ w, u2 @ w
    den = 1.0 - b * b
    if den < 1e-4:
        raise ValueError("consecutive joint axes (nearly) parallel: D-H is ill defined")
    t1, t2 = (b * e - d) / den, (e - b * d) / den
    return p1 + t1 * u1, p2 + t2 * u2


def cyclic_table(points: np.ndarray, dirs: np.ndarray, theta_home: np.ndarray) -> np.ndarray:
    """The closed-chain D-H table (n, 4) of n joint axes (lines) at readings `theta_home`.

    Frame j-1 has z along axis j; x_j is the common normal from axis j to axis j+1 (axis n+1 =
    axis 1: frame n is frame 0), its origin the foot on axis j+1; row j = F_{j-1}^-1 F_j
    decomposed as Rot(z, th) Trans(z, s) Trans(x, a) Rot(x, alpha), theta_off = th - theta_home_j.
    """
    n = len(points)
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    frames = []
    for j in range(n):  # frame j: z along axis j+1 (0-based: u[(j+1) % n]), x from axis j to axis j+1
        a, b = j, (j + 1) % n
        f1, f2 = common_normal(points[a], u[a], points[b], u[b])
        x = f2 - f1
        if np.linalg.norm(x) < 1e-9:  # intersecting axes: x along their common perpendicular
            x = np.cross(u[a], u[b])
        x = x / np.linalg.norm(x)
        R = np.column_stack([x, np.cross(u[b], x), u[b]])
        frames.append(pin.SE3(R, f2))
    rows = []
    for j in range(n):  # row j+1 relates frame j (z on axis j+1) to frame j+1
        A = frames[j - 1].actInv(frames[j])
        R, t = A.rotation, A.translation
        th = np.arctan2(R[1, 0], R[0, 0])
        al = np.arctan2(R[2, 1], R[2, 2])
        aa = t[0] * np.cos(th) + t[1] * np.sin(th)
        rows.append([th - theta_home[j], t[2], aa, al])
        assert np.allclose(dh_A(th, t[2], aa, al).homogeneous, A.homogeneous, atol=1e-10)
    return np.array(rows)


def axes_of(frames: list[pin.SE3]) -> tuple[np.ndarray, np.ndarray]:
    """Joint axis lines (point, direction) of an open chain: joint j turns about z of frame j-1."""
    return np.array([F.translation for F in frames]), np.array([F.rotation[:, 2] for F in frames])


# ----------------------------------------------------------------------------- Pinocchio truth
def pin_model(rows: np.ndarray) -> pin.Model:
    """One revolute-z joint per row; joint j placed at C_{j-1} Rot(z, theta_off_j); frame 'end' = C_n."""
    model = pin.Model()
    parent, place = 0, pin.SE3.Identity()
    for j, (off, s, a, al) in enumerate(rows):
        parent = model.addJoint(parent, pin.JointModelRZ(), place * pin.SE3(rot("z", off), np.zeros(3)), f"j{j + 1}")
        place = dh_const(s, a, al)
    model.addFrame(pin.Frame("end", parent, 0, place, pin.FrameType.OP_FRAME))
    return model


class Chain:
    """FK and Jacobian of the 'end' frame of a D-H chain (Pinocchio)."""

    def __init__(self, rows: np.ndarray):
        self.model = pin_model(rows)
        self.data = self.model.createData()
        self.fid = self.model.getFrameId("end")

    def pose(self, th) -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(th, float))
        return self.data.oMf[self.fid].copy()

    def jac(self, th, ref=pin.LOCAL) -> np.ndarray:
        return pin.computeFrameJacobian(self.model, self.data, np.asarray(th, float), self.fid, ref)


def newton(fun, x: np.ndarray, tol: float = 1e-12, iters: int = 60) -> np.ndarray | None:
    """Gauss-Newton with step limiting on fun(x) -> (r, J); None unless |r| < tol."""
    for _ in range(iters):
        r, J = fun(x)
        if np.linalg.norm(r) < tol:
            return x
        dx = -np.linalg.lstsq(J, r, rcond=None)[0]
        big = np.max(np.abs(dx))
        x = x + (dx * 0.2 / big if big > 0.2 else dx)
    return None


# ----------------------------------------------------------------------------- the examples
@dataclass
class Example:
    """A thesis example: true table, loop, fixed length and exact readings."""

    name: str
    rows: np.ndarray  # (n, 4) true theta_off, s, a, alpha
    closes: bool
    loop_specs: list[str]
    fixed: list[str]
    readings: np.ndarray  # (N, n)
    tip: np.ndarray | None = None  # true tool point in the end frame (point contact)
    meta: dict = field(default_factory=dict)

    @property
    def joints(self) -> list[str]:
        return [f"j{j + 1}" for j in range(len(self.rows))]


# Open-chain designs (s, a, alpha): consecutive axes never parallel; the upper arm is the unit length.
ARM7 = [
    (0.0, 0.2, -np.pi / 2),
    (0.15, 0.1, np.pi / 2),
    (1.0, 0.2, -np.pi / 2),
    (0.15, 0.2, np.pi / 2),
    (0.9, 0.1, -np.pi / 2),
    (0.1, 0.15, np.pi / 2),
    (0.2, 0.02, 0.0),
]
ARM6 = [
    (0.0, 0.1, -np.pi / 2),
    (0.1, 0.05, np.pi / 2),
    (1.0, 0.1, -np.pi / 2),
    (0.1, 0.1, np.pi / 2),
    (0.8, 0.05, -np.pi / 2),
    (0.15, 0.05, 0.4),
]
ARM6_POINT = [
    (0.2, 0.1, -np.pi / 2),
    (1.0, 0.1, np.pi / 2),
    (0.1, 0.1, -np.pi / 2),
    (0.8, 0.05, np.pi / 2),
    (0.1, 0.05, -np.pi / 2),
    (0.2, 0.05, 0.3),
]


def _open_rows(design, offsets=None) -> np.ndarray:
    offs = np.zeros(len(design)) if offsets is None else offsets
    return np.array([[o, s, a, al] for o, (s, a, al) in zip(offs, design)])


def _sweep(fun_free, x0: np.ndarray, drivers: np.ndarray) -> np.ndarray:
    """Solve the free unknowns for each driver value by Newton from the nearest solved one."""
    order = np.argsort(np.linalg.norm(drivers, axis=1))  # outward from the home configuration
    sols: dict[int, np.ndarray] = {}
    done = [(np.zeros(drivers.shape[1]), x0)]
    for i in order:
        k = int(np.argmin([np.linalg.norm(d - drivers[i]) for d, _ in done]))
        # continuation in small steps from the nearest solved driver value
        d_from, x = done[k]
        for t in np.linspace(0.0, 1.0, 6)[1:]:
            x = newton(lambda z: fun_free(d_from + t * (drivers[i] - d_from), z), x)
            if x is None:
                raise RuntimeError("the loop could not be closed along the sweep (singular or lost)")
        sols[i] = x
        done.append((drivers[i], x))
    return np.array([sols[i] for i in range(len(drivers))])


def _closed_chain(name: str, points, dirs, home, drivers_idx, drivers, fixed) -> Example:
    """A closed chain from its joint axes at `home`; `drivers` give the readings of `drivers_idx`."""
    rows = cyclic_table(points, dirs, home)
    chain = Chain(rows)
    n = len(rows)
    free = [j for j in range(n) if j not in drivers_idx]

    def fun(d, z):
        th = home.copy()
        th[drivers_idx] = home[drivers_idx] + d
        th[free] = z
        T = chain.pose(th)
        return pin.log6(T).vector, (pin.Jlog6(T) @ chain.jac(th))[:, free]

    Z = _sweep(fun, home[free].copy(), drivers)
    TH = np.tile(home, (len(drivers), 1))
    TH[:, drivers_idx] += drivers
    TH[:, free] = Z
    return Example(name, rows, True, [], fixed, TH)


@functools.lru_cache(maxsize=None)
def example1() -> Example:
    """7-DOF arm, end effector grasping the ground; theta_1 = 0..0.5 rad, 40 configurations."""
    home = np.array([0.0, 0.5, 0.3, 1.2, -0.4, 0.8, 0.5])
    F = open_frames(_open_rows(ARM7), home)
    p, u = axes_of(F[:7])
    return _closed_chain("example1", p, u, home, [0], np.linspace(0.0, 0.5, 40)[:, None], ["j3.s"])


@functools.lru_cache(maxsize=None)
def example2() -> Example:
    """Two 6-DOF arms grasping each other (12 joints); theta_1..6 in 0..0.25 rad, 40 configurations."""
    hA, hB = np.array([0.2, 0.6, 0.2, 1.3, 0.3, 0.7]), np.array([-0.28, 1.23, -1.37, 0.97, -0.25, 0.99])
    FA = open_frames(_open_rows(ARM6), hA)
    FB = open_frames(_open_rows(ARM6), hB)
    grasp = pin.SE3(rot("x", np.pi) @ rot("z", 0.3), np.array([0.05, 0.0, 0.1]))
    base_B = FA[-1] * grasp * FB[-1].inverse()
    pA, uA = axes_of(FA[:6])
    pB, uB = axes_of([base_B * f for f in FB[:6]])
    points = np.vstack([pA, pB[::-1]])
    dirs = np.vstack([uA, -uB[::-1]])
    home = np.concatenate([np.zeros(6), np.zeros(6)])
    rng = np.random.default_rng(2)
    return _closed_chain("example2", points, dirs, home, list(range(6)), rng.uniform(0.0, 0.25, (40, 6)), ["j3.s"])


@functools.lru_cache(maxsize=None)
def door() -> Example:
    """6-DOF arm opening a door (hinge unknown); theta_1 = 0..0.5 rad, 40 configurations."""
    rows = _open_rows(ARM6, np.array([0.1, -0.2, 0.3, 0.15, -0.25, 0.2]))
    chain = Chain(rows)
    home = np.array([0.0, 0.6, 0.2, 1.3, 0.3, 0.7])
    T0 = chain.pose(home)
    u = np.array([0.1, 0.2, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(u, T0.rotation[:, 0])
    c = T0.translation + 0.6 * w / np.linalg.norm(w)

    def fun(d, z):  # z = (theta_2..6, phi)
        th = np.concatenate([[home[0] + d[0]], z[:5]])
        R = pin.exp3(u * z[5])
        tgt = pin.SE3(R, c - R @ c) * T0
        E = tgt.actInv(chain.pose(th))
        J = np.zeros((6, 6))
        J[:, :5] = (pin.Jlog6(E) @ chain.jac(th))[:, 1:]
        h = 1e-7
        R2 = pin.exp3(u * (z[5] + h))
        E2 = (pin.SE3(R2, c - R2 @ c) * T0).actInv(chain.pose(th))
        J[:, 5] = (pin.log6(E2).vector - pin.log6(E).vector) / h
        return pin.log6(E).vector, J

    Z = _sweep(fun, np.concatenate([home[1:], [0.0]]), np.linspace(0.0, 0.5, 40)[:, None])
    TH = np.column_stack([home[0] + np.linspace(0.0, 0.5, 40), Z[:, :5]])
    return Example(
        "door",
        rows,
        False,
        ["hinge:frame=door_end,name=door"],
        ["j3.s"],
        TH,
        meta={"axis_point": c, "axis_dir": u, "phi": Z[:, 5]},
    )


@functools.lru_cache(maxsize=None)
def point_contact() -> Example:
    """6-DOF arm under point contact; theta_4..6 in 0..0.5 rad, 30 configurations; s2 fixed."""
    rows = _open_rows(ARM6_POINT, np.array([-0.1, 0.2, 0.1, -0.3, 0.25, 0.15]))
    chain = Chain(rows)
    home = np.array([0.0, 0.04, 1.35, -1.07, 1.35, -0.56])
    tip = np.array([0.1, 0.05, 0.3])
    P = chain.pose(home).act(tip)

    def fun(d, z):  # the wrist joints 4..6 are driven, the arm joints 1..3 keep the tip on the point
        th = np.concatenate([z, home[3:] + d])
        T = chain.pose(th)
        J = chain.jac(th, pin.LOCAL)
        Jp = T.rotation @ (J[:3] - pin.skew(tip) @ J[3:])  # world velocity of the tip point
        return T.act(tip) - P, Jp[:, :3]

    D = np.random.default_rng(3).uniform(0.0, 0.5, (30, 3))
    Z = _sweep(fun, home[:3].copy(), D)
    TH = np.column_stack([Z, home[3:] + D])
    return Example("point", rows, False, ["point:frame=point_end,name=contact"], ["j2.s"], TH, tip=tip)


EXAMPLES = {"example1": example1, "example2": example2, "door": door, "point": point_contact}


# ----------------------------------------------------------------------------- calibration starts
def write_table(ex: Example, rows: np.ndarray, path: Path) -> Path:
    """The table in closedloop's D-H YAML format (metres, radians)."""
    joints = [
        {"name": n, "convention": "dh", **{f: float(v) for f, v in zip(FIELDS, r)}} for n, r in zip(ex.joints, rows)
    ]
    path.write_text(
        yaml.safe_dump(
            {"name": ex.name, "closes": ex.closes, "units": {"length": "m", "angle": "rad"}, "joints": joints},
            sort_keys=False,
        )
    )
    return path


def thesis_start(ex: Example, rng: np.random.Generator) -> np.ndarray:
    """A thesis-sized starting guess: lengths +-0.1, twists +-0.3 rad, offsets +-0.6 rad; fixed lengths kept."""
    rows = ex.rows.copy()
    n = len(rows)
    rows[:, 0] += rng.uniform(-0.6, 0.6, n)
    rows[:, 1] += rng.uniform(-0.1, 0.1, n)
    rows[:, 2] += rng.uniform(-0.1, 0.1, n)
    rows[:, 3] += rng.uniform(-0.3, 0.3, n)
    for f in ex.fixed:
        j, fld = f.split(".")
        rows[int(j[1:]) - 1, FIELDS.index(fld)] = ex.rows[int(j[1:]) - 1, FIELDS.index(fld)]
    return rows


def rows_of(values: dict[str, float], ex: Example) -> np.ndarray:
    return np.array([[values[f"{j}.{f}"] for f in FIELDS] for j in ex.joints])


def mechanism_error(ex: Example, rows: np.ndarray, values: dict[str, float], n: int = 50, seed: int = 7) -> float:
    """Gauge-free distance between a calibrated table and the truth (m, rad mixed; unit lengths).

    Closed chains: origins and z axes of every D-H frame over random readings (a D-H table's
    discrete re-labellings, theta + pi with a, alpha negated, move neither).  Door: end-frame
    poses after the best base and tool transforms.  Point contact: tool-point positions
    (calibrated tip from the loop) after the best base transform.
    """
    from zoo import _fit_rigid

    TH = np.random.default_rng(seed).uniform(-np.pi, np.pi, (n, len(ex.joints)))
    if ex.closes:
        err = 0.0
        for th in TH:
            for Ft, Fc in zip(open_frames(ex.rows, th), open_frames(rows, th)):
                err = max(
                    err,
                    np.abs(Ft.translation - Fc.translation).max(),
                    np.abs(Ft.rotation[:, 2] - Fc.rotation[:, 2]).max(),
                )
        return float(err)
    ct, cc = Chain(ex.rows), Chain(rows)
    if ex.tip is None:  # door
        Tt = np.stack([ct.pose(t).homogeneous for t in TH])
        Tc = np.stack([cc.pose(t).homogeneous for t in TH])
        P, RB, RE, _, _ = _fit_rigid(Tc, Tt, False)
        ang = [np.linalg.norm(pin.log3(RB @ c[:3, :3] @ RE @ t[:3, :3].T)) for c, t in zip(Tc, Tt)]
        return float(max(np.abs(P[:, 0] - Tt[:, :3, 3]).max(), max(ang)))
    loop = ex.loop_specs[0].split("name=")[1]
    tip = np.array([values.get(f"{loop}.tip_{c}", np.nan) for c in "xyz"])
    pt = np.array([ct.pose(t).act(ex.tip) for t in TH])
    pc = np.array([cc.pose(t).act(tip) for t in TH])
    if not np.all(np.isfinite(pc)):
        return float("inf")
    mc, mt = pc.mean(0), pt.mean(0)
    U, _, Vt = np.linalg.svd((pc - mc).T @ (pt - mt))
    R = Vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))]) @ U.T
    return float(np.abs((pc - mc) @ R.T + mt - pt).max())


@dataclass
class StartOutcome:
    example: str
    seed: int
    recovered: bool
    status: str  # verdict status, 'ok?' without one, 'failed' for a closedloop error, 'crash'
    converged: bool
    error: float  # mechanism_error
    param_error: float  # max |calibrated - true| over table parameters (angles wrapped)
    seconds: float
    message: str = ""

    @property
    def refused(self) -> bool:
        return self.status in ("suspect", "failed")

    @property
    def accepted(self) -> bool:
        """Recovered and not refused outright (a 'failed' verdict on the right answer is a false alarm)."""
        return self.recovered and self.status not in ("failed", "crash")

    def line(self) -> str:
        tag = (
            "recovered"
            if self.accepted
            else "RIGHT BUT FAILED"
            if self.recovered
            else "REFUSED"
            if self.refused
            else "CRASH"
            if self.status == "crash"
            else "CONFIDENTLY WRONG"
        )
        return (
            f"{self.example:9s} start {self.seed:3d} {tag:18s} verdict={self.status:7s} conv={self.converged!s:5s} "
            f"mechanism err {self.error:.2e} param err {self.param_error:.2e} {self.seconds:5.2f}s {self.message}"
        )


def run_start(ex: Example, seed: int, options=None, workdir: Path | None = None) -> StartOutcome:
    """Calibrate `ex` from thesis-sized start number `seed` with closedloop's Python API."""
    import time

    from closedloop import CalibrationOptions, ClosedLoopError, RobotModel, calibrate, read_log
    from closedloop.loops.spec import default_loops, parse_loop

    wd = Path(workdir) if workdir else scratch_dir(f"basin_{ex.name}_")
    start = thesis_start(ex, np.random.default_rng([seed, len(ex.joints)]))
    table = write_table(ex, start, wd / f"{ex.name}_start_{seed}.yaml")
    log = wd / f"{ex.name}.csv"
    if not log.exists():
        log.write_text(
            ",".join(ex.joints) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in ex.readings) + "\n"
        )
    opt = options or CalibrationOptions()
    opt.fix = {**{f: None for f in ex.fixed}, **opt.fix}
    t0 = time.perf_counter()
    try:
        robot = RobotModel.from_file(table)
        loops = default_loops(robot) + [parse_loop(s, robot) for s in ex.loop_specs]
        res = calibrate(robot, read_log(log, robot.joint_names), loops, opt)
    except ClosedLoopError as exc:
        return StartOutcome(ex.name, seed, False, "failed", False, np.inf, np.inf, time.perf_counter() - t0, str(exc))
    except Exception as exc:  # noqa: BLE001 - a crash is reported, not hidden
        return StartOutcome(
            ex.name,
            seed,
            False,
            "crash",
            False,
            np.inf,
            np.inf,
            time.perf_counter() - t0,
            f"{type(exc).__name__}: {exc}",
        )
    dt = time.perf_counter() - t0
    values = res.as_dict()
    rows = rows_of(values, ex)
    d = rows - ex.rows
    d[:, [0, 3]] = (d[:, [0, 3]] + np.pi) % (2 * np.pi) - np.pi
    err = mechanism_error(ex, rows, values)
    v = getattr(res, "verdict", None)
    status = "ok?" if v is None else str(getattr(v, "status", v))
    after = "; ".join(
        f"closure {r.rms_m if r.rms_m is not None else float('nan'):.2e} m "
        f"{r.rms_rad if r.rms_rad is not None else float('nan'):.2e} rad"
        for r in res.fit.residuals_after
    )
    msg = (
        f"{after}; {res.fit.iterations} it; {sum(s == 'dropped' for s in res.fit.status)} dropped, "
        f"{sum(s == 'unidentifiable' for s in res.fit.status)} unidentifiable"
    )
    return StartOutcome(
        ex.name, seed, bool(err < TOL), status, bool(res.converged), err, float(np.abs(d).max()), dt, msg
    )
