"""Thesis 2.5: the planar 3-DOF arm with its tip pinned to the ground, linear vs general solver."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location(
    "planar_ground_contact", Path(__file__).resolve().parents[1] / "examples" / "planar_ground_contact.py"
)
planar = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(planar)

TRUTH = np.array([1.05, 0.75, 0.65])


def test_data_close_the_loop():
    theta = planar.closure_data(TRUTH, 1.0, np.linspace(1.8, 2.9, 25))
    C, y = planar.linear_system(theta)
    assert np.abs(C @ TRUTH + y).max() < 1e-12  # eqs. (2.1)-(2.2)


def test_linear_and_general_solutions_agree():
    theta = planar.closure_data(TRUTH, 1.0, np.linspace(1.8, 2.9, 25))
    a_lin = planar.linear_solution(theta)
    a_gen, res = planar.general_solution(theta)
    assert np.abs(a_lin - TRUTH).max() < 1e-10
    assert np.abs(a_gen - a_lin).max() < 1e-8
    assert [res.fit.status[res.fit.names.index(n)] for n in ("joint2.x", "joint3.x", "ground.tip_x")] == [
        "estimated"
    ] * 3
    assert not res.identifiability.dropped and not res.identifiability.weak
    assert not any("length scale" in n for n in res.notes)  # a4 = 1 (the known ground point) sets it


def test_other_elbow_branch_and_scale():
    """The other assembly mode, a different ground link: still the same answer."""
    truth = np.array([1.2, 0.9, 0.5])
    theta = planar.closure_data(truth * 2.0, 2.0, np.linspace(1.9, 2.8, 15), elbow=-1.0)
    a_lin = planar.linear_solution(theta, a4=2.0)
    a_gen, _ = planar.general_solution(theta, a4=2.0)
    assert np.abs(a_lin - 2 * truth).max() < 1e-10
    assert np.abs(a_gen - a_lin).max() < 1e-8


def test_parallelogram_singularity_4():
    """a1 = a3, a2 = a4: opposite sides stay parallel; only a1 - a3 is determined.

    The structural reduction is decided at the start, on the data projected
    onto the NOMINAL model's closure manifold, which is not a parallelogram;
    re-checked at the solution, which is one, the dependency is structural
    there: a1 is dropped, absorbed by the tip (a1 + a3 free), and the problem
    re-solved (Singularity 4 is a property of the mechanism, not of the start).
    """
    a_par, theta = planar.parallelogram_data(0.7, 1.0, np.linspace(0.3, 1.3, 25))
    C, y = planar.linear_system(theta)
    S = np.linalg.svd(C, compute_uv=False)
    assert S[-1] < 1e-12 * S[0]  # columns of C dependent: cos(phi3) = -cos(phi1)
    a_gen, res = planar.general_solution(theta)
    dropped = {d.name: d for d in res.identifiability.dropped}
    assert set(dropped) == {"joint2.x"}
    assert dict(dropped["joint2.x"].absorbed_into) == pytest.approx({"ground.tip_x": -1.0})
    assert any("re-checked at the solution" in n for n in res.notes)
    assert res.fit.status[res.fit.names.index("joint2.x")] == "dropped"
    assert res.fit.status[res.fit.names.index("joint3.x")] == "estimated"
    assert abs(a_gen[1] - a_par[1]) < 1e-8  # a2 = a4
    assert abs((a_gen[0] - a_gen[2]) - (a_par[0] - a_par[2])) < 1e-8  # the determined difference
