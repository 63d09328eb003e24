"""The measurement server's counters as its metrics HTTP server serves them (JSON and Prometheus text)."""

from __future__ import annotations

from typing import Any

from dc_core.http_status import PrometheusText

# Counters of every measurement (dc_measurements.runner.RunnerStats), then those some plugins add.
MEASUREMENT_COUNTERS = {
    "collected": "Samples collected (collect() called or a record emitted by an event)",
    "published": "Records published on the measurement's output topic",
    "gated": "Samples not published because the conditions said no",
    "empty": "Collections that returned nothing",
    "invalid": "Records that failed JSON schema validation (published unless drop_invalid)",
    "errors": "Collections or record builds that raised, or records not valid JSON (NaN, lone surrogate)",
    "overrun": "Polls skipped because the previous collection still ran on the worker (collect_in_worker)",
    "malformed": "Input messages that were not a JSON object DC can carry, skipped (StringStamped)",
    "lost": "Input messages DDS overwrote before they were taken, from publisher sequence gaps (StringStamped)",
    "replaced": "Input records a newer one replaced before a poll published them (StringStamped, timer_based)",
}


def measurement_prometheus_text(document: dict[str, Any]) -> str:
    """Prometheus text of :meth:`dc_measurements.server.MeasurementServer.metrics_document`."""
    text = PrometheusText()
    measurements: dict[str, dict[str, int]] = document["measurements"]
    keys = list(MEASUREMENT_COUNTERS)
    keys += sorted({key for values in measurements.values() for key in values} - set(keys))
    counters = [(key, "counter", MEASUREMENT_COUNTERS.get(key, f"Plugin counter {key}")) for key in keys]
    text.counter_table("dc_measurement", "measurement", measurements, counters)
    return text.text()
