"""Every threshold of the verdict is a field of `VerdictRules`, documented, and the instance passed in is the one
applied: by `judge`, and by the pipeline (`CalibrationOptions.rules`)."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from closedloop import CalibrationOptions, JointLog, WeldLoop, calibrate
from closedloop.calibration.verdict import VerdictRules, judge

ROOT = Path(__file__).resolve().parents[1]


def _hook():
    spec = importlib.util.spec_from_file_location("generated_hook", ROOT / "docs" / "hooks" / "generated.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_rule_has_a_unit_and_a_meaning_and_a_row_in_the_docs_table():
    table = _hook().rules_reference().splitlines()
    fields = dataclasses.fields(VerdictRules)
    assert len(fields) >= 30
    assert len(table) == 2 + len(fields)
    for f, row in zip(fields, table[2:]):
        assert f.metadata["unit"] in ("1", "m", "rad", "px"), f.name
        assert len(f.metadata["meaning"]) > 10, f.name
        assert row.startswith(f"| `{f.name}` | {f.default:g} |"), row
    page = (ROOT / "docs" / "guide" / "verdict.md").read_text()
    assert "<!-- generated: verdict-rules -->" in page


def test_rules_are_frozen_and_read_by_unit():
    rules = VerdictRules()
    with pytest.raises(dataclasses.FrozenInstanceError):
        rules.chi2_failed = 1.0  # type: ignore[misc]
    assert (rules.floor("rms_m"), rules.floor("rms_rad"), rules.floor("rms_px")) == (1e-7, 1e-7, 1e-4)
    assert (rules.roundoff("rms_m"), rules.roundoff("rms_px")) == (1e-12, 1e-9)
    assert rules.sets_size(1.0) and not rules.sets_size(0.8) and not rules.sets_size(1.2)
    assert CalibrationOptions().rules == rules


@pytest.fixture(scope="module")
def noisy_weld(panda, panda_weld):
    rng = np.random.default_rng(11)
    log = JointLog(panda_weld.joints, panda_weld.readings + rng.normal(0.0, 1e-4, panda_weld.readings.shape))
    return panda, log, [WeldLoop("fixture", "panda_hand")]


def test_custom_rules_reach_the_pipelines_verdict(noisy_weld):
    """A rule that calls every moved joint origin implausible turns the pipeline's own verdict suspect; the
    default rules leave the same fit ok, and `judge` with the same rules agrees with the pipeline."""
    robot, log, loops = noisy_weld
    strict = VerdictRules(origin_suspect=0.0, origin_suspect_min=1e-7, corrections_failed=1e9)
    default = calibrate(robot, log, loops, CalibrationOptions(noise=None))
    custom = calibrate(robot, log, loops, CalibrationOptions(noise=None, rules=strict))
    assert default.verdict is not None and custom.verdict is not None
    assert default.verdict.status == "ok", default.verdict.describe()
    assert custom.verdict.status == "suspect"
    assert any("implausibly large corrections" in r for r in custom.verdict.reasons)
    np.testing.assert_allclose(
        custom.fit.values, default.fit.values, rtol=0, atol=1e-12
    )  # the same fit, judged otherwise
    assert judge(default, rules=strict).status == "suspect"
    assert judge(default).status == "ok"
