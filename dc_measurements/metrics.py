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


# Counters whose growth means records were lost or not made: a measurement with any of them is WARN.
PROBLEM_COUNTERS = ("errors", "invalid", "malformed", "lost", "overrun")


def measurement_diagnosis(
    counters: dict[str, int], before: dict[str, int] | None, seconds: float | None
) -> tuple[str, str, dict[str, Any]]:
    """(``"ok"`` or ``"warn"``, message, values) of one measurement for /diagnostics.

    ``before``: its counters at the previous status, ``seconds`` since then (None at the first):
    the level says what happened in between, not since the start.
    """
    grew = {key: counters.get(key, 0) - (before or {}).get(key, 0) for key in counters}
    values: dict[str, Any] = dict(counters)
    values["records_per_s"] = round(grew["published"] / seconds, 3) if seconds else ""
    problems = [f"{grew[key]} {key}" for key in PROBLEM_COUNTERS if grew.get(key, 0) > 0]
    if problems:
        since = f"in the last {seconds:.0f} s" if seconds else "since configure"
        return "warn", f"{', '.join(problems)} {since} (the server's log says why)", values
    if grew.get("published", 0):
        return "ok", "publishing", values
    if grew.get("gated", 0):
        return "ok", "collecting; its conditions hold the records back", values
    if grew.get("empty", 0):
        return "ok", "collecting; nothing to report", values
    return "ok", "idle: nothing collected since the previous status", values
