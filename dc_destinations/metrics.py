"""Per-destination delivery counters and their Prometheus text.

Counters are since the pipeline started (the database keeps lifetime totals for ``dc status``).
A notable event (record dropped, send failed) increments its counter and goes through a
:class:`dc_core.logs.BurstLog` in the same place, so a flood of drops is one log line when it
starts and one summary when it ends, never one line per record.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

from dc_core.http_status import PrometheusText, prometheus_labels

COUNTERS = (
    "received",
    "sent",
    "retried",
    "failed",
    "dropped",
    "malformed",
    "dead_lettered",
    "dead_letters_dropped",
)


@dataclass
class _Counts:
    received: int = 0
    sent: int = 0
    retried: int = 0
    failed: int = 0
    dropped: int = 0
    malformed: int = 0
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


def prometheus_text(destinations: dict[str, dict[str, Any]], buffer: dict[str, Any]) -> str:
    """Prometheus text exposition (format 0.0.4) of :meth:`DeliveryPipeline.metrics`."""
    text = PrometheusText()
    family = text.family

    def label(destination: str) -> str:
        return prometheus_labels(destination=destination)

    for counter, doc in (
        ("received", "Records routed to the destination"),
        ("sent", "Records the destination confirmed"),
        ("retried", "Records put back in the queue after a failed attempt"),
        ("failed", "send() calls that failed in whole or in part, and failed buffer operations of the sender"),
        ("dropped", "Records dropped by the size limit or a full intake queue"),
        ("malformed", "Records the buffer could not store: not valid UTF-8 JSON (normally caught at intake)"),
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
        [(label(name), float(values["oldest_pending_age_s"] or 0.0)) for name, values in sorted(destinations.items())],
    )
    family(
        "dc_delivery_buffer_quarantined_total",
        "counter",
        "Corrupt buffer files moved aside",
        [("", buffer["quarantined"])],
    )
    family(
        "dc_delivery_commit_failing_seconds",
        "gauge",
        "How long group commits to the buffer have been failing (0 when they succeed)",
        [("", float(buffer.get("commit_failing_s") or 0.0))],
    )
    family(
        "dc_delivery_intake_pending",
        "gauge",
        "Records waiting for the next group commit",
        [("", buffer["intake_pending"])],
    )
    return text.text()
