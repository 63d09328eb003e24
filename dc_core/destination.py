"""The destination plugin contract: ``send(batch)`` with typed outcomes.

Buffering, batching, retries with backoff, dead letters and counters live once, in the
destination server; a destination only delivers. ``send`` returns ``None`` when every record of the
batch was confirmed, a :class:`SendOutcome` for per-record results, or raises
:class:`RetryableError` (the whole batch is retried later) or :class:`RejectedError` (the whole
batch is dead-lettered). Any other exception counts as retryable. ``send`` runs in the
destination's own worker thread, never on the ROS executor, so it may block on I/O.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from dc_core.errors import DcError
from dc_core.plugin import ParamsT, Plugin, PluginContext
from dc_core.records import dump_record


class RetryableError(DcError):
    """Delivery failed for a reason that may pass (network down, server busy, 5xx)."""


class RejectedError(DcError):
    """The destination refused the records for good (malformed, 4xx): do not retry."""


@dataclass
class SendOutcome:
    """Per-record result of a batch: indexes into the batch with the reason. Others succeeded."""

    retry: dict[int, str] = field(default_factory=dict)
    reject: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class OutgoingRecord:
    """A record routed to one destination: ``tags`` removed, time key and ``record_id`` added.

    Destinations read it and never change it: ``data`` and ``to_json()`` must stay the same record.
    """

    record_id: str
    topic: str
    stamp_ns: int
    data: dict[str, Any]
    # The JSON text of ``data`` as the buffer holds it, when the record comes from the buffer:
    # to_json() returns it instead of serialising again (``data`` is read-only for destinations).
    json_text: str | None = field(default=None, compare=False, repr=False)

    def to_json(self) -> str:
        """Compact JSON text; :class:`dc_core.records.MalformedRecord` if ``data`` is not valid UTF-8 JSON."""
        if self.json_text is not None:
            return self.json_text
        return dump_record(self.data)


DestinationContext = PluginContext
"""What the destination server gives a destination plugin (the common plugin context)."""


class Destination(Plugin[ParamsT]):
    """Base class of destination plugins."""

    @abc.abstractmethod
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        """Deliver ``batch``; see the module documentation for the outcomes."""
