"""Local servers DC's storage destinations deliver to — PostgreSQL, an S3-compatible store (SeaweedFS),
InfluxDB — started on loopback for trying DC and its demos (`dc servers start`) and by the tests.

Each server is a :class:`LocalServer`: ``start()`` returns once it answers (a readiness probe, never a
fixed sleep) or raises :class:`ServerError` with the end of its log; ``stop()`` sends SIGTERM, then
SIGKILL. A server keeps its data, log and pid under its own state folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from dc_core.errors import DcError


class ServerError(DcError):
    """A local server that is not installed, cannot start, or did not become ready."""


class LocalServer(Protocol):
    name: str
    state_dir: Path
    port: int

    def start(self, timeout: float = 30.0) -> None:
        """Start (initialising the state folder the first time) and wait until it answers."""

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout`` s; nothing when not running."""

    def running(self) -> bool: ...

    def settings(self) -> dict[str, str | int]:
        """What a destination's parameters need to reach it (host, port, user, password, bucket…)."""
