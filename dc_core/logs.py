"""The logger interface DC code uses (satisfied by rclpy loggers and by :mod:`logging` loggers),
and once-per-burst logging of events that can repeat thousands of times a second."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol


class Logger(Protocol):
    def debug(self, message: str, /, **kwargs: Any) -> Any: ...
    def info(self, message: str, /, **kwargs: Any) -> Any: ...
    def warning(self, message: str, /, **kwargs: Any) -> Any: ...
    def error(self, message: str, /, **kwargs: Any) -> Any: ...


class BurstLog:
    """Log the first event of a burst at once, then a summary when ``quiet`` seconds pass without one.

    While a burst lasts longer than ``interval``, a summary is also written every ``interval``
    seconds, so a drop that never stops stays visible. Call :meth:`tick` periodically. With
    ``each`` above 1, the first ``each`` events of a burst get a line of their own (their details
    differ: two malformed records are two different mistakes), the rest are counted.
    """

    def __init__(
        self,
        log: Callable[[str], Any],
        what: str,
        *,
        quiet: float = 5.0,
        interval: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
        each: int = 1,
    ) -> None:
        self._log = log
        self._each = each
        self._logged_in_burst = 0
        self._what = what
        self._quiet = quiet
        self._interval = interval
        self._clock = clock
        self._lock = threading.Lock()
        self._pending = 0
        self._last_detail = ""
        self._burst_start: float | None = None
        self._last_event = 0.0
        self._last_summary = 0.0

    def event(self, count: int, detail: str) -> bool:
        """Count ``count`` events; True when this call logged a line of its own."""
        now = self._clock()
        message = None
        with self._lock:
            if self._burst_start is None:
                self._burst_start = self._last_summary = now
                self._logged_in_burst = 0
            if self._logged_in_burst < self._each:
                self._logged_in_burst += 1
                message = f"{self._what}: {count} ({detail})"
            else:
                self._pending += count
                self._last_detail = detail
            self._last_event = now
        if message is not None:
            self._log(message)
        self.tick()
        return message is not None

    def tick(self) -> None:
        now = self._clock()
        message = None
        with self._lock:
            if self._burst_start is None:
                return
            ended = now - self._last_event >= self._quiet
            if self._pending and (ended or now - self._last_summary >= self._interval):
                message = (
                    f"{self._what}: {self._pending} more in the last {now - self._last_summary:.0f} s"
                    f" (latest: {self._last_detail})"
                )
                self._pending = 0
                self._last_summary = now
            if ended:
                self._burst_start = None
        if message is not None:
            self._log(message)
