"""A file a supervising process can wait for: the work of a command has started.

A program that stops a run (a test sending SIGTERM, a job scheduler's wrapper, a watchdog) needs to know
when the work is under way, not guess it with a sleep that a slower or busier machine outruns.  Where the
environment variable ``CLOSEDLOOP_RUNNING_MARKER`` names a file, :func:`mark_running` appends one line to
it at each defined point of a run:

* ``calibrate``: a calibration starts its fit (every call of `calibration.pipeline.calibrate`: the
  command's fit, each held-out fold's refit, each job of a batch, in whichever process runs it);
* ``simulate``: a simulation has built its scene and starts to drive the robot through the configurations.

The file is opened for appending (one ``write`` of one short line per mark, so the lines of several worker
processes do not mix) and is never removed or truncated.  Without the variable nothing is written.
"""

from __future__ import annotations

import os

RUNNING_MARKER = "CLOSEDLOOP_RUNNING_MARKER"


def mark_running(what: str) -> None:
    """Append the line `what` to the file named by ``CLOSEDLOOP_RUNNING_MARKER``, if it is set (module doc)."""
    path = os.environ.get(RUNNING_MARKER)
    if not path:
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        os.write(fd, f"{what}\n".encode())
    finally:
        os.close(fd)
