"""Uptime measurement."""

from __future__ import annotations

from typing import Any

from dc_core.measurement import Measurement
from dc_core.params import NoParams

PROC_UPTIME = "/proc/uptime"


class Uptime(Measurement[NoParams]):
    """Seconds since the system booted (integer, from /proc/uptime)."""

    def collect(self) -> dict[str, Any] | None:
        with open(PROC_UPTIME) as f:
            return {"time": int(float(f.read().split()[0]))}
