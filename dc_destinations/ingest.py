"""``dc ingest``: the fleet side. Records read from a JetStream durable pull consumer are delivered by
DC's own destinations, and acknowledged to JetStream only once every destination confirmed them.

The design (docs/fleet.md): the destinations of a ``destination_server`` section run as they do on
a robot, behind DC's delivery pipeline (buffer, one sender per destination, backoff, dead letters,
counters, health). The pipeline tells :class:`Settlements` the outcome of each send once it is
final (dc_destinations.sender.OutcomeListener): a record is *settled* for a destination once it
confirmed it, or once its dead letter (refused for good, or failed beyond ``retry_limit``) is
committed to this worker's buffer, counted, as on a robot. When every destination has settled a
record, its JetStream message is acknowledged; until then JetStream keeps it, and redelivers it
after ``ack_wait`` to whichever worker asks (another one if this one died). A record the worker's
buffer drops (a size limit, the disk budget: sender.DropListener) is no outcome: its message is
handed back (nak, redelivered after ``handback_delay``), or terminated when no delivery can ever
succeed, never acknowledged (:class:`Settlements`, docs/fleet.md). A hand-back, by any worker, does
not count against ``retry_limit``: the workers share how often each message was handed back
(dc_destinations.handbacks). So:

- several ``dc ingest`` processes on one consumer share its messages (JetStream hands each
  message to one of them at a time);
- one killed with -9 loses nothing: what it had not acknowledged is redelivered; what it had
  delivered but not yet acknowledged is delivered twice, and a store keyed on ``record_id``
  (PgSQL's unique index) keeps it once; what it had in its queues is taken out when it starts
  again (:meth:`Ingest._forget_last_run`), as its messages come again.

The local buffer is the price of reusing the pipeline unchanged (~10 µs of SQLite per record and
destination); it also gives each destination an independent queue, so a slow one does not hold up
the others' confirmations, only the acknowledgement of the records it has not settled.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, RejectedError, SendOutcome
from dc_core.logs import BurstLog, Logger
from dc_core.params import NoParams
from dc_core.records import MalformedRecord, parse_record
from dc_core.supervision import Supervisor
from dc_destinations.config import DestinationServerConfig
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.handbacks import HandbackRecord
from dc_destinations.jetstream import HEADER_ID, HEADER_STAMP, HEADER_TOPIC
from dc_destinations.record_ids import new_record_id
from dc_destinations.routing import NO_LISTENER, TAGS_KEY, RoutingTable
from dc_destinations.sender import DROP_FILE_EVICTED, DROP_NOT_STORABLE

ACK, NAK, TERM = "ack", "nak", "term"

# Drops after which no delivery of the record by this worker can ever succeed (its payload, a file
# gone): its message is terminated. After any other drop (a size limit, the disk budget, the intake,
# a failed commit) the record is worth trying again later and the stream still holds it: its
# message is handed back (docs/fleet.md, "When a worker's buffer drops a record").
_FOR_GOOD = frozenset({DROP_NOT_STORABLE, DROP_FILE_EVICTED})


@dataclass
class _InFlight:
    key: Any
    owed: set[str]
    done: set[str] = field(default_factory=set)  # confirmed, or dead-lettered
    handed_back: dict[str, str] = field(default_factory=dict)  # destination: why it dropped the record
    given_up: dict[str, str] = field(default_factory=dict)  # destination: why it can never take it
    handbacks: int = 0  # times workers (this one, or any by the shared record) handed the message back


@dataclass(frozen=True)
class Taken:
    """A record taken in flight: the destinations to submit it to, and how often workers handed its
    message back before (deliveries that are no failure of the record)."""

    destinations: list[str]
    handbacks: int = 0


# (key, ACK | NAK | TERM, reason, destination, hand-backs): the reason and destination of the first
# drop that decided a NAK or TERM, "" for an ACK; how often the message was handed back, a NAK's own
# hand-back included.
Verdict = Callable[[Any, str, str, str, int], None]


class Settlements:
    """Which destinations still owe each record in flight an outcome; ``on_settled(key, verdict, …)``
    once none does: ACK when each confirmed it or committed its dead letter, NAK when one dropped it
    (a size limit, the disk budget…: the stream keeps it, to be delivered again), TERM when one can
    never take it.

    A record handed back is remembered (at most ``remember`` of them, the oldest forgotten first):
    when its message comes back to this worker it goes only to the destinations that had not
    settled it. Its hand-backs are known to every worker by the shared record
    (dc_destinations.handbacks), which :meth:`add` is told; this worker's own count stands in for it
    when the shared record could not be written.

    Thread-safe: senders and the buffer's writer report from their threads.
    """

    def __init__(self, on_settled: Verdict, remember: int = 20_000) -> None:
        self._owed: dict[str, _InFlight] = {}
        self._handed_back: dict[str, _InFlight] = {}
        self._remember = remember
        self._lock = threading.Lock()
        self._on_settled = on_settled

    def add(self, record_id: str, key: Any, destinations: Iterable[str], handbacks: int = 0) -> Taken | None:
        """Track ``record_id`` until ``destinations`` settled it; None when it is in flight already (a
        redelivery): ``key`` replaces the old. ``handbacks``: how often workers handed its message
        back, by the shared record."""
        with self._lock:
            known = self._owed.get(record_id)
            if known is not None:
                known.key = key
                return None
            entry = _InFlight(key, set(destinations), handbacks=handbacks)
            before = self._handed_back.pop(record_id, None)
            if before is not None:
                entry.done, entry.given_up = before.done, before.given_up
                entry.handbacks = max(handbacks, before.handbacks)
                entry.owed -= entry.done | set(entry.given_up)
            taken = Taken(sorted(entry.owed), entry.handbacks)
            if entry.owed:
                self._owed[record_id] = entry
                return taken
            verdict = self._finish(record_id, entry)  # every destination settled it before its hand-back
        self._on_settled(*verdict)
        return taken

    def settled(self, destination: str, record_ids: Sequence[str]) -> None:
        """``destination`` confirmed these records, or committed their dead letters."""
        self._outcome(destination, record_ids, None)

    def dropped(self, destination: str, record_ids: Sequence[str], reason: str) -> None:
        """``destination``'s pipeline dropped these records without an outcome (sender.DropListener)."""
        self._outcome(destination, record_ids, reason)

    def _outcome(self, destination: str, record_ids: Sequence[str], dropped: str | None) -> None:
        done = []
        with self._lock:
            for record_id in record_ids:
                entry = self._owed.get(record_id)
                # Not in flight here: a dead letter replayed (`dc buffer replay`), a salvaged row, a
                # row sent while the size limit dropped it (its message went back already).
                if entry is None or destination not in entry.owed:
                    continue
                entry.owed.discard(destination)
                if dropped is None:
                    entry.done.add(destination)
                elif dropped in _FOR_GOOD:
                    entry.given_up[destination] = dropped
                else:
                    entry.handed_back[destination] = dropped
                if not entry.owed:
                    del self._owed[record_id]
                    done.append(self._finish(record_id, entry))
        for verdict in done:
            self._on_settled(*verdict)

    def _finish(self, record_id: str, entry: _InFlight) -> tuple[Any, str, str, str, int]:
        """The verdict on a record no destination owes anything; under the lock."""
        if entry.handed_back:
            entry.handbacks += 1
            self._handed_back[record_id] = entry
            while len(self._handed_back) > self._remember:
                del self._handed_back[next(iter(self._handed_back))]
            destination, reason = next(iter(entry.handed_back.items()))
            key, entry.key, entry.handed_back = entry.key, None, {}  # the message is not kept for it
            return key, NAK, reason, destination, entry.handbacks
        if entry.given_up:
            destination, reason = next(iter(entry.given_up.items()))
            return entry.key, TERM, reason, destination, entry.handbacks
        return entry.key, ACK, "", "", entry.handbacks

    def __len__(self) -> int:
        with self._lock:
            return len(self._owed)

    def waiting(self) -> list[Any]:
        """The keys of the records not settled yet."""
        with self._lock:
            return [entry.key for entry in self._owed.values()]


class RedeliveryBound(Destination[NoParams]):
    """A destination as DC configured it, which refuses the records :meth:`doom` marked (their message
    was redelivered beyond ``retry_limit``) instead of handing them to it: the sender dead-letters
    and counts them as any other refusal."""

    def __init__(self, inner: Destination[Any], retry_limit: int = -1) -> None:
        super().__init__(inner.context, NoParams())
        self.inner = inner
        self.retry_limit = retry_limit
        self._doomed: dict[str, str] = {}
        self._lock = threading.Lock()

    def doom(self, record_id: str, reason: str) -> None:
        with self._lock:
            self._doomed[record_id] = reason

    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        with self._lock:
            doomed = {i: self._doomed.pop(r.record_id) for i, r in enumerate(batch) if r.record_id in self._doomed}
        return self._send_without(batch, doomed) if doomed else self.inner.send(batch)

    def _send_without(self, batch: Sequence[OutgoingRecord], doomed: dict[int, str]) -> SendOutcome:
        kept = [i for i in range(len(batch)) if i not in doomed]
        outcome = SendOutcome(reject=dict(doomed))
        try:
            inner = self.inner.send([batch[i] for i in kept]) if kept else None
        except RejectedError as exc:
            outcome.reject.update(dict.fromkeys(kept, str(exc)))
            return outcome
        except Exception as exc:  # the rest retried as a raising send() would be
            outcome.retry.update(dict.fromkeys(kept, f"{type(exc).__name__}: {exc}"))
            return outcome
        if inner is not None:
            for field_name in ("retry", "reject", "waiting"):
                getattr(outcome, field_name).update({kept[j]: why for j, why in getattr(inner, field_name).items()})
            outcome.retry_after = inner.retry_after
        return outcome

    @property
    def stopping(self) -> threading.Event:
        return self.inner.stopping

    def probe(self) -> Any:
        return self.inner.probe()

    def counters(self) -> dict[str, int]:
        return self.inner.counters()

    def on_activate(self) -> None:
        self.inner.on_activate()

    def on_deactivate(self) -> None:
        self.inner.on_deactivate()

    def on_cleanup(self) -> None:
        self.inner.on_cleanup()


@dataclass
class WorkerContext:
    """What a destination's context offers outside ROS (``dc check`` configures them alike): its name,
    a logger, and threads under a supervisor that logs and counts a thread that dies."""

    name: str
    logger: Logger
    supervisor: Supervisor

    def start_thread(self, target: Callable[[], Any], name: str) -> threading.Thread:
        return self.supervisor.start_thread(target, name=name)


def configure_destinations(config: DestinationServerConfig, logger_name: str = "dc.ingest") -> dict[str, Any]:
    """The destinations of ``config`` configured outside ROS, as ``dc check`` configures them."""
    import logging

    from dc_core.logs import SeverityLogger

    destinations: dict[str, Destination[Any]] = {}
    for d in config.destinations:
        plugin_logger = SeverityLogger(logging.getLogger(f"{logger_name}.{d.name}"))
        context = WorkerContext(d.name, plugin_logger, Supervisor(plugin_logger))
        destination = d.plugin_class(context, d.plugin_params)
        destination.on_configure()
        destinations[d.name] = destination
    return destinations


@dataclass
class IngestOptions:
    servers: list[str]
    stream: str
    consumer: str
    filter: str = "dc.>"
    batch: int = 500
    ack_wait: float = 60.0
    max_in_flight: int = 5000
    # Seconds before a message handed back (its record dropped by the worker's buffer) is delivered
    # again, and during which the worker takes no new messages: its buffer is full.
    handback_delay: float = 5.0
    connect: dict[str, Any] = field(default_factory=dict)  # credentials and TLS for nats.connect


@dataclass
class IngestCounters:
    received: int = 0
    redelivered: int = 0
    acknowledged: int = 0
    malformed: int = 0
    fetch_failures: int = 0
    # Messages whose record no destination takes (acknowledged: nothing will ever take them), by reason.
    unrouted: Counter[str] = field(default_factory=Counter)
    # Deliveries of redelivered messages refused beyond their destination's retry_limit (dead letters).
    over_retry_limit: int = 0
    # Messages taken that a worker (this one or another) had handed back before: their hand-backs are
    # not counted against retry_limit (the shared record, dc_destinations.handbacks).
    came_back: int = 0
    # Hand-backs the shared record could not store, and messages delivered before whose count it could
    # not read (neither bounded by retry_limit at that delivery, rather than counting hand-backs).
    handback_record_failures: int = 0
    # Records the worker's last run left in its queues, taken out at start: JetStream delivers again
    # every one whose message it did not acknowledge, and those it did are in their store already.
    left_by_last_run: int = 0
    # Messages handed back to the stream (nak, delivered again after handback_delay) because a
    # destination's queue dropped their record, by reason (dc_destinations.sender's DROP_*).
    handed_back: Counter[str] = field(default_factory=Counter)
    # Messages terminated because a destination can never take their record (not storable), by reason.
    terminated: Counter[str] = field(default_factory=Counter)


class Ingest:
    """One ingest worker: see the module documentation."""

    def __init__(
        self,
        config: DestinationServerConfig,
        destinations: dict[str, Destination[Any]],
        options: IngestOptions,
        storage_path: Path,
        logger: Logger,
    ) -> None:
        import dataclasses

        self.options = options
        self.logger = logger
        self.counters = IngestCounters()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._settled: asyncio.Queue[tuple[Any, str, str, str, int]] | None = None
        self._handbacks: HandbackRecord | None = None  # opened by run()
        self._handing_back: set[asyncio.Task[None]] = set()
        self.settlements = Settlements(self._on_settled, remember=max(options.max_in_flight * 4, 1000))
        self.routing = RoutingTable.from_destinations(config.destinations)
        self._wrapped = {
            d.name: RedeliveryBound(destinations[d.name], d.delivery.retry_limit) for d in config.destinations
        }
        settings = dataclasses.replace(config.node.flb, storage_path=str(storage_path))
        self.pipeline = DeliveryPipeline(
            settings, {d.name: (self._wrapped[d.name], d.delivery) for d in config.destinations}, logger
        )
        # A record is settled for a destination when it confirmed it, or once its dead letter is on
        # disk: acknowledged before that, a crash would leave it nowhere (docs/fleet.md).
        self.pipeline.add_outcome_listener(lambda name, record_ids, _dead: self.settlements.settled(name, record_ids))
        # A record the buffer drops (its size limit, the disk budget…) is no outcome: its message goes
        # back to the stream, which still holds it, never acknowledged (docs/fleet.md).
        self.pipeline.add_drop_listener(self.settlements.dropped)
        self._handback_log = BurstLog(
            logger.warning,
            f"messages handed back to the stream (delivered again in {options.handback_delay:g} s; "
            "counted in handed_back)",
        )
        self._terminated_log = BurstLog(logger.error, "messages terminated: a destination can never take their record")
        self._handback_record_log = BurstLog(
            logger.warning,
            "the shared record of hand-backs (a JetStream key-value bucket) failed; those messages are not "
            "bounded by retry_limit at their next delivery (counted in handback_record_failures)",
        )
        # The loop's time until which no new message is taken: the buffer dropped records just now.
        self._resume_fetch_at = 0.0
        self.pipeline.add_metrics_section("ingest", self._counters_document)
        self._logged: set[tuple[str, str]] = set()
        self.stop_requested = asyncio.Event()

    def _counters_document(self) -> dict[str, Any]:
        # Not dataclasses.asdict: it would rebuild the Counter from (key, value) pairs.
        c = self.counters
        return {
            **vars(c),
            "unrouted": dict(c.unrouted),
            "handed_back": dict(c.handed_back),
            "terminated": dict(c.terminated),
        }

    def _on_settled(self, msg: Any, verdict: str, reason: str, destination: str, handbacks: int) -> None:
        # From a sender's or the writer's thread: the ack (nak, term) goes out on the loop.
        assert self._loop is not None and self._settled is not None
        self._loop.call_soon_threadsafe(self._settled.put_nowait, (msg, verdict, reason, destination, handbacks))

    async def run(self) -> IngestCounters:
        import nats
        import nats.errors
        from nats.js.api import AckPolicy, ConsumerConfig

        self._loop = asyncio.get_running_loop()
        self._settled = asyncio.Queue()
        o = self.options
        nc = await nats.connect(servers=o.servers, name=f"dc ingest {o.consumer}", **o.connect)
        js = nc.jetstream()
        config = ConsumerConfig(
            durable_name=o.consumer,
            ack_policy=AckPolicy.EXPLICIT,
            ack_wait=o.ack_wait,
            max_ack_pending=max(o.max_in_flight * 4, 1000),
            filter_subject=o.filter,
        )
        sub = await js.pull_subscribe(o.filter, durable=o.consumer, stream=o.stream, config=config)
        try:
            shared = self._handbacks = await HandbackRecord.open(js, o.stream, o.consumer)
        except Exception:
            await nc.close()
            raise
        self.counters.left_by_last_run = self._forget_last_run()
        self.pipeline.start()
        acker = asyncio.create_task(self._acknowledge())
        self.logger.info(
            f"ingesting {o.filter} of stream {o.stream} as consumer {o.consumer} from {', '.join(o.servers)}"
        )
        try:
            while not self.stop_requested.is_set():
                self._handback_log.tick()
                self._terminated_log.tick()
                self._handback_record_log.tick()
                room = o.max_in_flight - len(self.settlements)
                if room <= 0:
                    await asyncio.sleep(0.02)
                    continue
                pause = self._resume_fetch_at - self._loop.time()
                if pause > 0:  # what it would take now would be dropped too, and handed back
                    await asyncio.sleep(min(pause, 0.1))
                    continue
                try:
                    messages = await sub.fetch(min(o.batch, room), timeout=1.0)
                except (TimeoutError, nats.errors.TimeoutError):
                    continue  # nothing to take within the second
                except Exception as exc:  # a server lost, a cluster electing: nats-py reconnects meanwhile
                    self.counters.fetch_failures += 1
                    self.logger.warning(f"cannot fetch from stream {o.stream}: {exc!r}; trying again in 1 s")
                    await asyncio.sleep(1.0)
                    continue
                # Only for messages delivered before: no round-trip on the normal path.
                handbacks = await shared.counts(messages)
                malformed, unrouted = self._take(messages, handbacks)
                for msg in malformed:
                    await msg.term()  # never redelivered: it can never be delivered
                for msg in unrouted:
                    await self._ack(msg)
        finally:
            self.pipeline.stop(self.pipeline.settings.grace)
            # What is not settled goes back at once rather than after ack_wait: another worker takes it.
            for msg in self.settlements.waiting():
                try:
                    await msg.nak()
                except Exception as exc:  # the connection may be gone: JetStream redelivers after ack_wait
                    self.logger.warning(f"cannot give back a message: {exc}")
            await self._drain_acks()
            acker.cancel()
            if self._handing_back:
                await asyncio.wait(set(self._handing_back))
            self._handback_log.tick()
            self._terminated_log.tick()
            self._handback_record_log.tick()
            await nc.close()
            self.pipeline.release_storage()
        return self.counters

    def _forget_last_run(self) -> int:
        """Take out of the queues what the worker's last run left there (killed, or stopped past its
        grace): how many records.

        Each is either settled, its message acknowledged, and then its destination has it, or not,
        and then its message comes again: sent from here too, a record would reach its store twice,
        or its dead letters twice (the message redelivered, the old row sent). A record is settled
        for a destination only once it left its queue for good (confirmed, or its dead letter
        committed), so no row here is a record the stream let go of.
        """
        from dc_destinations.buffer import BufferCorrupted, SqliteBuffer

        storage_file = self.pipeline.claim_storage()
        if not storage_file.exists():
            return 0
        try:
            with contextlib.closing(SqliteBuffer(storage_file, repair=False)) as buffer:
                left = {name: buffer.evict_oldest(name, sys.maxsize)[0] for name in self._wrapped}
        except BufferCorrupted as exc:  # the pipeline sets it aside and salvages it: those are sent, as before
            self.logger.warning(f"the queues of the last run are not emptied: {exc}")
            return 0
        taken = {name: n for name, n in left.items() if n}
        if taken:
            self.logger.info(
                "left in the queues by the last run, taken out (JetStream delivers again the records whose "
                "message was not acknowledged; the others are in their store): "
                + ", ".join(f"{name} {n}" for name, n in taken.items())
            )
        return sum(taken.values())

    def _take(self, messages: list[Any], handbacks: dict[int, int | None]) -> tuple[list[Any], list[Any]]:
        """Route the messages' records to the pipeline: (messages that hold no DC record, messages whose
        record no destination takes). ``handbacks``: the shared record's counts of the messages
        delivered before, by stream sequence (None: unreadable)."""
        malformed, unrouted = [], []
        for msg in messages:
            self.counters.received += 1
            taken = self._record_of(msg)
            if taken is None:
                malformed.append(msg)
                continue
            topic, stamp_ns, record_id, data = taken
            # The robot's routing consumed its tags (they named the robot's destinations): a record
            # without any goes to every destination listening on its topic; one that still has tags
            # (not published by DC) to those it names, as on a robot. trusted=False: a robot's record
            # never makes this worker read files of its own (docs/security.md).
            listeners = self.routing.listeners(topic)
            if listeners and TAGS_KEY not in data:
                data[TAGS_KEY] = listeners
            routed = self.routing.route(topic, data, stamp_ns, partial(str, record_id), trusted=False)
            if routed.refused:
                self._log_once(topic, f"not delivered to {', '.join(routed.refused)}: they read files records name")
            if routed.unrouted_reason is not None:
                reason = routed.unrouted_reason if listeners else NO_LISTENER
                self.counters.unrouted[reason] += 1
                self._log_once(topic, f"a record reaches no destination: {reason}")
                unrouted.append(msg)
                continue
            shared = handbacks.get(msg.metadata.sequence.stream, 0)
            names = [name for name, _ in routed.deliveries]
            in_flight = self.settlements.add(record_id, msg, names, shared or 0)
            if in_flight is None:
                self.counters.redelivered += 1  # still in this worker's queues: acknowledged when settled
                continue
            if in_flight.handbacks:
                self.counters.came_back += 1
            if shared is None:
                self.counters.handback_record_failures += 1
                self._handback_record_log.event(1, f"cannot read message {msg.metadata.sequence.stream}'s count")
            # A hand-back, by any worker, is no failure of the record: only the other deliveries (a
            # worker killed, stopped, or past ack_wait) count against retry_limit. Not knowing the
            # hand-backs, the bound waits for the next delivery rather than count them.
            redeliveries = -1 if shared is None else msg.metadata.num_delivered - 1 - in_flight.handbacks
            for name, outgoing in routed.deliveries:
                if name not in in_flight.destinations:
                    continue  # settled it before the message was handed back
                limit = self._wrapped[name].retry_limit
                if 0 <= limit < redeliveries:
                    self.counters.over_retry_limit += 1
                    besides = f" (besides {in_flight.handbacks} hand-backs, which do not count)"
                    self._wrapped[name].doom(
                        record_id,
                        f"its message was redelivered {redeliveries} times, beyond retry_limit {limit}"
                        + (besides if in_flight.handbacks else ""),
                    )
                self.pipeline.submit(name, outgoing)
        return malformed, unrouted

    def _log_once(self, topic: str, what: str) -> None:
        if (topic, what) not in self._logged:
            self._logged.add((topic, what))
            self.logger.warning(f"{topic}: {what}; further ones are counted (dc ingest's summary)")

    def _record_of(self, msg: Any) -> tuple[str, int, str, dict[str, Any]] | None:
        """(topic, stamp in ns, record_id, record) of a message: from the headers the NATS destination
        sets, else its subject, its time in the stream, the record's own record_id."""
        try:
            data = parse_record(msg.data.decode("utf-8"))
        except (UnicodeDecodeError, MalformedRecord) as exc:
            self.counters.malformed += 1
            self.logger.error(
                f"message {msg.metadata.sequence.stream} on {msg.subject} is not a DC record ({exc}): terminated"
            )
            return None
        headers = msg.headers or {}
        record_id = headers.get(HEADER_ID) or str(data.get("record_id") or "") or new_record_id()
        topic = headers.get(HEADER_TOPIC) or msg.subject
        stamp = headers.get(HEADER_STAMP, "")
        stamp_ns = int(stamp) if stamp.isdigit() else int(msg.metadata.timestamp.timestamp() * 1e9)
        return topic, stamp_ns, record_id, data

    async def _acknowledge(self) -> None:
        assert self._settled is not None
        while True:
            await self._answer(*await self._settled.get())

    async def _drain_acks(self) -> None:
        assert self._settled is not None
        while not self._settled.empty():
            await self._answer(*self._settled.get_nowait())

    async def _answer(self, msg: Any, verdict: str, reason: str, destination: str, handbacks: int) -> None:
        """Tell JetStream what became of a message whose record every destination settled."""
        if verdict == ACK:
            await self._ack(msg)
            return
        what = f"destination {destination}: {reason}"
        if verdict == NAK:
            self.counters.handed_back[reason] += 1
            self._handback_log.event(1, what)
            assert self._loop is not None
            self._resume_fetch_at = self._loop.time() + self.options.handback_delay
            # Its own task: the bucket's round-trip must not hold up the acks queued behind it.
            task = asyncio.create_task(self._hand_back(msg, handbacks))
            self._handing_back.add(task)
            task.add_done_callback(self._handing_back.discard)
            return
        self.counters.terminated[reason] += 1
        self._terminated_log.event(1, f"{what} (message {msg.metadata.sequence.stream} on {msg.subject})")
        try:
            await msg.term()
        except Exception as exc:  # JetStream delivers it again after ack_wait all the same
            self.logger.warning(f"cannot terminate message {msg.metadata.sequence.stream}: {exc}")

    async def _hand_back(self, msg: Any, handbacks: int) -> None:
        """Record the hand-back in the shared record, then nak: once the nak is out, any worker may take
        the message, and must find it counted. Killed in between, the message comes back after
        ack_wait with this hand-back counted although none happened: one delivery not bounded, and
        nothing lost (nothing here acknowledges)."""
        assert self._handbacks is not None
        try:
            await self._handbacks.record(msg, handbacks)
        except Exception as exc:  # this worker's own count still knows it, if the message comes back here
            self.counters.handback_record_failures += 1
            self._handback_record_log.event(1, f"cannot record message {msg.metadata.sequence.stream}: {exc!r}")
        try:
            await msg.nak(delay=self.options.handback_delay)
        except Exception as exc:  # JetStream delivers it again after ack_wait all the same
            self.logger.warning(f"cannot nak message {msg.metadata.sequence.stream}: {exc}")

    async def _ack(self, msg: Any) -> None:
        try:
            await msg.ack()
            self.counters.acknowledged += 1
        except Exception as exc:  # redelivered after ack_wait, delivered again: a duplicate the store removes
            self.logger.warning(f"cannot acknowledge message {msg.metadata.sequence.stream}: {exc}")


def connect_options_from_env(environ: dict[str, str] | None = None) -> dict[str, Any]:
    """nats.connect's credentials from the environment, never from the command line (it is visible in ps)."""
    env = os.environ if environ is None else environ
    options: dict[str, Any] = {}
    if env.get("NATS_USER"):
        options.update(user=env["NATS_USER"], password=env.get("NATS_PASSWORD") or None)
    if env.get("NATS_TOKEN"):
        options["token"] = env["NATS_TOKEN"]
    if env.get("NATS_CREDS"):
        options["user_credentials"] = env["NATS_CREDS"]
    if env.get("NATS_NKEY"):
        options["nkeys_seed"] = env["NATS_NKEY"]
    return options


def run_ingest(ingest: Ingest, report_every: float = 10.0) -> IngestCounters:
    """Run ``ingest`` until SIGTERM or SIGINT; its counters and the destinations' logged every ``report_every`` s."""

    async def main() -> IngestCounters:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, ingest.stop_requested.set)

        async def report() -> None:
            while True:
                await asyncio.sleep(report_every)
                ingest.logger.info(f"ingest: {summary(ingest)}")

        reporter = asyncio.create_task(report())
        try:
            return await ingest.run()
        finally:
            reporter.cancel()

    started = time.monotonic()
    counters = asyncio.run(main())
    ingest.logger.info(f"ingest stopped after {time.monotonic() - started:.0f} s: {summary(ingest)}")
    return counters


def summary(ingest: Ingest) -> str:
    c = ingest.counters
    parts = [
        f"received {c.received}, acknowledged {c.acknowledged}, taken again while in flight {c.redelivered}, "
        f"malformed {c.malformed}, unrouted {sum(c.unrouted.values())}, "
        f"dead-lettered as redelivered beyond retry_limit {c.over_retry_limit}, fetch failures {c.fetch_failures}, "
        f"left by the last run {c.left_by_last_run}, handed back {sum(c.handed_back.values())}"
        + (f" ({', '.join(f'{why} {n}' for why, n in sorted(c.handed_back.items()))})" if c.handed_back else "")
        + f", came back after a hand-back {c.came_back}, hand-back record failures {c.handback_record_failures}"
        + f", terminated {sum(c.terminated.values())}"
    ]
    for name, m in ingest.pipeline.metrics().items():
        waiting = "" if m["buffered"] is None else f", buffered {m['buffered']}"
        parts.append(f"{name}: sent {m['sent']}, dead_lettered {m['dead_lettered']}{waiting}")
    return "; ".join(parts)
