"""Compare a calibration report with simulation ground truth (`closedloop check`).

Two views.  By default the robots are judged by what they do (`check_kinematics`): the
calibrated and the true robot are driven by the same joint readings, drawn within the joint
ranges, each through its own sensor model (thesis eq. 4.4); each loop's frame is followed
(its tool point in the world for a point, plane or tracker loop, its pose for a weld or a
hinge), and what the data cannot see is removed before comparing: a rigid transform of the
base, a constant tool transform for a pose loop, and the overall size where the data do
not measure it.  A correct robot in another parametrization (a slide along a joint axis
moved to the next joint, a tool point given as a frame or as a tip) passes; a robot that
moves its tool elsewhere fails.  Where the size is not measured it is compared on its own
row ('size'), so a robot of the wrong size fails there.

The second view (`check_parameters`, ``closedloop check --parameters``) is the parameter
table.  Only parameters the report marks as estimated (identifiable) are compared; the
others are listed as not compared, with their status.  Truth omits the parameters it did
not perturb: their true value is their nominal (placement errors and offsets 0, scales 1,
D-H values as in the model, i.e. the report's initial value).  A loop's rotation vector
(rx, ry, rz) is compared as one rotation: the geodesic angle between the calibrated and
the true rotation.
"""

from __future__ import annotations

import json

import numpy as np
import pinocchio as pin

from closedloop.analysis.accuracy import N_WORKSPACE, POINT_LOOPS, POSE_LOOPS, SIZE_BLIND, random_readings
from closedloop.errors import InputError
from closedloop.records import FORETOLD  # an error at most this many times the prediction is foretold

NOMINAL = {"placement": 0.0, "offset": 0.0, "scale": 1.0}


def check_report(
    truth: dict,
    report: dict,
    tol_m: float,
    tol_rad: float,
    tol_scale: float,
    tol_px: float = 1.0,
    truth_source: str = "truth file",
    report_source: str = "report file",
    model=None,
    view: str = "auto",
    truth_model=None,
) -> tuple[list[dict], bool]:
    """Rows of (name, true, calibrated, error, tol, result) and whether all compared rows pass.

    `view`: 'kinematics' (what the robots do, `check_kinematics`), 'parameters' (the
    parameter table, `check_parameters`) or 'auto': kinematics where the robot model is
    known (`model`, a `RobotModel` or a path, else the report's 'model' field) and the
    report has a loop to follow, else the parameter table.  `truth_model`: the true robot's
    model file where it is not the calibrated one's (another robot's log), else the truth's
    'model' field, else the report's model at the geometry it was calibrated from (a recalibration's
    model, a calibrated URDF, carries its corrections: `RobotModel.calibrated_from_model`).  Both documents are validated
    first (:data:`~closedloop.io.schemas.TRUTH_SCHEMA`, :data:`~closedloop.io.schemas.REPORT_SCHEMA`);
    every tolerance must be a finite number > 0.
    """
    if view not in ("auto", "kinematics", "parameters"):
        raise InputError(f"view '{view}': expected auto, kinematics or parameters")
    rows, ok = check_parameters(truth, report, tol_m, tol_rad, tol_scale, tol_px, truth_source, report_source)
    if view == "parameters":
        return rows, ok
    robot = _robot_of(report, model, report_source, required=view == "kinematics")
    if robot is None or not _followed_loops(report):
        if view == "kinematics":
            raise InputError(f"{report_source}: no loop whose frames can be followed: compare with --parameters")
        return rows, ok
    # the truth's corrections are of the model the simulator started from: a calibrated model's own (a
    # recalibration's report) carries its corrections already, and its nominal geometry is written beside them
    true_robot = robot.calibrated_from_model()
    if truth_model is not None or truth.get("model"):
        true_robot = _robot_of(truth, truth_model, truth_source, required=True)
    return check_kinematics(
        truth, report, robot, tol_m, tol_rad, tol_scale, truth_source, report_source, true_robot=true_robot
    )


def check_parameters(
    truth: dict,
    report: dict,
    tol_m: float,
    tol_rad: float,
    tol_scale: float,
    tol_px: float = 1.0,
    truth_source: str = "truth file",
    report_source: str = "report file",
) -> tuple[list[dict], bool]:
    """The parameter table (module docstring): rows of (name, true, calibrated, error, tol, result), all pass."""
    from closedloop.io.schemas import REPORT_SCHEMA, TRUTH_SCHEMA, is_number, validate

    for opt, tol in (("--tol-m", tol_m), ("--tol-rad", tol_rad), ("--tol-scale", tol_scale), ("--tol-px", tol_px)):
        if not is_number(tol) or tol <= 0:
            raise InputError(f"{opt} {tol}: a tolerance must be a finite number > 0")
    if not isinstance(truth, dict) or "parameters" not in truth:
        raise InputError(f"{truth_source}: expected a 'parameters' object of name: true value")
    if not isinstance(report, dict) or "parameters" not in report:
        raise InputError(f"{report_source}: expected a 'parameters' list (a closedloop report)")
    validate(truth, TRUTH_SCHEMA, truth_source)
    validate(report, REPORT_SCHEMA, report_source, rows="parameters")
    true = truth["parameters"]
    rep = {}
    for i, p in enumerate(report["parameters"], start=1):
        if p["name"] in rep:
            raise InputError(f"{report_source}: parameters row {i}: duplicate parameter '{p['name']}'")
        if p["kind"] == "dh" and p["name"] not in true and not is_number(p.get("initial")):
            raise InputError(f"{report_source}: parameters row {i} ('{p['name']}'): missing field 'initial'")
        rep[p["name"]] = p
    _same_robot(truth, report, truth_source, report_source)
    unknown = [n for n in true if n not in rep]
    rows = []
    tol_by_unit = {"m": tol_m, "rad": tol_rad, "1": tol_scale, "px": tol_px}
    done: set[str] = set()
    for name, p in rep.items():
        if name in done:
            continue
        if name in true:
            tv = float(true[name])
        elif p["kind"] in NOMINAL:
            tv = NOMINAL[p["kind"]]
        elif p["kind"] == "dh":
            tv = float(p["initial"])
        else:  # a loop parameter the truth does not know: said, not skipped silently
            if p["status"] == "estimated":
                rows.append(_row(name, None, float(p["calibrated"]), None, None, "not compared (no truth)"))
            continue
        if p["status"] != "estimated":
            if name in true:
                rows.append(_row(name, tv, None, None, None, f"not compared ({p['status']})"))
            continue
        if p["unit"] not in tol_by_unit:  # a unit with no tolerance (compliance, rad/(N m)): say so
            rows.append(
                _row(
                    name,
                    tv,
                    float(p["calibrated"]),
                    float(p["calibrated"]) - tv,
                    None,
                    f"not compared (no tolerance for unit {p['unit']})",
                )
            )
            continue
        tol = tol_by_unit[p["unit"]]
        if p["kind"] == "loop" and name.endswith(".rx"):
            base = name[:-3]
            trip = [f"{base}.{a}" for a in ("rx", "ry", "rz")]
            if all(t in rep and t in true for t in trip) and all(rep[t]["status"] == "estimated" for t in trip):
                rc = np.array([rep[t]["calibrated"] for t in trip])
                rt = np.array([float(true[t]) for t in trip])
                err = float(np.linalg.norm(pin.log3(pin.exp3(rc).T @ pin.exp3(rt))))
                rows.append(
                    _row(
                        f"{base}.rotation",
                        float(np.linalg.norm(rt)),
                        float(np.linalg.norm(rc)),
                        err,
                        tol,
                        "ok" if err <= tol else "FAIL",
                    )
                )
                done.update(trip)
                continue
        err = float(p["calibrated"]) - tv
        rows.append(_row(name, tv, float(p["calibrated"]), err, tol, "ok" if abs(err) <= tol else "FAIL"))
    for n in unknown:
        rows.append(_row(n, float(true[n]), None, None, None, "not in report"))
    ok = all(r["result"] != "FAIL" for r in rows) and any(r["result"] == "ok" for r in rows)
    return rows, ok


def _same_robot(truth: dict, report: dict, truth_source: str, report_source: str) -> None:
    """Refuse a truth and a report of different robots: no joint in common, or no parameter in common."""
    tj, rj = truth.get("joint_names"), report.get("joints")
    if isinstance(tj, list) and isinstance(rj, list) and tj and rj and not set(map(str, tj)) & set(map(str, rj)):
        raise InputError(
            f"{report_source}: calibrates joints {', '.join(map(str, rj[:3]))}, ... and {truth_source} "
            f"is the truth of joints {', '.join(map(str, tj[:3]))}, ...: not the same robot"
        )
    names = {p.get("name") for p in report["parameters"] if isinstance(p, dict)}
    if truth["parameters"] and not names & set(truth["parameters"]):
        raise InputError(
            f"{report_source}: none of the {len(truth['parameters'])} parameters of {truth_source} "
            "is in the report: not the same robot or loops"
        )
    _same_loop(truth, report, truth_source, report_source)


WORLD_FRAMES = (None, "", "universe", "world")  # a loop's second frame when it closes to the world


def _same_loop(truth: dict, report: dict, truth_source: str, report_source: str) -> None:
    """Refuse a simulation's truth whose loop closes to something no loop of the report closes to (the other
    robot frame of a loop between two, or the world): the truth of another dataset of the same robot, whose
    true robot is another draw.  The tool's own frame is not compared: a calibration may follow the frame
    the tool hangs from, with the tool point estimated (`simulate --tool`'s `<frame>_tip`).  A truth without
    a loop record (written by hand) is not judged."""
    loop, loops = truth.get("loop"), report.get("loops")
    if not isinstance(loop, dict) or not loop.get("frame") or not isinstance(loops, list) or not loops:
        return
    world = lambda f: None if f in WORLD_FRAMES else str(f)  # noqa: E731
    to = world(loop.get("to"))
    pairs = [(world(lp.get("frame_a")), world(lp.get("frame_b"))) for lp in loops if isinstance(lp, dict)]
    if not any(to in pair for pair in pairs):
        between = lambda fs: " and ".join(sorted(f for f in fs if f) + ["the world"] * (None in fs))  # noqa: E731
        raise InputError(
            f"{report_source}: its loops close {'; '.join(between(p) for p in pairs)}, and {truth_source} is "
            f"the truth of a loop between {between((str(loop['frame']), to))}: the truth of another dataset "
            "(check the report against the truth.json of the dataset it calibrated)"
        )


def _row(name, true, cal, err, tol, result):
    return {"name": name, "true": true, "calibrated": cal, "error": err, "tol": tol, "result": result}


# --------------------------------------------------------------------------- what the robots do
CAMERA_LOOPS = ("CameraLoop", "camera")  # followed by their marker: a tool point on the robot, in the world
N_CHECK = N_WORKSPACE  # configurations the robots are compared at: those the accuracy is predicted at


def _robot_of(report: dict, model, report_source: str, required: bool):
    """The robot model the report calibrated: `model` (a RobotModel or a path), else the report's 'model' file."""
    from pathlib import Path

    from closedloop.errors import ClosedLoopError
    from closedloop.model.robot import RobotModel

    if isinstance(model, RobotModel):
        return model
    path = model if model is not None else report.get("model")
    if not path:
        if required:
            raise InputError(f"{report_source}: names no robot model: give it with --model FILE")
        return None
    if not Path(path).is_file():
        if required or model is not None:
            raise InputError(f"{path}: robot model of {report_source} not found: give it with --model FILE")
        return None
    try:
        return RobotModel.from_file(path)
    except ClosedLoopError as exc:
        raise InputError(f"{path}: {str(exc).splitlines()[0]}") from None


def _followed_loops(report: dict) -> list[dict]:
    """The report's loops whose robot frames `check_kinematics` follows (points and poses)."""
    followed = POINT_LOOPS + POSE_LOOPS + CAMERA_LOOPS
    return [lp for lp in report.get("loops", []) if isinstance(lp, dict) and lp.get("type") in followed]


def _size_measured(report: dict) -> bool:
    """Whether the data measured the robot's size: the verdict's field, else the loop types."""
    v = report.get("verdict")
    if not isinstance(v, dict):
        v = {}
    if isinstance(v.get("size_measured"), bool):
        return v["size_measured"]
    loops = [lp for lp in report.get("loops", []) if isinstance(lp, dict)]
    return not all(lp.get("type") in SIZE_BLIND for lp in loops)


def _values(robot, report_params: dict[str, float]):
    """(RobotParameters over every movable joint, the parameter vector with `report_params` set)."""
    from closedloop.model.parameters import RobotParameters

    rp = RobotParameters(robot, robot.joint_names)
    x = rp.nominal.copy()
    for name, v in report_params.items():
        if name in rp.index:
            x[rp.index[name]] = float(v)
    return rp, x


def _truth_loop(truth: dict, name: str, n_loops: int) -> dict:
    """The truth's description of loop `name` (simulate's 'loop' or 'loops'), {} if it has none."""
    given = truth.get("loops")
    found = [lp for lp in (given if isinstance(given, list) else [truth.get("loop")]) if isinstance(lp, dict)]
    for lp in found:
        if lp.get("name") == name:
            return lp
    return found[0] if len(found) == 1 and n_loops == 1 else {}


def _frame_name(value: object, what: str) -> str:
    """A frame field of a report's or truth's loop: a frame name (an InputError naming `what` otherwise)."""
    if not isinstance(value, str) or not value:
        raise InputError(f"{what}: expected a frame name, got {json.dumps(value, default=str)}")
    return value


def _tip(params: dict, loop_name: str, fixed) -> np.ndarray:
    """The tool point in its frame: the loop's tip parameters, else its fixed tip, else the frame's origin."""
    names = [f"{loop_name}.tip_{a}" for a in "xyz"]
    if all(n in params for n in names):
        return np.array([float(params[n]) for n in names])
    if isinstance(fixed, (list, tuple)) and len(fixed) == 3:
        return np.asarray(fixed, dtype=float)
    return np.zeros(3)


def _poses(robot, rp, x, readings: np.ndarray, joints: list[str], frames: list[str]) -> np.ndarray:
    """World poses (n, F, 4, 4) of `frames` at joint `readings` through the sensor model of x."""
    state = rp.apply(x)
    col = [rp.joints.index(j) for j in joints]
    q = robot.configurations(readings * state.scale[col] + state.offset[col], joints)
    fids = [robot.frame_id(f) for f in frames]
    out = np.empty((q.shape[0], len(frames), 4, 4))
    for i, qi in enumerate(q):
        pin.framesForwardKinematics(state.model, state.data, qi)
        for k, f in enumerate(fids):
            out[i, k] = state.data.oMf[f].homogeneous
    return out


def check_kinematics(
    truth: dict,
    report: dict,
    robot,
    tol_m: float,
    tol_rad: float,
    tol_scale: float,
    truth_source: str = "truth file",
    report_source: str = "report file",
    n: int = N_CHECK,
    seed: int = 0,
    true_robot=None,
) -> tuple[list[dict], bool]:
    """The calibrated and the true robot compared by what they do (module docstring).

    Rows: per loop, the largest position error of its tool point or frame (m) and, for a
    pose loop, the largest rotation error (rad) over `n` readings drawn within the joint
    ranges, after the best rigid base transform (one for the loops closed to the world, one
    per loop between two robot frames, whose pose in its second frame is what is compared),
    a constant tool transform per pose loop, and the overall size where the report says the data do not
    measure it; then that size against the truth's ('size', relative).  `true_robot`: the
    true robot's model where it is not `robot` (joints matched by name).
    """
    from scipy.optimize import least_squares

    from closedloop.errors import ClosedLoopError

    cal = {p["name"]: p["calibrated"] for p in report["parameters"] if isinstance(p, dict)}
    loops = _followed_loops(report)
    joints = [j for j in report.get("joints", []) if j in robot.joints] or robot.joint_names
    readings = random_readings(robot, joints, n, seed)  # the readings the report's prediction is made at
    rp_c, x_c = _values(robot, cal)
    true_robot = true_robot or robot
    missing = [j for j in joints if j not in true_robot.joints]
    if missing:
        raise InputError(f"{truth_source}: the true robot has no joint {missing[0]}: not the same robot's joints")
    rp_t, x_t = _values(true_robot, truth["parameters"])
    # (label, kind, cal frame, cal tip, true frame, true tip, cal frame_b, true frame_b)
    items: list[tuple[str, str, str, np.ndarray, str, np.ndarray, str | None, str | None]] = []
    for lp in loops:
        name = str(lp.get("name"))
        tl = _truth_loop(truth, name, len(loops))
        where, twhere = f"{report_source}: loop '{name}'", f"{truth_source}: loop '{name}'"
        frame = _frame_name(lp.get("frame_a"), f"{where}: frame_a")
        camera = lp.get("type") in CAMERA_LOOPS  # its marker, wherever the cameras are: a tool point in the world
        b = None if camera else lp.get("frame_b")
        frame_b = None if b in (None, "universe", "world") else _frame_name(b, f"{where}: frame_b")
        tframe = _frame_name(tl.get("frame", frame), f"{twhere}: frame")
        tb = None if camera else tl.get("to", frame_b)
        tframe_b = None if tb is None else _frame_name(tb, f"{twhere}: to")
        try:
            for f in (frame, frame_b):
                if f is not None:
                    robot.frame_id(f)
        except ClosedLoopError as exc:
            raise InputError(f"{report_source} / {truth_source}: loop '{name}': {exc}") from None
        try:
            for f in (tframe, tframe_b):
                if f is not None:
                    true_robot.frame_id(f)
        except ClosedLoopError as exc:  # a frame of the simulator's model (a stylus `simulate --tool` added)
            raise InputError(
                f"{truth_source}: loop '{name}': the truth's {exc} in the true robot's model; where the "
                "simulation added it, give the simulator's model: --truth-model <dataset>/nominal.urdf"
            ) from None
        point = lp.get("type") in POINT_LOOPS or camera
        tip_c = _tip(cal, name, lp.get("tip")) if point else np.zeros(3)
        tip_t = _tip(truth["parameters"], str(tl.get("name", name)), lp.get("tip")) if point else np.zeros(3)
        items.append((name, "point" if point else "pose", frame, tip_c, tframe, tip_t, frame_b, tframe_b))

    def relative(rob, rp, x, fa: str, fb: str | None) -> np.ndarray:
        """Poses of fa in the world, or in fb where the loop joins two robot frames (what it sees)."""
        T = _poses(rob, rp, x, readings, joints, [fa] + ([fb] if fb else []))
        if not np.all(np.isfinite(T)):
            raise InputError(f"{report_source}: the robots' kinematics are not finite")
        return T[:, 0] if not fb else np.linalg.inv(T[:, 1]) @ T[:, 0]

    Tc = [relative(robot, rp_c, x_c, it[2], it[6]) for it in items]
    Tt = [relative(true_robot, rp_t, x_t, it[4], it[7]) for it in items]
    scaled = not _size_measured(report)
    # unknowns: log size, one base transform for the loops closed to the world and one per loop between two
    # robot frames (in its frame_b), one tool transform per pose loop
    group = [0 if it[6] is None else 1 + k for k, it in enumerate(items)]
    bases = sorted(set(group))
    tools = [k for k, it in enumerate(items) if it[1] == "pose"]

    def predict(z: np.ndarray) -> list[tuple[np.ndarray, np.ndarray | None]]:
        s = float(np.exp(z[0])) if scaled else 1.0
        out: list[tuple[np.ndarray, np.ndarray | None]] = []
        for k, (_, kind, _, tc, _, _, _, _) in enumerate(items):
            b = 1 + 6 * bases.index(group[k])
            B = pin.exp6(z[b : b + 6])
            T = Tc[k]
            if kind == "point":
                p = s * (T[:, :3, :3] @ tc + T[:, :3, 3])
                out.append((p @ B.rotation.T + B.translation, None))
            else:
                t = 1 + 6 * len(bases) + 6 * tools.index(k)
                Y = pin.exp6(z[t : t + 6])
                p = s * (T[:, :3, :3] @ Y.translation + T[:, :3, 3])
                out.append((p @ B.rotation.T + B.translation, B.rotation @ T[:, :3, :3] @ Y.rotation))
        return out

    targets: list[tuple[np.ndarray, np.ndarray | None]] = []  # (positions, rotations of a pose loop)
    for k, (_, kind, _, _, _, tt, _, _) in enumerate(items):
        T = Tt[k]
        targets.append((T[:, :3, :3] @ tt + T[:, :3, 3], T[:, :3, :3] if kind == "pose" else None))

    def residual(z: np.ndarray) -> np.ndarray:
        r = []
        for (p, R), (pt, Rt) in zip(predict(z), targets):
            r.append(((p - pt) / tol_m).ravel())
            if R is not None and Rt is not None:  # a pose loop
                r.append(np.array([pin.log3(a.T @ b) for a, b in zip(R, Rt)]).ravel() / tol_rad)
        return np.concatenate(r)

    fit = least_squares(residual, np.zeros(1 + 6 * (len(bases) + len(tools))), method="lm", xtol=1e-15, ftol=1e-15)
    rows = []
    for (name, kind, fc, _, _, _, fb, _), (p, R), (pt, Rt) in zip(items, predict(fit.x), targets):
        what = "tool point" if kind == "point" else "frame"
        rel = f" relative to {fb}" if fb else ""  # a loop between two robot frames: what it sees
        err = float(np.linalg.norm(p - pt, axis=1).max())
        rows.append(
            _row(f"{name}: {what} {fc}{rel} position", None, None, err, tol_m, "ok" if err <= tol_m else "FAIL")
        )
        if R is not None and Rt is not None:  # a pose loop
            ang = float(max(np.linalg.norm(pin.log3(a.T @ b)) for a, b in zip(R, Rt)))
            rows.append(
                _row(f"{name}: frame {fc}{rel} rotation", None, None, ang, tol_rad, "ok" if ang <= tol_rad else "FAIL")
            )
    if scaled:  # the size the data do not measure: the calibrated robot is 1/s the truth's
        size = 1.0 / float(np.exp(fit.x[0]))
        rows.append(
            _row(
                "size (not measured by the data)",
                1.0,
                size,
                size - 1.0,
                tol_scale,
                "ok" if abs(size - 1.0) <= tol_scale else "FAIL",
            )
        )
    for r in rows:
        r["view"] = "kinematics"
    if n == N_CHECK and seed == 0:  # the readings the report's prediction was made at
        with_prediction(rows, report, [(it[0], it[2]) for it in items])
    return rows, all(r["result"] != "FAIL" for r in rows)


def with_prediction(rows: list[dict], report: dict, frames: list[tuple[str, str]]) -> None:
    """Beside each observed error, the report's predicted one (`closedloop.analysis.accuracy`: the expected
    largest error over the same readings, 'predicted'; 95 % of calibrated robots stay below 'bound') and
    their ratio ('ratio' = observed / predicted); on the size row, the predicted relative size error
    (``accuracy.workspace.size``: expected |error| and 95 % bound).  Nothing where the report has no
    prediction at these readings (an older report, or one predicted at a ``--workspace`` of its own)."""
    from closedloop.io.schemas import is_number

    acc = report.get("accuracy")
    ws = acc.get("workspace") if isinstance(acc, dict) else None
    if not isinstance(ws, dict) or not ws.get("check_readings") or not isinstance(ws.get("frames"), list):
        return
    pred = {f.get("loop"): f for f in ws["frames"] if isinstance(f, dict)}
    size = ws.get("size")
    if isinstance(size, dict) and is_number(size.get("predicted")) and size["predicted"] > 0:
        for r in rows:
            if r["name"].startswith("size ") and r["error"] is not None:
                r["predicted"] = float(size["predicted"])
                r["bound"] = float(size["predicted95"]) if is_number(size.get("predicted95")) else None
                r["ratio"] = abs(r["error"]) / r["predicted"]
    for loop, _ in frames:
        f = pred.get(loop)
        if f is None:
            continue
        for r in rows:
            if not r["name"].startswith(f"{loop}: "):
                continue
            unit = "m" if r["name"].endswith(" position") else "rad" if r["name"].endswith(" rotation") else None
            p, bound = f.get(f"predicted_max_{unit}"), f.get(f"predicted_max95_{unit}")
            if unit is None or not isinstance(p, (int, float)) or not is_number(p) or p <= 0:
                continue
            r["predicted"] = float(p)
            r["bound"] = float(bound) if isinstance(bound, (int, float)) and is_number(bound) else None
            r["ratio"] = r["error"] / r["predicted"] if r["error"] is not None else None


def prediction_finding(rows: list[dict]) -> str | None:
    """One line: whether every observed error is within the report's prediction (below its 95 % bound of
    the largest error), with the largest ratio observed / predicted; None where nothing was predicted."""
    compared = [r for r in rows if r.get("ratio") is not None]
    if not compared:
        return None
    worst = max(compared, key=lambda r: r["ratio"])
    outside = [r for r in compared if r.get("bound") is not None and abs(r["error"]) > r["bound"]]
    if not outside:
        return f"observed within prediction: the largest error is {worst['ratio']:.2g}x the predicted ({worst['name']})"
    names = ", ".join(f"{r['name']} {r['ratio']:.2g}x" for r in outside)
    return f"observed NOT within prediction (above the 95 % bound of the largest error): {names}"


def said(row: dict) -> float | None:
    """The largest error a report said a row's robot may have: its 95 % bound of the largest error
    ('bound'), else the expected largest error ('predicted'); None where nothing was predicted."""
    p, bound = row.get("predicted"), row.get("bound")
    if p is None:
        return None
    return max(p, bound) if bound is not None else p


def unforetold(rows: list[dict]) -> list[dict]:
    """The rows outside tolerance that the report's prediction did not foretell: none predicted, a
    prediction whose 95 % bound of the largest error (`said`) is within the tolerance (the report promised
    what the robot does not do), or an observed error more than `FORETOLD` times the expected largest one.
    A report whose verdict is ``ok`` with such a row misleads its reader: a confidently wrong answer.  A row
    outside tolerance that the prediction foretold is an honest answer: the report said the robot may not be
    that accurate (95 % of calibrated robots stay below the bound, not below the tolerance), and by about how
    much.  `within_bound_only` names those foretold by the bound alone (the expected error within the
    tolerance), which a table counts apart."""
    out = []
    for r in rows:
        if r.get("result") != "FAIL":
            continue
        p, err, tol, bound = r.get("predicted"), r.get("error"), r.get("tol"), said(r)
        if p is None or bound is None or err is None or tol is None or bound <= tol or abs(err) > FORETOLD * p:
            out.append(r)
    return out


def within_bound_only(rows: list[dict]) -> list[dict]:
    """The rows outside tolerance foretold (`unforetold`) by the 95 % bound alone: the expected largest error
    within the tolerance, its bound above it.  The report said the robot may be out of tolerance, not that it
    is expected to be: an answer a reader must read the bound to see."""
    bad = {id(r) for r in unforetold(rows)}
    return [
        r
        for r in rows
        if r.get("result") == "FAIL" and id(r) not in bad and r["predicted"] is not None and r["predicted"] <= r["tol"]
    ]
