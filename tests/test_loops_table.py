"""One explicit table of loop types: the parser, ``closedloop loops`` and the simulator read it."""

from __future__ import annotations

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
    with pytest.raises(LoopError, match="unknown loop type 'spring' .known: camera, hinge,"):
        spec.parse_loop("spring:frame=tool0", None)


def test_loops_command_lists_the_whole_table(capsys):
    assert main(["loops"]) == 0
    out = capsys.readouterr().out
    listed = [ln for ln in out.splitlines() if ln and not ln.startswith((" ", "Frames", "Every loop"))]
    assert listed == sorted(spec.LOOP_TYPES)  # camera too (its module loads on first use)
    assert "Every loop type also takes: fixture, log, sigma_task" in out  # once, not per type
    assert all(ln.startswith("  syntax:  ") for ln in out.splitlines()[2::4])  # every type has its syntax line


def test_simulator_loop_types_are_table_entries():
    from closedloop.sims.loop_types import SIM_LOOP_NAMES, SIM_LOOPS

    assert set(SIM_LOOPS) <= set(spec.LOOP_TYPES)
    assert all(v in spec.LOOP_TYPES for v in SIM_LOOP_NAMES.values())
