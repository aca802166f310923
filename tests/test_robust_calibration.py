"""Robust fitting (issue 5, item 3): three 5 cm outliers in 200 configurations change neither the
estimated parameter set nor the held-out error by more than 10%, and are reported as suspects."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.calibration import CalibrationOptions, calibrate, residual_stats
from closedloop.data import JointLog
from closedloop.loops import WeldLoop
from closedloop.truth import make_dataset

from conftest import PANDA_Q0


@pytest.fixture(scope="module")
def data(panda):
    rng = np.random.default_rng(21)
    ds = make_dataset(panda, WeldLoop("fixture", "panda_hand"), PANDA_Q0, 400, rng)
    train = ds.readings[::2] + rng.normal(0.0, 1e-4, ds.readings[::2].shape)
    held_out = ds.readings[1::2]  # exact readings of the same true robot
    return ds, train, held_out


def held_out_error(res, held_out) -> float:
    ev = res.problem.evaluate(res.values, False, [held_out])
    return residual_stats(res.problem, ev)[0].rms_m


def test_three_outliers(panda, data):
    ds, train, held_out = data
    clean = calibrate(panda, JointLog(ds.joints, train), [WeldLoop("fixture", "panda_hand")])
    bad_rows = [17, 88, 150]
    corrupt = train.copy()
    corrupt[bad_rows, 1] += 0.1  # shoulder: ~0.1 rad x ~0.5 m reach = ~5 cm closure error
    ev = clean.problem.evaluate(clean.values, False, [corrupt])[0]
    assert np.linalg.norm(ev.r[bad_rows, :3], axis=1).min() > 0.03
    robust = calibrate(panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")],
                       CalibrationOptions(robust="cauchy"))
    assert robust.converged
    assert [n for n, s in zip(robust.names, robust.status) if s == "estimated"] == \
        [n for n, s in zip(clean.names, clean.status) if s == "estimated"]
    h0, h1 = held_out_error(clean, held_out), held_out_error(robust, held_out)
    assert abs(h1 / h0 - 1.0) < 0.10, (h0, h1)
    assert sorted(s.row for s in robust.suspects) == [r + 1 for r in bad_rows]  # 1-based log rows
    assert any("suspect configuration: log row 18" in n for n in robust.notes)
    # plain least squares is pulled away by the same outliers
    plain = calibrate(panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")],
                      CalibrationOptions(weighting="none", robust=None))
    assert held_out_error(plain, held_out) > 3 * h0


def test_default_rejects_the_three_outliers(panda, data):
    """The default (robust='auto') finds the same three rows, leaves them out, and predicts as the clean fit."""
    ds, train, held_out = data
    clean = calibrate(panda, JointLog(ds.joints, train), [WeldLoop("fixture", "panda_hand")])
    corrupt = train.copy()
    corrupt[[17, 88, 150], 1] += 0.1
    res = calibrate(panda, JointLog(ds.joints, corrupt), [WeldLoop("fixture", "panda_hand")])
    assert sorted(r.row for r in res.rejected) == [18, 89, 151]
    h0, h1 = held_out_error(clean, held_out), held_out_error(res, held_out)
    assert abs(h1 / h0 - 1.0) < 0.10, (h0, h1)
    assert res.verdict.status == "ok", res.verdict.describe()
