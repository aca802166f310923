"""Per-loop task-space noise: one component when the loops' estimates agree, their own when not.

Two rigs with the same true robot (examples/ball_socket_rig.py, seed 0): two places with 0.2 mm of play in
the sockets and two with 0.8 mm.  Each loop's variance component is estimated (`variance.variance_components`);
Bartlett's test (`variance.homogeneous`) pools those that agree.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_rigs import _loops, rigmod

from closedloop import CalibrationOptions, RobotModel, calibrate
from closedloop.io.logs import JointLog


def _log(rigs: dict[str, object], n: int) -> tuple[JointLog, list[str]]:
    rows, labels = [], []
    for prefix, rig in rigs.items():
        for k in rig.loop_names():
            rows.append(rig.readings[k])
            labels += [prefix + k[5:]] * n
    first = next(iter(rigs.values()))
    return JointLog(first.joints, np.vstack(rows), None, np.array(labels)), list(dict.fromkeys(labels))


def test_equal_play_pooled_unequal_not(tmp_path: Path):
    tight = rigmod.make_rig(seed=0, n=30, places=2, sigma_task=2e-4)
    wide = rigmod.make_rig(seed=0, n=30, places=2, sigma_task=8e-4)
    assert tight.true_urdf == wide.true_urdf
    (tmp_path / "nominal.urdf").write_text(tight.nominal)
    robot = RobotModel.from_file(tmp_path / "nominal.urdf")
    # the same play everywhere: one component, right to 10 % (seed 0: 0.202 mm)
    log, names = _log({"place": tight}, 30)
    res = calibrate(robot, log, _loops(robot, names), CalibrationOptions())
    model = {d["loop"]: d for d in res.noise.noise_model}
    assert all(model[n]["task_pooled"] for n in names)
    assert len({round(model[n]["task_sigma_m"], 12) for n in names}) == 1
    assert abs(model[names[0]]["task_sigma_m"] / 2e-4 - 1.0) < 0.1, model
    # 0.2 mm at two places, 0.8 mm at two others: each loop its own, each within 20 % of its truth
    log, names = _log({"place": tight, "wide": wide}, 30)
    res = calibrate(robot, log, _loops(robot, names), CalibrationOptions())
    model = {d["loop"]: d for d in res.noise.noise_model}
    assert not any(d["task_pooled"] for d in model.values())
    for n in names:
        truth = 2e-4 if n.startswith("place") else 8e-4
        assert abs(model[n]["task_sigma_m"] / truth - 1.0) < 0.2, (n, model[n])


def test_batched_pseudo_inverse_is_the_eigenvalue_one():
    """`_wpinv`: the batched inverse of well-conditioned matrices, the eigenvalue pseudo-inverse (eigenvalues
    below 1e-12 of the largest dropped) of the others, in one stack; 1 x 1 matrices by division."""
    from closedloop.estimate.variance import _eigen_pinv, _wpinv

    rng = np.random.default_rng(0)
    J = rng.normal(size=(40, 3, 5))
    W = J @ np.swapaxes(J, 1, 2)
    W[3] = np.diag([1.0, 1e-14, 2.0])  # a cut eigenvalue on a well-scaled diagonal: the inverse would keep it
    singular = W.copy()
    singular[7] = np.diag([0.0, 1.0, 1.0])  # no inverse: the stack by eigenvalues
    for stack in (W, singular):
        ref = _eigen_pinv(stack)
        got = _wpinv(stack)
        assert np.abs(got - ref).max() <= 1e-9 * np.abs(ref).max()
        assert got[3, 1, 1] == 0.0
    assert _wpinv(singular)[7, 0, 0] == 0.0
    w = np.array([2.0, 0.0, 0.5])[:, None, None]
    assert np.array_equal(_wpinv(w)[:, 0, 0], [0.5, 0.0, 2.0])
