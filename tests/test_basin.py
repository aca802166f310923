"""Basin of convergence, quick: a few thesis-sized random starts per chapter 3 example (issue 10, item 3).

Exact data from `thesis_examples.py` (loops closed with Pinocchio on the true D-H table).  On
Examples 1 and 2 and point contact all starts here but at most one must be recovered (the calibrated
mechanism equals the truth to 1e-6, gauge-free, and the verdict is not 'failed'; Example 2's start 2 is
one of its two refusals in 40); Example 1's starts 11 and 16
are ones where the start model closes only one of the 40 configurations, so the reduction must be
decided at the solution (`identifiability.Structure.provisional`).  The door (hinge unknown; its
data's weakest direction is 3e-8 of the strongest): start 8 stops at a local minimum 1e-6 m above
zero whose residual is smooth along the swing, which sends it to restarts (`staging._systematic`);
start 12's start drops j5.s as redundant, which it is not at the solution (`structure_holds`).  The
rates over 40-100 starts are `benchmarks/basin.py`'s.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import thesis_examples as te

STARTS = {"example1": [0, 1, 2, 3, 11, 16], "example2": [0, 1, 2, 3], "door": [0, 8, 12], "point": [0, 1, 2, 3, 4]}


def test_examples_are_exact_closed_loops():
    """The generated data close each loop on the true table to 1e-11, and the tables have the thesis's fixed length."""
    for name, make in te.EXAMPLES.items():
        ex = make()
        chain = te.Chain(ex.rows)
        T = [chain.pose(th) for th in ex.readings]
        if ex.closes:
            assert max(np.linalg.norm(pin.log6(t).vector) for t in T) < 1e-11, name
        elif ex.tip is not None:
            p = np.array([t.act(ex.tip) for t in T])
            assert np.abs(p - p[0]).max() < 1e-11
        else:  # door: relative motions of the tool are rotations about one fixed line
            c, u = ex.meta["axis_point"], ex.meta["axis_dir"]
            for t, phi in zip(T, ex.meta["phi"]):
                R = pin.exp3(u * phi)
                assert np.linalg.norm(pin.log6((pin.SE3(R, c - R @ c) * T[0]).actInv(t)).vector) < 1e-11
        j, f = ex.fixed[0].split(".")
        assert ex.rows[int(j[1:]) - 1, te.FIELDS.index(f)] == 1.0


def test_mechanism_error_is_gauge_free():
    """Zero for the truth and for its D-H re-labelling (theta + pi, a and alpha negated); large for a start."""
    ex = te.example1()
    rows = ex.rows.copy()
    rows[2, 0] += np.pi
    rows[2, 2:] *= -1
    rows[3, 0] += np.pi
    assert te.mechanism_error(ex, rows, {}) < 1e-12
    assert te.mechanism_error(ex, te.thesis_start(ex, np.random.default_rng(0)), {}) > 0.05


@pytest.mark.parametrize("name", list(STARTS))
def test_basin_quick(name):
    ex = te.EXAMPLES[name]()
    outs = [te.run_start(ex, seed) for seed in STARTS[name]]
    lines = "\n".join(o.line() for o in outs)
    if any(not o.recovered and not o.refused for o in outs):
        pytest.fail(f"not recovered and not refused:\n{lines}", pytrace=False)
    # 95 % over 40 starts (benchmarks/basin.py): here at most one of these starts may be refused
    if sum(o.accepted for o in outs) < len(outs) - (name != "door"):  # the door's three: all
        pytest.fail(f"more than one start not recovered:\n{lines}", pytrace=False)
