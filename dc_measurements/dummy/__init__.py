"""Dummy measurement: publishes a configured JSON record."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from dc_core.errors import ConfigError
from dc_core.measurement import Measurement
from dc_core.params import param


@dataclass(frozen=True, kw_only=True)
class DummyParams:
    record: str = param('{"message": "Hello from ROS 2 DC"}', doc="JSON object published at every poll")

    def __post_init__(self) -> None:
        try:
            parsed = json.loads(self.record)
        except json.JSONDecodeError as exc:
            raise ConfigError("record", f"not valid JSON: {exc}") from exc
        if not isinstance(parsed, dict):
            raise ConfigError("record", "expected a JSON object")


class Dummy(Measurement[DummyParams]):
    """A fixed JSON record, for trying pipelines and destinations."""

    def on_configure(self) -> None:
        self._record: dict[str, Any] = json.loads(self.params.record)

    def collect(self) -> dict[str, Any] | None:
        return dict(self._record)
