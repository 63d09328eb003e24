"""What to evict from the buffer to keep it within ``flb.disk_budget_mb``: decided here, done by the pipeline.

The budget covers the records waiting in every destination's queue (their JSON, as the queues count
it). Over it, the oldest records of the destination with the lowest ``retention_priority`` go first,
and a destination's records are evicted only while no destination of a lower retention priority has
any left; among destinations of one priority, the largest queue gives first. Each eviction is counted
in the destination's ``evicted`` and logged once per burst (dc_destinations.delivery).
"""

from __future__ import annotations

from collections.abc import Mapping


def eviction_plan(queued: Mapping[str, int], retention: Mapping[str, int], budget: int) -> list[tuple[str, int]]:
    """(destination, bytes) to evict from the head of its queue; empty while within ``budget``."""
    excess = sum(queued.values()) - budget
    plan = []
    for name in sorted(queued, key=lambda n: (retention.get(n, 0), -queued[n], n)):
        if excess <= 0:
            break
        take = min(queued[name], excess)
        if take > 0:
            plan.append((name, take))
            excess -= take
    return plan
