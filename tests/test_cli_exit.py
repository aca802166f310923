"""The program's own process: numerical libraries started as the calibration wants them unless the user set
otherwise, and an end without the interpreter's teardown, except under a profiler, which writes at exit."""

from __future__ import annotations

import os
import subprocess
import sys

DEFAULTS = "import os, closedloop.cli.main as m; m._numerical_defaults(); print(os.environ.get('{}'))"


def _run(code: str, **env: str) -> str:
    clean = {
        k: v
        for k, v in os.environ.items()
        if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "GOTO_NUM_THREADS", "NUMPY_MADVISE_HUGEPAGE")
    }
    return subprocess.run(
        [sys.executable, "-c", code], env=clean | env, capture_output=True, text=True, check=True
    ).stdout.strip()


def test_openblas_one_thread_and_no_huge_pages_unless_the_user_set_them():
    assert _run(DEFAULTS.format("OPENBLAS_NUM_THREADS")) == "1"
    assert _run(DEFAULTS.format("NUMPY_MADVISE_HUGEPAGE")) == "0"
    assert _run(DEFAULTS.format("OPENBLAS_NUM_THREADS"), OMP_NUM_THREADS="3") == "None"  # a count the user set
    assert _run(DEFAULTS.format("OPENBLAS_NUM_THREADS"), OPENBLAS_NUM_THREADS="2") == "2"
    assert _run(DEFAULTS.format("NUMPY_MADVISE_HUGEPAGE"), NUMPY_MADVISE_HUGEPAGE="1") == "1"


def test_the_program_ends_with_its_code_and_a_profiler_still_writes(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "closedloop.cli", "calibrate", "--help"], capture_output=True, text=True
    )
    assert run.returncode == 0 and "usage: closedloop calibrate" in run.stdout
    bad = subprocess.run(
        [sys.executable, "-m", "closedloop.cli", "calibrate", "none.urdf", "none.csv"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert bad.returncode == 2 and bad.stderr.startswith("error:"), bad.stderr
    out = tmp_path / "profile.out"
    prof = subprocess.run(
        [sys.executable, "-m", "cProfile", "-o", str(out), "-m", "closedloop.cli", "calibrate", "--help"],
        capture_output=True,
        text=True,
    )
    assert prof.returncode == 0 and out.stat().st_size > 0, prof.stderr
