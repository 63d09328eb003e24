"""OS measurement: distribution, kernel release, logical CPU count and installed memory."""

from __future__ import annotations

import os
import platform
from typing import Any

import psutil

from dc_core.measurement import Measurement
from dc_core.params import NoParams

_GIB = 1024**3


def distribution_name() -> str:
    """PRETTY_NAME of os-release, or the system name when the file is missing."""
    try:
        release = platform.freedesktop_os_release()
    except OSError:
        return platform.system()
    return release.get("PRETTY_NAME") or release.get("NAME") or platform.system()


class OperatingSystem(Measurement[NoParams]):
    """Operating system name, kernel release, number of CPUs and total memory (GiB)."""

    def collect(self) -> dict[str, Any]:
        return {
            "os": distribution_name(),
            "kernel": platform.release(),
            "cpus": os.cpu_count() or 0,
            "memory": round(psutil.virtual_memory().total / _GIB, 2),
        }
