"""Test doubles shared by the test modules."""

from __future__ import annotations

from typing import Any


class RecordingLogger:
    """A dc_core.logs.Logger that keeps (level, message) pairs for assertions."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def debug(self, message: str, /, **kwargs: Any) -> None:
        self.lines.append(("debug", message))

    def info(self, message: str, /, **kwargs: Any) -> None:
        self.lines.append(("info", message))

    def warning(self, message: str, /, **kwargs: Any) -> None:
        self.lines.append(("warning", message))

    def error(self, message: str, /, **kwargs: Any) -> None:
        self.lines.append(("error", message))

    def at(self, level: str) -> list[str]:
        return [m for lvl, m in self.lines if lvl == level]
