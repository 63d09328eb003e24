"""The logger interface DC code uses (satisfied by rclpy loggers and by :mod:`logging` loggers),
a logger safe for any caller, and once-per-burst logging of events that can repeat thousands of times a second.

rclpy remembers the severity each call site (the frame that called ``logger.warning`` …) used on a
logger, and raises ``ValueError: Logger severity cannot be changed between calls`` when that line
logs at another severity. A helper that logs for its callers (``BurstLog``, a callable passed as
``log=``) is one such line for all of them: the second severity raised, in whatever thread logged
it, and killed the buffer's writer. :class:`SeverityLogger` calls the logger it wraps from one line
per severity, so no caller can reach one line with two severities; DC's nodes hand out only
such loggers (``ManagedServer.get_logger``), and :class:`BurstLog` wraps whatever it is given.
rclpy's per-call-site filters (``once=``, ``throttle_duration_sec=``) would be shared by every
caller of a line: DC does not use them (a repeated event is a :class:`BurstLog`), and
:class:`SeverityLogger` does not accept them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

SEVERITIES = ("debug", "info", "warning", "error", "fatal")


class Logger(Protocol):
    def debug(self, message: str, /) -> Any: ...
    def info(self, message: str, /) -> Any: ...
    def warning(self, message: str, /) -> Any: ...
    def error(self, message: str, /) -> Any: ...


class SeverityLogger:
    """A logger (rclpy's, or any :class:`Logger`) called from one line per severity: safe for any caller.

    See the module documentation. Everything else (``name``, ``set_level``, ``is_enabled_for`` …)
    is the wrapped logger's; ``get_child`` gives a :class:`SeverityLogger` too.
    """

    def __init__(self, logger: Any) -> None:
        self.wrapped: Any = logger.wrapped if isinstance(logger, SeverityLogger) else logger

    # Each method calls the wrapped logger from a line of its own: rclpy keys its severity on it.
    def debug(self, message: str, /) -> None:
        self.wrapped.debug(message)

    def info(self, message: str, /) -> None:
        self.wrapped.info(message)

    def warning(self, message: str, /) -> None:
        self.wrapped.warning(message)

    def warn(self, message: str, /) -> None:
        self.wrapped.warning(message)

    def error(self, message: str, /) -> None:
        self.wrapped.error(message)

    def fatal(self, message: str, /) -> None:
        fatal = getattr(self.wrapped, "fatal", None) or self.wrapped.critical  # rclpy / logging
        fatal(message)

    def critical(self, message: str, /) -> None:
        self.fatal(message)

    def log_at(self, severity: str, message: str) -> None:
        """Log at a severity chosen at run time (one of :data:`SEVERITIES`)."""
        if severity not in SEVERITIES:
            raise ValueError(f"unknown severity {severity!r}, expected one of {', '.join(SEVERITIES)}")
        getattr(self, severity)(message)

    def get_child(self, name: str) -> SeverityLogger:
        return SeverityLogger(self.wrapped.get_child(name))

    def __getattr__(self, name: str) -> Any:
        if name == "wrapped":  # not set yet (a copy being made): never recurse
            raise AttributeError(name)
        return getattr(self.wrapped, name)


def one_line_per_severity(log: Callable[[str], Any]) -> Callable[[str], Any]:
    """``log`` made safe to call from one line whatever severity it logs at.

    A bound severity method of a logger (``logger.error``) becomes the same method of a
    :class:`SeverityLogger` around that logger; any other callable is returned as it is.
    """
    owner = getattr(log, "__self__", None)
    name = getattr(log, "__name__", "")
    if owner is None or isinstance(owner, SeverityLogger) or name not in (*SEVERITIES, "warn", "critical"):
        return log
    method: Callable[[str], Any] = getattr(SeverityLogger(owner), name)
    return method


class BurstLog:
    """Log the first event of a burst at once, then a summary when ``quiet`` seconds pass without one.

    While a burst lasts longer than ``interval``, a summary is also written every ``interval``
    seconds, so a drop that never stops stays visible. Call :meth:`tick` periodically. With
    ``each`` above 1, the first ``each`` events of a burst get a line of their own (their details
    differ: two malformed records are two different mistakes), the rest are counted.

    ``log`` is a logger's method (``logger.warning``); any number of burst logs at any severities
    may share one logger (:func:`one_line_per_severity`).
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
        self._log = one_line_per_severity(log)
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
