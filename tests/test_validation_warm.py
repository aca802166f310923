"""Held-out refits on a long log's sample of training rows start at the calibration's solution (a warm
refit, `closedloop.validation.kfold`): the held-out figures of a calibration of its own on the same rows,
in a fraction of its work; on a short log every refit stays a calibration of its own."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import ROBOTS
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.studies.truth import make_dataset
from closedloop.validation import kfold
from closedloop.validation.regions import region_validate

NOISE = 1e-4  # rad of joint noise on every reading


@pytest.fixture(scope="module")
def panda_case():
    """The Panda welded to a fixture, 160 configurations with NOISE, and its calibration."""
    robot = RobotModel.from_file(ROBOTS["panda"].path)
    loop = WeldLoop("fixture", "panda_hand")
    rng = np.random.default_rng(7)
    ds = make_dataset(robot, loop, [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 160, rng)
    lg = JointLog(list(ds.joints), ds.readings + rng.normal(0.0, NOISE, ds.readings.shape))
    res = calibrate(robot, lg, [loop], CalibrationOptions())
    assert res.converged and not res.outliers.rejected
    return robot, loop, lg, list(ds.joints), res


def _rms(fold: dict, part: str) -> tuple[float, float]:
    row = fold[part]["loops"][0]
    return row["rms_m"], row["rms_rad"]


@pytest.mark.slow
def test_sampled_training_rows_refit_warm_with_the_figures_of_a_calibration_of_its_own(panda_case, monkeypatch):
    """With the cap at 100 rows per loop the 160-row log is 'long': each region's refit trains on an even
    sample of 100 of its training rows.  Started at the calibration's solution it reaches the minimum a
    calibration of its own on those rows reaches: held-out and training closures alike to 1e-3 (both stop
    within a small fraction of a standard error of it, the solver's tolerance)."""
    robot, loop, lg, joints, res = panda_case
    monkeypatch.setattr(kfold, "VALIDATION_ROWS", 100)
    warm = region_validate(robot, lg, [loop], joints, CalibrationOptions(), exclude=[], result=res)
    cold = region_validate(robot, lg, [loop], joints, CalibrationOptions(), exclude=[])
    assert [f["warm"] for f in warm["folds"]] == [True] * len(warm["folds"])
    assert not any(f["warm"] for f in cold["folds"])
    assert all(f["n_train"] == 100 for f in warm["folds"])  # the sample, said in the record
    assert [f["n_test"] for f in warm["folds"]] == [min(len(r), 100) for r in warm["regions"]]
    for w, c in zip(warm["folds"], cold["folds"]):
        assert w["converged"] and c["converged"]
        for part in ("test", "train"):
            assert _rms(w, part) == pytest.approx(_rms(c, part), rel=1e-3)
        assert _rms(w, "test")[0] > 0.01 * NOISE  # a closure of the noise's size, not zero


@pytest.mark.slow
def test_short_log_refits_stay_calibrations_of_their_own(panda_case):
    """Below the cap no row is sampled and the calibration given changes nothing: every refit is a
    calibration of its own, on all its training rows (the documented outputs of short logs)."""
    robot, loop, lg, joints, res = panda_case
    rv = region_validate(robot, lg, [loop], joints, CalibrationOptions(), exclude=[], result=res)
    assert not any(f["warm"] for f in rv["folds"])
    assert [f["n_train"] for f in rv["folds"]] == [len(lg) - len(r) for r in rv["regions"]]


def test_warm_refits_run_on_threads_with_the_serial_engines_figures(panda_case, monkeypatch):
    """Warm refits (each on a problem of its own) run on threads of the process (`parallel.engine.ThreadEngine`)
    where no engine is given: every figure to the bit that of the refits one after the other."""
    from closedloop.parallel import engine as engine_module

    robot, loop, lg, joints, res = panda_case
    monkeypatch.setattr(kfold, "VALIDATION_ROWS", 100)
    used = []
    real = engine_module.ThreadEngine.imap

    def spy(self, *args, **kwargs):
        used.append(self.workers)
        yield from real(self, *args, **kwargs)

    monkeypatch.setattr(engine_module.ThreadEngine, "imap", spy)
    threads = region_validate(robot, lg, [loop], joints, CalibrationOptions(), exclude=[], result=res)
    serial = region_validate(
        robot, lg, [loop], joints, CalibrationOptions(), exclude=[], result=res, executor=engine_module.SerialEngine()
    )
    assert used and used[0] >= 1 and len(used) == 1
    assert [f["warm"] for f in threads["folds"]] == [True] * len(threads["folds"])
    for a, b in zip(threads["folds"], serial["folds"]):
        assert a["values"] == b["values"] and a["test"] == b["test"] and a["train"] == b["train"]


def test_a_warm_refit_solves_once_where_its_structure_and_start_are_those_of_its_first_fit(panda_case, monkeypatch):
    """A warm refit whose fit truncates a direction reads the structure again; where nothing is then held and
    no direction lies below the noise at its start, the fit it would solve again is the one it solved (the
    same problem, parameters and start): it is not solved again.  (The truncation is made here: the Panda's
    weld determines every direction.)"""
    from closedloop.validation import refit as refit_module

    robot, loop, lg, joints, res = panda_case
    calls = []

    def first_truncates(*args, **kwargs):
        stage = refit_module.weighted_stage.__wrapped__(*args, **kwargs)
        stage.solution.truncated = 0 if calls else 1
        calls.append(stage)
        return stage

    first_truncates.__wrapped__ = refit_module.weighted_stage
    monkeypatch.setattr(refit_module, "weighted_stage", first_truncates)
    warm = refit_module._warm(res, robot, lg, [loop], CalibrationOptions())
    assert warm is not None and warm.warm and len(calls) == 1
    np.testing.assert_array_equal(warm.values, calls[0].fun.normalized(calls[0].fun.full(calls[0].solution.x)))
    assert warm.iterations == calls[0].solution.iterations
