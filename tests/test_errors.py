"""The exception tree (`closedloop.errors`): user mistakes are `InputError`s that still are the builtins
callers catch, solver states are `CalibrationError`s; the CLI maps them to exit 2 and 3, one line each."""

from __future__ import annotations

import pytest

from closedloop import errors
from closedloop.cli.main import main


def test_tree_and_builtin_compatibility(tmp_path):
    from closedloop.assets.catalog import nominal_urdf
    from closedloop.estimate.robust import default_c
    from closedloop.sims import simulate

    with pytest.raises(errors.UnknownScenarioError) as info:
        simulate("nope", 2, 0, tmp_path)
    exc = info.value
    assert isinstance(exc, KeyError) and isinstance(exc, errors.InputError)
    assert str(exc).startswith("unknown scenario 'nope'")  # not quoted as a KeyError's message would be
    with pytest.raises(errors.SettingError) as info:
        simulate("ur5_socket", 2, 0, tmp_path, no_such_setting=1)
    assert isinstance(info.value, TypeError) and "no_such_setting" in str(info.value)
    with pytest.raises(errors.UnknownRobotError, match="unknown robot 'nope'") as info:
        nominal_urdf("nope")
    assert isinstance(info.value, KeyError) and isinstance(info.value, errors.ModelError)
    with pytest.raises(errors.OptionError, match="not 'l1'") as info:
        default_c("l1", 3)
    assert isinstance(info.value, ValueError)
    for cls in (errors.NotIdentifiableError, errors.ConvergenceError):
        assert issubclass(cls, errors.CalibrationError) and not issubclass(cls, errors.InputError)
    assert issubclass(errors.SimulationError, RuntimeError) and issubclass(
        errors.SimulationError, errors.ClosedLoopError
    )


@pytest.mark.parametrize(
    "exc, code",
    [
        (errors.NotIdentifiableError("nothing moves"), 3),
        (errors.ConvergenceError("no convergence in 3 iterations"), 3),
        (errors.ScenarioError("bad scenario"), 2),
        (errors.SimulationError("the hand does not close"), 2),
    ],
)
def test_cli_exit_codes(monkeypatch, capsys, exc, code):
    import closedloop.cli.main as cli

    def boom(args):
        raise exc

    monkeypatch.setattr(cli, "cmd_inspect", boom)
    assert main(["inspect", "x.urdf"]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(exc) in err[0]
