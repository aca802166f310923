"""Real robots: public recordings (``../shared/real-data/<folder>/``, each with a README naming its source,
commit and licence; `real_data.RECORDINGS`) calibrated with closedloop's defaults.  Where a recording's
folder is absent the tests skip, naming it.

Held-out protocol (docs/validation/real-robots.md): the rows whose 0-based index is a multiple of 5
are held out, the others train; what is fitted on the training rows is used as it is on the held-out
rows (the tracker's frame and the marker point are estimated once, from the training rows; nothing is
refitted on the held-out rows).  The bar is the figure the robot's makers published, and the better of
the two estimators a user could pick by hand (``weighting='none'`` and errors in variables) within 2 %.
"""

from __future__ import annotations

import numpy as np
import pytest
from real_data import RECORDINGS, chain_urdf, figaroh_log

from closedloop.assets.catalog import example_robot_data_dir
from closedloop.calibration.pipeline import PLAIN, SANDWICH
from closedloop.io.logs import JointLog
from closedloop.loops.measured import MeasuredPointLoop
from closedloop.model.robot import RobotModel
from closedloop.records import CalibrationOptions
from closedloop.validation.kfold import holdout, subset

TALOS_FACTOR = 2.3  # published: held-out RMS of the calibrated model <= nominal / 2.3
TIAGO_RMSE = 5.7e-3  # published: m


def held_out(robot: RobotModel, log_: JointLog, frame: str, options: CalibrationOptions) -> dict:
    """Fit on the rows whose index is not a multiple of 5, the RMS marker error on those that are."""
    idx = np.arange(len(log_))
    test = idx % 5 == 0
    loops = [MeasuredPointLoop("m", frame)]
    h = holdout(robot, subset(log_, idx[~test]), subset(log_, idx[test]), loops, options)
    return {"result": h["result"], "train": h["train"]["loops"][0]["rms_m"], "test": h["test"]["loops"][0]["rms_m"]}


@pytest.fixture(scope="module", params=sorted(RECORDINGS))
def real(request, tmp_path_factory):
    """Each recording's held-out figures with the defaults, plain, errors in variables and the nominal."""
    name = request.param
    rec = RECORDINGS[name]
    log_ = figaroh_log(name)  # skips, naming the folder, where ../shared/real-data/<folder> is absent
    src = example_robot_data_dir() / rec.urdf
    robot = RobotModel.from_file(chain_urdf(src, rec.frame, tmp_path_factory.mktemp(name) / "chain.urdf"))
    options = {
        "default": CalibrationOptions(),
        "none": CalibrationOptions(weighting="none"),
        "eiv": CalibrationOptions(choose_estimator=False),
        "nominal": CalibrationOptions(identify=["loop"]),  # the makers' model: only the tracker and marker fitted
    }
    out = {k: held_out(robot, log_, rec.frame, o) for k, o in options.items()}
    return name, out


@pytest.mark.slow
def test_default_at_or_below_published_figure(real):
    name, out = real
    if name == "talos":
        assert out["default"]["test"] <= out["nominal"]["test"] / TALOS_FACTOR
    else:
        assert out["default"]["test"] <= TIAGO_RMSE
    assert out["default"]["test"] < out["nominal"]["test"]  # and better than the makers' model


@pytest.mark.slow
def test_default_not_worse_than_either_estimator(real):
    _, out = real
    assert out["default"]["test"] <= 1.02 * min(out["none"]["test"], out["eiv"]["test"])


@pytest.mark.slow
def test_model_error_found_and_said(real):
    """The residual is model error: the hypothesis fails, the plain fit is chosen and says why."""
    _, out = real
    res = out["default"]["result"]
    ev = res.noise.model_error
    assert not ev["noise_explains"]
    assert ev["joint_noise_implied"] > 2.0 * ev["joint_noise_tested"]
    assert res.noise.estimator == PLAIN and res.noise.weighting == "none"
    assert res.noise.error_bars == SANDWICH
    assert "joint noise does not explain the residual" in res.noise.estimator_reason
    assert res.notes[0].startswith(f"estimator: {PLAIN}")
    # too few configurations per parameter for the sandwich: the verdict says the error bars are not reliable
    assert res.verdict.status == "suspect"
    assert any("error bars are not reliable" in x for x in res.verdict.reasons)
    # errors in variables as asked says nothing was decided
    assert out["eiv"]["result"].noise.estimator_reason == "as asked"


def test_absent_recording_skips_naming_its_folder(monkeypatch, tmp_path):
    """A checkout without ../shared/real-data beside it: the test skips, and the reason names the folder."""
    import real_data

    monkeypatch.setattr(real_data, "REAL_DATA", tmp_path / "shared" / "real-data")
    with pytest.raises(pytest.skip.Exception, match="shared/real-data/figaroh-tiago-mocap"):
        real_data.figaroh_log("tiago")
    with pytest.raises(SystemExit, match="shared/real-data/figaroh-talos-left-arm"):
        real_data.figaroh_log("talos", skip=False)
