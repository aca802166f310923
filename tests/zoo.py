"""A robot zoo: ground truth for closed-loop calibration, independent of the calibrator.

Every serial arm of example-robot-data that Pinocchio loads is cut down to the
chain base -> tool (links and joints on that path only; continuous joints become
revolute on [-pi, pi]; a fixed, off-axis ``zoo_tool`` link is appended), and
written, mesh-free, as the *nominal* URDF the calibrator reads.

The *true* robot is the nominal URDF text with EVERY joint origin, fixed joints
included, perturbed in its parent frame (xyz +- ``err_m``, rpy +- ``err_rad``,
uniform), and joint offsets ``reading = q_true - offset``.  Nothing here uses
closedloop's parametrization: the loops are closed with Pinocchio on the true
model by damped least squares, and :func:`judge` compares what the calibrated
robot does (forward kinematics of the tool frame from raw readings) with the
truth after the best rigid base and tool transforms (and the best length scale
only for loops that cannot see it), so a wrong gauge or a wrong redundancy
reduction is visible.

Loops (``Case.loop_specs`` are ``--loop`` strings):

* ``weld``: the tool held at one pose (redundant, 7-DOF arms);
* ``point``: the tool point pressed at a fixed world point;
* ``plane``: the tool point on a plane;
* ``hinge``: the tool grasping a handle turning about a fixed axis (a door);
* ``measured_point``: a tracker measures the tool point (own noise ``sigma_t``).

``judge``, ``run_case`` and ``predicted_std`` live in ``zoo_judge.py`` and are re-exported here.
Quick subset: ``tests/test_zoo.py``; the full zoo: ``benchmarks/zoo.py``.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin
from scratch import scratch_dir

from closedloop.assets.catalog import example_robot_data_dir

TOOL = "zoo_tool"
SCALE_BLIND = {"weld", "point", "plane", "hinge"}  # loops that close at any overall size


@dataclass(frozen=True)
class ZooRobot:
    """A serial arm of example-robot-data: file, base link and the link carrying the tool."""

    name: str
    relpath: str
    base: str
    tip: str
    tool_xyz: tuple[float, float, float] = (0.03, -0.02, 0.06)
    tool_rpy: tuple[float, float, float] = (0.2, -0.1, 0.3)


ZOO: dict[str, ZooRobot] = {
    r.name: r
    for r in [
        ZooRobot("panda", "panda_description/urdf/panda.urdf", "panda_link0", "panda_hand_tcp"),
        ZooRobot("ur3", "ur_description/urdf/ur3_robot.urdf", "base_link", "tool0"),
        ZooRobot("ur5", "ur_description/urdf/ur5_robot.urdf", "base_link", "tool0"),
        ZooRobot("ur10", "ur_description/urdf/ur10_robot.urdf", "base_link", "tool0"),
        ZooRobot("kinova", "kinova_description/robots/kinova.urdf", "base", "j2s6s200_end_effector"),
        ZooRobot("xarm7", "xarm_description/urdf/xarm7.urdf", "link_base", "link_eef"),
        ZooRobot("z1", "z1_description/urdf/z1.urdf", "link00", "link06"),
        ZooRobot("baxter_left", "baxter_description/urdf/baxter.urdf", "base", "left_gripper"),
        ZooRobot("tiago", "tiago_description/robots/tiago.urdf", "torso_lift_link", "arm_tool_link"),
        ZooRobot("pr2_left", "pr2_description/urdf/pr2.urdf", "torso_lift_link", "l_gripper_tool_frame"),
        ZooRobot("talos_left", "talos_data/robots/talos_reduced.urdf", "torso_2_link", "arm_left_7_link"),
        ZooRobot(
            "tiago_pro_left", "tiago_pro_description/robots/tiago_pro.urdf", "torso_lift_link", "arm_left_tool_link"
        ),
        ZooRobot("g1_left", "g1_description/urdf/g1_29dof_rev_1_0.urdf", "torso_link", "left_wrist_yaw_link"),
    ]
}

# robots outside example-robot-data, for single tests (not in the zoo's benchmark): a KUKA iiwa14 (mesh-free,
# ROS-Industrial joint names), the ball at the flange
EXTRA: dict[str, ZooRobot] = {
    "iiwa14": ZooRobot(
        "iiwa14",
        str(Path(__file__).resolve().parent / "data" / "iiwa14.urdf"),
        "base_link",
        "tool0",
        (0, 0, 0),
        (0, 0, 0),
    )
}

MOVABLE = ("revolute", "continuous", "prismatic")


# ----------------------------------------------------------------------------- URDF
def chain_urdf(robot: ZooRobot) -> str:
    """The mesh-free nominal URDF of the chain base -> tip, plus the fixed ``zoo_tool`` link."""
    root = ET.parse(example_robot_data_dir() / robot.relpath).getroot()
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    path, link = [], robot.tip
    while link != robot.base:
        if link not in by_child:
            raise ValueError(f"{robot.name}: {robot.tip} does not descend from {robot.base}")
        path.append(by_child[link])
        link = path[-1].find("parent").get("link")
    out = ET.Element("robot", name=f"zoo_{robot.name}")
    ET.SubElement(out, "link", name=robot.base)
    for j in reversed(path):
        j = copy.deepcopy(j)
        for tag in ("dynamics", "safety_controller", "calibration", "mimic"):
            for el in list(j.findall(tag)):
                j.remove(el)
        if j.find("origin") is None:
            ET.SubElement(j, "origin", xyz="0 0 0", rpy="0 0 0")
        if j.get("type") == "continuous":
            j.set("type", "revolute")
            lim = j.find("limit")
            if lim is None:
                lim = ET.SubElement(j, "limit", effort="10", velocity="1")
            lim.set("lower", repr(-np.pi))
            lim.set("upper", repr(np.pi))
        if j.get("type") == "fixed":
            for tag in ("axis", "limit"):
                for el in list(j.findall(tag)):
                    j.remove(el)
        ET.SubElement(out, "link", name=j.find("child").get("link"))
        out.append(j)
    ET.SubElement(out, "link", name=TOOL)
    tj = ET.SubElement(out, "joint", name=f"{TOOL}_joint", type="fixed")
    ET.SubElement(tj, "parent", link=robot.tip)
    ET.SubElement(tj, "child", link=TOOL)
    ET.SubElement(tj, "origin", xyz=" ".join(map(repr, robot.tool_xyz)), rpy=" ".join(map(repr, robot.tool_rpy)))
    ET.indent(out)
    return ET.tostring(out, encoding="unicode")


def _vec(text: str | None) -> np.ndarray:
    return np.array([float(t) for t in (text or "0 0 0").split()], dtype=float)


def perturb_urdf(urdf: str, rng: np.random.Generator, err_m: float, err_rad: float) -> str:
    """Every joint origin moved in its parent frame: xyz + U(-err_m, err_m), R <- Rot(U(-err_rad, err_rad)) R."""
    root = ET.fromstring(urdf)
    for j in root.findall("joint"):
        o = j.find("origin")
        xyz = _vec(o.get("xyz")) + rng.uniform(-err_m, err_m, 3)
        R = pin.rpy.rpyToMatrix(*_vec(o.get("rpy")))
        R = pin.rpy.rpyToMatrix(*rng.uniform(-err_rad, err_rad, 3)) @ R
        o.set("xyz", " ".join(repr(float(v)) for v in xyz))
        o.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(R)))
    return ET.tostring(root, encoding="unicode")


# ----------------------------------------------------------------------------- kinematics
class Kin:
    """Forward kinematics of one frame of a Pinocchio model, in joint-name order."""

    def __init__(self, model: pin.Model, joints: list[str], frame: str = TOOL):
        self.model, self.data = model, model.createData()
        self.fid = model.getFrameId(frame)
        self.iq = np.array([model.joints[model.getJointId(n)].idx_q for n in joints])
        self.iv = np.array([model.joints[model.getJointId(n)].idx_v for n in joints])
        self.q = pin.neutral(model)

    def _set(self, th: np.ndarray) -> np.ndarray:
        q = self.q.copy()
        q[self.iq] = th
        return q

    def pose(self, th: np.ndarray) -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, self._set(th))
        return self.data.oMf[self.fid].copy()

    def jacobian(self, th: np.ndarray, ref=pin.LOCAL) -> np.ndarray:
        J = pin.computeFrameJacobian(self.model, self.data, self._set(th), self.fid, ref)
        return J[:, self.iv]

    def poses(self, TH: np.ndarray) -> np.ndarray:
        """(N, 4, 4) homogeneous poses."""
        return np.stack([self.pose(t).homogeneous for t in TH])


def joint_info(model: pin.Model) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Movable joint names (model order) and their limits."""
    names = [model.names[i] for i in range(1, model.njoints) if model.joints[i].nv == 1]
    iq = [model.joints[model.getJointId(n)].idx_q for n in names]
    return names, model.lowerPositionLimit[iq].copy(), model.upperPositionLimit[iq].copy()


def _project(fun, th: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-12, iters: int = 80):
    """Damped least squares th <- th - J^T (J J^T + lam I)^-1 r until |r| < tol; None if it fails or leaves limits."""
    for _ in range(iters):
        r, J = fun(th)
        nr = float(np.linalg.norm(r))
        if nr < tol:
            return th if np.all(th > lo) and np.all(th < hi) else None
        lam = 1e-3 * nr * nr + 1e-14
        dq = -J.T @ np.linalg.solve(J @ J.T + lam * np.eye(J.shape[0]), r)
        big = np.max(np.abs(dq))
        th = th + (dq * 0.3 / big if big > 0.3 else dq)
    return None


def on_true_loop(case):
    """The point or plane loop of a zoo `case` on its true robot, for `_project`: readings (model order, the
    true offsets included) -> (the tool point's closure, its Jacobian): its offset from the socket, or its
    distance from the plane."""
    kin = Kin(case.true_model, case.joints)
    geo = case.meta["geo"]
    point = geo["T0"].translation

    def socket(th):
        return kin.pose(th).translation - point, kin.jacobian(th, pin.LOCAL_WORLD_ALIGNED)[:3]

    def plane(th):
        J = kin.jacobian(th, pin.LOCAL_WORLD_ALIGNED)[:3]
        return np.array([geo["normal"] @ (kin.pose(th).translation - point)]), (geo["normal"] @ J)[None]

    return plane if "normal" in geo else socket


def _well_conditioned(kin: Kin, th: np.ndarray, fun, min_sv: float = 0.03) -> bool:
    """Away from arm singularities (6 x n tool Jacobian) and from constraint singularities."""
    s_arm = np.linalg.svd(kin.jacobian(th), compute_uv=False)
    if s_arm[min(5, s_arm.size - 1)] < min_sv:
        return False
    if fun is None:
        return True
    s_c = np.linalg.svd(fun(th)[1], compute_uv=False)
    return s_c[-1] > min_sv * 0.3


def _random_start(kin: Kin, lo, hi, rng, tries: int = 200) -> np.ndarray:
    for _ in range(tries):
        th = rng.uniform(lo, hi)
        if _well_conditioned(kin, th, None):
            return th
    raise RuntimeError("no well-conditioned configuration found")


def _hinge_pose(c: np.ndarray, u: np.ndarray, phi: float, T0: pin.SE3) -> pin.SE3:
    """T0 rotated by phi about the line through c with direction u."""
    R = pin.exp3(u * phi)
    return pin.SE3(R, c - R @ c) * T0


def _constraint(kind: str, kin: Kin, th0: np.ndarray, rng: np.random.Generator):
    """(fun(th, target) -> (r, J), geometry dict) for the loop through the true tool at th0."""
    T0 = kin.pose(th0)
    P = T0.translation.copy()
    geo: dict = {"T0": T0}
    if kind in ("weld", "hinge"):

        def fun(th, target=T0):
            E = target.actInv(kin.pose(th))
            return pin.log6(E).vector, pin.Jlog6(E) @ kin.jacobian(th)

        if kind == "hinge":
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            w = np.cross(u, rng.normal(size=3))
            geo.update(axis_u=u, axis_c=P + 0.3 * w / np.linalg.norm(w))
        return fun, geo
    if kind == "point":

        def fun(th, target=None):
            return kin.pose(th).translation - P, kin.jacobian(th, pin.LOCAL_WORLD_ALIGNED)[:3]

        return fun, geo
    if kind == "plane":
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        geo["normal"] = n

        def fun(th, target=None):
            J = kin.jacobian(th, pin.LOCAL_WORLD_ALIGNED)[:3]
            return np.array([n @ (kin.pose(th).translation - P)]), (n @ J)[None]

        return fun, geo
    raise ValueError(f"unknown loop kind {kind!r}")


def sample_loop(
    kind: str,
    kin: Kin,
    lo,
    hi,
    n: int,
    rng: np.random.Generator,
    step: float = 0.4,
    phi_max: float = 0.5,
    max_tries: int = 40,
) -> tuple[np.ndarray, dict]:
    """n true joint configurations on the loop: random moves + DLS projection (|r| < 1e-12)."""
    margin = 0.05
    lo_m, hi_m = lo + margin, hi - margin
    for _attempt in range(max_tries):
        th0 = _random_start(kin, lo_m, hi_m, rng)
        fun, geo = _constraint(kind, kin, th0, rng)
        if not _well_conditioned(kin, th0, fun):
            continue
        accepted, phis = [th0], [0.0]
        # hinge: door angles on a grid over [-phi_max, phi_max], reached outward from 0 by continuation,
        # then random angles within the range reached
        grid = np.linspace(-phi_max, phi_max, n + 1)
        targets = sorted((float(g) for g in grid if abs(g) > 1e-12), key=abs) if kind == "hinge" else []
        fails = 0
        while len(accepted) < n and fails < 20 * n:
            if kind == "hinge":
                phi = targets.pop(0) if targets else float(rng.uniform(min(phis), max(phis)))
                k = int(np.argmin(np.abs(np.array(phis) - phi)))
                tgt = _hinge_pose(geo["axis_c"], geo["axis_u"], phi, geo["T0"])
                start = accepted[k] + rng.normal(scale=0.1 if kin.iq.size > 6 else 0.01, size=kin.iq.size)
            else:
                phi, tgt = 0.0, None
                start = accepted[rng.integers(len(accepted))] + rng.normal(scale=step, size=kin.iq.size)
            th = _project(lambda t: fun(t, tgt) if tgt is not None else fun(t), start, lo_m, hi_m)
            if th is None or not _well_conditioned(kin, th, (lambda t: fun(t, tgt)) if tgt is not None else fun):
                fails += 1
                continue
            accepted.append(th)
            phis.append(phi)
        if len(accepted) >= n and (kind != "hinge" or np.ptp(phis[:n]) >= phi_max):
            geo["phi"] = np.array(phis[:n])
            return np.array(accepted[:n]), geo
    raise RuntimeError(f"could not sample {n} configurations of a {kind} loop")


# ----------------------------------------------------------------------------- cases
@dataclass
class Case:
    """One zoo experiment: the files the calibrator reads and the truth it is judged against."""

    robot: str
    loop: str
    seed: int
    nominal_urdf: Path
    log_csv: Path
    loop_specs: list[str]
    true_model: pin.Model
    true_offsets: dict[str, float]
    joints: list[str]
    readings: np.ndarray  # (N, n) as logged (noise and corruption included)
    q_true: np.ndarray  # (N, n) true joint angles
    sigma: float  # joint noise std (rad)
    sigma_t: float = 0.0  # tracker noise (m), measured_point only
    corrupted: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # corrupted row indices (0-based)
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    reach: float = 1.0  # max distance of the tool from the base over the joint ranges (m)
    meta: dict = field(default_factory=dict)

    @property
    def scale_visible(self) -> bool:
        return self.loop not in SCALE_BLIND

    def true_distance(self, frame_a: str, frame_b: str) -> float:
        """The true distance between two frames at zero readings (the true model at the true offsets): what a
        caliper between them measures (`closedloop.problem.lengths.LengthLoop`)."""
        tm = self.true_model
        td = tm.createData()
        q = pin.neutral(tm)
        for j, off in self.true_offsets.items():
            q[tm.joints[tm.getJointId(j)].idx_q] = off
        pin.framesForwardKinematics(tm, td, q)
        return float(
            np.linalg.norm(td.oMf[tm.getFrameId(frame_b)].translation - td.oMf[tm.getFrameId(frame_a)].translation)
        )

    @property
    def label(self) -> str:
        tags = [t for t in (self.meta.get("tag"),) if t]
        return f"{self.robot}/{self.loop}/s{self.seed}" + "".join(f"/{t}" for t in tags)

    def tolerances(self) -> dict[str, float]:
        """What 'right' means.

        pos / rot: 0.1 mm / 1 mrad noise-free, plus with noise 5x the largest tool error std that the
        noise alone leaves (Cramer-Rao bound, zoo_judge.predicted_std).
        rel_pos (relative motions of configuration pairs): 2 pos + 2 reach x the noise part of rot.
        scale (loops blind to it): the calibrator fixes one length at its nominal value, so the
        calibrated size is off by that length's error over its length; with origin errors up to
        err_m per axis and err_rad per angle and a fixed length of at least 10 cm (the README
        promises the longest free one): sqrt(3) (err_m / 0.1 m + err_rad).
        """
        scale = np.sqrt(3.0) * (self.meta.get("err_m", 2e-3) / 0.1 + self.meta.get("err_rad", 2e-3))
        tol = {"pos": 1e-4, "rot": 1e-3, "scale": float(scale)}
        if self.sigma > 0 or self.sigma_t > 0:
            std = predicted_std(self)
            tol["pos"] += 5.0 * std["pos"]
            tol["rot"] += 5.0 * std["rot"]
        # a relative motion carries the position errors of both ends and the orientation error of
        # the first one over the distance between them (at most twice the reach)
        tol["rel_pos"] = 2.0 * tol["pos"] + 2.0 * self.reach * (tol["rot"] - 1e-3)
        return tol


def make_case(
    robot: str,
    loop: str,
    n: int = 60,
    sigma: float = 0.0,
    seed: int = 0,
    *,
    err_m: float = 2e-3,
    err_rad: float = 2e-3,
    offset_rad: float = 0.02,
    corrupt_rows: float = 0.0,
    corrupt_cells: int = 0,
    cell_value: float = 1e6,
    sigma_t: float = 0.0,
    workdir: str | Path | None = None,
    tag: str = "",
) -> Case:
    """Generate a zoo case (files under `workdir`, a fresh temporary directory by default).

    corrupt_rows: fraction of rows replaced by uniform random readings within the limits;
    corrupt_cells: number of single cells set to `cell_value`.
    """
    rng = np.random.default_rng([seed, sum(map(ord, robot)), sum(map(ord, loop))])
    src = ZOO[robot] if robot in ZOO else EXTRA[robot]
    nominal = chain_urdf(src)
    truth = perturb_urdf(nominal, rng, err_m, err_rad)
    model = pin.buildModelFromXML(truth)
    joints, lo, hi = joint_info(model)
    hi = np.minimum(hi, np.pi)
    lo = np.maximum(lo, -np.pi)
    offsets = rng.uniform(-offset_rad, offset_rad, len(joints))
    kin = Kin(model, joints)
    name = {"measured_point": "meas"}.get(loop, loop)
    extra: dict[str, np.ndarray] = {}
    if loop == "measured_point":
        TH = np.array([_random_start(kin, lo + 0.05, hi - 0.05, rng) for _ in range(n)])
        X = pin.SE3(pin.exp3(rng.normal(size=3)), rng.uniform(-1.0, 1.0, 3) + np.array([1.5, 0, 0]))
        pts = np.array([X.actInv(kin.pose(t).translation) for t in TH]) + rng.normal(scale=sigma_t, size=(n, 3))
        extra = {f"{name}:{c}": pts[:, k] for k, c in enumerate("xyz")}
        spec = f"measured_point:frame={TOOL},name={name}" + (f",sigma_t={sigma_t!r}" if sigma_t > 0 else "")
        geo = {"X": X, "meas": pts}
    else:
        TH, geo = sample_loop(loop, kin, lo, hi, n, rng)
        spec = f"{loop}:frame={TOOL},name={name}"
    readings = TH - offsets + rng.normal(scale=sigma, size=TH.shape) if sigma > 0 else TH - offsets
    bad = np.zeros(0, int)
    if corrupt_rows > 0:
        bad = np.sort(rng.choice(n, int(round(corrupt_rows * n)), replace=False))
        readings[bad] = rng.uniform(lo, hi, (bad.size, len(joints)))
    if corrupt_cells > 0:
        rows = rng.choice(n, corrupt_cells, replace=False)
        readings[rows, rng.integers(0, len(joints), corrupt_cells)] = cell_value
        bad = np.union1d(bad, rows)
    wd = Path(workdir) if workdir else scratch_dir(f"zoo_{robot}_{loop}_")
    wd.mkdir(parents=True, exist_ok=True)
    (wd / "nominal.urdf").write_text(nominal)
    (wd / "truth.urdf").write_text(truth)
    cols = {j: readings[:, k] for k, j in enumerate(joints)} | extra
    lines = [",".join(cols)] + [",".join(repr(float(c[i])) for c in cols.values()) for i in range(n)]
    (wd / "log.csv").write_text("\n".join(lines) + "\n")
    reach = float(np.max(np.linalg.norm(kin.poses(rng.uniform(lo, hi, (200, len(joints))))[:, :3, 3], axis=1)))
    return Case(
        robot,
        loop,
        seed,
        wd / "nominal.urdf",
        wd / "log.csv",
        [spec],
        model,
        dict(zip(joints, offsets)),
        joints,
        readings,
        TH,
        sigma,
        sigma_t,
        bad,
        lo,
        hi,
        reach,
        {"tag": tag, "n": n, "err_m": err_m, "err_rad": err_rad, "offset_rad": offset_rad, "geo": geo},
    )


# The judge and the runner live in zoo_judge.py (module size); re-exported here.
from zoo_judge import (  # noqa: E402,F401
    Judgement,
    Outcome,
    _fit_rigid,
    calibrated_model_path,
    folded_truth_urdf,
    judge,
    predicted_std,
    run_case,
    verdict_status,
)
