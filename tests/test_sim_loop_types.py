"""The simulator's loop types (`closedloop.sims.loop_types.SIM_LOOPS`): registered under the names of the one
loop registry (`closedloop.loops.spec.LOOP_TYPES`), read by the scenario parser with the vocabulary of
``calibrate --loop``, and each type's nominal residual has the Jacobian it claims."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from closedloop.assets.catalog import ROBOTS, nominal_urdf
from closedloop.errors import InputError, LoopError, ScenarioError
from closedloop.loops.spec import LOOP_TYPES, parse_loop
from closedloop.sims import SCENARIOS
from closedloop.sims.driver import NominalLoop
from closedloop.sims.loop_types import SIM_LOOPS, sim_loop, simulated_types, simulates
from closedloop.sims.scenario_files import parse_sim_loop

SIMULATED = "hinge, measured_point, plane, point, weld"


def test_simulator_types_are_registry_types():
    assert set(SIM_LOOPS) == {"weld", "point", "hinge", "plane", "measured_point"} and set(SIM_LOOPS) <= set(LOOP_TYPES)
    assert all(SIM_LOOPS[k].kind == k for k in SIM_LOOPS) and simulated_types() == SIMULATED.split(", ")
    assert {k: v.constraints for k, v in SIM_LOOPS.items()} == {
        "weld": 6,
        "hinge": 5,
        "point": 3,
        "plane": 1,
        "measured_point": 0,
    }
    with pytest.raises(LoopError, match="'spring' has no entry in closedloop.loops.spec.LOOP_TYPES"):
        simulates("spring")
    # a registry type the simulator lacks: one line naming the simulated types
    with pytest.raises(ScenarioError) as info:
        sim_loop("camera")
    assert str(info.value) == f"the simulator has no 'camera' loop (it simulates: {SIMULATED})"
    assert isinstance(info.value, InputError) and "\n" not in str(info.value)


def test_simulate_and_calibrate_take_the_same_loop_types():
    """Every registry type calibrate parses is either simulated or refused by name; an unknown one (``door``)
    is refused by both, with calibrate's message."""
    for kind in LOOP_TYPES:
        if kind in SIM_LOOPS:
            assert parse_sim_loop(f"{kind}:frame=t")[0] == kind
        else:
            with pytest.raises(InputError, match=f"the simulator has no '{kind}' loop .it simulates: {SIMULATED}.$"):
                parse_sim_loop(f"{kind}:frame=t")
    with pytest.raises(LoopError) as core:
        parse_loop("door:frame=tool0", None)
    with pytest.raises(InputError) as sim:
        parse_sim_loop("door:frame=tool0")
    assert str(sim.value) == f"{core.value}; the simulator simulates: {SIMULATED}"
    for spec, expected in (
        ("weld:frame=t", ("weld", "t", None, "fixture")),
        ("hinge:frame=t", ("hinge", "t", None, "door")),
        ("point:frame=t", ("point", "t", None, "socket")),
        ("plane:frame=t,name=p", ("plane", "t", None, "p")),
        ("weld:frame=t,to=u", ("weld", "t", "u", "fixture")),
    ):
        assert parse_sim_loop(spec) == expected
    with pytest.raises(InputError, match="only a weld closes two chains"):
        parse_sim_loop("point:frame=t,to=u")


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_core_loop_is_the_scenarios_loop_type(name, tmp_path):
    sc = SCENARIOS[name]
    path = tmp_path / "nominal.urdf"
    path.write_text(nominal_urdf(sc.robot))
    loop = SIM_LOOPS[sc.loop_type].core_loop(sc, path)
    core = {
        "weld": "WeldLoop",
        "point": "PointLoop",
        "hinge": "HingeLoop",
        "plane": "PlaneLoop",
        "measured_point": "MeasuredPointLoop",
    }[sc.loop_type]
    assert type(loop).__name__ == core and loop.name == sc.loop_name and loop.frame_a == sc.tool_frame


@pytest.mark.parametrize("kind", ["weld", "point", "hinge", "plane"])
def test_nominal_residual_jacobian_matches_finite_differences(kind):
    """e(q) is zero at the grasp and de/dq (`SimLoop.nominal_residual`) is its derivative (central differences)."""
    model = pin.buildModelFromXML(nominal_urdf("ur5"))
    tool = [f.name for f in model.frames][-1]
    r0 = np.array([0.1, -1.2, 1.4, -1.6, -1.5, 0.3])[: model.nq]
    data = model.createData()
    pin.framesForwardKinematics(model, data, r0)
    oMt = data.oMf[model.getFrameId(tool)]
    hinge = pin.SE3(np.eye(3), oMt.translation + np.array([0.3, 0.1, 0.0])) if kind == "hinge" else None
    normal = np.array([0.2, -0.1, 1.0]) if kind == "plane" else None
    loop = NominalLoop(model, tool, kind, r0, hinge=hinge, normal=normal)
    q0 = loop.full_q(r0)
    e0, _ = loop.residual(q0)
    assert e0.shape == (SIM_LOOPS[kind].residual_rows,) == (loop.n_constraints,)
    assert np.abs(e0).max() < 1e-12
    q = q0 + np.random.default_rng(0).uniform(-0.2, 0.2, q0.size)
    _, J = loop.residual(q)
    h = 1e-6
    fd = np.column_stack(
        [(loop.residual(q + h * d)[0] - loop.residual(q - h * d)[0]) / (2 * h) for d in np.eye(q.size)]
    )
    assert np.abs(fd - J).max() < 1e-6


def test_measured_point_has_no_nominal_loop():
    model = pin.buildModelFromXML(nominal_urdf("ur5"))
    assert "ur5" in ROBOTS and not SIM_LOOPS["measured_point"].closed
    with pytest.raises(ScenarioError, match="no nominal loop"):
        NominalLoop(model, [f.name for f in model.frames][-1], "measured_point", np.zeros(model.nq))
