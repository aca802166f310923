"""Exceptions raised by closedloop: one tree, rooted at `ClosedLoopError`.

    ClosedLoopError
    +-- InputError                 a user's mistake: the CLI prints its one line and exits with code 2
    |   +-- ModelError             the robot model (file, joint, frame); UnknownRobotError (also a KeyError)
    |   +-- LogError               a joint log
    |   +-- ParameterError         a parameter name or value
    |   +-- LoopError              a loop specification
    |   +-- OptionError            a library option's value (a method, a loss, a count); also a ValueError
    |   +-- ScenarioError          a simulation scenario, its settings or robot; also a ValueError
    |       +-- UnknownScenarioError   (also a KeyError)
    |       +-- SettingError           an unknown simulation setting (also a TypeError)
    +-- CalibrationError           the data or the solver cannot give a calibration (the CLI: exit 3)
    |   +-- NotIdentifiableError
    |   +-- ConvergenceError
    +-- SimulationError            the simulator cannot produce the data asked for (also a RuntimeError)
        +-- EmptySimulationError   no configuration recorded (`closedloop simulate`: exit 3, nothing written)

The classes that also derive from a builtin do so because callers (and the
tests) catch that builtin: ``simulate("nope")`` was a KeyError, an unknown
setting a TypeError, a bad option a ValueError; they still are.  Everything
else is a bug and is reported as such.
"""

from __future__ import annotations

from types import ModuleType


class ClosedLoopError(Exception):
    """Base class of every closedloop exception."""


class InputError(ClosedLoopError):
    """A user's input is wrong: the message names the file, row, joint or parameter."""


class ModelError(InputError):
    """The robot model cannot be loaded or does not support a request."""


class LogError(InputError):
    """A joint log is malformed (missing columns, NaN, too few rows)."""


class ParameterError(InputError):
    """A parameter name or value given by the user is wrong."""


class LoopError(InputError):
    """A loop specification is wrong (unknown frame, bad closure)."""


class _PlainMessage:
    """str() is the message itself (a KeyError's str() would quote it)."""

    def __str__(self) -> str:
        return Exception.__str__(self)  # type: ignore[arg-type]


class UnknownRobotError(_PlainMessage, ModelError, KeyError):
    """A built-in robot name that is not registered (`closedloop.assets.catalog.ROBOTS`)."""


class OptionError(InputError, ValueError):
    """A library function's option value is not one it knows (a method, a criterion, a loss, a count)."""


class ScenarioError(InputError, ValueError):
    """A simulation scenario is wrong: its loop, its robot's frames and joints, an argument to `simulate`."""


class UnknownScenarioError(_PlainMessage, ScenarioError, KeyError):
    """A scenario name that is not registered (`closedloop.sims.SCENARIOS`)."""


class SettingError(ScenarioError, TypeError):
    """A simulation setting that does not exist (`closedloop.sims.SimSettings`)."""


class CalibrationError(ClosedLoopError):
    """The data or the solver cannot give a calibration (a solver state, not a user's typo)."""


class NotIdentifiableError(CalibrationError):
    """Nothing can be identified from the data (immobile loop, no free parameter)."""


class ConvergenceError(CalibrationError):
    """The solver did not converge within its iteration budget."""


class SimulationError(ClosedLoopError, RuntimeError):
    """The simulator cannot produce the data asked for (a loop that does not close, a model MuJoCo lacks)."""


class EmptySimulationError(SimulationError):
    """The simulator recorded no configuration (the message says why and what to change)."""


#: The command line's exit codes: 0 done, 2 a user's input (`InputError`), 3 a failed calibration
#: (`CalibrationError` or a verdict 'failed'), 70 a bug, 130 interrupted, 141 the output's reader closed it.
EXIT_INPUT = 2
EXIT_FAILED = 3
EXIT_INTERNAL = 70
EXIT_PIPE = 141  # 128 + SIGPIPE (`closedloop ... | head`)


class MissingExtraError(InputError):
    """A feature needs an optional package that is not installed: one line naming the feature, the package
    and the install lines (for an installed closedloop, and from a checkout).  Raised by `require` only."""

    def __init__(self, feature: str, module: str, extra: str):
        self.feature, self.module, self.extra = feature, module, extra
        super().__init__(
            f"{feature}: needs {module.split('.')[0]}, which is not installed: "
            f'pip install "closedloop[{extra}]" (from a checkout: pip install ".[{extra}]")'
        )


def require(module: str, feature: str, extra: str) -> ModuleType:
    """`module` imported, for `feature` (an option, a command or an input file, as the user named it);
    refused with `MissingExtraError` when the optional package of `extra` (pyproject.toml) is not
    installed.  The one way the package refuses a missing optional package: called before any work where
    the need is known from the options, else where the package is first used.

    ``pip install "closedloop[{extra}]"`` works wherever closedloop is installed (pip keeps the installed
    closedloop and adds the extra's packages); a checkout's user may run ``pip install ".[{extra}]"``."""
    from importlib import import_module

    try:
        return import_module(module)
    except ImportError:  # not installed, or installed without a package of its own (pip repairs both)
        raise MissingExtraError(feature, module, extra) from None
