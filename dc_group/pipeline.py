"""One group at work, without ROS: synchronise parsed input records, merge each set, count.

The server feeds it messages and a clock; it returns what to publish. Every outcome logs once
where it happens and increments its counter there; a silent input is logged when it starts and
when it ends, not for every set it spoils.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from dc_core.logs import Logger
from dc_group.config import GroupConfig
from dc_group.merge import InputRecord, merge
from dc_group.sync import ApproximateTimeSync, SyncedSet


@dataclass(frozen=True)
class GroupOutput:
    """A merged record ready to publish."""

    stamp_ns: int
    data: str
    group_key: str
    complete: bool


@dataclass
class GroupCounters:
    published: int = 0
    published_partial: int = 0
    dropped_incomplete: int = 0
    renamed_keys: int = 0


class GroupPipeline:
    def __init__(self, group: GroupConfig, logger: Logger) -> None:
        self.group = group
        self.logger = logger
        self.counters = GroupCounters()
        self.sync: ApproximateTimeSync[InputRecord] = ApproximateTimeSync(
            len(group.inputs),
            slop_ns=round(group.sync_delay * 1e9),
            timeout=group.sync_timeout,
            queue_size=group.queue_size,
        )
        self._input_index = {topic: i for i, topic in enumerate(group.inputs)}
        self._missing: tuple[str, ...] = ()
        self._warned_renames: set[tuple[str, str]] = set()
        self._warned_overflow = False

    def offer(self, record: InputRecord, stamp_ns: int, now: float) -> list[GroupOutput]:
        """A message of one of the group's inputs arrived; what is due is returned."""
        out = self.expire(now)
        synced = self.sync.offer(self._input_index[record.topic], stamp_ns, record, now)
        if synced is not None:
            out.append(self._complete(synced))
        elif self.sync.counters.overflowed and not self._warned_overflow:
            self._warned_overflow = True
            self.logger.warning(
                f"group {self.group.name}: an input queue is full (queue_size {self.group.queue_size}): "
                "its oldest message is discarded; raise queue_size if inputs publish faster than "
                "the slowest one by more than that"
            )
        return out

    def expire(self, now: float) -> list[GroupOutput]:
        """Incomplete sets that timed out: dropped, or published with emit_partial."""
        return [o for s in self.sync.expire(now) if (o := self._incomplete(s)) is not None]

    def flush(self) -> list[GroupOutput]:
        """At deactivation: every pending message is an incomplete set now."""
        return [o for s in self.sync.flush() if (o := self._incomplete(s)) is not None]

    # -- outcomes --------------------------------------------------------------------------
    def _complete(self, synced: SyncedSet[InputRecord]) -> GroupOutput:
        if self._missing:
            self.logger.info(f"group {self.group.name}: every input publishes again")
            self._missing = ()
        self.counters.published += 1
        return self._output(synced, complete=True)

    def _incomplete(self, synced: SyncedSet[InputRecord]) -> GroupOutput | None:
        missing = tuple(self.group.inputs[i] for i in synced.missing)
        if missing != self._missing:
            self._missing = missing
            outcome = "published without them" if self.group.emit_partial else "dropped"
            self.logger.warning(
                f"group {self.group.name}: nothing from {', '.join(missing)} within "
                f"{self.group.sync_timeout:g} s of the other inputs: sets are {outcome} "
                f"(on_sync_timeout: {'emit_partial' if self.group.emit_partial else 'drop'})"
            )
        if not self.group.emit_partial:
            self.counters.dropped_incomplete += 1
            return None
        self.counters.published_partial += 1
        return self._output(synced, complete=False)

    def _output(self, synced: SyncedSet[InputRecord], *, complete: bool) -> GroupOutput:
        members = [m.payload if m is not None else None for m in synced.members]
        merged = merge(self.group, members)
        for wanted, given in merged.renamed:
            self.counters.renamed_keys += 1
            if (wanted, given) not in self._warned_renames:
                self._warned_renames.add((wanted, given))
                self.logger.warning(
                    f'group {self.group.name}: the key "{wanted}" is taken by an earlier input or by '
                    f'the group itself; this record is published under "{given}" instead'
                )
        data = json.dumps(merged.record, ensure_ascii=False, separators=(",", ":"))
        return GroupOutput(stamp_ns=synced.stamp_ns, data=data, group_key=self.group.group_key, complete=complete)

    def stats(self) -> dict[str, int]:
        sync = self.sync.counters
        return {
            "published": self.counters.published,
            "published_partial": self.counters.published_partial,
            "dropped_incomplete": self.counters.dropped_incomplete,
            "superseded": sync.superseded,
            "late": sync.late,
            "overflowed": sync.overflowed,
            "renamed_keys": self.counters.renamed_keys,
            "pending": self.sync.pending_count(),
        }
