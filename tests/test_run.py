"""One calibration run (`closedloop.run.calibrate_files`): the options' verdict rules reach the fit's
judgement, the verdict with the held-out evidence keeps what the fit's own judgement found, and the run
writes what its verdict allows."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from closedloop.assets.catalog import ROBOTS
from closedloop.calibration.pipeline import CalibrationOptions, calibrate
from closedloop.calibration.verdict import Verdict, VerdictRules, final_verdict, judge
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.model.robot import RobotModel
from closedloop.records import SUSPECT
from closedloop.run import CalibrateOptions, calibrate_files
from closedloop.studies.truth import make_dataset

NOISE = 1e-4  # rad: the joint noise drawn, which the fit estimates


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    loop = WeldLoop("fixture", "panda_hand")
    ds = make_dataset(robot, loop, [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 40, np.random.default_rng(3), noise=NOISE)
    log = JointLog(list(ds.joints), ds.noisy)
    path = tmp_path_factory.mktemp("run") / "log.csv"
    log.write_csv(path)
    res = calibrate(robot, log, [loop], CalibrationOptions())
    return robot, log, loop, path, res


def test_the_fit_is_judged_by_the_options_rules(data):
    """A plausible-noise limit below the estimated noise makes the same fit suspect, by that rule alone."""
    robot, log, loop, _, res = data
    sigma = res.noise.sigma
    assert 0.5 * NOISE < sigma < 2 * NOISE  # the fit estimates the noise drawn
    strict = VerdictRules(plausible_joint_noise=sigma / 2)
    res_strict = calibrate(robot, log, [loop], CalibrationOptions(rules=strict))
    said = [r for r in res_strict.verdict.reasons if "larger than encoders give" in r]
    assert res_strict.verdict.status == SUSPECT and len(said) == 1, res_strict.verdict.reasons
    assert not any("larger than encoders give" in r for r in res.verdict.reasons), res.verdict.reasons


def test_the_held_out_verdict_keeps_what_the_fit_found(data):
    """Judged again with held-out fixtures, a verdict keeps the reasons and evidence its fit's own judgement
    added beyond the rules (as the length guard does: `length_left_out`)."""
    _, _, _, _, res = data
    own = Verdict(res.verdict.status, list(res.verdict.reasons), dict(res.verdict.evidence))
    own.add(SUSPECT, "the known length does not set the size: solved without it")
    own.evidence["length_left_out"] = True
    fixtures = {"suspect": ["held-out fixture b: closure 3.1 mm, worse than the nominal model's 2.0 mm"]}
    v = final_verdict(replace(res, verdict=own), None, fixtures)
    assert v.status == SUSPECT and v.evidence["length_left_out"] is True
    assert f"{SUSPECT}: the known length does not set the size: solved without it" in v.reasons
    assert f"{SUSPECT}: {fixtures['suspect'][0]}" in v.reasons
    assert set(judge(res, fixtures=fixtures).reasons) <= set(v.reasons)  # the rules' own findings, all kept
    assert final_verdict(res, None, None) is res.verdict  # nothing held out: the fit's judgement stands


def _panda_weld(data, **options) -> CalibrateOptions:
    """The module's Panda weld log through `calibrate_files`, with `options`."""
    return CalibrateOptions(
        model=str(ROBOTS["panda"].path), log=str(data[3]), loop=["weld:frame=panda_hand,name=fixture"], **options
    )


def test_a_run_writes_what_its_verdict_allows(data, tmp_path):
    """From files to files through the API, each long stage told to the progress display; a verdict failed
    by the options' rules writes the report only."""
    base = _panda_weld(data, out=str(tmp_path / "ok.urdf"), report=str(tmp_path / "ok.json"), cv=2)
    told: list[str] = []
    run = calibrate_files(base, lambda task, done, total=None, note="": told.append(task))
    report = json.loads((tmp_path / "ok.json").read_text())
    # every stage that takes seconds on a long log shows a progress line, in the order the run takes them
    stages = ["reading", "analysing", "solving", "predicting accuracy", "validating", "validating regions"]
    assert [t for t in dict.fromkeys(told) if t in stages] == stages, told
    assert run.model_written and (tmp_path / "ok.urdf").is_file()
    assert report["verdict"]["status"] == run.verdict.status != "failed"
    assert report["validation"]["k"] == 2 and len(report["validation"]["folds_converged"]) == 2
    assert report["inputs"] == {"readings": "measured", "weighting": "noise", "torques": report["inputs"]["torques"]}
    assert report["outputs"] == {"model": str(tmp_path / "ok.urdf")}
    failing = base.with_values(
        out=str(tmp_path / "no.urdf"),
        report=str(tmp_path / "no.json"),
        rules=VerdictRules(failed_joint_noise=run.result.noise.sigma / 2),
        cv=0,  # the fit's own rule fails it: no held-out evidence needed
        regions=0,
    )
    run = calibrate_files(failing)
    assert run.verdict.status == "failed" and not run.model_written
    assert not (tmp_path / "no.urdf").exists()
    assert json.loads((tmp_path / "no.json").read_text())["outputs"] == {"model": None}


def test_a_failed_fit_is_not_validated(data, tmp_path):
    """A fit its own verdict fails (here the options' joint-noise rule) is not refitted on held-out rows or
    regions: those refits can only add to a failed verdict (nine of them took over 90 % of a many-fingered
    hand's run); the report says why each was not run, and the run tells no validating stage."""
    res = data[4]
    failing = _panda_weld(
        data,
        report=str(tmp_path / "no.json"),
        rules=VerdictRules(failed_joint_noise=res.noise.sigma / 2),
        cv=2,
        regions=2,
    )
    told: list[str] = []
    run = calibrate_files(failing, lambda task, done, total=None, note="": told.append(task))
    report = json.loads((tmp_path / "no.json").read_text())
    assert run.verdict.status == "failed" and not any(t.startswith("validating") for t in told), told
    why = "the fit failed (its verdict): refits of held-out rows cannot make it right"
    assert report["validation"] == {"k": 2, "skipped": why}
    assert report["accuracy"]["regions"] == {"k": 2, "skipped": why}
    assert f"held-out validation not run: {why}" in run.result.notes
