"""The machine a benchmark ran on, for the figures in the README."""

from __future__ import annotations

import os
import platform


def machine() -> str:
    """CPU model, logical CPU count and Python version."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}; {os.cpu_count()} logical cpus; python {platform.python_version()}"
