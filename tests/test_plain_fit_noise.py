"""A plain loop-closure fit (eq. 3.8) weighs no row by a joint noise: its residual scale is a closure in
metres and radians, and the summary, the report and the HTML page do not call it the joint noise."""

from __future__ import annotations

import json

import numpy as np
import pytest

from closedloop.assets.catalog import nominal_urdf
from closedloop.cli.main import main
from closedloop.io.logs import JointLog
from closedloop.loops import WeldLoop

NOISE = 1e-5


@pytest.fixture(scope="module")
def files(panda_weld, tmp_path_factory):
    """The shared Panda weld (200 configurations, `conftest.panda_weld`), its readings with 1e-5 rad of
    joint noise added."""
    d = tmp_path_factory.mktemp("plain")
    nominal = d / "panda.urdf"
    nominal.write_text(nominal_urdf("panda"))
    ds = panda_weld.log()
    noisy = ds.angles + np.random.default_rng(3).normal(0.0, NOISE, ds.angles.shape)
    log = d / "log.csv"
    JointLog(list(ds.joints), noisy).write_csv(log)
    return nominal, log, d


def _calibrate(files, capsys, name: str, *extra: str) -> tuple[dict, str]:
    nominal, log, d = files
    args = ["calibrate", str(nominal), str(log), "--loop", "weld:frame=panda_hand,name=fixture"]
    args += ["--report", str(d / f"{name}.json"), "--cv", "0", "--regions", "0", *extra]
    assert main(args) == 0
    return json.loads((d / f"{name}.json").read_text()), capsys.readouterr().out


def test_a_plain_fit_given_a_noise_does_not_print_its_closure_as_the_given_noise(files, capsys):
    """--noise 1e-5 --weighting none: the line said 'joint noise <closure RMS> rad (given)', a figure in
    metres the user never gave; the report's joint_sigma held it and a chi-square test of 1 by construction."""
    report, out = _calibrate(files, capsys, "plain", "--noise", str(NOISE), "--weighting", "none")
    noise = report["noise"]
    assert noise["joint_sigma"] is None and noise["p_value"] is None and noise["consistent"] is None
    # the closure residual per degree of freedom: the loop's position and rotation closures over the dof
    after = report["residuals"]["after"][0]
    closure = noise["closure_sigma"]
    assert closure == pytest.approx(np.sqrt(after["n"] * (after["rms_m"] ** 2 + after["rms_rad"] ** 2) / noise["dof"]))
    line = next(ln for ln in out.splitlines() if "closure residual" in ln)
    assert f"closure residual {closure:.3g} per degree of freedom" in line and "no joint noise" in line
    assert "(given)" not in out and "rad, estimated from the residual" not in out


def test_a_weighted_fit_keeps_its_joint_noise_and_test(files, capsys):
    """The errors-in-variables fit with the noise given: the noise is the one given, tested by chi-square."""
    report, out = _calibrate(files, capsys, "eiv", "--noise", str(NOISE))
    noise = report["noise"]
    assert noise["joint_sigma"] == NOISE and noise["closure_sigma"] is None
    assert noise["p_value"] is not None and 0.7 < noise["chi2_per_dof"] < 1.4  # the noise drawn is the noise given
    assert f"joint noise {NOISE:.3g} rad (given)" in out


@pytest.mark.slow
def test_the_html_page_says_the_same(files, capsys):
    """The HTML report's noise row reads the same record (slow: the page draws its figures)."""
    pytest.importorskip("matplotlib", reason="the HTML report needs matplotlib (closedloop[report])")
    nominal, log, d = files
    page = d / "plain.html"
    _calibrate(files, capsys, "plain_html", "--weighting", "none", "--html", str(page))
    text = page.read_text()
    assert "no joint noise weighs the rows (plain least squares)" in text


def test_the_spectrum_draws_the_plain_fits_own_truncation(files):
    """The HTML spectrum's truncation line (thesis 4.2.6) of a plain fit given a noise is the fit's own,
    snr times its closure scale, not the whitened fit's 1 (which fell back to a line between two values)."""
    from closedloop import CalibrationOptions, calibrate, read_log
    from closedloop.model.robot import RobotModel
    from closedloop.output.html import truncation_threshold

    nominal, log, _ = files
    robot = RobotModel.from_file(nominal)
    res = calibrate(
        robot,
        read_log(log, robot.joint_names),
        [WeldLoop("fixture", "panda_hand")],
        CalibrationOptions(noise=NOISE, weighting="none"),
    )
    S = np.asarray(res.identifiability.singular_values)
    assert truncation_threshold(res) == pytest.approx(max(1e-10 * S[0], res.noise.sigma))
    assert int(np.sum(S > truncation_threshold(res))) == res.identifiability.rank
