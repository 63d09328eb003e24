"""The group server's counters as the metrics HTTP server serves them (JSON and Prometheus text)."""

from __future__ import annotations

from typing import Any

from dc_core.http_status import PrometheusText

# (key in GroupPipeline.stats(), Prometheus kind, help text)
GROUP_COUNTERS = (
    ("published", "counter", "Complete sets merged and published"),
    ("published_partial", "counter", "Incomplete sets published at their timeout (on_sync_timeout emit_partial)"),
    ("dropped_incomplete", "counter", "Incomplete sets dropped at their timeout (on_sync_timeout drop)"),
    ("superseded", "counter", "Pending messages discarded because a set used a newer one of their input"),
    ("late", "counter", "Messages stamped at or before the last one used from their input, discarded"),
    ("overflowed", "counter", "Messages discarded from a full input queue (queue_size), oldest stamp first"),
    ("renamed_keys", "counter", "Keys renamed <key>_2... because two inputs had them"),
    ("pending", "gauge", "Messages waiting for the partners of their set"),
)


def group_prometheus_text(document: dict[str, Any]) -> str:
    """Prometheus text of :meth:`dc_group.server.GroupServer.metrics_document`."""
    text = PrometheusText()
    text.counter_table("dc_group", "group", document["groups"], GROUP_COUNTERS)
    text.counter_table(
        "dc_group",
        "topic",
        document["inputs"],
        [("malformed", "counter", "Input messages that were not a JSON object DC can carry, ignored")],
    )
    return text.text()
