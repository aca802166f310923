"""The command line's progress display: a `closedloop.progress.ProgressReporter` drawn with tqdm.

One bar on stderr for the task that runs (the solver's iterations with its cost, the k-fold refits, the
simulated configurations, a batch's jobs), replaced when another task starts and erased when the
display closes, so that no stale line stays above the summary.  Only on a terminal: nothing is drawn
(and tqdm is not even imported) when stderr is a file or a pipe (a log, CI) or with ``--quiet``.
"""

from __future__ import annotations

import sys
from typing import Any

#: what a task counts, shown after the count
UNITS = {"solving": " iterations", "validating": " folds", "simulating": " configurations"}


class ProgressDisplay:
    """``progress(task, done, total, note)`` drawn as a tqdm bar (module doc); `close` erases it.

    Use it as a context manager, or call `close` before printing to the terminal."""

    def __init__(self, quiet: bool = False, stream: Any = None, prefix: str = ""):
        self.stream = sys.stderr if stream is None else stream
        self.prefix = prefix
        self.shown = not quiet and bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar: Any = None
        self.task: str | None = None

    def __call__(self, task: str, done: int, total: int | None = None, note: str = "") -> None:
        if not self.shown:
            return
        if self.bar is None or task != self.task or total != self.bar.total or done < self.bar.n:
            self.close()
            self.bar = _bar(self.prefix + task, total, UNITS.get(task, ""), self.stream)
            self.task = task
        if note:
            self.bar.set_postfix_str(note, refresh=False)
        self.bar.update(done - self.bar.n)  # drawn at most every 0.1 s
        if total is not None and done >= total:
            self.close()  # the last one: erased now, before whatever is printed next

    def close(self) -> None:
        """Erase the bar (the summary says what was done)."""
        if self.bar is not None:
            self.bar.close()
            self.bar, self.task = None, None

    def __enter__(self) -> ProgressDisplay:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _bar(desc: str, total: int | None, unit: str, stream: Any):
    from tqdm import tqdm

    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: the command's own thread draws every update

    return Bar(total=total, desc=desc, unit=unit, file=stream, leave=False, dynamic_ncols=True, mininterval=0.1)
