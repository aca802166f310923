"""Where to measure next, in words: where what the data cannot see is most of the error left after the
suggested configurations, the summary says that they leave it and that only a loop that sees more would
not (an Allegro finger pressing a socket: its abduction joint does not move on that loop)."""

from __future__ import annotations

import numpy as np
import pytest

from closedloop.output.report import next_poses_words


def _record(before: float, after: float, unseen: float) -> dict:
    return {
        "file": "next.csv",
        "loop": "socket",
        "configurations": 10,
        "candidates": 400,
        "predicted_rms_before_m": before,
        "predicted_rms_after_m": list(np.linspace(before, after, 10)),
        "predicted_unseen_rms_m": unseen,
    }


def test_the_words_name_an_unseen_share_the_suggestions_leave():
    """The Allegro finger socket of `closedloop simulate` (100 configurations, 1e-4 rad, seed 1): 0.402 mm
    predicted, 0.374 mm of it unseen, 0.388 mm promised after ten suggestions (0.3955 mm once recorded)."""
    words = next_poses_words(_record(0.402e-3, 0.388e-3, 0.374e-3))
    assert words.startswith("10 configurations of loop socket in next.csv: predicted RMS 0.402 mm -> 0.388 mm")
    assert "(0.374 mm RMS of it from what this loop's data cannot see, which these configurations leave" in words


def test_the_words_stay_plain_where_the_suggestions_remove_most_of_the_error():
    """Go2's leg on a plane (100 configurations, 1e-4 rad, seed 1): 1.08 mm -> 0.0463 mm promised, nothing
    unseen; and a record written before the unseen share was recorded."""
    assert next_poses_words(_record(1.08e-3, 0.0463e-3, 5.66e-9)).endswith("once recorded and calibrated again")
    old = _record(1.08e-3, 0.0463e-3, 0.0)
    del old["predicted_unseen_rms_m"]
    assert next_poses_words(old).endswith("once recorded and calibrated again")


@pytest.mark.slow
def test_an_allegro_finger_socket_is_told_its_suggestions_leave_the_unseen_error():
    """A pure-kinematic Allegro finger pressing a socket (60 configurations, 1e-4 rad): its abduction joint
    does not move on the loop, what that hides is most of the predicted error, and the suggestions, all on
    the same loop, promise to remove little of it; the words say so, with the prediction's own figure."""
    from closedloop import CalibrationOptions, RobotModel, calibrate
    from closedloop.analysis.accuracy import predict_from_result
    from closedloop.assets.catalog import example_robot_data_dir
    from closedloop.design.next_poses import suggest_next
    from closedloop.loops.spec import parse_loop
    from closedloop.studies.truth import make_dataset

    robot = RobotModel.from_file(f"{example_robot_data_dir()}/allegro_hand_description/urdf/allegro_right_hand.urdf")
    spec = "point:frame=link_3.0_tip,name=socket"
    ds = make_dataset(robot, parse_loop(spec, robot), [0.06, 0.8, 0.8, 0.8], 60, np.random.default_rng(1), noise=1e-4)
    res = calibrate(robot, ds.log(), [parse_loop(spec, robot)], CalibrationOptions(noise=1e-4))
    acc = predict_from_result(res)
    nxt = suggest_next(res, acc, 10)
    assert nxt is not None
    frame = acc.frames[0]
    assert frame.unseen_rms_m > 0.8 * frame.rms_m
    # what the loop cannot see, it still cannot see after the suggestions: the share left is the share before
    assert nxt.unseen_rms_m == pytest.approx(frame.unseen_rms_m, rel=0.05)
    assert nxt.rms_after_m[-1] > 0.9 * nxt.rms_before_m  # the same loop cannot see it
    record = nxt.record("next.csv")
    assert record["predicted_unseen_rms_m"] == nxt.unseen_rms_m
    assert f"({nxt.unseen_rms_m * 1e3:.3g} mm RMS of it from what this loop's data cannot see" in next_poses_words(
        record
    )
