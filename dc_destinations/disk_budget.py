"""What to evict to keep DC within its disk budget: decided here, done by the pipeline.

The budget (``flb.disk_budget``, ``disk_budget_mb``) covers the records waiting in every
destination's queue (their JSON, as the queues count it) and DC's saved files (images, maps,
recordings: dc_destinations.saved_files) together. Over it, by value, not by age alone:

1. saved files already delivered and verified by every destination that carries them go first
   (they are safe elsewhere), the lowest retention priority first, oldest first;
2. then, one retention priority at a time from the lowest: the files of that priority not yet
   delivered, oldest first; the records of that priority, oldest first across every queue (a
   destination's records have its ``retention_priority``, or the one its ``retention_priorities``
   gives their input topic); and last the files kept as the first or last of their run
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
class RecordClass:
    """Records waiting in one destination's queue with one retention priority: those of ``topics``
    (None: the whole queue)."""

    destination: str
    topics: tuple[str, ...] | None
    priority: int
    nbytes: int


@dataclass(frozen=True)
class Step:
    """Evict the file ``name``, or ``nbytes`` of the oldest records of ``parts`` together: (destination,
    its topics or None for all) of one retention priority (``name``: that priority)."""

    kind: str  # "records" or "file"
    name: str
    nbytes: int
    parts: tuple[tuple[str, tuple[str, ...] | None], ...] = ()


def queue_classes(queued: Mapping[str, int], retention: Mapping[str, int]) -> list[RecordClass]:
    """Each queue one class of its destination's retention priority (no priority per topic)."""
    return [RecordClass(name, None, retention.get(name, 0), size) for name, size in queued.items()]


def budget_plan(
    records: Sequence[RecordClass],
    files: Sequence[FileCandidate],
    excess: int,
) -> list[Step]:
    """The steps that free at least ``excess`` bytes (all there are, if fewer), in the order of the
    module documentation; no ``records``: files only (the free-space floor)."""
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
    waiting = [c for c in records if c.nbytes > 0]
    for priority in sorted({f.priority for f in files} | {c.priority for c in waiting}):
        for candidate in sorted(
            (f for f in files if f.priority == priority and not f.delivered and not f.protected), key=lambda f: f.seq
        ):
            if take_file(candidate):
                return plan
        these = sorted((c for c in waiting if c.priority == priority), key=lambda c: c.destination)
        if these:
            take = min(sum(c.nbytes for c in these), excess)
            plan.append(Step("records", str(priority), take, tuple((c.destination, c.topics) for c in these)))
            excess -= take
            if excess <= 0:
                return plan
        for candidate in sorted(
            (f for f in files if f.priority == priority and f.protected), key=lambda f: (not f.delivered, f.seq)
        ):
            if take_file(candidate):
                return plan
    return plan
