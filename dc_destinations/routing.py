"""Which destinations a record goes to, and what each of them receives.

A record that arrived on topic T reaches destination D only if D lists T in its ``inputs`` and D's
name is one of the record's ``tags`` — compared whole: the original matched tags as substrings, so
a destination ``flb_pg`` also caught records tagged ``flb_pgsql``. Each delivery is a copy of the
record without ``tags``, with the destination's time key first (the header stamp in its
``time_format``) and a fresh ``record_id``, serialised (:func:`dc_core.records.dump_parsed`, which
raises ``MalformedRecord`` for a record that is not valid UTF-8 JSON). Pure: no ROS, no I/O.

A record's tags are trusted only as far as its publisher is: destinations that read the files a
record names (``trusted_only``) are not reached from a publisher the server does not trust
(``route(..., trusted=False)``), and the routing says which ones it refused (docs/security.md).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from dc_core.confined_files import ConfinementParams
from dc_core.destination import OutgoingRecord
from dc_core.records import dump_parsed
from dc_core.timefmt import format_stamp
from dc_destinations.config import DestinationConfig
from dc_destinations.record_ids import new_record_id

RECORD_ID_KEY = "record_id"
TAGS_KEY = "tags"

# Reasons a record reaches no destination (also the keys of the server's unrouted counters).
NO_TAGS = "no tags"
BAD_TAGS = "tags is not a list of strings"
NO_LISTENER = "its tags name no destination listening on this topic"
UNTRUSTED = "its tags name only file destinations, and its publisher is not one of DC's servers"


@dataclass(frozen=True)
class RouteTarget:
    """What routing needs to know of one destination."""

    name: str
    time_key: str
    time_format: str
    trusted_only: bool = False  # reads the files records name: only records of trusted publishers


@dataclass(frozen=True)
class Routed:
    """The result of routing one record: deliveries as (destination name, record), or why there are none."""

    deliveries: list[tuple[str, OutgoingRecord]] = field(default_factory=list)
    unrouted_reason: str | None = None
    refused: list[str] = field(default_factory=list)  # trusted_only destinations the tags named, not reached


def record_tags(record: Mapping[str, Any]) -> list[str] | None:
    """The destination names a record is tagged with; ``None`` when ``tags`` is not usable.

    A list of strings is the contract; a comma-separated string is accepted too, as the original
    turned the list into one before matching.
    """
    tags = record.get(TAGS_KEY)
    if isinstance(tags, list):
        for tag in tags:  # a loop, not all(generator): this runs for every record
            if not isinstance(tag, str):
                return None
        return tags
    if isinstance(tags, str):
        return [t.strip() for t in tags.split(",") if t.strip()]
    return None


class RoutingTable:
    """Destinations by input topic, built once at configure."""

    def __init__(self, targets_by_topic: Mapping[str, Iterable[RouteTarget]]) -> None:
        self._by_topic: dict[str, dict[str, RouteTarget]] = {
            topic: {t.name: t for t in targets} for topic, targets in targets_by_topic.items()
        }

    @classmethod
    def from_destinations(cls, destinations: Iterable[DestinationConfig]) -> RoutingTable:
        by_topic: dict[str, list[RouteTarget]] = {}
        for d in destinations:
            target = RouteTarget(
                d.name, d.common.time_key, d.common.time_format, isinstance(d.plugin_params, ConfinementParams)
            )
            for topic in dict.fromkeys(d.common.inputs):
                by_topic.setdefault(topic, []).append(target)
        return cls(by_topic)

    @property
    def topics(self) -> list[str]:
        return sorted(self._by_topic)

    def listeners(self, topic: str) -> list[str]:
        return list(self._by_topic.get(topic, {}))

    def has_trusted_only(self, topic: str) -> bool:
        """Whether a destination that only trusted publishers reach listens on ``topic``."""
        return any(t.trusted_only for t in self._by_topic.get(topic, {}).values())

    def route(
        self,
        topic: str,
        record: Mapping[str, Any],
        stamp_ns: int,
        new_record_id: Callable[[], str] = new_record_id,
        trusted: bool = True,
    ) -> Routed:
        if TAGS_KEY not in record:
            return Routed(unrouted_reason=NO_TAGS)
        tags = record_tags(record)
        if tags is None:
            return Routed(unrouted_reason=BAD_TAGS)
        if not tags:
            return Routed(unrouted_reason=NO_TAGS)
        listening = self._by_topic.get(topic, {})
        if len(tags) == 1:  # most records: one tag, no list of names to build
            only = listening.get(tags[0])
            targets = [only] if only is not None else []
        else:
            # dict.fromkeys: a destination tagged twice still receives the record once, in tag order.
            targets = [listening[name] for name in dict.fromkeys(tags) if name in listening]
        refused: list[str] = []
        if not trusted:
            refused = [t.name for t in targets if t.trusted_only]
            if refused:
                targets = [t for t in targets if not t.trusted_only]
                if not targets:
                    return Routed(unrouted_reason=UNTRUSTED, refused=refused)
        if not targets:
            return Routed(unrouted_reason=NO_LISTENER)
        # One id per received record, shared by its destinations and kept in the delivered JSON so
        # that sinks can deduplicate what at-least-once delivery may send twice.
        record_id = new_record_id()
        shared: dict[str, Any] | None = None
        body: Mapping[str, Any] = record  # one destination: its one copy below takes the time key and the id
        if len(targets) > 1 or targets[0].time_key == TAGS_KEY:
            body = shared = {k: v for k, v in record.items() if k != TAGS_KEY}
            shared[RECORD_ID_KEY] = record_id
        deliveries = []
        stamps: dict[str, float | str] = {}
        for target in targets:
            time_key = target.time_key
            stamp: float | str | None = None
            if time_key:
                stamp = stamps.get(target.time_format)
                if stamp is None:
                    stamp = stamps[target.time_format] = format_stamp(stamp_ns, target.time_format)
                # First, as the original's output showed it: {"date": ..., <record>}, and in place
                # of a key of the record so named.
                data: dict[str, Any] = {time_key: stamp, **body}
            elif shared is not None and target is targets[-1]:
                data = shared  # the last destination may have the body itself: nothing else keeps it
            else:
                data = dict(body)
            if shared is None:
                del data[TAGS_KEY]
                data[RECORD_ID_KEY] = record_id
            if time_key:
                data[time_key] = stamp
            # Serialised here, once: what cannot be written back as JSON (an infinite number, a lone
            # surrogate) raises MalformedRecord before any copy reaches the buffer.
            deliveries.append(
                (target.name, OutgoingRecord.serialised(record_id, topic, stamp_ns, data, dump=dump_parsed))
            )
        return Routed(deliveries, refused=refused)
