"""One explicit table of loop types: the parser, ``closedloop loops`` and the simulator read it.

A new loop type costs three things (docs/architecture/adding-a-loop-type.md): its module (a factory
registered with ``closedloop.loops.spec.register``), one entry in ``closedloop.loops.spec.LOOP_TYPES``
and its simulator class (registered with ``closedloop.sims.loop_types.simulates``).  The last test
adds a toy type in exactly those three places and runs it through the parser, ``closedloop loops``,
``simulate``, the ``calibrate`` command simulate prints, and ``check``.
"""

from __future__ import annotations

import json
import shlex
import sys

import pytest

from closedloop.cli.main import main
from closedloop.errors import LoopError
from closedloop.loops import spec


def test_every_table_entry_registers_its_type_in_its_module():
    types = spec.all_loop_types()
    assert list(types) == list(spec.LOOP_TYPES)
    for kind, (factory, keys) in types.items():
        assert factory.__module__ == "closedloop.loops" + spec.LOOP_TYPES[kind], kind
        assert "name" in keys and ("frame" in keys or kind == "camera"), (kind, keys)


def test_a_type_missing_from_the_table_cannot_register():
    with pytest.raises(LoopError, match="no entry in closedloop.loops.spec.LOOP_TYPES"):
        spec.register("spring", {"frame"})
    with pytest.raises(LoopError, match="unknown loop type 'spring' .known: camera, face, hinge,"):
        spec.parse_loop("spring:frame=tool0", None)


def test_loops_command_lists_the_whole_table(capsys):
    assert main(["loops"]) == 0
    out = capsys.readouterr().out
    listed = [ln for ln in out.splitlines() if ln and not ln.startswith((" ", "Frames", "Every loop"))]
    assert listed == sorted(spec.LOOP_TYPES)  # camera too (its module loads on first use)
    assert "Every loop type also takes: fixture, log, sigma_task" in out  # once, not per type
    assert all(ln.startswith("  syntax:  ") for ln in out.splitlines()[2::4])  # every type has its syntax line


def test_simulator_loop_types_are_table_entries():
    from closedloop.sims.loop_types import SIM_LOOPS

    assert set(SIM_LOOPS) <= set(spec.LOOP_TYPES) and all(v.kind == k for k, v in SIM_LOOPS.items())


#: the toy type's module: a weld to a world fixture under its own name (a real module would add its residual)
TOY_MODULE = '''
from closedloop.loops.spec import register
from closedloop.loops.weld import WeldLoop


class ToyLoop(WeldLoop):
    """The tool welded to an unknown world pose (a weld under another name)."""


@register("toy", {"frame"})
def toy(kw, robot):
    """toy:frame=tool  (the tool welded to an unknown world pose)"""
    return ToyLoop(kw.get("name", "toy"), kw["frame"])
'''


@pytest.fixture
def toy_type(tmp_path, monkeypatch):
    """The toy loop type in its three places, each restored after the test."""
    from closedloop.sims import loop_types

    (tmp_path / "toy_loop.py").write_text(TOY_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(spec, "REGISTRY", dict(spec.REGISTRY))  # the factories of the loaded modules
    monkeypatch.setitem(spec.LOOP_TYPES, "toy", "toy_loop")  # 1. the registry entry (2. is its module)
    monkeypatch.setitem(loop_types.SIM_LOOPS, "toy", None)

    @loop_types.simulates("toy")  # 3. its simulator class: MuJoCo closes it as a weld to a world fixture
    class ToySim(loop_types.WeldSim):
        default_name = "toy"

        def core_loop(self, sc, nominal_path=None, sigma_t=None):
            from toy_loop import ToyLoop

            return ToyLoop(sc.loop_name, sc.tool_frame)

    yield ToySim
    sys.modules.pop("toy_loop", None)


def test_a_new_loop_type_costs_its_module_its_entry_and_its_simulator_class(toy_type, tmp_path, capsys):
    from closedloop.assets.catalog import ROBOTS, nominal_urdf
    from closedloop.model.robot import RobotModel
    from closedloop.sims.loop_types import sim_loop

    # the parser (its module loads on first use) and `closedloop loops`
    (tmp_path / "panda.urdf").write_text(nominal_urdf("panda"))
    loop = spec.parse_loop("toy:frame=panda_hand,name=grip", RobotModel.from_file(tmp_path / "panda.urdf"))
    assert type(loop).__name__ == "ToyLoop" and (loop.name, loop.frame_a) == ("grip", "panda_hand")
    assert main(["loops"]) == 0
    out = capsys.readouterr().out
    assert "toy\n  keys:    frame, name\n  syntax:  toy:frame=tool" in out
    # the simulator: a robot file closed by the toy loop, then the commands it prints
    assert isinstance(sim_loop("toy"), toy_type)
    sim = tmp_path / "sim"
    robot = str(ROBOTS["panda"].path)
    assert main(["simulate", "--robot", robot, "--loop", "toy:frame=panda_hand", "--n", "40", "--out", str(sim)]) == 0
    lines = capsys.readouterr().out.splitlines()
    truth = json.loads((sim / "truth.json").read_text())
    assert truth["loop"]["type"] == "toy" and truth["loop"]["calibrate"] == "toy:frame=panda_hand,name=toy"
    assert any(n.startswith("panda_joint2.") for n in truth["parameters"])  # the truth drawn on the toy's loop
    calibrate = next(ln for ln in lines if ln.strip().startswith("calibrate:")).split(":", 1)[1]
    check = next(ln for ln in lines if ln.strip().startswith("check:")).split(":", 1)[1]
    assert main(shlex.split(calibrate)[1:] + ["--quiet"]) == 0
    assert main(shlex.split(check)[1:]) == 0  # every compared parameter within 1 mm / 5 mrad
    assert " 0 outside" in capsys.readouterr().out
