"""Workers that end with their batch: a pool worker watches the batch process and exits when it dies.

A local pool forks its workers from a fork server; the batch starts that server with this module
preloaded (`closedloop.fleet.batch.start_worker_server`), so every worker forked from it starts
`watch` on the batch's process id (environment variable `BATCH_PID`) before it runs anything.  A
worker's parent is the fork server, which itself lives as long as its workers hold its pipe, so the
parent-death signal (``prctl(PR_SET_PDEATHSIG)``) cannot be used: the watch is a daemon thread that
waits on a pidfd of the batch (Linux ``pidfd_open``; elsewhere it polls the pid every 0.2 s) and ends
the process with ``os._exit`` the moment the batch is gone, however it died (SIGKILL included).
"""

from __future__ import annotations

import os
import threading

#: environment variable holding the batch's process id (set by the batch for its fork server)
BATCH_PID = "CLOSEDLOOP_BATCH_PID"
_watching: list[int] = []


def watch(pid: int) -> None:
    """End this process (``os._exit(1)``) as soon as process `pid` has exited (once per process)."""
    if pid <= 0 or pid == os.getpid() or _watching:
        return
    _watching.append(pid)

    def wait() -> None:
        import select
        import time

        try:
            fd = os.pidfd_open(pid)
        except (AttributeError, OSError):
            fd = None
        if fd is not None:
            select.select([fd], [], [])
        else:  # pragma: no cover - no pidfd (non-Linux, old kernel)
            while True:
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    pass
                time.sleep(0.2)
        os._exit(1)

    try:
        os.kill(pid, 0)
    except ProcessLookupError:  # already gone before the watch started
        os._exit(1)
    except PermissionError:
        pass
    threading.Thread(target=wait, name="closedloop-batch-watch", daemon=True).start()


def _after_fork_in_child() -> None:
    _watching.clear()  # (a thread does not survive fork: a child starts its own watch)
    pid = int(os.environ.get(BATCH_PID, "0") or 0)
    if pid:
        watch(pid)


os.register_at_fork(after_in_child=_after_fork_in_child)
