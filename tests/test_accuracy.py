"""Predicted accuracy over the workspace (`closedloop.analysis.accuracy`), the held-out validation by
region (`closedloop.validation.regions`), and check's comparison of the prediction with the truth.

Data from the robot zoo (`tests/zoo.py`: errors on every joint origin, a generator independent of
closedloop's parametrization), judged by `closedloop check`'s kinematic view against the true URDF.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
import zoo

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.analysis.accuracy import PriorTolerance, predict_from_result, random_readings
from closedloop.calibration.verdict import judge_accuracy, judge_workspace
from closedloop.cli.main import main
from closedloop.errors import InputError
from closedloop.io.logs import JointLog
from closedloop.loops.spec import parse_loop
from closedloop.output.report import accuracy_section, build_report, verdict_record
from closedloop.run.accuracy import parse_accuracy, parse_box
from closedloop.validation.check import (
    FORETOLD,
    check_kinematics,
    prediction_finding,
    unforetold,
    within_bound_only,
)
from closedloop.validation.kfold import folds
from closedloop.validation.regions import regions


@functools.lru_cache(maxsize=None)
def _case(robot: str, loop: str, sigma: float):
    return zoo.make_case(robot, loop, n=60, sigma=sigma, seed=0)


def _judged(case, readings: np.ndarray):
    """Calibrate `readings` of the case's configurations; (result, prediction, check's rows with it)."""
    robot = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    res = calibrate(robot, JointLog(list(case.joints), readings), loops, CalibrationOptions())
    acc = predict_from_result(res)
    report = build_report(res)
    report["verdict"] = verdict_record(res.verdict)
    report["accuracy"] = accuracy_section(acc)
    truth = {"parameters": {f"{j}.offset": float(v) for j, v in case.true_offsets.items()}}
    true_robot = RobotModel.from_file(case.nominal_urdf.parent / "truth.urdf")
    rows, _ = check_kinematics(truth, report, robot, 1e-3, 5e-3, 5e-3, true_robot=true_robot)
    return res, acc, rows, report, truth


def test_prediction_matches_the_observed_error_over_noise_draws():
    """One-socket point loop on a UR5, 1e-4 rad of joint noise: over six noise draws, the observed largest
    tool error over the workspace (check, against the true robot) is within a factor 2 of the predicted one
    on average; and check's row carries the prediction and the ratio."""
    case = _case("ur5", "point", 1e-4)
    offsets = np.array([case.true_offsets[j] for j in case.joints])
    rng = np.random.default_rng(11)
    observed, predicted = [], []
    for _ in range(6):
        readings = case.q_true - offsets + rng.normal(scale=1e-4, size=case.q_true.shape)
        res, acc, rows, _, _ = _judged(case, readings)
        row = rows[0]
        assert row["name"].endswith("position") and row["predicted"] == pytest.approx(acc.frames[0].max_m)
        assert row["ratio"] == pytest.approx(row["error"] / row["predicted"])
        observed.append(row["error"])
        predicted.append(row["predicted"])
    ratio = np.mean(observed) / np.mean(predicted)
    assert 0.5 < ratio < 2.0, (observed, predicted)
    # the noise sets the error: about 0.1 mm per 1e-5 rad, nothing from what the data cannot see
    assert 2e-4 < np.mean(predicted) < 1e-2
    assert acc.frames[0].unseen_rms_m < 0.05 * acc.frames[0].rms_m


def test_unseen_parameters_enter_with_the_nominal_tolerance():
    """A weld on a 7-DOF arm sees the arm along its self-motion only: the parameters it cannot see move the
    tool over the joint ranges, and enter the prediction in proportion to the nominal tolerance."""
    case = _case("baxter_left", "weld", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    res = calibrate(robot, JointLog(list(case.joints), case.readings), loops, CalibrationOptions())
    base = predict_from_result(res)
    wide = predict_from_result(res, prior=PriorTolerance(length_m=1e-2, angle_rad=1e-2, offset_rad=0.1))
    f, g = base.frames[0], wide.frames[0]
    assert f.unseen_rms_m > 0.0
    assert g.unseen_rms_m == pytest.approx(10 * f.unseen_rms_m, rel=1e-6)
    assert g.rms_m > f.rms_m
    # the prediction of the default prior against the truth on this draw: within a factor 2
    _, _, rows, _, _ = _judged(case, case.readings)
    frames = [r for r in rows if r.get("ratio") is not None and not r["name"].startswith("size")]
    assert len(frames) == 2 and all(0.5 < r["ratio"] < 2.0 for r in frames), rows
    # the size (held by a 69 mm length whose possible 2 mm error dominates its prediction): within 3x
    size = [r for r in rows if r["name"].startswith("size")][0]
    assert abs(size["error"]) < FORETOLD * size["predicted"], size


@pytest.mark.slow  # about 10 s on a loaded machine
def test_a_move_along_what_the_data_cannot_see_is_predicted_as_error():
    """An xArm 7 weld (1-DOF self-motion) with 1e-5 rad of joint noise, a draw where the fit moved weak
    combinations (joint5.x, joint6.y) by about 15 mm before setting them aside: the tool is 20 mm and the
    size 4 % off the truth.  The prediction counts that move as error (module docstring of
    `closedloop.analysis.accuracy`), so check finds every row outside tolerance foretold (predicted above
    the tolerance, observed within 3x), and the workspace judgement fails the calibration: the calibrated
    model is not expected to be better than the nominal one."""
    case = zoo.make_case("xarm7", "weld", n=60, sigma=1e-5, seed=22)
    res, acc, rows, _, _ = _judged(case, case.readings)
    failing = [r for r in rows if r["result"] == "FAIL"]
    assert {r["name"].split(" ")[-1] for r in failing} == {"position", "rotation", "data)"}, rows
    assert failing[0]["error"] > 0.01 and not unforetold(rows), rows
    assert acc.frames[0].unseen_rms_m > 0.5 * acc.frames[0].rms_m  # the move, not the noise, dominates
    assert judge_workspace(res.verdict, acc).status == "failed"


def test_regions_are_compact_and_cover_the_log():
    """k-means regions: disjoint, covering every row, and farther from the rest of the log than random folds."""
    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    lg = JointLog(list(case.joints), case.readings)
    parts = regions(lg, robot, list(case.joints), k=4)
    assert len(parts) >= 3
    assert np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(lg)))

    def gap(sets):  # mean distance of a held-out row to its nearest training row
        X = case.readings
        d = []
        for s in sets:
            rest = np.setdiff1d(np.arange(len(X)), s)
            d.extend(np.min(np.linalg.norm(X[s, None] - X[None, rest], axis=2), axis=1))
        return float(np.mean(d))

    assert gap(parts) > 1.2 * gap(folds(lg, 4))


def test_regions_of_a_long_log_are_its_clusters():
    """Above `CLUSTER_SAMPLE` rows the k-means centres come from an even sample and every row joins its nearest:
    four separate clouds of configurations, 2,500 rows each in an interleaved order, are the four regions,
    row for row."""
    from closedloop.assets.catalog import ROBOTS
    from closedloop.validation.regions import CLUSTER_SAMPLE

    robot = RobotModel.from_file(ROBOTS["panda"].path)
    joints = [f"panda_joint{i}" for i in range(1, 8)]
    rng = np.random.default_rng(4)
    centres = rng.uniform(-1.0, 1.0, (4, 7)) * [2.0, 1.2, 2.0, 0.0, 2.0, 0.0, 2.0] + [0, 0, 0, -1.8, 0, 2.0, 0]
    centres[:, 3] += [-0.8, -0.3, 0.3, 0.8]  # the clouds apart on the fourth joint too
    cloud = np.tile(np.arange(4), 2500)
    X = centres[cloud] + rng.normal(0.0, 0.03, (cloud.size, 7))
    assert cloud.size > CLUSTER_SAMPLE
    parts = regions(JointLog(joints, X), robot, joints, k=4)
    assert sorted(sorted(set(cloud[p])) for p in parts) == [[0], [1], [2], [3]]
    assert sorted(p.size for p in parts) == [2500] * 4


def test_region_holdout_in_the_cli_report(tmp_path, capsys):
    """calibrate: the region validation and the prediction in the report and the summary's first lines;
    check: the predicted error beside the observed and the line 'observed within prediction' (or not)."""
    case = _case("ur5", "point", 1e-5)
    rep = tmp_path / "r.json"
    rc = main(
        [
            "calibrate",
            str(case.nominal_urdf),
            str(case.log_csv),
            "--loop",
            case.loop_specs[0],
            "--report",
            str(rep),
            "--cv",
            "0",
            "--regions",
            "3",
        ]
    )
    out = capsys.readouterr().out.splitlines()
    assert rc == 0
    assert out[0].startswith("verdict:") and out[1].startswith("predicted accuracy over the workspace")
    assert any("3 regions held out in turn" in line for line in out)
    report = json.loads(rep.read_text())
    ws = report["accuracy"]["workspace"]
    frame = ws["frames"][0]
    assert ws["check_readings"] and frame["predicted_max_m"] >= frame["predicted_p95_m"] >= 0.0
    assert frame["predicted_max95_m"] >= frame["predicted_max_m"]
    assert set(frame["worst_configuration"]) == set(case.joints)
    reg = report["accuracy"]["regions"]
    assert reg["k"] == 3 and sum(reg["rows"]) == 60 and reg["test"][0]["rms_m"] > 0
    truth = tmp_path / "truth.json"
    truth.write_text(
        json.dumps(
            {
                "parameters": {f"{j}.offset": float(v) for j, v in case.true_offsets.items()},
                "model": str(case.nominal_urdf.parent / "truth.urdf"),
            }
        )
    )
    rows_json = tmp_path / "check.json"
    rc = main(["check", str(truth), str(rep), "--json", str(rows_json)])
    text = capsys.readouterr().out
    assert "predicted" in text.splitlines()[1] and "ratio" in text.splitlines()[1]
    assert "observed within prediction" in text or "observed NOT within prediction" in text
    # --json: the same rows for a script, with the verdict and whether every row is within tolerance
    doc = json.loads(rows_json.read_text())
    assert doc["verdict"] == report["verdict"]["status"] and doc["pass"] == (rc == 0)
    row = doc["rows"][0]
    assert row["predicted"] == pytest.approx(frame["predicted_max_m"]) and f"{row['error']:12.3g}" in text
    # and never over an input
    assert main(["check", str(truth), str(rep), "--json", str(rep)]) == 2


def test_prediction_finding_names_what_is_outside():
    rows = [
        {"name": "a: tool point f position", "error": 3e-3, "predicted": 1e-3, "bound": 2e-3, "ratio": 3.0},
        {"name": "b: frame g rotation", "error": 1e-3, "predicted": 1e-3, "bound": 2e-3, "ratio": 1.0},
    ]
    line = prediction_finding(rows)
    assert (
        line is not None and line.startswith("observed NOT within prediction") and "a: tool point f position 3x" in line
    )
    line = prediction_finding(rows[1:])
    assert line is not None and line.startswith("observed within prediction")
    assert prediction_finding([{"name": "size", "error": 0.0}]) is None


def test_unforetold_rows_are_the_failures_the_prediction_did_not_say():
    """A row outside tolerance is foretold when the report predicted more than the tolerance and the
    observed error is at most FORETOLD times the prediction; otherwise (no prediction, a prediction within
    the tolerance, or far above it) an ok verdict with it is confidently wrong."""
    row = {"name": "p: tool point f position", "error": 2.5e-3, "tol": 1e-3, "result": "FAIL"}
    assert unforetold([row | {"predicted": 1.5e-3}]) == []
    assert unforetold([row | {"predicted": 2.5e-3 / (FORETOLD + 0.1)}]) != []  # observed above 3x
    assert unforetold([row | {"predicted": 0.9e-3}]) != []  # it promised the tolerance
    assert unforetold([row]) != []  # nothing predicted
    assert unforetold([row | {"predicted": 0.1e-3, "error": 0.5e-3, "result": "ok"}]) == []  # within tolerance
    size = {"name": "size (not measured by the data)", "error": -0.02, "tol": 5e-3, "result": "FAIL"}
    assert unforetold([size | {"predicted": 0.01}]) == []  # the size's error is signed: |error| against it


def test_a_95_percent_bound_above_the_tolerance_foretells_a_row_and_is_counted_apart():
    """The xArm 7 weld of the robot sweep (1e-5 rad): 1.24 mm observed against 0.66 mm expected, the report's
    95 % bound of the largest error 1.28 mm, tolerance 1 mm.  The report said the robot may be out of
    tolerance: foretold, by the bound alone (`within_bound_only`), which a table counts apart.  A bound within
    the tolerance promised it (confidently wrong), as does an observed error above 3x the expected."""
    row = {"name": "fixture: frame link_eef position", "error": 1.24e-3, "tol": 1e-3, "result": "FAIL"}
    xarm = row | {"predicted": 0.66e-3, "bound": 1.28e-3}
    assert unforetold([xarm]) == [] and within_bound_only([xarm]) == [xarm]
    assert unforetold([xarm | {"bound": 0.95e-3}]) == [xarm | {"bound": 0.95e-3}]  # the bound promised 1 mm
    far = xarm | {"error": 2.1e-3, "bound": 2.5e-3}  # above 3x the expected 0.66 mm: not foretold
    assert unforetold([far]) == [far] and within_bound_only([far]) == []
    above = row | {"predicted": 1.5e-3, "bound": 2.6e-3}  # the expected error above the tolerance: not apart
    assert unforetold([above]) == [] and within_bound_only([above]) == []
    assert within_bound_only([xarm | {"error": 0.9e-3, "result": "ok"}]) == []  # within tolerance: right


@pytest.mark.slow  # about 5 s on a loaded machine
def test_size_prediction_foretells_the_held_length_error():
    """A weld closes at any size: the calibration holds panda_joint3.z (316 mm) at its nominal value, which
    the zoo's truth perturbs with every other origin (2 mm errors).  The report predicts the size's error
    (the held length's possible 2 mm over 316 mm, and the fit's share); check's size row observes the truth's
    and carries that prediction, and the observed size error is foretold by it (within 3x, and above check's
    tolerance only where the prediction is)."""
    case = zoo.make_case("panda", "weld", n=60, seed=3)
    res, acc, rows, report, _ = _judged(case, case.readings)
    assert acc.size_held_std == pytest.approx(2e-3 / res.scale.gauge_length)
    assert acc.size_std >= acc.size_held_std and report["accuracy"]["workspace"]["size"]["predicted"] > 0
    size = [r for r in rows if r["name"].startswith("size")][0]
    assert size["predicted"] == pytest.approx(acc.size_predicted)
    assert 0.0 < abs(size["error"]) < FORETOLD * size["predicted"], size
    assert not unforetold(rows), rows
    # a nominal model declared good to 20 mm only: the held length is, too (not the 2 mm a model file may carry)
    loose = predict_from_result(res, prior=PriorTolerance(length_m=2e-2))
    assert loose.size_held_std == pytest.approx(2e-2 / res.scale.gauge_length)
    assert predict_from_result(res, prior=PriorTolerance(length_m=1e-3)).size_held_std == acc.size_held_std


def test_accuracy_target_makes_ok_impossible_above_it():
    """--accuracy: a prediction above the target is never ok; below it the verdict is untouched."""
    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    res = calibrate(robot, JointLog(list(case.joints), case.readings), loops, CalibrationOptions())
    acc = predict_from_result(res)
    assert res.verdict.status == "ok"
    v, rec = judge_accuracy(res.verdict, acc, 0.5 * acc.max_m, None)
    assert v.status == "suspect" and not rec["met"] and "accuracy target not met" in v.reasons[-1]
    v, rec = judge_accuracy(res.verdict, acc, 2.0 * acc.max_m, None)
    assert v.status == "ok" and rec["met"]
    assert res.verdict.status == "ok"  # the verdict given is not changed


def test_a_target_met_by_the_expected_error_and_not_by_its_95_percent_bound_is_stated():
    """--accuracy 1mm on the robot sweep's xArm 7 weld prediction (0.663 mm expected largest error, 95 % bound
    1.28 mm): the target is met by the expected error, and the verdict (still ok) and the summary say the bound
    is above it; a bound within the target adds nothing; an expected error above it is suspect as before."""
    from types import SimpleNamespace

    from closedloop.calibration.verdict import Verdict
    from closedloop.cli.accuracy import accuracy_lines

    ws = SimpleNamespace(max_m=0.663e-3, max95_m=1.28e-3, max_rad=None, max95_rad=None)
    v, rec = judge_accuracy(Verdict("ok", [], {}), ws, 1e-3, None)
    assert v.status == "ok" and rec["met"] and not rec["met_95"] and rec["predicted_max95_m"] == 1.28e-3
    assert v.reasons == [
        "note: accuracy target 1 mm met by the expected largest error (0.663 mm), not by its 95 % bound "
        "(1.28 mm): the robot may be outside the target"
    ]
    v, rec = judge_accuracy(Verdict("ok", [], {}), ws, 1.5e-3, None)
    assert v.status == "ok" and v.reasons == [] and rec["met_95"]
    v, rec = judge_accuracy(Verdict("ok", [], {}), ws, 0.5e-3, None)
    assert v.status == "suspect" and not rec["met"] and not rec["met_95"]
    frame = {"loop": "fixture", "kind": "pose", "frame": "link_eef", "predicted_max_m": 0.663e-3}
    frame |= {"predicted_max_rad": 1e-3, "predicted_max95_m": 1.28e-3, "predicted_max95_rad": 2e-3}
    frame |= {"predicted_rms_m": 0.3e-3, "predicted_unseen_rms_m": 1e-6}
    section = {"workspace": {"source": "s", "error_bars": "e", "frames": [frame]}, "target": rec | {"describe": "1 mm"}}
    section["target"].update(met=True, met_95=False)
    lines = accuracy_lines(section)
    assert "0.663 mm, 1 mrad at most expected (95 % bound 1.28 mm, 2 mrad; RMS 0.3 mm;" in lines[1]
    assert lines[-1] == "  target 1 mm: met by the expected largest error, NOT by its 95 % bound"
    from closedloop.output.html import _accuracy  # the HTML report's section says the same

    page = _accuracy({"accuracy": section})
    assert "<th>max, 95 % bound [mm]</th>" in page and "<td>1.28</td>" in page
    assert "accuracy target 1 mm: met by the expected largest error, not by its 95 % bound" in page
    old = {k: v for k, v in frame.items() if "95" not in k}  # a report written before the bound was stated
    assert (
        "at most expected (RMS 0.3 mm;" in accuracy_lines({"workspace": {**section["workspace"], "frames": [old]}})[1]
    )


def test_no_better_than_the_nominal_model_is_failed():
    """The nominal model's expected error (its tolerance propagated alike) beside the calibrated one's: a
    calibration predicted no better than the nominal model is failed (the nominal model is the better one)."""
    from dataclasses import replace

    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    res = calibrate(robot, JointLog(list(case.joints), case.readings), loops, CalibrationOptions())
    acc = predict_from_result(res)
    f = acc.frames[0]
    # the nominal model within 1 mm / 1 mrad / 10 mrad: millimetres at the tool; calibrated: a tenth of that
    assert f.nominal_rms_m > 1e-3 and f.rms_m < 0.1 * f.nominal_rms_m and acc.better_than_nominal
    assert judge_workspace(res.verdict, acc) is res.verdict
    worse = replace(acc, frames=(replace(f, nominal_rms_m=0.5 * f.rms_m),))
    v = judge_workspace(res.verdict, worse)
    assert v.status == "failed" and "does not make the robot more accurate" in v.reasons[-1]
    # ten times the tolerance: ten times the nominal model's expected error
    wide = predict_from_result(res, prior=PriorTolerance(length_m=1e-2, angle_rad=1e-2, offset_rad=0.1, scale=1e-2))
    assert wide.frames[0].nominal_rms_m == pytest.approx(10 * f.nominal_rms_m, rel=1e-6)


def test_option_values():
    assert parse_accuracy("0.2mm") == (pytest.approx(2e-4), None)
    assert parse_accuracy("0.2mm,1mrad") == (pytest.approx(2e-4), pytest.approx(1e-3))
    for bad in ("0.2", "fast", "-1mm", "0mm"):
        with pytest.raises(InputError, match="--accuracy"):
            parse_accuracy(bad)
    with pytest.raises(InputError, match="two position targets"):  # not the last kept silently
        parse_accuracy("0.01mm,5mm")
    with pytest.raises(InputError, match="two angle targets"):
        parse_accuracy("1mm,1mrad,1deg")
    with pytest.raises(InputError, match="below 1000"):
        parse_accuracy("1e9mm")
    assert parse_box("j1=-1:1, j2=0:0.5") == {"j1": (-1.0, 1.0), "j2": (0.0, 0.5)}
    with pytest.raises(InputError, match="--workspace"):
        parse_box("j1=1")
    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    j = case.joints[0]
    X = random_readings(robot, list(case.joints), 50, box={j: (-0.1, 0.2)})
    assert X[:, 0].min() >= -0.1 and X[:, 0].max() <= 0.2 and np.ptp(X[:, 1]) > 1.0
    with pytest.raises(InputError, match=f"joint '{j}'"):
        random_readings(robot, list(case.joints), 5, box={j: (0.5, 0.1)})


def test_evaluate_compares_new_data_with_the_prediction(tmp_path, capsys):
    """evaluate on new configurations of the same robot: beside the calibrated model's closure, the closure
    its calibration predicts there (its parameter uncertainty propagated, and the fit's noise), within 2x."""
    a = _case("ur5", "point", 1e-4)
    b = zoo.make_case("ur5", "point", n=160, sigma=1e-4, seed=0)  # the same robot and socket, 100 more rows
    assert a.true_offsets == b.true_offsets
    lines = b.log_csv.read_text().splitlines()
    new = tmp_path / "new.csv"
    new.write_text("\n".join([lines[0]] + lines[61:]) + "\n")
    cal, rep = tmp_path / "cal.urdf", tmp_path / "r.json"
    spec = a.loop_specs[0]
    args = ["calibrate", str(a.nominal_urdf), str(a.log_csv), "--loop", spec, "--out", str(cal)]
    assert main([*args, "--report", str(rep), "--cv", "0", "--regions", "0", "--quiet"]) == 0
    out_json = tmp_path / "ev.json"
    main(["evaluate", str(cal), str(new), "--loop", spec, "--calibration", str(rep), "--report", str(out_json)])
    out = capsys.readouterr().out
    assert "predicted by its calibration" in out and "observed within prediction" in out
    pred = json.loads(out_json.read_text())["models"][0]["prediction"][0]
    assert pred["unit"] == "m" and 0.5 < pred["ratio"] < 2.0
    assert pred["ratio"] == pytest.approx(pred["observed_rms"] / pred["predicted_rms"])


def test_evaluate_says_where_the_observation_is_far_below_the_prediction():
    """The predicted closure RMS is an expectation: observed within 2x of it either way is within prediction,
    above 2x not, below half of it said so (a Go2 foot's suggested rows: 0.66 mm observed, 1.89 mm predicted,
    was printed within prediction)."""
    from closedloop.validation.evaluate import prediction_lines

    def finding(ratio):
        row = {"loop": "floor", "unit": "m", "observed_rms": 1e-3 * ratio, "predicted_rms": 1e-3, "ratio": ratio}
        return prediction_lines("cal.urdf", [row])[-1]

    assert "observed within prediction (within 2x either way)" in finding(0.6)
    assert "observed within prediction" in finding(1.9)
    assert "observed NOT within prediction: loop floor 2.5x (m)" in finding(2.5)
    assert "observed below prediction: loop floor 0.35x (m)" in finding(0.35)


def test_bad_workspace_is_refused_before_the_fit(tmp_path, capsys):
    case = _case("ur5", "point", 1e-5)
    base = ["calibrate", str(case.nominal_urdf), str(case.log_csv), "--loop", case.loop_specs[0], "--cv", "0"]
    for bad, said in (
        ("nojoint=-1:1", "joint 'nojoint' is not one of the calibrated joints"),
        ("a.csv", "no such file"),
    ):
        assert main([*base, "--workspace", bad]) == 2
        cap = capsys.readouterr()
        assert said in cap.err and len(cap.err.strip().splitlines()) == 1
        assert not cap.out  # refused before the fit: no summary


def test_suggested_poses_recorded_and_recalibrated_reduce_the_error_as_predicted(tmp_path, capsys):
    """Closed loop on the UR5 socket (1e-4 rad): the 8 suggested configurations, recorded on the true robot
    (moved onto its loop from the suggested readings) and calibrated again with the 60 first rows: over
    three noise draws the observed largest tool error over the workspace falls more than 2x, and lands
    within 1.5x of the error predicted after them."""

    from closedloop.design.next_poses import suggest_poses

    case = _case("ur5", "point", 1e-4)
    robot = RobotModel.from_file(case.nominal_urdf)
    loops = [parse_loop(s, robot) for s in case.loop_specs]
    offsets = np.array([case.true_offsets[j] for j in case.joints])
    on_true_loop = zoo.on_true_loop(case)

    def observed(readings):
        res = calibrate(robot, JointLog(list(case.joints), readings), loops, CalibrationOptions())
        acc = predict_from_result(res)
        report = build_report(res)
        report["accuracy"] = accuracy_section(acc)
        truth = {"parameters": {f"{j}.offset": float(v) for j, v in case.true_offsets.items()}}
        true_robot = RobotModel.from_file(case.nominal_urdf.parent / "truth.urdf")
        rows, _ = check_kinematics(truth, report, robot, 1e-3, 5e-3, 5e-3, true_robot=true_robot)
        return res, acc, rows[0]["error"]

    rng = np.random.default_rng(3)
    before, after, predicted = [], [], []
    for _ in range(3):
        readings = case.q_true - offsets + rng.normal(scale=1e-4, size=case.q_true.shape)
        res, acc, error = observed(readings)
        nxt = suggest_poses(res, acc, 8)
        assert nxt is not None and nxt.readings.shape == (8, len(case.joints))
        assert np.all(np.diff(nxt.rms_after_m) <= 1e-15) and nxt.rms_before_m == pytest.approx(acc.frames[0].rms_m)
        new = [zoo._project(on_true_loop, r + offsets, case.lower - 1.0, case.upper + 1.0) for r in nxt.readings]
        new = [th - offsets + rng.normal(scale=1e-4, size=th.shape) for th in new if th is not None]
        assert len(new) == 8  # each suggestion is a configuration the true robot reaches at the socket
        res2, acc2, error2 = observed(np.vstack([readings, new]))
        before.append(error)
        after.append(error2)
        predicted.append(acc.max_m * nxt.rms_after_m[-1] / nxt.rms_before_m)
        # the recalibration's own prediction agrees with the suggestion's
        assert acc2.frames[0].rms_m == pytest.approx(nxt.rms_after_m[-1], rel=0.3)
    assert np.mean(after) < 0.5 * np.mean(before), (before, after)
    assert 1 / 1.5 < np.mean(after) / np.mean(predicted) < 1.5, (after, predicted)


def test_suggest_writes_a_log_the_robot_can_play(tmp_path, capsys):
    """--accuracy not met and --suggest FILE: the CSV of joint readings (header of joint names, within the
    limits), the report's record and the summary's line."""
    case = _case("ur5", "point", 1e-5)
    nxt, rep = tmp_path / "next.csv", tmp_path / "r.json"
    args = ["calibrate", str(case.nominal_urdf), str(case.log_csv), "--loop", case.loop_specs[0], "--cv", "0"]
    rc = main(
        [*args, "--regions", "0", "--accuracy", "1um", "--suggest", str(nxt), "--suggest-n", "5", "--report", str(rep)]
    )
    out = capsys.readouterr().out
    assert rc == 0 and "accuracy target not met" in out.splitlines()[0]
    assert f"next: 5 configurations of loop point in {nxt}" in out
    assert f"  wrote {nxt}" in out.splitlines()  # listed with the other files written
    lines = nxt.read_text().splitlines()
    assert lines[0].split(",") == list(case.joints) and len(lines) == 6
    X = np.array([[float(v) for v in row.split(",")] for row in lines[1:]])
    assert np.all(X >= case.lower - 1e-9) and np.all(X <= case.upper + 1e-9)
    rec = json.loads(rep.read_text())["accuracy"]["next_poses"]
    assert rec["configurations"] == 5 and rec["predicted_rms_after_m"][-1] < rec["predicted_rms_before_m"]


def test_suggest_on_a_log_with_joint_torques(tmp_path, capsys):
    """A log with joint torques (``tau:<joint>``, the compliance then estimated): the suggested
    configurations carry the model's gravity torques, not the log's rows (a log of another length)."""
    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    tau = robot.gravity_torques(case.readings, list(case.joints))
    lines = case.log_csv.read_text().splitlines()
    log = tmp_path / "torques.csv"
    log.write_text(
        "\n".join(
            [lines[0] + "," + ",".join(f"tau:{j}" for j in case.joints)]
            + [row + "," + ",".join(repr(float(v)) for v in t) for row, t in zip(lines[1:], tau)]
        )
        + "\n"
    )
    nxt = tmp_path / "next.csv"
    args = ["calibrate", str(case.nominal_urdf), str(log), "--loop", case.loop_specs[0], "--cv", "0", "--regions", "0"]
    assert main([*args, "--suggest", str(nxt), "--suggest-n", "3", "--quiet"]) == 0
    rows = nxt.read_text().splitlines()
    assert rows[0].split(",") == list(case.joints) and len(rows) == 4


def test_regions_of_a_rig_whose_loops_each_have_their_own_log():
    """Two sockets recorded apart (the log's 'loop' column), each in its own part of joint space: every
    region holds rows of both loops (a refit without one of them could not be done), the regions cover
    the log, and each loop's share of a region is compact (closer to itself than to the loop's other rows)."""
    case = _case("ur5", "point", 1e-5)
    robot = RobotModel.from_file(case.nominal_urdf)
    X = case.readings
    first = X[:, 0] < np.median(X[:, 0])  # two places: the rows of each half of the first joint's range
    lg = JointLog(list(case.joints), X, loop=np.where(first, "a", "b"))
    parts = regions(lg, robot, list(case.joints), k=4)
    assert len(parts) == 4
    assert np.array_equal(np.sort(np.concatenate(parts)), np.arange(len(lg)))
    for p in parts:
        assert set(lg.loop[p]) == {"a", "b"}, p
    for name in ("a", "b"):
        rows = np.flatnonzero(lg.loop == name)
        own = [np.intersect1d(p, rows) for p in parts]
        spread = np.mean([np.linalg.norm(X[o] - X[o].mean(axis=0), axis=1).mean() for o in own])
        assert spread < np.linalg.norm(X[rows] - X[rows].mean(axis=0), axis=1).mean()
    # a loop with fewer rows than two per region is refused in one line naming it
    few = JointLog(list(case.joints), X[:50], loop=np.array(["a"] * 45 + ["b"] * 5))
    with pytest.raises(Exception, match="loop 'b'"):
        regions(few, robot, list(case.joints), k=4)


def test_prior_tolerance_values():
    """--prior-tolerance: parsed into the prior (units, defaults for the keys not given), refused in one
    line naming the item."""
    from closedloop.run.accuracy import parse_prior
    from closedloop.run.options import CalibrateOptions

    p = parse_prior("length=0.3mm,offset=1deg")
    assert p == PriorTolerance(length_m=pytest.approx(3e-4), offset_rad=pytest.approx(np.pi / 180))
    assert parse_prior("scale=1e-4,angle=0.002") == PriorTolerance(scale=1e-4, angle_rad=0.002)
    for bad, said in (("length=1", "below 1"), ("length=2cm", "unit of m, mm, um"), ("size=1mm", "keys length")):
        with pytest.raises(InputError, match=said):
            parse_prior(bad)
    with pytest.raises(InputError, match="^prior_tolerance 'scale=1mm'"):
        CalibrateOptions(model="m.urdf", log="l.csv", prior_tolerance="scale=1mm")


@pytest.mark.slow
def test_prior_tolerance_through_the_command_line(tmp_path, capsys):
    """calibrate --prior-tolerance: a bad one refused before the fit; the report's prior, the share from what
    the data cannot see and the nominal model's expected error follow the tolerance given."""
    case = _case("ur5", "point", 1e-5)
    base = ["calibrate", str(case.nominal_urdf), str(case.log_csv), "--loop", case.loop_specs[0], "--cv", "0"]
    assert main([*base, "--prior-tolerance", "length=1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "error: --prior-tolerance 'length=1': a tolerance must be below 1 (m, rad or a ratio)"
    reports = []
    for prior in ("length=1mm,angle=1mrad,offset=10mrad", "length=10mm,angle=10mrad,offset=100mrad"):
        rep = tmp_path / f"r{len(reports)}.json"
        args = [*base, "--regions", "0", "--quiet", "--report", str(rep), "--prior-tolerance", prior]
        assert main(args) == 0
        reports.append(json.loads(rep.read_text())["accuracy"]["workspace"])
    assert reports[1]["prior"]["length_m"] == pytest.approx(1e-2)
    f, g = reports[0]["frames"][0], reports[1]["frames"][0]
    assert f["predicted_unseen_rms_m"] > 0.0
    # the tolerance's share scales with it; the fit's own move along those directions is the same in both
    assert g["predicted_unseen_rms_m"] == pytest.approx(10 * f["predicted_unseen_rms_m"], rel=1e-3)
    assert g["nominal_rms_m"] == pytest.approx(10 * f["nominal_rms_m"], rel=0.02)  # the scales' share stays


@pytest.mark.slow
def test_region_validation_leaves_the_rejected_rows_out_of_regions_and_refits():
    """A reading of 100 rad the calibration rejects is in no region (alone, it would be a region of its own,
    judged on nothing), and no refit trains on it: every region judged, the held-out closure that of exact data."""
    from closedloop.assets.catalog import ROBOTS
    from closedloop.loops import WeldLoop
    from closedloop.studies.truth import make_dataset
    from closedloop.validation.regions import region_validate

    robot = RobotModel.from_file(ROBOTS["panda"].path)
    loop = WeldLoop("fixture", "panda_hand")
    ds = make_dataset(robot, loop, [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 30, np.random.default_rng(4))
    th = ds.readings.copy()
    th[11, 2] = 100.0
    lg = JointLog(list(ds.joints), th)
    res = calibrate(robot, lg, [loop], CalibrationOptions())
    bad = [rj.row - 1 for rj in res.outliers.rejected]
    assert bad == [11]
    rv = region_validate(robot, lg, [loop], list(ds.joints), CalibrationOptions(), exclude=bad)
    assert all(11 not in r for r in rv["regions"]) and sum(len(r) for r in rv["regions"]) == 29
    assert all(f["n_train"] + f["n_test"] == 29 for f in rv["folds"])
    assert all(f["converged"] for f in rv["folds"])
    assert rv["test"][0]["rms_m"] is not None and rv["test"][0]["rms_m"] < 1e-6
