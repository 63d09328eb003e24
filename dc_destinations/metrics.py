"""Per-destination delivery counters and their Prometheus text.

Counters are since the pipeline started (the database keeps lifetime totals for ``dc status``).
A notable event (record dropped, send failed) increments its counter and goes through a
:class:`dc_core.logs.BurstLog` in the same place, so a flood of drops is one log line when it
starts and one summary when it ends, never one line per record.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from dc_core.http_status import PrometheusText, prometheus_labels
from dc_core.metrics_document import by_measurement_key, per_measurement
from dc_destinations.settings import by_measurement

# (key in DeliveryPipeline.metrics(), Prometheus kind, help text)
DELIVERY_COUNTERS = (
    ("received", "counter", "Records routed to the destination"),
    ("sent", "counter", "Records the destination confirmed"),
    ("retried", "counter", "Records put back in the queue after a failed attempt"),
    ("failed", "counter", "send() calls that failed in whole or in part, and failed buffer operations of the sender"),
    ("dropped", "counter", "Records dropped by the size limit or a full intake queue"),
    ("malformed", "counter", "Records the buffer could not store: not valid UTF-8 JSON (normally caught at intake)"),
    ("dead_lettered", "counter", "Records moved to the dead-letter table"),
    ("dead_letters_dropped", "counter", "Oldest dead letters deleted by dead_letter_limit_size"),
    ("salvaged", "counter", "Records read back from a damaged buffer file into the new buffer"),
    ("lost_to_damage", "counter", "Records of a damaged buffer file that could not be read"),
    ("evicted", "counter", "Records deleted from the buffer unsent to keep within the disk budget"),
    ("files_evicted", "counter", "Saved files this destination carries, evicted by the disk budget before it had them"),
)
# The counters of one destination, in their order in metrics() and the Prometheus text.
COUNTERS = tuple(key for key, _kind, _doc in DELIVERY_COUNTERS)
# Counters also kept per measurement (`<counter>_by_measurement`, dc_delivery_<counter>_by_measurement_total):
# a measurement's records may be worth more than another's in the same queue (retention_priorities),
# and which of them a budget or a size limit gave up is what a user asks first. The help texts.
PER_MEASUREMENT = {
    "evicted": "Records evicted unsent by the disk budget, per measurement (the last part of their input topic)",
    "dropped": "Records dropped by the size limit or a full intake queue, per measurement (the last part of "
    "their input topic)",
}


class DestinationMetrics:
    """Thread-safe counters of one destination, and when it last delivered and last failed.

    Times are wall-clock epoch seconds (UTC), None until the first: a dashboard compares them with
    other machines' clocks, which a monotonic clock could not be.
    """

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self._counts = dict.fromkeys(COUNTERS, 0)
        # Of the counters in PER_MEASUREMENT: records per measurement (the last part of their input topic).
        self._by_measurement: dict[str, dict[str, int]] = {counter: {} for counter in PER_MEASUREMENT}
        self.last_error = ""
        self.last_error_time: float | None = None
        self.last_delivery: float | None = None

    def add(self, counter: str, n: int = 1) -> None:
        if n:
            with self._lock:
                self._counts[counter] += n
                # Records are counted sent once the destination confirmed them, wherever the sender
                # counts them: stamping here keeps `sent` and `last_delivery` from ever disagreeing.
                if counter == "sent":
                    self.last_delivery = self._clock()

    def add_by_topic(self, counter: str, by_topic: Mapping[str, int]) -> None:
        """Records per input topic added to ``counter`` (one of PER_MEASUREMENT) and to its counts per
        measurement (``<counter>_by_measurement``)."""
        if not by_topic:
            return
        with self._lock:
            self._counts[counter] += sum(by_topic.values())
            counts = self._by_measurement[counter]
            for name, n in by_measurement(by_topic).items():
                counts[name] = counts.get(name, 0) + n

    def set_error(self, error: str) -> None:
        with self._lock:
            self.last_error = error
            self.last_error_time = self._clock()

    def get(self, counter: str) -> int:
        with self._lock:
            return self._counts[counter]

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            out: dict[str, Any] = dict(self._counts)
            for counter, counts in self._by_measurement.items():
                out[by_measurement_key(counter)] = dict(sorted(counts.items()))
            out["last_error"] = self.last_error
            out["last_error_time"] = self.last_error_time
            out["last_delivery"] = self.last_delivery
        return out


# (metric name, key in DeliveryPipeline.metrics(), help text)
_QUEUE_GAUGES = (
    ("dc_delivery_buffered_records", "buffered", "Records waiting in the buffer"),
    ("dc_delivery_buffered_bytes", "buffered_bytes", "Bytes of records waiting in the buffer"),
    ("dc_delivery_dead_letters", "dead_letters", "Records in the dead-letter table"),
    (
        "dc_delivery_oldest_pending_age_seconds",
        "oldest_pending_age_s",
        "Age of the oldest waiting record (0 when empty)",
    ),
)

# (metric name, key in DeliveryPipeline.metrics(), help text): no sample for a destination without one yet.
_TIME_GAUGES = (
    (
        "dc_delivery_last_success_timestamp_seconds",
        "last_delivery",
        "When records were last confirmed by the destination (Unix time)",
    ),
    ("dc_delivery_last_error_timestamp_seconds", "last_error_time", "When delivery last failed (Unix time)"),
)


def prometheus_text(destinations: dict[str, dict[str, Any]], buffer: dict[str, Any]) -> str:
    """Prometheus text exposition (format 0.0.4) of :meth:`DeliveryPipeline.metrics`."""
    text = PrometheusText()
    text.counter_table("dc_delivery", "destination", destinations, DELIVERY_COUNTERS)
    # The plugins' own counters (Destination.counters()), one family per name.
    plugin_rows = {name: values.get("plugin") or {} for name, values in destinations.items()}
    plugin_keys = sorted({key for counters in plugin_rows.values() for key in counters})
    text.counter_table(
        "dc_delivery_plugin",
        "destination",
        plugin_rows,
        [(key, "counter", f"Plugin counter {key}") for key in plugin_keys],
    )
    for name, key, doc in _QUEUE_GAUGES:
        samples = [(prometheus_labels(destination=d), values[key]) for d, values in sorted(destinations.items())]
        if key == "oldest_pending_age_s":
            samples = [(labels, float(value or 0.0)) for labels, value in samples]
        text.family(name, "gauge", doc, samples)
    for name, key, doc in _TIME_GAUGES:
        # Whole seconds: PrometheusText writes floats with 6 significant digits, which would round
        # a Unix time to about 20 minutes.
        samples = [
            (prometheus_labels(destination=d), int(values[key]))
            for d, values in sorted(destinations.items())
            if values.get(key) is not None
        ]
        text.family(name, "gauge", doc, samples)
    for state in ("retrying", "failing"):
        samples = [
            (prometheus_labels(destination=d), int((values.get("health") or {}).get("state") == state))
            for d, values in sorted(destinations.items())
        ]
        text.family(
            f"dc_delivery_{state}",
            "gauge",
            f"1 while the destination is {state} (dc_destinations.health), else 0",
            samples,
        )
    for counter, doc in PER_MEASUREMENT.items():
        text.family(
            f"dc_delivery_{counter}_by_measurement_total",
            "counter",
            doc,
            [
                (prometheus_labels(destination=d, measurement=m), n)
                for d, values in sorted(destinations.items())
                for m, n in per_measurement(values, counter)
            ],
        )
    text.family(
        "dc_delivery_held",
        "gauge",
        "1 while the destination's only_when holds its records in the buffer (the reason is in the JSON metrics)",
        [(prometheus_labels(destination=d), int(bool(v.get("held")))) for d, v in sorted(destinations.items())],
    )
    text.family(
        "dc_delivery_buffer_quarantined_total",
        "counter",
        "Corrupt buffer files moved aside",
        [("", buffer["quarantined"])],
    )
    text.family(
        "dc_delivery_buffer_lost_to_damage_unknown_total",
        "counter",
        "Records of a damaged buffer file lost whose destination could not be read",
        [("", int(buffer.get("lost_to_damage_unknown") or 0))],
    )
    text.family(
        "dc_delivery_buffer_damaged",
        "gauge",
        "1 while the last integrity check (PRAGMA quick_check) of the buffer file found damage",
        [("", int(bool(buffer.get("buffer_damaged"))))],
    )
    if buffer.get("last_check_time") is not None:
        text.family(
            "dc_delivery_buffer_last_check_timestamp_seconds",
            "gauge",
            "When the buffer file's integrity was last checked (Unix time)",
            [("", int(buffer["last_check_time"]))],
        )
    text.family(
        "dc_delivery_commit_failing_seconds",
        "gauge",
        "How long group commits to the buffer have been failing (0 when they succeed)",
        [("", float(buffer.get("commit_failing_s") or 0.0))],
    )
    text.family(
        "dc_delivery_intake_pending",
        "gauge",
        "Records waiting for the next group commit",
        [("", buffer["intake_pending"])],
    )
    text.family(
        "dc_delivery_intake_pending_bytes",
        "gauge",
        "Bytes of the records waiting for the next group commit (intake_queue_limit_bytes)",
        [("", buffer.get("intake_pending_bytes") or 0)],
    )
    return text.text()


# (key in HopIntake.stats(), Prometheus kind, help text): the hop into destination_server, per input topic.
HOP_COUNTERS = (
    ("received", "counter", "Records received on the input topic, replays included"),
    ("duplicates", "counter", "Records dropped as copies of one already handled (replays, records sent again)"),
    ("missing", "counter", "Records known lost before destination_server: numbers that never arrived"),
    ("gaps", "counter", "Jumps in a publisher's numbers, and ended hand-off publishers, that missing counts"),
    ("writers", "counter", "Publishers recognised since the start (a restarted publisher is a new one)"),
    ("unkeyed", "counter", "Records without a source timestamp or sequence number: not deduplicated"),
    ("writers_ended", "counter", "Hand-off publishers announced ended holding records not acknowledged"),
)


def hop_prometheus_text(hop: dict[str, dict[str, int]], announcements_refused: int) -> str:
    """The hop counters (dc_destinations.hop) per input topic, and the hand-off announcements refused."""
    text = PrometheusText()
    text.counter_table("dc_hop", "topic", hop, HOP_COUNTERS)
    text.family(
        "dc_hop_handoff_announcements_refused_total",
        "counter",
        "Announcements on dc/handoff_ended refused: a publisher there was not one of DC's servers",
        [("", announcements_refused)],
    )
    return text.text()
