"""Simulate a ball-and-socket rig: a 7-DOF arm with a ball on its flange, a two-socket block at several places.

The data a real rig gives: the ball pressed by hand into each socket of a printed block (two
sockets a known distance apart), the block then moved to other places; joint readings only, one
header-less CSV per socket and place.  The truth is independent of closedloop's parametrization: every
joint origin of the nominal URDF (fixed joints included) moved in its parent frame, joint offsets added,
and the closures solved with Pinocchio on the true model.  Noise: the ball's play in its socket (an
isotropic task-space error of the ball centre, ``sigma_task``) and joint reading noise (``sigma_q``).

    python examples/ball_socket_rig.py --out out/rig            # writes nominal.urdf, truth.json and
                                                                # place{p}_{a,b}.csv (no header)

``make_rig`` is the same in Python (the tests use it).
"""

from __future__ import annotations

import argparse
import copy
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

BALL = "ball"
BALL_XYZ = (0.03, 0.0, 0.12)  # the ball centre in the flange frame (nominal: the ball frame's origin)


def nominal_urdf(base: str = "panda_link0", tip: str = "panda_link8") -> str:
    """Mesh-free Panda chain base -> flange, plus a fixed 'ball' link at BALL_XYZ."""
    from closedloop.assets.catalog import example_robot_data_dir

    root = ET.parse(example_robot_data_dir() / "panda_description/urdf/panda.urdf").getroot()
    by_child = {j.find("child").get("link"): j for j in root.findall("joint")}
    path, link = [], tip
    while link != base:
        path.append(by_child[link])
        link = path[-1].find("parent").get("link")
    out = ET.Element("robot", name="panda_ball")
    ET.SubElement(out, "link", name=base)
    for j in reversed(path):
        j = copy.deepcopy(j)
        for tag in ("dynamics", "safety_controller", "calibration", "mimic"):
            for el in list(j.findall(tag)):
                j.remove(el)
        if j.find("origin") is None:
            ET.SubElement(j, "origin", xyz="0 0 0", rpy="0 0 0")
        ET.SubElement(out, "link", name=j.find("child").get("link"))
        out.append(j)
    ET.SubElement(out, "link", name=BALL)
    bj = ET.SubElement(out, "joint", name="ball_joint", type="fixed")
    ET.SubElement(bj, "parent", link=tip)
    ET.SubElement(bj, "child", link=BALL)
    ET.SubElement(bj, "origin", xyz=" ".join(map(repr, BALL_XYZ)), rpy="0 0 0")
    ET.indent(out)
    return ET.tostring(out, encoding="unicode")


def perturb(urdf: str, rng: np.random.Generator, err_m: float, err_rad: float) -> str:
    """Every joint origin moved in its parent frame: xyz + U(-err_m, err_m), R <- Rot(U(-err_rad, err_rad)) R."""
    root = ET.fromstring(urdf)
    for j in root.findall("joint"):
        o = j.find("origin")
        xyz = np.array([float(t) for t in o.get("xyz").split()]) + rng.uniform(-err_m, err_m, 3)
        R = pin.rpy.rpyToMatrix(*rng.uniform(-err_rad, err_rad, 3)) @ pin.rpy.rpyToMatrix(
            *[float(t) for t in o.get("rpy", "0 0 0").split()]
        )
        o.set("xyz", " ".join(repr(float(v)) for v in xyz))
        o.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(R)))
    return ET.tostring(root, encoding="unicode")


def fold_offsets(urdf: str, offsets: dict[str, float]) -> str:
    """The URDF whose joint angles are the readings: origin <- origin Rot(axis, offset) (revolute joints)."""
    root = ET.fromstring(urdf)
    for j in root.findall("joint"):
        if j.get("name") not in offsets:
            continue
        o = j.find("origin")
        axis = np.array(
            [float(t) for t in (j.find("axis").get("xyz") if j.find("axis") is not None else "1 0 0").split()]
        )
        R = pin.rpy.rpyToMatrix(*[float(t) for t in o.get("rpy", "0 0 0").split()]) @ pin.exp3(
            axis / np.linalg.norm(axis) * offsets[j.get("name")]
        )
        o.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(R)))
    return ET.tostring(root, encoding="unicode")


@dataclass
class Rig:
    """Files and truth of a simulated rig."""

    nominal: str  # URDF text
    true_urdf: str  # the true robot, offsets folded: its joint angles are the (noise-free) readings
    joints: list[str]
    offsets: np.ndarray  # reading = q_true - offset
    places: list[dict]  # per place: socket positions {'a': xyz, 'b': xyz}
    readings: dict[str, np.ndarray]  # 'place1_a' -> (n, 7) readings
    q_true: dict[str, np.ndarray]
    ball_true: np.ndarray  # ball centre in the flange frame (panda_link8)
    sigma_task: float
    sigma_q: float
    distance: float
    meta: dict = field(default_factory=dict)

    def loop_names(self) -> list[str]:
        return list(self.readings)

    def write(self, out: str | Path) -> list[Path]:
        """nominal.urdf, true.urdf, truth.json and one header-less CSV per socket and place."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "nominal.urdf").write_text(self.nominal)
        (out / "true.urdf").write_text(self.true_urdf)
        files = []
        for name, th in self.readings.items():
            f = out / f"{name}.csv"
            f.write_text("\n".join(",".join(repr(float(v)) for v in row) for row in th) + "\n")
            files.append(f)
        truth = {
            "joints": self.joints,
            "offsets": self.offsets.tolist(),
            "ball_in_flange": self.ball_true.tolist(),
            "places": [{k: np.asarray(v).tolist() for k, v in p.items()} for p in self.places],
            "sigma_task": self.sigma_task,
            "sigma_q": self.sigma_q,
            "distance": self.distance,
        }
        (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
        return files


def _dls(fun, th, lo, hi, iters=60, tol=1e-12):
    for _ in range(iters):
        r, J = fun(th)
        nr = float(np.linalg.norm(r))
        if nr < tol:
            return th if np.all(th > lo) and np.all(th < hi) else None
        dq = -J.T @ np.linalg.solve(J @ J.T + (1e-3 * nr * nr + 1e-14) * np.eye(J.shape[0]), r)
        big = np.max(np.abs(dq))
        th = th + (dq * 0.3 / big if big > 0.3 else dq)
    return None


def make_rig(
    seed: int = 0,
    n: int = 30,
    places: int = 3,
    sigma_task: float = 2e-4,
    sigma_q: float = 2e-5,
    distance: float = 0.05,
    err_m: float = 1e-3,
    err_rad: float = 1e-3,
    offset_rad: float = 5e-3,
    spread: float = 0.35,
    place_configs: list[np.ndarray] | None = None,
    encoder_error: tuple[int, float] | None = None,
    block: list | None = None,
) -> Rig:
    """A simulated rig (module docstring); `encoder_error` = (joint index, amplitude): an unmodelled
    reading error amplitude * sin(2 reading) of that joint (a cyclic encoder error); `block`: the
    sockets' positions in the block's frame (sockets a, b, c, ...; default [0,0,0] and [distance,0,0]),
    the block turned about the vertical by a random angle at each place."""
    block = np.array([[0.0, 0.0, 0.0], [distance, 0.0, 0.0]] if block is None else block, dtype=float)
    rng = np.random.default_rng(seed)
    nominal = nominal_urdf()
    true_urdf = perturb(nominal, rng, err_m, err_rad)
    model = pin.buildModelFromXML(true_urdf)
    data = model.createData()
    joints = [model.names[i] for i in range(1, model.njoints)]
    lo, hi = model.lowerPositionLimit + 0.1, model.upperPositionLimit - 0.1
    offsets = rng.uniform(-offset_rad, offset_rad, len(joints))
    fid = model.getFrameId(BALL)

    def fk(q):
        pin.framesForwardKinematics(model, data, q)
        return data.oMf[fid].translation.copy()

    def jac(q):
        return pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)[:3]

    def well(q):
        return np.linalg.svd(pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL), compute_uv=False)[5] > 0.05

    readings, qs, place_list = {}, {}, []
    defaults = [
        np.array([0.0, 0.3, 0.0, -1.8, 0.0, 2.1, 0.8]),
        np.array([0.6, 0.5, 0.2, -1.5, -0.2, 2.0, 0.5]),
        np.array([-0.7, 0.6, -0.1, -1.3, 0.3, 2.2, 1.1]),
        np.array([0.3, -0.2, 0.4, -2.2, 0.1, 1.9, 0.2]),
    ]
    for p in range(places):
        th0 = (place_configs[p] if place_configs is not None else defaults[p % len(defaults)]).copy()
        P = fk(th0)
        ang = rng.uniform(0, 2 * np.pi)
        Rz = np.array([[np.cos(ang), -np.sin(ang), 0.0], [np.sin(ang), np.cos(ang), 0.0], [0.0, 0.0, 1.0]])
        sockets = {"abcdefgh"[k]: P + Rz @ v for k, v in enumerate(block)}
        place_list.append(sockets)
        for s, S in sockets.items():
            rows, q_rows, start, fails = [], [], th0, 0
            while len(rows) < n and fails < 50 * n:
                target = S + rng.normal(0.0, sigma_task, 3)  # the ball's play in the socket
                th = _dls(lambda t: (fk(t) - target, jac(t)), start + rng.normal(0, spread, 7), lo, hi)
                if th is None or not well(th):
                    fails += 1
                    continue
                rows.append(th)
                q_rows.append(th)
            if len(rows) < n:
                raise RuntimeError(f"place {p + 1} socket {s}: only {len(rows)} configurations")
            q = np.array(q_rows)
            read = q - offsets
            if encoder_error is not None:
                j, amp = encoder_error  # q_true = reading + offset + amp sin(2 reading): solve by fixed point
                for _ in range(8):
                    read[:, j] = q[:, j] - offsets[j] - amp * np.sin(2 * read[:, j])
            read = read + rng.normal(0.0, sigma_q, read.shape)
            name = f"place{p + 1}_{s}"
            readings[name], qs[name] = read, q
    M = model.frames[fid].placement
    return Rig(
        nominal,
        fold_offsets(true_urdf, dict(zip(joints, offsets))),
        joints,
        offsets,
        place_list,
        readings,
        qs,
        M.translation.copy(),
        sigma_task,
        sigma_q,
        distance,
        {"seed": seed, "encoder_error": encoder_error, "block": block.tolist()},
    )


def commands(out: Path, rig: Rig) -> str:
    """The calibrate command for the files written to `out`."""
    loops = " ".join(
        f"--loop point:frame={BALL},name={nm},tip=@ball,fixture={nm.split('_')[0]},log={out / nm}.csv"
        for nm in rig.readings
    )
    dist = " ".join(
        f"--distance place{p + 1}_a.point place{p + 1}_b.point {rig.distance}" for p in range(len(rig.places))
    )
    return (
        f"closedloop calibrate {out}/nominal.urdf {loops} --joints {','.join(rig.joints)} {dist} "
        f"--out {out}/calibrated.urdf --report {out}/report.json"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n", type=int, default=30, help="configurations per socket and place")
    ap.add_argument("--places", type=int, default=3)
    ap.add_argument("--sigma-task", type=float, default=2e-4, help="ball play in the socket (m)")
    ap.add_argument("--sigma-q", type=float, default=2e-5, help="joint reading noise (rad)")
    a = ap.parse_args()
    rig = make_rig(a.seed, a.n, a.places, a.sigma_task, a.sigma_q)
    files = rig.write(a.out)
    print(f"wrote {len(files)} logs of {a.n} configurations, nominal.urdf, true.urdf and truth.json to {a.out}")
    print(commands(Path(a.out), rig))


if __name__ == "__main__":
    main()
