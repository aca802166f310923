"""A stage on a long log is first solved on an evenly spaced sample (`residual.presolved`: 100,000
configurations in at most 5 s); the whole log then finishes it.  The answer must be the whole log's own fit,
to a small fraction of its standard errors, and a sample whose fit fails must not be used."""

from __future__ import annotations

import logging

import numpy as np
import pytest

import closedloop.estimate.residual as fit_module
from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.assets.catalog import ROBOTS
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop
from closedloop.studies.truth import make_dataset


@pytest.fixture(scope="module")
def long_log():
    """1,200 rows: 300 exact self-motion configurations of a random true Panda, four times, 1e-4 rad noise."""
    panda = RobotModel.from_file(ROBOTS["panda"].path)
    rng = np.random.default_rng(11)
    ds = make_dataset(
        panda, WeldLoop("fixture", "panda_hand"), [0.0, 0.3, 0.0, -1.8, 0.0, 2.0, 0.8], 300, rng, stride=1
    )
    th = np.tile(ds.readings, (4, 1))
    return panda, ds, JointLog(ds.joints, th + rng.normal(0.0, 1e-4, th.shape))


@pytest.fixture(scope="module")
def whole(long_log):
    """The long log calibrated as it is (1,200 configurations: below the presolve's threshold)."""
    panda, _, log = long_log
    return calibrate(panda, log, [WeldLoop("fixture", "panda_hand")], CalibrationOptions())


def _presolve_above(monkeypatch, above: int, rows: int) -> None:
    """The presolve on loops above `above` configurations, on `rows` of them."""
    monkeypatch.setattr(fit_module, "PRESOLVE_ABOVE", above)
    monkeypatch.setattr(fit_module, "PRESOLVE_ROWS", rows)


def test_presolved_fit_is_the_whole_logs_fit(long_log, whole, monkeypatch, caplog):
    panda, ds, log = long_log
    loops = [WeldLoop("fixture", "panda_hand")]
    _presolve_above(monkeypatch, 1000, 150)
    with caplog.at_level(logging.INFO, logger="closedloop.estimate.residual"):
        pre = calibrate(panda, log, loops, CalibrationOptions())
    assert any("solved on 150 configurations" in m for m in caplog.messages)  # the presolve ran
    assert whole.verdict.status == pre.verdict.status == "ok"
    assert whole.fit.status == pre.fit.status and whole.scale.gauge == pre.scale.gauge
    est = np.array(whole.fit.estimated)
    z = np.abs(pre.fit.values[est] - whole.fit.values[est]) / whole.fit.std[est]
    assert np.nanmax(z) < 0.05, np.nanmax(z)  # the same minimum, to 5 % of a standard error
    assert np.allclose(pre.fit.std[est], whole.fit.std[est], rtol=1e-3, equal_nan=True)
    # the same robot by what it does: the hand's place over the log, both calibrations against each other
    hand = [
        np.asarray(r.problem.loop_poses(r.fit.values, 0, ds.readings)[0])[:, :3, 3] for r in (whole, pre)
    ]  # panda_hand
    assert np.linalg.norm(hand[0] - hand[1], axis=1).max() < 1e-7  # nominal: 14 mm


def test_the_whole_log_finishes_with_one_jacobian_less(long_log, whole, monkeypatch):
    """From the sample's solution the whole log is finished with chord steps (`residual.FINISH_CHORD`): its
    Jacobian over every row is formed once fewer than without them, at the same minimum and with standard
    errors within 1e-3 of the whole log's own fit (measured: 2.7e-5)."""
    from closedloop.problem.problem import CalibrationProblem

    panda, _, log = long_log
    loops = [WeldLoop("fixture", "panda_hand")]
    _presolve_above(monkeypatch, 1000, 150)
    real = CalibrationProblem._evaluate
    passes = {"n": 0}

    def counting(self, values, jacobian, thetas, columns):
        if jacobian and (columns is None or len(columns)) and sum(b.theta.shape[0] for b in self.blocks) == len(log):
            passes["n"] += 1
        return real(self, values, jacobian, thetas, columns)

    monkeypatch.setattr(CalibrationProblem, "_evaluate", counting)
    counts, fits = [], []
    for chord in (fit_module.FINISH_CHORD, 0.0):
        monkeypatch.setattr(fit_module, "FINISH_CHORD", chord)
        passes["n"] = 0
        fits.append(calibrate(panda, log, loops, CalibrationOptions()))
        counts.append(passes["n"])
    assert counts[0] == counts[1] - 1, counts
    est = np.array(whole.fit.estimated)
    for pre in fits:
        assert pre.verdict.status == "ok"
        assert np.nanmax(np.abs(pre.fit.values[est] - whole.fit.values[est]) / whole.fit.std[est]) < 0.05
        assert np.allclose(pre.fit.std[est], whole.fit.std[est], rtol=1e-3, equal_nan=True)


def test_a_sample_that_does_not_converge_is_not_used(long_log, whole, monkeypatch, caplog):
    panda, _, log = long_log
    loops = [WeldLoop("fixture", "panda_hand")]
    _presolve_above(monkeypatch, 1000, 150)
    real = fit_module.levenberg_marquardt

    def failing_on_samples(fun, x0, *args, **kwargs):
        res = real(fun, x0, *args, **kwargs)
        if fun.problem.blocks[0].theta.shape[0] == 150:  # the sample's fit: report it unconverged, far away
            res.status, res.message, res.x = "max_iter", "no convergence (test)", res.x + 0.3
        return res

    monkeypatch.setattr(fit_module, "levenberg_marquardt", failing_on_samples)
    with caplog.at_level(logging.INFO, logger="closedloop.estimate.residual"):
        pre = calibrate(panda, log, loops, CalibrationOptions())
    assert any("did not converge cleanly" in m for m in caplog.messages)
    est = np.array(whole.fit.estimated)
    assert np.allclose(pre.fit.values[est], whole.fit.values[est], rtol=0, atol=1e-9)
    assert pre.verdict.status == "ok"


@pytest.mark.slow
def test_presolved_passive_door_is_the_truth(tmp_path, monkeypatch):
    """A case the presolve was not designed around: the UR5 door through its passive chain (a weakly
    determined valley, 100 iterations).  Presolved on 40 of its 150 configurations, the calibration must
    still meet the simulated truth (a whole-log finish without the geodesic probes did not: three
    parameters 0.5-1.4 mrad off with a closure as small, which is why the finish keeps them)."""
    import json

    from closedloop.assets.catalog import model_file
    from closedloop.io.logs import read_log
    from closedloop.loops import PassiveChainLoop
    from closedloop.output.report import build_report
    from closedloop.sims import simulate
    from closedloop.validation.check import check_report

    simulate("ur5_door", 150, 1, tmp_path)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    log = read_log(tmp_path / "log.csv", robot.joint_names)
    _presolve_above(monkeypatch, 100, 40)
    res = calibrate(robot, log, [PassiveChainLoop("door", "tool0", model_file("tasks/hinged_door.urdf"), "grip")])
    assert res.converged and res.verdict.status == "ok"
    truth = json.loads((tmp_path / "truth.json").read_text())
    rows, ok = check_report(truth, build_report(res), tol_m=1e-4, tol_rad=1e-3, tol_scale=1e-3)
    assert ok, [r for r in rows if r["result"] == "FAIL"]


def test_a_long_logs_start_and_check_read_an_even_sample(long_log, whole, monkeypatch):
    """The loops' start values and the check of the data read `selection.START_ROWS` configurations of a long
    log (`CalibrationProblem.sampled`), not every row: the same minimum as the start from all of them."""
    import closedloop.calibration.pipeline as pipeline
    from closedloop.loops.weld import WeldLoop as Weld

    panda, _, log = long_log
    seen: list[int] = []
    real = Weld.initialize_frames

    def spy(self, Ts, meas=None):
        seen.append(Ts[0].shape[0])
        return real(self, Ts, meas)

    monkeypatch.setattr(Weld, "initialize_frames", spy)
    monkeypatch.setattr(pipeline, "START_ROWS", 150)
    res = calibrate(panda, log, [WeldLoop("fixture", "panda_hand")], CalibrationOptions())
    assert seen and max(seen) == 150, seen  # the start read the sample, never the 1,200 rows
    est = np.array(whole.fit.estimated)
    assert res.verdict.status == whole.verdict.status == "ok" and list(res.fit.estimated) == list(est)
    z = np.abs(res.fit.values[est] - whole.fit.values[est]) / whole.fit.std[est]
    assert np.nanmax(z) < 0.05, np.nanmax(z)


def test_one_sample_per_size_kept_with_its_evaluations(long_log):
    """`sampled` gives the same sample (and its memo) for the same size, a new one once the noise records or
    the blocks change."""
    from closedloop.calibration.pipeline import build_problem

    panda, _, log = long_log
    problem = build_problem(panda, log, [WeldLoop("fixture", "panda_hand")])
    a = problem.sampled(150)
    assert a is problem.sampled(150) and a is not problem.sampled(151)
    assert a.blocks[0].theta.shape[0] == 150 and problem.sampled(5000) is problem  # all rows: itself
    problem.noise = list(problem.noise)  # another weighting's records: another sample
    assert problem.sampled(150) is not a


def test_the_left_out_prediction_reads_the_fits_kept_evaluation(long_log, monkeypatch):
    """On a long log the model-error test's left-out prediction reads the whole log's kept evaluation at its
    sample's rows (`CalibrationProblem.kept`): the figure an evaluation of the sample gives, to 1e-6."""
    import closedloop.estimate.model_error as me
    import closedloop.problem.problem as problem_module
    from closedloop.problem.problem import CalibrationProblem

    panda, _, log = long_log
    loops = [WeldLoop("fixture", "panda_hand")]
    _presolve_above(monkeypatch, 1000, 150)
    monkeypatch.setattr(problem_module, "MEMO_ROWS", 1000)  # 1,200 rows: a long log's memo (kept, shared)
    monkeypatch.setattr(me, "LOO_SAMPLE", 200)
    monkeypatch.setattr(fit_module, "FINISH_CHORD", 0.0)  # a Jacobian at the solution: both read the same point
    real, found = CalibrationProblem.kept, []

    def spy(self, values, columns):
        out = real(self, values, columns)
        found.append(out is not None)
        return out

    monkeypatch.setattr(CalibrationProblem, "kept", spy)
    read = calibrate(panda, log, loops, CalibrationOptions())
    assert any(found), found  # the kept evaluation was read
    monkeypatch.setattr(CalibrationProblem, "kept", lambda self, values, columns: None)
    fresh = calibrate(panda, log, loops, CalibrationOptions())
    a, b = (r.noise.model_error.get("left_out_rms_eiv") for r in (read, fresh))
    assert a is not None and b is not None and abs(a - b) <= 1e-6 * b, (a, b)
