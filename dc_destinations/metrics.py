"""Per-destination delivery counters and once-per-burst logging of repeated events.

Counters are since the pipeline started (the database keeps lifetime totals for ``dc status``).
A notable event (record dropped, send failed) increments its counter and goes through a
:class:`BurstLog` in the same place, so a flood of drops is one log line when it starts and one
summary when it ends, never one line per record.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

COUNTERS = ("received", "sent", "retried", "failed", "dropped", "dead_lettered", "dead_letters_dropped")


@dataclass
class _Counts:
    received: int = 0
    sent: int = 0
    retried: int = 0
    failed: int = 0
    dropped: int = 0
    dead_lettered: int = 0
    dead_letters_dropped: int = 0


class DestinationMetrics:
    """Thread-safe counters of one destination."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = _Counts()
        self.last_error = ""
        self.last_error_time: float | None = None

    def add(self, counter: str, n: int = 1) -> None:
        if n:
            with self._lock:
                setattr(self._counts, counter, getattr(self._counts, counter) + n)

    def set_error(self, error: str) -> None:
        with self._lock:
            self.last_error = error
            self.last_error_time = time.time()

    def get(self, counter: str) -> int:
        with self._lock:
            return int(getattr(self._counts, counter))

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            out: dict[str, Any] = {name: getattr(self._counts, name) for name in COUNTERS}
            out["last_error"] = self.last_error
        return out


class BurstLog:
    """Log the first event of a burst at once, then a summary when ``quiet`` seconds pass without one.

    While a burst lasts longer than ``interval``, a summary is also written every ``interval``
    seconds, so a drop that never stops stays visible. Call :meth:`tick` periodically.
    """

    def __init__(
        self,
        log: Callable[[str], Any],
        what: str,
        *,
        quiet: float = 5.0,
        interval: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log = log
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

    def event(self, count: int, detail: str) -> None:
        now = self._clock()
        message = None
        with self._lock:
            if self._burst_start is None:
                self._burst_start = self._last_summary = now
                message = f"{self._what}: {count} ({detail})"
            else:
                self._pending += count
                self._last_detail = detail
            self._last_event = now
        if message is not None:
            self._log(message)
        self.tick()

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


def prometheus_text(destinations: dict[str, dict[str, Any]], buffer: dict[str, Any]) -> str:
    """Prometheus text exposition (format 0.0.4) of :meth:`DeliveryPipeline.metrics`."""
    lines: list[str] = []

    def family(name: str, kind: str, doc: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {doc}")
        lines.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            lines.append(
                f"{name}{labels} {value:g}" if isinstance(value, float) else f"{name}{labels} {value}"
            )

    def label(destination: str) -> str:
        escaped = destination.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return f'{{destination="{escaped}"}}'

    for counter, doc in (
        ("received", "Records routed to the destination"),
        ("sent", "Records the destination confirmed"),
        ("retried", "Records put back in the queue after a failed attempt"),
        ("failed", "send() calls that failed in whole or in part"),
        ("dropped", "Records dropped by the size limit or a full intake queue"),
        ("dead_lettered", "Records moved to the dead-letter table"),
        ("dead_letters_dropped", "Oldest dead letters deleted by dead_letter_limit_size"),
    ):
        family(
            f"dc_delivery_{counter}_total",
            "counter",
            doc,
            [(label(name), values[counter]) for name, values in sorted(destinations.items())],
        )
    family(
        "dc_delivery_buffered_records",
        "gauge",
        "Records waiting in the buffer",
        [(label(name), values["buffered"]) for name, values in sorted(destinations.items())],
    )
    family(
        "dc_delivery_buffered_bytes",
        "gauge",
        "Bytes of records waiting in the buffer",
        [(label(name), values["buffered_bytes"]) for name, values in sorted(destinations.items())],
    )
    family(
        "dc_delivery_dead_letters",
        "gauge",
        "Records in the dead-letter table",
        [(label(name), values["dead_letters"]) for name, values in sorted(destinations.items())],
    )
    family(
        "dc_delivery_oldest_pending_age_seconds",
        "gauge",
        "Age of the oldest waiting record (0 when empty)",
        [
            (label(name), float(values["oldest_pending_age_s"] or 0.0))
            for name, values in sorted(destinations.items())
        ],
    )
    family(
        "dc_delivery_buffer_quarantined_total",
        "counter",
        "Corrupt buffer files moved aside",
        [("", buffer["quarantined"])],
    )
    family(
        "dc_delivery_intake_pending",
        "gauge",
        "Records waiting for the next group commit",
        [("", buffer["intake_pending"])],
    )
    return "\n".join(lines) + "\n"
