"""How long work tells how far it has come: `ProgressReporter`, a callable that the library calls and the
command line's display (`closedloop.cli.progress`) implements.

The library never draws progress itself: the calibration's solver, the k-fold refits, the simulator and
the executor's jobs call ``progress(task, done, total, note)`` as they advance, and nothing when no
reporter is given.  A reporter is any callable of that shape (a function, a lambda, an object with
``__call__``); it must return quickly and never raise.
"""

from __future__ import annotations

from typing import Protocol


class ProgressReporter(Protocol):
    """``progress(task, done, total=None, note="")``, called as work advances.

    * `task`: what runs, a short lower-case phrase (``"solving"``, ``"validating"``, ``"simulating"``,
      ``"batch"``); a new task, or `done` going back, starts a new count;
    * `done`: units finished so far (iterations, folds, configurations, jobs);
    * `total`: how many there will be, None when not known beforehand (an iterative solve);
    * `note`: a short status that is no count (``"cost 1.2e-03"``, ``"4 ok, 1 failed, 2 running"``).
    """

    def __call__(self, task: str, done: int, total: int | None = None, note: str = "") -> None: ...
