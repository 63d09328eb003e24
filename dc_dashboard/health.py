"""DC's own health as its servers report it: GET /api/v1/metrics of each configured server."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import Any


@dataclass
class ServerHealth:
    label: str
    url: str
    error: str = ""
    destinations: dict[str, dict[str, Any]] = field(default_factory=dict)
    buffer: dict[str, Any] = field(default_factory=dict)
    # The disk budget's saved files per measurement (dc_destinations.saved_files); empty without a budget.
    saved_files: dict[str, Any] = field(default_factory=dict)

    @property
    def pending(self) -> int:
        return sum(int(d.get("buffered") or 0) for d in self.destinations.values()) + int(
            self.buffer.get("intake_pending") or 0
        )

    @property
    def dead_letters(self) -> int:
        return sum(int(d.get("dead_letters") or 0) for d in self.destinations.values())

    @property
    def last_delivery(self) -> float | None:
        """The newest ``last_delivery`` of its destinations (Unix time), None before any."""
        times = [float(t) for d in self.destinations.values() if isinstance(t := d.get("last_delivery"), int | float)]
        return max(times, default=None)


def read(label: str, url: str, timeout: float = 3.0) -> ServerHealth:
    health = ServerHealth(label, url)
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            document = json.loads(response.read(4 * 1024 * 1024))
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc
        health.error = f"cannot read {url}: {reason} (is the server active, with its HTTP server on?)"
        return health
    if not isinstance(document, dict):
        health.error = f"{url} did not answer with DC's metrics"
        return health
    destinations = document.get("destinations")
    if isinstance(destinations, dict):
        health.destinations = {k: v for k, v in destinations.items() if isinstance(v, dict)}
    buffer = document.get("buffer")
    if isinstance(buffer, dict):
        health.buffer = buffer
    saved = document.get("saved_files")
    if isinstance(saved, dict):
        health.saved_files = saved
    if not health.destinations and not health.buffer:
        health.error = f"{url} answered, but not as a destination server (no destinations in its metrics)"
    return health
