"""Storage measurement: space left on the file system holding a directory."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError, PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param
from dc_core.paths import expand_env


@dataclass(frozen=True, kw_only=True)
class StorageParams:
    path: str = param(doc="Directory whose file system is measured ($ENV expanded)")


class Storage(Measurement[StorageParams]):
    """Free space (available to unprivileged users) and capacity of the file system holding `path`."""

    def __init__(self, context: MeasurementContext, params: StorageParams) -> None:
        super().__init__(context, params)
        self.path = ""
        self._missing_reported = False

    def on_configure(self) -> None:
        try:
            self.path = expand_env(self.params.path)
        except ConfigError as exc:
            raise PluginError(f"{self.context.name}: path: {exc.message}") from exc
        if not os.path.exists(self.path):
            raise PluginError(f"{self.context.name}: path {self.path!r} does not exist")

    def collect(self) -> dict[str, Any] | None:
        try:
            fs = os.statvfs(self.path)
        except OSError as exc:
            # A removable drive may come back: say it once, publish nothing meanwhile.
            if not self._missing_reported:
                self.context.logger.warning(f"{self.context.name}: cannot stat {self.path}: {exc.strerror}")
                self._missing_reported = True
            return None
        self._missing_reported = False
        capacity = fs.f_blocks * fs.f_frsize
        # f_bavail, not f_bfree: blocks reserved for root are not usable by the robot's software.
        free = fs.f_bavail * fs.f_frsize
        free_percent = free / capacity * 100.0 if capacity else 0.0
        return {"free_percent": round(free_percent, 2), "free": free, "capacity": capacity}
