"""Suggested configurations keep away from the joint stops (`closedloop.design.next_poses.inside_limits`)."""

from __future__ import annotations

import numpy as np

from closedloop.design.next_poses import LIMIT_MARGIN, inside_limits


def test_suggested_readings_keep_off_the_joint_stops():
    """A reading 1 mrad inside a limit is not suggested (the robot may not reach it, or rests on the stop);
    0.15 rad inside is; a 4 cm prismatic travel keeps all but 4 mm at each end."""
    lo, hi = np.array([-2.0, 0.0]), np.array([2.0, 0.04])
    X = np.array(
        [
            [-2.0 + 1e-3, 0.02],
            [2.0 - 0.15, 0.02],
            [0.0, 0.003],
            [0.0, 0.0365],
            [-2.0 + LIMIT_MARGIN, 0.0045],
        ]
    )
    assert inside_limits(X, lo, hi).tolist() == [False, True, False, False, True]
