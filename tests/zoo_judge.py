"""Judging a calibrated robot against the zoo's truth, and running closedloop on a zoo case.

:func:`judge` compares what the robot does, without gauges: tool-frame forward kinematics of the
calibrated URDF (fed raw readings: closedloop folds the offsets into it) against the true model
(fed readings + offsets) on fresh random configurations over the joint ranges, after the best rigid
base and tool transforms (least squares on SE(3)) and the best length scale only when the loop cannot
see it; plus relative motions between consecutive test configurations.

:func:`predicted_std` gives the tool errors that joint (and tracker) noise alone should leave, from
the Cramer-Rao bound of the zoo's own parametrization (a twist on every joint placement and on the
tool frame, the loop's own unknowns, per-configuration hinge angles), errors in variables: each
configuration's residual whitened by (sigma^2 J_theta J_theta^T + Sigma_meas)^-1/2.  Noisy cases are
judged against 0.1 mm + 5x that prediction, so weakly conditioned data (one weld pose) are not
called wrong for what no calibrator could do.
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from zoo import TOOL, Case, Kin, _hinge_pose, _vec


# ----------------------------------------------------------------------------- judge
@dataclass
class Judgement:
    """Tool-frame errors of a calibrated robot against the truth (m, rad), after the best base/tool/scale."""

    pos_rms: float
    pos_max: float
    rot_rms: float
    rot_max: float
    rel_pos_rms: float  # relative motions between consecutive test configurations
    rel_pos_max: float
    rel_rot_rms: float
    rel_rot_max: float
    scale: float  # size of the calibrated robot relative to the truth (1 when the loop sees the scale)
    n: int

    def right(self, tol: dict[str, float]) -> bool:
        """Within `tol` (Case.tolerances())."""
        return bool(
            self.pos_max < tol["pos"]
            and self.rot_max < tol["rot"]
            and self.rel_pos_max < tol["rel_pos"]
            and self.rel_rot_max < 2 * tol["rot"]
            and abs(self.scale - 1.0) < tol["scale"]
        )

    def summary(self) -> str:
        return (
            f"pos rms {self.pos_rms * 1e3:.3g} max {self.pos_max * 1e3:.3g} mm, rot max "
            f"{self.rot_max * 1e3:.3g} mrad, rel pos max {self.rel_pos_max * 1e3:.3g} mm, scale {self.scale:.6g}"
        )


def _fit_rigid(Tc: np.ndarray, Tt: np.ndarray, fit_scale: bool, arm: float = 0.1):
    """min over B, E, s of sum |B S_s(Tc_k) E e_m - Tt_k e_m|^2, e_m = origin and `arm` along each axis.

    S_s scales the translation of the calibrated robot's poses (the tool offset of E with it).
    Started from Umeyama's similarity fit of the tool origins; refined by Levenberg-Marquardt.
    """
    from scipy.optimize import least_squares

    pc, pt = Tc[:, :3, 3], Tt[:, :3, 3]
    mc, mt = pc.mean(0), pt.mean(0)
    H = (pc - mc).T @ (pt - mt)
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    RB0 = Vt.T @ D @ U.T
    s0 = float(np.trace(np.diag(S) @ D) / np.sum((pc - mc) ** 2)) if fit_scale else 1.0
    tB0 = mt - s0 * RB0 @ mc
    M = np.einsum("kji,jl,kln->in", Tc[:, :3, :3], RB0.T, Tt[:, :3, :3])  # sum Rc^T RB^T Rt
    u, _, vt = np.linalg.svd(M)
    RE0 = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    E = np.concatenate([np.zeros((1, 3)), arm * np.eye(3)])  # marker points (4, 3)

    def pred(x):
        RB, RE = pin.exp3(x[:3]) @ RB0, RE0 @ pin.exp3(x[6:9])
        s = s0 * np.exp(x[12]) if fit_scale else 1.0
        tE = x[9:12]
        local = s * (pc[:, None, :] + np.einsum("kij,j->ki", Tc[:, :3, :3], tE)[:, None, :]) + np.einsum(
            "kij,jl,ml->kmi", Tc[:, :3, :3], RE, E
        )
        return np.einsum("ij,kmj->kmi", RB, local) + (tB0 + x[3:6]), RB, RE, s

    target = pt[:, None, :] + np.einsum("kij,mj->kmi", Tt[:, :3, :3], E)

    def res(x):
        return (pred(x)[0] - target).ravel()

    x = least_squares(res, np.zeros(13 if fit_scale else 12), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    P, RB, RE, s = pred(x)
    return P, RB, RE, s, x[9:12]


def calibrated_model_path(case: Case, calibrated) -> Path:
    """`calibrated` is a URDF path or a dict of parameter values (written with closedloop's exporter)."""
    if isinstance(calibrated, (str, Path)):
        return Path(calibrated)
    from closedloop import RobotModel
    from closedloop.output.urdf import write_urdf

    out = case.nominal_urdf.parent / "judged.urdf"
    write_urdf(RobotModel.from_file(case.nominal_urdf), dict(calibrated), out)
    return out


def judge(case: Case, calibrated, n: int = 200, seed: int = 12345) -> Judgement:
    """Compare what the calibrated robot does with the truth, without gauges (see module doc).

    Fresh readings r uniform over the joint ranges; the calibrated URDF (offsets folded in) gets r,
    the true model r + offset.  Positions of the tool origin and orientation errors after the best
    rigid base and tool transforms (and length scale when the loop cannot see it); relative motions
    T_k^-1 T_k+1 of consecutive test configurations.
    """
    path = calibrated_model_path(case, calibrated)
    model = pin.buildModelFromUrdf(str(path))
    rng = np.random.default_rng(seed)
    R = rng.uniform(case.lower + 0.05, case.upper - 0.05, (n, len(case.joints)))
    off = np.array([case.true_offsets[j] for j in case.joints])
    Tt = Kin(case.true_model, case.joints).poses(R + off)
    Tc = Kin(model, case.joints).poses(R)
    if not np.all(np.isfinite(Tc)):
        inf = float("inf")
        return Judgement(inf, inf, inf, inf, inf, inf, inf, inf, float("nan"), n)
    P, RB, RE, s, tE = _fit_rigid(Tc, Tt, not case.scale_visible)
    dp = np.linalg.norm(P[:, 0] - Tt[:, :3, 3], axis=1)
    Rp = np.einsum("ij,kjl,lm->kim", RB, Tc[:, :3, :3], RE)
    ang = np.array([np.linalg.norm(pin.log3(a.T @ b)) for a, b in zip(Rp, Tt[:, :3, :3])])
    # relative motions: E^-1 S(Tc_k)^-1 S(Tc_k+1) E against Tt_k^-1 Tt_k+1
    Sc = Tc.copy()
    Sc[:, :3, 3] *= s
    Eh = np.eye(4)
    Eh[:3, :3], Eh[:3, 3] = RE, s * tE
    Pk = Sc @ Eh
    rel_p = np.linalg.inv(Pk[:-1]) @ Pk[1:]
    rel_t = np.linalg.inv(Tt[:-1]) @ Tt[1:]
    drel = np.linalg.norm(rel_p[:, :3, 3] - rel_t[:, :3, 3], axis=1)
    arel = np.array([np.linalg.norm(pin.log3(a[:3, :3].T @ b[:3, :3])) for a, b in zip(rel_p, rel_t)])
    rms = lambda v: float(np.sqrt(np.mean(v**2)))  # noqa: E731
    return Judgement(
        rms(dp),
        float(dp.max()),
        rms(ang),
        float(ang.max()),
        rms(drel),
        float(drel.max()),
        rms(arel),
        float(arel.max()),
        float(1.0 / s),
        n,
    )


def folded_truth_urdf(case: Case) -> Path:
    """The true robot as a calibrated URDF would be: offsets folded into the origins (judge self-test)."""
    root = ET.fromstring((case.nominal_urdf.parent / "truth.urdf").read_text())
    for j in root.findall("joint"):
        if j.get("name") not in case.true_offsets:
            continue
        o = j.find("origin")
        axis = _vec(j.find("axis").get("xyz") if j.find("axis") is not None else "1 0 0")
        turn = pin.exp3(axis / np.linalg.norm(axis) * case.true_offsets[j.get("name")])
        R = pin.rpy.rpyToMatrix(*_vec(o.get("rpy"))) @ turn
        o.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(R)))
    out = case.nominal_urdf.parent / "truth_folded.urdf"
    out.write_text(ET.tostring(root, encoding="unicode"))
    return out


# ----------------------------------------------------------------------------- running closedloop
@dataclass
class Outcome:
    """A calibration of a case and its judgement."""

    case: Case
    judgement: Judgement | None
    status: str  # verdict status ('ok' | 'suspect' | 'failed'), or 'ok?' when the calibrator gives none
    converged: bool
    right: bool
    seconds: float
    error: str = ""
    result: object = None
    cpu_seconds: float = float("nan")  # the calibration's own CPU time (reading, calibrating, writing; not judging)

    @property
    def refused(self) -> bool:
        return self.status in ("suspect", "failed")

    @property
    def confidently_wrong(self) -> bool:
        return not self.right and not self.refused and self.status != "crash"

    def line(self, tag: str | None = None) -> str:
        """One line: the case, its class (`tag`, or one read off the outcome), the verdict, the time, the errors."""
        j = self.judgement.summary() if self.judgement else self.error
        tag = tag or (
            "right"
            if self.right and not self.refused
            else "RIGHT BUT FLAGGED"
            if self.right
            else "REFUSED"
            if self.refused
            else "CRASH"
            if self.status == "crash"
            else "CONFIDENTLY WRONG"
        )
        return (
            f"{self.case.label:34s} {tag:18s} verdict={self.status:7s} conv={self.converged!s:5s} "
            f"{self.seconds:5.2f}s  {j}"
        )


def verdict_status(res) -> str:
    v = getattr(res, "verdict", None)
    if v is None:
        return "ok?"
    return str(getattr(v, "status", v))


def run_case(case: Case, options=None) -> Outcome:
    """`closedloop calibrate` through its Python API, then the calibrated URDF judged against the truth."""
    from closedloop import CalibrationOptions, ClosedLoopError, RobotModel, calibrate, read_log
    from closedloop.loops.spec import parse_loop
    from closedloop.output.urdf import write_model

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        robot = RobotModel.from_file(case.nominal_urdf)
        log = read_log(case.log_csv, robot.joint_names)
        loops = [parse_loop(s, robot) for s in case.loop_specs]
        res = calibrate(robot, log, loops, options or CalibrationOptions())
        out = case.nominal_urdf.parent / "calibrated.urdf"
        write_model(robot, res.as_dict(), out)
    except ClosedLoopError as exc:  # a user-facing refusal (InputError, NotIdentifiableError, ...)
        return Outcome(
            case,
            None,
            "failed",
            False,
            False,
            time.perf_counter() - t0,
            f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}",
        )
    except Exception as exc:  # a crash is neither right nor a refusal
        return Outcome(
            case,
            None,
            "crash",
            False,
            False,
            time.perf_counter() - t0,
            f"CRASH {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}",
        )
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    j = judge(case, out)
    status = verdict_status(res)
    return Outcome(case, j, status, bool(res.converged), j.right(case.tolerances()), dt, result=res, cpu_seconds=cpu)


# ----------------------------------------------------------------------------- what noise alone leaves
def _model_with(model: pin.Model, jids: list[int], fid: int, d: np.ndarray) -> pin.Model:
    """Copy of `model` with joint placements M exp6(d_j) and tool frame placement F exp6(d_tool)."""
    m = pin.Model(model)
    for k, jid in enumerate(jids):
        m.jointPlacements[jid] = m.jointPlacements[jid] * pin.exp6(d[6 * k : 6 * k + 6])
    f = m.frames[fid]
    f.placement = f.placement * pin.exp6(d[6 * len(jids) : 6 * len(jids) + 6])
    m.frames[fid] = f
    return m


def _loop_residuals(case: Case, kin: Kin, TH: np.ndarray, lp: np.ndarray) -> np.ndarray:
    """(N, m) loop residuals of the true geometry moved by the loop parameters `lp` (see predicted_std)."""
    geo = case.meta["geo"]
    T = [kin.pose(t) for t in TH]
    if case.loop == "weld":
        tgt = geo["T0"] * pin.exp6(lp[:6])
        return np.array([pin.log6(tgt.actInv(t)).vector for t in T])
    if case.loop == "point":
        return np.array([t.translation for t in T]) - (geo["T0"].translation + lp[:3])
    if case.loop == "plane":
        n = pin.exp3(lp[:3]) @ geo["normal"]
        return (np.array([t.translation for t in T]) - geo["T0"].translation) @ n[:, None] - lp[3]
    if case.loop == "hinge":
        c, u = geo["axis_c"] + lp[:3], pin.exp3(lp[3:6]) @ geo["axis_u"]
        T0 = geo["T0"] * pin.exp6(lp[6:12])
        phi = geo["phi"] + lp[12:]
        return np.array([pin.log6(_hinge_pose(c, u, f, T0).actInv(t)).vector for f, t in zip(phi, T)])
    X = geo["X"] * pin.exp6(lp[:6])  # measured_point: X^-1 p - y
    return np.array([X.actInv(t.translation) for t in T]) - geo["meas"]


def _n_loop(case: Case) -> int:
    return {"weld": 6, "point": 3, "plane": 4, "measured_point": 6}.get(case.loop, 12 + len(case.q_true))


def predicted_std(case: Case, n: int = 60, seed: int = 12345, h: float = 1e-6) -> dict[str, float]:
    """Largest predicted tool position / orientation error std over random configurations (see module doc).

    Fisher information A^T A of the whitened residual Jacobian A with respect to every joint placement
    twist, the tool frame twist and the loop's unknowns (central differences at the truth); its
    pseudo-inverse (directions below 1e-9 of the largest singular value are gauges: no variance)
    propagated to the tool pose: std_k^2 = trace(G_k C G_k^T).
    """
    if "std" in case.meta:
        return case.meta["std"]
    model = case.true_model
    jids = [model.getJointId(j) for j in case.joints]
    fid = model.getFrameId(TOOL)
    P = 6 * len(jids) + 6
    L = _n_loop(case)
    TH = case.q_true
    kin = Kin(model, case.joints)
    r0 = _loop_residuals(case, kin, TH, np.zeros(L))
    N, m = r0.shape
    Jp = np.zeros((N, m, P + L))
    for k in range(P + L):
        e = np.zeros(P + L)
        e[k] = h
        rr = []
        for sgn in (1, -1):
            km = Kin(_model_with(model, jids, fid, sgn * e[:P]), case.joints) if k < P else kin
            rr.append(_loop_residuals(case, km, TH, sgn * e[P:]))
        Jp[:, :, k] = (rr[0] - rr[1]) / (2 * h)
    Jt = np.zeros((N, m, len(case.joints)))
    for j in range(len(case.joints)):
        d = np.zeros_like(TH)
        d[:, j] = h
        z = np.zeros(L)
        Jt[:, :, j] = (_loop_residuals(case, kin, TH + d, z) - _loop_residuals(case, kin, TH - d, z)) / (2 * h)
    S = case.sigma**2 * np.einsum("nij,nkj->nik", Jt, Jt)
    if case.loop == "measured_point":
        S = S + case.sigma_t**2 * np.eye(3)
    w, V = np.linalg.eigh(S)
    inv_sqrt = np.where(w > 1e-12 * w.max(axis=1, keepdims=True), 1.0 / np.sqrt(np.maximum(w, 1e-300)), 0.0)
    A = np.einsum("nij,nj,nkj,nkp->nip", V, inv_sqrt, V, Jp).reshape(N * m, P + L)
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    keep = s > 1e-9 * s[0]
    C = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
    R = np.random.default_rng(seed).uniform(case.lower + 0.05, case.upper - 0.05, (n, len(case.joints)))
    off = np.array([case.true_offsets[j] for j in case.joints])
    T0 = [pin.SE3(t) for t in kin.poses(R + off)]
    G = np.zeros((n, 6, P + L))
    for k in range(P):
        e = np.zeros(P)
        e[k] = h
        Tp = Kin(_model_with(model, jids, fid, e), case.joints).poses(R + off)
        G[:, :, k] = np.array([pin.log6(a.actInv(pin.SE3(b))).vector for a, b in zip(T0, Tp)]) / h
    Rw = np.array([t.rotation for t in T0])
    Gp = np.einsum("nij,njp->nip", Rw, G[:, :3])  # tool position error in the world
    pos = np.sqrt(np.einsum("nip,pq,niq->n", Gp, C, Gp))
    rot = np.sqrt(np.einsum("nip,pq,niq->n", G[:, 3:], C, G[:, 3:]))
    case.meta["std"] = {"pos": float(pos.max()), "rot": float(rot.max())}
    return case.meta["std"]
