"""Memory measurement: share of RAM in use, counting reclaimable page cache as free."""

from __future__ import annotations

from typing import Any

import psutil

from dc_core.measurement import Measurement
from dc_core.params import NoParams


class Memory(Measurement[NoParams]):
    """System memory used, in percent of total RAM (from available memory)."""

    def collect(self) -> dict[str, Any]:
        memory = psutil.virtual_memory()
        # MemAvailable, not MemFree: page cache and reclaimable slab are free for applications,
        # so counting them as used (as the original did) reports a nearly full machine.
        used = (memory.total - memory.available) / memory.total * 100.0
        return {"used": round(used, 2)}
