"""A simulated fleet for `closedloop batch`: many Pandas welded to a fixture, each with its own joint
offsets and noise, logged on one or more dates, and the batch manifest that calibrates them.

Every robot shares one geometry (one production batch: the truth of `weld_scenario`, drawn once, and
its configurations spread over the whole self-motion); each robot has its own encoder offsets, drawn
N(0, `offset_sd`) per joint, and its own noise draws.  A reading follows the sensor model of eq. 4.4
inverted, ``reading = (theta' - offset) / scale``: a robot whose offset of joint k is larger by d reads
d / scale less in the same pose.  `drift` adds, from a given date on, a change of one joint's offset to
chosen robots (a collision, a slipped encoder).  Drawing the geometry's configurations is the slow part
(tens of seconds for 200); the per-robot logs are cheap.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from closedloop.io.logs import JointLog

LOOP = "weld:frame=panda_hand,name=fixture"
HELD = ["panda_joint4.x"]  # the length that sets the scale (thesis 3.3), held on every date


@dataclass(frozen=True)
class FleetDrift:
    """A change of one joint's offset (rad) on one robot, from date index `since` on."""

    robot: str
    joint: str
    change: float
    since: int = 1


@dataclass(frozen=True)
class FleetSpec:
    """What `write_fleet` simulates: `robots` robots on `dates` dates, `noise` rad of joint noise."""

    robots: int
    dates: list[str] = field(default_factory=lambda: ["2026-03-02"])
    noise: float = 1e-4
    offset_sd: float = 1e-3
    drift: list[FleetDrift] = field(default_factory=list)
    cv: int = 0  # k-fold validation (`--cv`); 0: none
    regions: int = 0  # held-out validation by region (`--regions`); 0: none, one calibration per job
    seed: int = 0


def robot_name(i: int) -> str:
    return f"arm{i:05d}"


def configurations(n: int, seed: int = 3) -> tuple[str, list[str], np.ndarray, dict[str, float]]:
    """The fleet's geometry: the model file, its joints, `n` exact readings spread over the whole
    self-motion of the welded Panda (`weld_scenario`, pool 'manifold'), and the true parameters."""
    from closedloop.studies.montecarlo import panda_urdf, weld_scenario

    sc = weld_scenario(n=1, seed=seed, pool="manifold", n_pool=n)
    return panda_urdf(), list(sc.joints), np.asarray(sc.pool, float), dict(sc.truth)


def write_fleet(
    folder: str | Path,
    spec: FleetSpec,
    geometry: tuple[str, list[str], np.ndarray, dict[str, float]],
    bad: tuple[str, ...] = (),
) -> Path:
    """Write one CSV log per robot and date, and the manifest ``fleet.yaml``; return its path.

    `geometry`: `configurations`' result (drawn once, reused for any number of fleets).  Robots named in
    `bad` get a log with a value that is not a number in row 1 (their job fails with one line; the
    others run).  Job names are ``ROBOT-DATE``, outputs ``calibrated/ROBOT-DATE``."""
    import yaml

    folder = Path(folder)
    (folder / "logs").mkdir(parents=True, exist_ok=True)
    model, joints, pool, truth = geometry
    scale = np.array([truth[f"{j}.scale"] for j in joints])
    rng = np.random.default_rng(spec.seed)
    jobs = []
    for i in range(spec.robots):
        robot = robot_name(i)
        offsets = rng.normal(0.0, spec.offset_sd, len(joints))
        for d, date in enumerate(spec.dates):
            delta = offsets.copy()
            for dr in spec.drift:
                if dr.robot == robot and d >= dr.since:
                    delta[joints.index(dr.joint)] += dr.change
            th = pool - delta / scale + rng.normal(0.0, spec.noise, pool.shape)
            name = f"{robot}-{date}"
            path = folder / "logs" / f"{name}.csv"
            JointLog(list(joints), th).write_csv(path)
            if robot in bad:
                lines = path.read_text().splitlines()
                cells = lines[1].split(",")
                cells[-1] = "n/a"
                lines[1] = ",".join(cells)
                path.write_text("\n".join(lines) + "\n")
            jobs.append(
                {"name": name, "robot": robot, "date": date, "log": f"logs/{name}.csv", "out": f"calibrated/{name}"}
            )
    manifest = folder / "fleet.yaml"
    doc = {
        "defaults": {
            "model": model,
            "loops": [LOOP],
            "options": {"noise": spec.noise, "regions": spec.regions, "fix": HELD},
            "cv": spec.cv,
        },
        "jobs": jobs,
    }
    manifest.write_text(yaml.safe_dump(doc, sort_keys=False))
    return manifest
