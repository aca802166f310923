"""Exceptions raised by closedloop.

`InputError` marks a user's mistake (a bad file, an unknown joint, a NaN in a
log row): the CLI prints its one-line message and exits with code 2.
Everything else is a bug or a numerical failure and is reported as such.
"""

from __future__ import annotations


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


class NotIdentifiableError(ClosedLoopError):
    """Nothing can be identified from the data (immobile loop, no free parameter)."""


class ConvergenceError(ClosedLoopError):
    """The solver did not converge within its iteration budget."""
