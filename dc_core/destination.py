"""The destination plugin contract: ``send(batch)`` with typed outcomes.

Buffering, batching, retries with backoff, dead letters and counters live once, in the
destination server; a destination only delivers. ``send`` returns ``None`` when every record of the
batch was confirmed, a :class:`SendOutcome` for per-record results, or raises
:class:`RetryableError` (the whole batch is retried later) or :class:`RejectedError` (the whole
batch is dead-lettered). Any other exception counts as retryable. A server's "not before" (HTTP's
Retry-After) goes in ``retry_after`` of either; the sender's backoff honours it. ``send`` runs in the
destination's own worker thread, never on the ROS executor, so it may block on I/O.

A failure that retrying alone cannot mend (a wrong password, a missing bucket or table, a refused
permission) is raised as :class:`ConfigurationProblem`, or as a :class:`RejectedError` with a
``fix``: the records are handled as before (retried, or dead-lettered), and the destination is
reported ``failing`` at once, its fix logged once at ERROR (dc_destinations.health). An unknown host
and a failed TLS verification are recognised by the server itself in the exception's chain.
"""

from __future__ import annotations

import abc
import functools
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

from dc_core.errors import DcError
from dc_core.plugin import ParamsT, Plugin
from dc_core.records import dump_record, parse_record


class RetryableError(DcError):
    """Delivery failed for a reason that may pass (network down, server busy, 5xx).

    ``retry_after``: seconds the server asked to be left alone (HTTP's Retry-After), when it said;
    the sender waits at least that long before the next attempt, but never longer than its
    ``scheduler_cap``. A destination never waits inside ``send`` for it.
    """

    def __init__(self, message: str, *, retry_after: float | None = None) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class ConfigurationProblem(RetryableError):
    """Delivery failed for a reason retrying alone will not mend: wrong credentials, a missing
    bucket, table or database, a permission refused.

    Still retried (someone may fix it while records wait), but the destination is reported
    ``failing`` at once rather than after ``unhealthy_after``; ``fix`` says what to check, in the
    user's words ("check the password parameter or PGPASSWORD"). Nothing secret in either text.
    """

    def __init__(self, message: str, *, fix: str = "") -> None:
        super().__init__(message)
        self.fix = fix


class RejectedError(DcError):
    """The destination refused the records for good (malformed, 4xx): do not retry.

    ``fix``: set when the refusal is about the destination's set-up rather than the records (an
    HTTP 401 or 403): the records are dead-lettered as for any refusal, and the destination is
    reported ``failing`` at once, as for a :class:`ConfigurationProblem`.
    """

    def __init__(self, message: str = "", *, fix: str = "") -> None:
        super().__init__(message)
        self.fix = fix


@dataclass
class SendOutcome:
    """Per-record result of a batch: indexes into the batch with the reason. Others succeeded.

    ``retry``: the destination failed with these records; they are tried again after the backoff.
    ``waiting``: these records cannot be confirmed *yet*, through no failure (FilesMetrics waits for
    another destination to upload a record's file): tried again like ``retry`` and counted against
    ``retry_limit``, but no failure: the destination stays healthy and no error is reported.
    ``retry_after``: as for :class:`RetryableError`, the server's wish before ``retry`` is tried again.
    """

    retry: dict[int, str] = field(default_factory=dict)
    reject: dict[int, str] = field(default_factory=dict)
    waiting: dict[int, str] = field(default_factory=dict)
    retry_after: float | None = None


@dataclass(frozen=True)
class OutgoingRecord:
    """A record routed to one destination: ``tags`` removed, time key and ``record_id`` added.

    Destinations read it and never change it: ``data`` and ``to_json()`` must stay the same record.
    """

    record_id: str
    topic: str
    stamp_ns: int
    data: dict[str, Any]
    # The JSON text of ``data``, when something has it already (routing serialises each record
    # once; the buffer holds it): to_json() returns it instead of serialising again (``data`` is
    # read-only for destinations).
    json_text: str | None = field(default=None, compare=False, repr=False)

    def to_json(self) -> str:
        """Compact JSON text; :class:`dc_core.records.MalformedRecord` if ``data`` is not valid UTF-8 JSON."""
        if self.json_text is not None:
            return self.json_text
        return dump_record(self.data)

    @classmethod
    def serialised(
        cls,
        record_id: str,
        topic: str,
        stamp_ns: int,
        data: dict[str, Any],
        dump: Callable[[dict[str, Any]], str] = dump_record,
    ) -> OutgoingRecord:
        """A record with its JSON text written now by dump_record (MalformedRecord if ``data`` cannot be).

        The buffer stores its text as DC JSON for certain, and delivery does not parse it again
        (:attr:`text_follows_rule`); a ``json_text`` given to the constructor is not trusted so.
        ``dump``: :func:`dc_core.records.dump_parsed` for data made of a parsed record (routing).
        """
        json_text = dump(data)
        # The fields set as the frozen dataclass's __init__ would set them, in one dict update: this
        # runs for every record routed, where __init__'s object.__setattr__ per field cost 2.5x more.
        record = cls.__new__(cls)
        record.__dict__.update(
            record_id=record_id,
            topic=topic,
            stamp_ns=stamp_ns,
            data=data,
            json_text=json_text,
            _text_follows_rule=True,
        )
        return record

    @property
    def text_follows_rule(self) -> bool:
        """Whether ``to_json()`` is DC JSON for certain: written by dump_record, now or in :meth:`serialised`."""
        return self.json_text is None or bool(self.__dict__.get("_text_follows_rule", False))

    def __eq__(self, other: object) -> bool:
        # Written out so that a StoredRecord equals the OutgoingRecord it was sent as.
        if not isinstance(other, OutgoingRecord):
            return NotImplemented
        return (self.record_id, self.topic, self.stamp_ns, self.data) == (
            other.record_id,
            other.topic,
            other.stamp_ns,
            other.data,
        )


class StoredRecord(OutgoingRecord):
    """A record read back from the buffer whose text is known to be DC JSON: ``data`` parsed on first read.

    Most destinations send ``to_json()`` and never read ``data``: parsing every record anyway was
    more than half of the sender's own cost (docs/performance.md). Only for a text that passed
    the record rule (dc_destinations.buffer.BufferedRow.as_appended), so that the parse cannot
    fail; were it to fail, the ``MalformedRecord`` raised in ``send()`` makes the batch retried.
    """

    def __init__(
        self,
        record_id: str,
        topic: str,
        stamp_ns: int,
        data: dict[str, Any] | None = None,
        json_text: str | None = None,
    ) -> None:
        # OutgoingRecord's parameters, so that dataclasses.replace() works on it too. The dataclass
        # is frozen: the fields go into the instance's dict directly, in one update rather than an
        # object.__setattr__ each (the sender makes one per record).
        if json_text is None:
            raise TypeError("StoredRecord needs json_text")
        fields = self.__dict__
        fields.update(record_id=record_id, topic=topic, stamp_ns=stamp_ns, json_text=json_text)
        if data is not None:
            fields["data"] = data

    @functools.cached_property
    def data(self) -> dict[str, Any]:
        assert self.json_text is not None
        return parse_record(self.json_text)

    def __repr__(self) -> str:
        return f"StoredRecord(record_id={self.record_id!r}, topic={self.topic!r}, stamp_ns={self.stamp_ns!r})"


class Closable(Protocol):
    def close(self) -> None: ...


ClosableT = TypeVar("ClosableT", bound=Closable)


@dataclass(frozen=True)
class ProbeResult:
    """What a destination's read-only probe found (``dc check``). Nothing secret in either text."""

    ok: bool
    reason: str  # what was checked ("connected, table dc exists, INSERT allowed") or what failed
    fix: str = ""  # when not ok: what the operator should check or change


class Destination(Plugin[ParamsT]):
    """Base class of destination plugins.

    The destination server never runs ``send`` at the same time as ``on_deactivate`` or
    ``on_cleanup`` (dc_destinations.sender.Gate): a plugin needs no lock of its own for what those
    share. What it keeps open between batches it hands to :meth:`keep` once; the default
    ``on_deactivate`` and ``on_cleanup`` close it.
    """

    def probe(self) -> ProbeResult | None:
        """A cheap, read-only check that this destination can be reached with its real settings
        and credentials, for ``dc check``; None (the default): the plugin has no probe.

        Called after ``on_configure`` and before ``on_cleanup``, never activated, on the caller's
        thread: it may block for about the destination's own timeouts. It writes nothing (``dc check
        --write-test`` sends a record through ``send`` for that). It may raise
        :class:`RetryableError` or :class:`ConfigurationProblem` (whose ``fix`` is shown) instead of
        returning a failed result.
        """
        return None

    @abc.abstractmethod
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        """Deliver ``batch``; see the module documentation for the outcomes."""

    def keep(self, resource: ClosableT) -> ClosableT:
        """``resource`` (a connection, dc_destinations.connection.Connection), closed on deactivate and cleanup."""
        kept: list[Closable] = self.__dict__.setdefault("_dc_kept", [])
        if not any(r is resource for r in kept):
            kept.append(resource)
        return resource

    def close_kept(self) -> None:
        """Close what :meth:`keep` was given; a plugin overriding the hooks calls it (or ``super()``)."""
        for resource in self.__dict__.get("_dc_kept", []):
            resource.close()

    def on_deactivate(self) -> None:
        self.close_kept()

    def on_cleanup(self) -> None:
        self.close_kept()

    def pace(self, nbytes: int) -> bool:
        """Wait until ``nbytes`` more may go within this destination's caps (``max_bytes_per_s``, its
        link's), after the records waiting for them; False when the server stops meanwhile (the
        send should then end, its records retried). Called by a plugin before each piece of what it
        sends besides the records themselves (MinIO: each file or part). Returns at once uncapped."""
        pace: Callable[[int], bool] | None = self.__dict__.get("_dc_pace")
        return pace is None or pace(nbytes)

    # True for a destination that records a file DC evicted itself (FilesMetrics writes its row with
    # ``evicted``): its records naming such a file are still sent. For the others they are taken out
    # of its queue, counted ``evicted`` (dc_destinations.saved_files).
    records_evictions = False

    def file_fields(self) -> list[str]:
        """Dotted paths (``local_paths.jpeg``) of the files this destination carries; [] for records only.

        A record it confirms counts as its files delivered and verified by it: a plugin returns
        fields here only if its confirmation means that (MinIO: uploaded and verified)."""
        return []

    def files_evicted(self, files: Mapping[str, Sequence[str]]) -> None:
        """DC evicted these files (path -> ids of records naming them) after this destination confirmed
        those records: a destination that ``records_evictions`` says so where it recorded them. Called
        on its sender's thread, between sends; raise RetryableError to be told again later."""

    def evicted_file(self, path: str) -> bool:
        """True when DC evicted ``path`` to keep within its disk budget before this destination had it."""
        evicted: Callable[[str], bool] | None = self.__dict__.get("_dc_evicted")
        return evicted is not None and evicted(path)

    @property
    def stopping(self) -> threading.Event:
        """Set when the server stops delivery while ``send`` still runs past the grace; cleared at the start.

        A ``send`` that waits for something (a rate's next slot, a file to be complete) waits on it,
        so that it returns at once, its records retried at the next start.
        """
        event: threading.Event = self.__dict__.setdefault("_dc_stopping", threading.Event())
        return event
