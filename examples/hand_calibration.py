"""The hand procedure of chapter 4 on a simulated Utah-MIT thumb-finger loop.

The true hand is the thesis's calibrated one (Table 4.2, offsets clipped to
0.5 rad, scale factors to 0.85-1.0); the calibration starts from the nominal
Table 4.1 with s_0 = -1.3 in and k_7 = 1 fixed, estimates the poorly known
parameters first, then everything (4.2.6), and converts the result to the
palm frame (4.5, Tables 4.3 and 4.4).

    python examples/hand_calibration.py
"""

from __future__ import annotations

import tempfile

from closedloop.io.logs import JointLog
from closedloop.loops.spec import default_loops
from closedloop.model.robot import RobotModel
from closedloop.studies.hand import (
    INCH,
    palm_frame_parameters,
    staged_calibration,
    table_4_1_path,
    thesis_hand_dataset,
    thesis_stages,
)


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        truth, readings, _ = thesis_hand_dataset(d, n=100)
    robot = RobotModel.from_file(table_4_1_path())
    results = staged_calibration(
        robot, JointLog(robot.joint_names, readings), default_loops(robot), thesis_stages(robot)
    )
    first = results[0].fit.residuals_before[0]
    print(f"nominal Table 4.1: closure RMS {first.rms_m / INCH:.3f} in, {first.rms_rad:.3f} rad")
    for i, res in enumerate(results, start=1):
        r = res.fit.residuals_after[0]
        print(f"stage {i}: {len(res.fit.estimated)} parameters -> {r.rms_m / INCH:.3g} in, {r.rms_rad:.3g} rad")
    final = results[-1]
    err = max(abs(final.fit.values[k] - truth[final.fit.names[k]]) for k in final.fit.estimated)
    print(f"largest parameter error against the true hand: {err:.2e}")
    print(f"{'parameter':<14}{'true':>10}{'calibrated':>12}")
    for k in final.fit.estimated:
        n = final.fit.names[k]
        if n.endswith((".theta_off", ".k")):
            print(f"{n:<14}{truth[n]:>10.4f}{final.fit.values[k]:>12.4f}")
    palm = palm_frame_parameters(robot, final.as_dict())
    for note in palm.notes:
        print("palm frame:", note)


if __name__ == "__main__":
    main()
