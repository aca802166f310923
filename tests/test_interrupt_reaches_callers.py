"""A real Ctrl-C or SIGTERM during an in-process `main()` stops its caller too (a script, a test run).

`main(argv)` prints its one line and cleans up; when the interrupt was a signal (not a KeyboardInterrupt
raised by code, which is answered with exit 130 as from the command line), it re-raises, so that
pytest stops the run instead of reporting a failed test and going on.
"""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

# the caller: main() on a simulation of NCONF configurations, reporting whether the interrupt reached it
CALLER = """
try:
    rc = main(["simulate", "panda_weld", "--n", "NCONF", "--out", sys.argv[1]])
except KeyboardInterrupt:
    print("caller interrupted")
    sys.exit(99)
print("main returned", rc)
"""

# the signal is sent once the simulation drives the robot (its mark, `closedloop.io.marker`), never after a fixed
# time a faster or slower machine outruns; a mark that never comes ends the child with 98
SCRIPT = """
import os, signal, sys, threading, time
from pathlib import Path
from closedloop.cli.main import main
from closedloop.io.marker import RUNNING_MARKER

marker = Path(sys.argv[1] + ".running")
os.environ[RUNNING_MARKER] = str(marker)

def fire():
    t0 = time.monotonic()
    while not (marker.exists() and "simulate" in marker.read_text().split()):
        if time.monotonic() - t0 > 300:
            os._exit(98)
        time.sleep(0.002)
    os.kill(os.getpid(), signal.{sig})

threading.Thread(target=fire, daemon=True).start()
""" + CALLER.replace("NCONF", "2000")


def _default_sigint() -> None:
    """In the child before exec: SIGINT's default disposition and unblocked (a test worker may ignore or block
    it, and both are inherited across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_during_main_reaches_the_caller(tmp_path, sig):
    p = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(sig=sig), str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=300,
        # a child of a process that ignores SIGINT inherits that: give it SIGINT's default disposition
        preexec_fn=_default_sigint,
    )
    assert p.returncode == 99 and "caller interrupted" in p.stdout, (p.stdout, p.stderr)
    assert "interrupted" in p.stderr.splitlines()[-1] or "interrupted" in p.stderr
    assert not (tmp_path / "out").exists()  # nothing published


def test_a_keyboard_interrupt_raised_by_code_is_an_exit_code(tmp_path, monkeypatch, capsys):
    """No signal: `main` answers 130 as the command line does (the caller goes on)."""
    import closedloop.sims
    from closedloop.cli.main import main

    def interrupt(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(closedloop.sims, "simulate", interrupt)
    assert main(["simulate", "panda_weld", "--n", "2", "--out", str(tmp_path / "o")]) == 130
    assert "interrupted" in capsys.readouterr().err


SWALLOW = """
import os, signal, sys, time
import closedloop.sims
from closedloop.cli.main import main

real = closedloop.sims.simulate

def swallowing(*a, **k):  # a library that catches everything, the interrupt too, and goes on
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)
    except BaseException:
        pass
    return real(*a, **k)

closedloop.sims.simulate = swallowing
""" + CALLER.replace("NCONF", "5")


def test_an_interrupt_a_library_swallowed_still_publishes_nothing(tmp_path):
    """The command ran on after its interrupt was caught inside a library: nothing is published and the
    caller is stopped all the same."""
    p = subprocess.run(
        [sys.executable, "-c", SWALLOW, str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_default_sigint,
    )
    assert p.returncode == 99 and "caller interrupted" in p.stdout, (p.stdout, p.stderr)
    assert "interrupted" in p.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
