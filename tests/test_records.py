"""A calibration result is a few small immutable records, and the report is built from them in one place
(`closedloop.output.report.build_report`)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from closedloop import CalibrationOptions, JointLog, WeldLoop, build_report, calibrate
from closedloop.records import AccuracyRecord, CalibrationResult


@pytest.fixture(scope="module")
def result(panda, panda_weld):
    rng = np.random.default_rng(3)
    log = JointLog(panda_weld.joints, panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape))
    return calibrate(panda, log, [WeldLoop("fixture", "panda_hand")], CalibrationOptions())


def test_the_result_is_a_few_frozen_records():
    top = dataclasses.fields(CalibrationResult)
    assert len(top) <= 12
    for f in top:
        if f.name in ("fit", "identifiability", "noise", "scale", "outliers"):
            cls = CalibrationResult.__dataclass_fields__[f.name].type
            assert isinstance(cls, str) and cls.endswith("Record")
    assert CalibrationResult.__dataclass_params__.frozen  # type: ignore[attr-defined]


def test_records_hold_the_fit_and_the_report_reads_them(result):
    """The records agree with each other and with the report built from them."""
    fit = result.fit
    with pytest.raises(dataclasses.FrozenInstanceError):
        fit.iterations = 0  # type: ignore[misc]
    assert result.converged and fit.converged
    assert len(fit.names) == len(fit.values) == len(fit.std) == len(fit.status) == len(result.problem.params)
    assert fit.covariance.shape == (len(fit.estimated), len(fit.estimated))
    assert result.noise.sigma_estimated and abs(result.noise.sigma / 1e-4 - 1.0) < 0.2  # the noise drawn
    assert result.scale.gauge == "panda_joint3.z" and result.scale.gauge_length == pytest.approx(0.316)
    assert result.outliers.rows_total == 200 and result.outliers.rejected == []
    assert result.accuracy is None and result.verdict is not None and result.verdict.status == "ok"
    report = build_report(result)
    assert report["solver"]["iterations"] == fit.iterations
    assert report["noise"]["joint_sigma"] == result.noise.sigma
    assert report["identifiability"]["rank"] == result.identifiability.rank
    assert report["gauge"]["length_scale_set_by"] == result.scale.gauge
    assert [p["calibrated"] for p in report["parameters"]] == [float(v) for v in fit.values]
    assert "accuracy" not in report and "validation" not in report


def test_a_runs_sections_and_the_accuracy_slot_go_in_by_keyword(result):
    regions = {"k": 4, "test": []}
    filled = dataclasses.replace(result, accuracy=AccuracyRecord(regions=regions, target={"met": True}))
    report = build_report(
        filled,
        inputs={"model": "arm.urdf"},
        timing={"seconds": 1.5, "cpu_seconds": 2.0},
        validation={"k": 5},
        outputs={"model": "cal.urdf"},
    )
    assert report["accuracy"] == {"workspace": None, "regions": regions, "target": {"met": True}}
    assert report["inputs"] == {"model": "arm.urdf"} and report["outputs"] == {"model": "cal.urdf"}
    assert report["validation"] == {"k": 5} and "fixture_validation" not in report
    assert report["solver"]["seconds"] == 1.5 and report["solver"]["status"] == "converged"
    json.dumps(report)  # plain data throughout
