"""What to evict to keep DC within its disk budget: decided here, done by the pipeline.

The budget (``flb.disk_budget``, ``disk_budget_mb``) covers the records waiting in every
destination's queue (their JSON, as the queues count it) and DC's saved files (images, maps,
recordings: dc_destinations.saved_files) together. Over it, by value, not by age alone:

1. saved files already delivered and verified by every destination that carries them go first
   (they are safe elsewhere), the lowest retention priority first, oldest first;
2. then, one retention priority at a time from the lowest: the files of that priority not yet
   delivered, oldest first; the records of the destinations of that ``retention_priority``, the
   oldest of the largest queue first; and last the files kept as the first or last of their run
   (``keep_run_ends``).

So nothing of a higher retention priority that is the only copy goes while anything of a lower one
is left. Each eviction is counted (``evicted`` of a destination, of a measurement) and logged once
per burst (dc_destinations.delivery). Under ``disk_free_floor`` only files are given up: the space
SQLite frees is reused by the buffer, not handed back to the filesystem.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class FileCandidate:
    """A saved file as the plan weighs it."""

    path: str
    size: int
    priority: int
    delivered: bool  # verified by every destination that carries it
    protected: bool  # one of the first or last keep_run_ends of its measurement and run
    seq: int  # registration order: lower is older


@dataclass(frozen=True)
class Step:
    """Evict ``nbytes`` from the head of destination ``name``'s queue, or the file ``name``."""

    kind: str  # "records" or "file"
    name: str
    nbytes: int


def eviction_plan(queued: Mapping[str, int], retention: Mapping[str, int], budget: int) -> list[tuple[str, int]]:
    """(destination, bytes) to evict from the head of its queue; empty while within ``budget``."""
    steps = budget_plan(queued, retention, [], sum(queued.values()) - budget)
    return [(step.name, step.nbytes) for step in steps]


def budget_plan(
    queued: Mapping[str, int],
    retention: Mapping[str, int],
    files: Sequence[FileCandidate],
    excess: int,
    *,
    records: bool = True,
) -> list[Step]:
    """The steps that free at least ``excess`` bytes (all there are, if fewer), in the order of the
    module documentation; ``records`` False: files only (the free-space floor)."""
    plan: list[Step] = []
    if excess <= 0:
        return plan

    def take_file(candidate: FileCandidate) -> bool:
        nonlocal excess
        plan.append(Step("file", candidate.path, candidate.size))
        excess -= candidate.size
        return excess <= 0

    for candidate in sorted((f for f in files if f.delivered and not f.protected), key=lambda f: (f.priority, f.seq)):
        if take_file(candidate):
            return plan
    queues = {name: size for name, size in queued.items() if size > 0} if records else {}
    priorities = sorted({f.priority for f in files} | {retention.get(name, 0) for name in queues})
    for priority in priorities:
        for candidate in sorted(
            (f for f in files if f.priority == priority and not f.delivered and not f.protected), key=lambda f: f.seq
        ):
            if take_file(candidate):
                return plan
        for name in sorted((n for n in queues if retention.get(n, 0) == priority), key=lambda n: (-queues[n], n)):
            take = min(queues[name], excess)
            plan.append(Step("records", name, take))
            excess -= take
            if excess <= 0:
                return plan
        for candidate in sorted(
            (f for f in files if f.priority == priority and f.protected), key=lambda f: (not f.delivered, f.seq)
        ):
            if take_file(candidate):
                return plan
    return plan
