"""Compare a calibration report with simulation ground truth (`closedloop check`).

Only parameters the report marks as estimated (identifiable) are compared;
the others are listed as not compared, with their status.  Truth omits the
parameters it did not perturb: their true value is their nominal (placement
errors and offsets 0, scales 1, D-H values as in the model, i.e. the report's
initial value).  A loop's rotation vector (rx, ry, rz) is compared as one
rotation: the geodesic angle between the calibrated and the true rotation.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from closedloop.errors import InputError

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
):
    """Rows of (name, true, calibrated, error, tol, result) and whether all compared rows pass.

    Both documents are validated first (:data:`~closedloop.io.schemas.TRUTH_SCHEMA`,
    :data:`~closedloop.io.schemas.REPORT_SCHEMA`); every tolerance must be a finite number > 0.
    """
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


def _row(name, true, cal, err, tol, result):
    return {"name": name, "true": true, "calibrated": cal, "error": err, "tol": tol, "result": result}
