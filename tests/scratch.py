"""Temporary folders of the test helpers (zoo cases, thesis examples, fuzzed files), removed at exit.

Every folder is made under one root per process, which is removed when the process ends: a zoo or basin
run writes thousands of cases, and the system's temporary folder is no place to leave them.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

_ROOT: list[Path] = []


def scratch_dir(prefix: str = "") -> Path:
    """A new empty folder under this process's scratch root (made on first use, removed at exit)."""
    if not _ROOT:
        _ROOT.append(Path(tempfile.mkdtemp(prefix="closedloop-tests-")))
        atexit.register(shutil.rmtree, _ROOT[0], True)
    return Path(tempfile.mkdtemp(prefix=prefix, dir=_ROOT[0]))
