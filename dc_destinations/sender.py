"""How a destination's ``send()`` is called, and retried: one sender thread per destination.

For a destination plugin's author, this is the whole story of delivery:

1. Records wait in the destination's queue in the durable buffer (dc_destinations.buffer), in
   the order they arrived.
2. The sender reads the oldest ``batch_size`` of them and calls ``send(batch)`` on its own thread,
   never on the server's main loop: ``send`` may block on the network (meanwhile the next batch
   is read, to be sent once this one is confirmed, and the batch confirmed before is deleted from
   the queue). It wakes up when ``batch_size`` records wait or ``flb.flush`` seconds passed.
3. ``send`` returns ``None``: every record is confirmed and deleted from the queue. It returns a
   :class:`~dc_core.destination.SendOutcome`: the indexes in ``reject`` go to the dead letters with
   their reason, those in ``retry`` stay in the queue with one more attempt counted, the others are
   confirmed. It raises :class:`~dc_core.destination.RejectedError`: the whole batch is
   dead-lettered. Any other exception (:class:`~dc_core.destination.RetryableError`, a socket
   error…) means the whole batch is retried.
4. A retry waits with exponential backoff and full jitter (``scheduler_base`` doubling up to
   ``scheduler_cap``); a success resets it. A ``retry_after`` the destination passes on (the
   server's Retry-After) lengthens that wait to at least it, and never beyond ``scheduler_cap``.
   A record retried more than ``retry_limit`` times (-1: never given up) is dead-lettered with its
   last error.
5. ``send`` never runs at the same time as the destination's ``on_deactivate`` or ``on_cleanup``
   (:class:`Gate`): a plugin needs no lock for the connection they share. A stop whose grace ends
   while ``send`` still runs sets the destination's ``stopping`` event and leaves those hooks to
   run on the sender's thread as soon as ``send`` returns: the server's transition is not held up.
6. ``send`` is called again with the same records (same ``record_id``) after a retry or a crash
   of the server between ``send`` and the deletion: a destination that can deduplicate on
   ``record_id`` delivers exactly once.

7. Whoever must know when an outcome is final (``dc ingest`` acknowledges a record's message then)
   registers an :data:`OutcomeListener`: called with the records the destination confirmed once
   ``send`` returned, and with the records dead-lettered only once their dead letters are committed
   to the buffer, never before: a crash between the two leaves them in the queue, to be sent again.

A failure of the buffer itself (a full disk) is counted in ``failed``, logged, and retried with the
same backoff: a sender never dies. Dead letters are bounded per destination by
``dead_letter_limit_size``, the oldest deleted first.
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

from dc_core.destination import (
    Destination,
    OutgoingRecord,
    RejectedError,
    RetryableError,
    SendOutcome,
    StoredRecord,
)
from dc_core.logs import BurstLog, Logger
from dc_core.records import MalformedRecord, parse_record
from dc_destinations.backoff import Backoff
from dc_destinations.buffer import Buffer, BufferClosed, BufferCorrupted, BufferedRow, QueueLimit
from dc_destinations.health import DEFAULT_UNHEALTHY_AFTER_S, DestinationHealth, attention_needed
from dc_destinations.links import FILES, HOLD_POLL_S, Network, Pacer, SendRules, TokenBucket
from dc_destinations.metrics import DestinationMetrics
from dc_destinations.saved_files import SavedFiles
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams, parse_rate, parse_size, priority_of

_T = TypeVar("_T")

# (destination, record_ids, dead_lettered): called on the sender's thread with the records the
# destination confirmed (dead_lettered False; their rows leave the queue afterwards, and a crash
# before that sends them again), and with those moved to the dead letters (True) once that move is
# committed. Fast, and raises nothing: what it raises is logged, the delivery goes on.
OutcomeListener = Callable[[str, list[str], bool], None]

# (destination, record_ids, reason): records that left the pipeline for that destination with no
# outcome, neither confirmed nor dead-lettered: called on the thread that dropped them, once the
# drop is committed. The reasons, for whoever decides what becomes of them (dc_destinations.ingest):
DROP_SIZE_LIMIT = "size_limit"  # storage_total_limit_size reached (when_full drop_newest or drop_oldest)
DROP_DISK_BUDGET = "disk_budget"  # evicted unsent to keep flb.disk_budget
DROP_INTAKE = "intake"  # refused at the hand-over: intake_queue_limit, or the pipeline not running
DROP_NOT_COMMITTED = "not_committed"  # its group commit failed at the stop (a full disk)
DROP_NOT_STORABLE = "not_storable"  # the buffer cannot hold it (not valid UTF-8 JSON): never deliverable
DROP_FILE_EVICTED = "file_evicted"  # the saved file it names was evicted before this destination had it
DropListener = Callable[[str, list[str], str], None]


def tell_dropped(
    listeners: Sequence[DropListener], logger: Logger, destination: str, record_ids: list[str], reason: str
) -> None:
    """Each listener told of ``record_ids`` dropped; one that raises is logged, never the caller's failure."""
    if not record_ids:
        return
    for listener in listeners:
        try:
            listener(destination, record_ids, reason)
        except Exception as exc:
            logger.error(
                f"destination {destination}: a drop listener failed: {type(exc).__name__}: {exc}\n"
                f"{traceback.format_exc()}"
            )


class Gate:
    """``send`` and the destination's other hooks one at a time: what :meth:`run` is given waits for
    the ``send`` under way, without holding up its caller (see the module documentation, 5.)."""

    def __init__(self, logger: Logger) -> None:
        self._busy = threading.Lock()
        self._owed: list[Callable[[], None]] = []
        self._owed_lock = threading.Lock()
        self._logger = logger

    def send(self, send: Callable[[], _T]) -> _T:
        with self._busy:
            result = send()
        self._settle()
        return result

    def run(self, hook: Callable[[], None]) -> bool:
        """``hook()`` now when no ``send`` runs: True, and what it raises passes. Otherwise False, and
        ``hook`` runs on the sender's thread once the ``send`` returns, what it raises logged there."""
        if self._busy.acquire(blocking=False):
            try:
                hook()
            finally:
                self._busy.release()
            self._settle()
            return True
        with self._owed_lock:
            self._owed.append(hook)
        # The send may have ended between the acquire and the append: settled here then.
        self._settle()
        return False

    def _settle(self) -> None:
        # Whoever releases the gate, or adds to _owed, runs what is owed unless the other holds the
        # gate: that one then runs it after its release. Nothing owed is left behind.
        while self._owed and self._busy.acquire(blocking=False):
            try:
                with self._owed_lock:
                    owed, self._owed = self._owed, []
                for hook in owed:
                    try:
                        hook()
                    except Exception as exc:
                        self._logger.error(f"{exc} (run once the send() that outlived the grace returned)")
            finally:
                self._busy.release()


@dataclass
class Route:
    """One destination's delivery: its plugin and parameters, counters, logs and wake-up."""

    name: str
    destination: Destination[Any]
    params: DestinationDeliveryParams
    limit: QueueLimit
    dead_letter_max_bytes: int | None
    metrics: DestinationMetrics
    drop_log: BurstLog
    failure_log: BurstLog
    dead_letter_log: BurstLog
    dead_letter_drop_log: BurstLog
    malformed_log: BurstLog
    evict_log: BurstLog
    health: DestinationHealth
    gate: Gate
    logger: Logger
    rules: SendRules
    pacer: Pacer
    wakeup: threading.Event = field(default_factory=threading.Event)
    # Why the destination may not send now (its only_when, dc_destinations.links); "" while it may.
    held: str = ""
    # Records committed since the sender last found its queue empty: it wakes at batch_size.
    pending_hint: int = 0
    thread: threading.Thread | None = None
    # The fields naming the files this destination carries (Destination.file_fields), and the
    # ledger of saved files while a disk budget is set (dc_destinations.saved_files).
    file_fields: list[str] = field(default_factory=list)
    saved: SavedFiles | None = None

    @classmethod
    def of(
        cls,
        name: str,
        destination: Destination[Any],
        params: DestinationDeliveryParams,
        logger: Logger,
        *,
        network: Network,
        links: dict[str, TokenBucket],
        burst_s: float,
        stop: threading.Event,
    ) -> Route:
        buckets = []
        rate = parse_rate(params.max_bytes_per_s, f"destination_server.{name}.max_bytes_per_s")
        if rate is not None:
            buckets.append(TokenBucket(rate, max(rate * burst_s, 1.0)))
        if params.link:
            buckets.append(links[params.link])
        pacer = Pacer(buckets, params.priority, stop)
        # Files a plugin sends itself (MinIO's) go through the same caps, after the records waiting.
        destination.__dict__["_dc_pace"] = lambda n: pacer.take(n, FILES)
        return cls(
            name=name,
            destination=destination,
            params=params,
            limit=QueueLimit(
                max_bytes=parse_size(params.storage_total_limit_size), drop_oldest=params.when_full == "drop_oldest"
            ),
            dead_letter_max_bytes=parse_size(params.dead_letter_limit_size),
            metrics=DestinationMetrics(),
            drop_log=BurstLog(logger.warning, f"destination {name}: records dropped"),
            failure_log=BurstLog(logger.warning, f"destination {name}: delivery failed, will retry"),
            dead_letter_log=BurstLog(logger.error, f"destination {name}: records dead-lettered"),
            dead_letter_drop_log=BurstLog(
                logger.warning,
                f"destination {name}: oldest dead letters deleted "
                f"(dead_letter_limit_size {params.dead_letter_limit_size})",
            ),
            malformed_log=BurstLog(
                logger.error, f"destination {name}: records not stored, they are not valid UTF-8 JSON"
            ),
            evict_log=BurstLog(
                logger.warning,
                f"destination {name}: records evicted unsent to keep DC within its disk budget "
                f"(retention_priority {params.retention_priority}"
                + "".join(f", {key} {p}" for key, p in params.retention_priorities.items())
                + ")",
            ),
            health=DestinationHealth(name, params.unhealthy_after or DEFAULT_UNHEALTHY_AFTER_S, logger),
            gate=Gate(logger),
            logger=logger,
            rules=SendRules(params.only_when, network),
            pacer=pacer,
            file_fields=destination.file_fields(),
        )

    @property
    def per_topic_retention(self) -> bool:
        """Whether its records' retention priorities differ by input topic (``retention_priorities``)."""
        return any(p != self.params.retention_priority for p in self.params.retention_priorities.values())

    def retention_of(self, topic: str) -> int:
        """The retention priority of its records that arrived on ``topic``."""
        return priority_of(self.params.retention_priorities, self.params.retention_priority, topic)

    def tick_logs(self) -> None:
        self.drop_log.tick()
        self.failure_log.tick()
        self.dead_letter_log.tick()
        self.dead_letter_drop_log.tick()
        self.malformed_log.tick()
        self.evict_log.tick()


@dataclass
class Closing:
    """Shared by the pipeline and its senders: set when the pipeline stops; senders deliver until ``deadline``."""

    event: threading.Event = field(default_factory=threading.Event)
    deadline: float = math.inf

    def reset(self) -> None:
        self.event.clear()
        self.deadline = math.inf


class Sender:
    """The thread that delivers one destination's queue; see the module documentation.

    ``wait`` (called with each backoff delay; returns True to give up because the pipeline is
    stopping) and ``uniform`` (the jitter draw) exist for tests.
    """

    def __init__(
        self,
        route: Route,
        buffer: Buffer,
        settings: DeliveryParams,
        closing: Closing,
        *,
        clock: Callable[[], float] = time.monotonic,
        wait: Callable[[float], bool] | None = None,
        uniform: Callable[[float, float], float] | None = None,
        listeners: Sequence[OutcomeListener] = (),
        drop_listeners: Sequence[DropListener] = (),
    ) -> None:
        self.route = route
        self.buffer = buffer
        self._listeners = listeners
        self._drop_listeners = drop_listeners
        self.settings = settings
        self.closing = closing
        self._clock = clock
        self._wait = wait
        self._backoff = Backoff(settings.scheduler_base, settings.scheduler_cap, uniform)
        # Row ids of the last batch the destination confirmed whole, not yet deleted from the queue,
        # and the delete of the batch before, running in the reader thread (see _run).
        self._confirmed: list[int] = []
        self._acknowledging: Future[None] | None = None
        # The server's wish (seconds) carried by the last failed send, for the backoff that follows.
        self._retry_after: float | None = None

    def run(self) -> None:
        # While send() waits on the destination, a reader thread reads and prepares the next batch
        # and deletes the batch confirmed before it: the sender's own work (SQLite, building the
        # records) and the destination's server then use the machine at the same time instead of
        # one after the other (docs/performance.md).
        with ThreadPoolExecutor(1, thread_name_prefix=f"dc-read-{self.route.name}") as reader:
            try:
                self._run(reader)
            finally:
                self._settle_on_exit()

    def _run(self, reader: ThreadPoolExecutor) -> None:
        route, buffer = self.route, self.buffer
        batch_size = route.params.batch_size
        # The batch after the one in flight, being read; and the row id it was read after.
        ahead: Future[_Batch] | None = None
        ahead_after = 0
        while True:
            closing = self.closing.event.is_set()
            if closing and self._clock() >= self.closing.deadline:
                return
            try:
                if route.rules.active and self._held():
                    ahead = None
                    if closing:
                        return
                    self._wait_held()
                    continue
                if route.saved is not None and route.destination.records_evictions and self._tell_evictions():
                    ahead = None
                    if closing or self._wait_backoff(self._retry_delay()):
                        return
                    continue
                batch = self._still_next(ahead, ahead_after) if ahead is not None else None
                ahead = None
                if batch is None:
                    self._settle()  # a queue read from its head holds no confirmed row
                    buffer.release(route.name)  # nor any row in a send(), whatever failed on the way
                    batch = self._prepare(buffer.read_batch(route.name, batch_size))
                else:
                    # Submitted before the next read ahead, so that once that read is done, this
                    # delete is too: the reader thread is idle when the read's result is checked.
                    self._acknowledge_behind(reader)
            except BufferCorrupted:
                ahead = None
                continue
            except BufferClosed:
                return
            except Exception as exc:  # disk full, I/O error: the sender waits and tries again, never dies
                ahead = None
                if self._buffer_trouble(f"reading the buffer: {type(exc).__name__}: {exc}"):
                    return
                continue
            rows = batch.rows
            if not rows:
                if closing:
                    return
                self._idle()
                route.tick_logs()
                continue
            if len(rows) == batch_size:  # a short batch emptied the queue: nothing to read ahead
                ahead_after = rows[-1].row_id
                ahead = reader.submit(self._read_after, ahead_after)
            try:
                must_retry = self.deliver(rows, batch, defer_delete=True)
            except (BufferClosed, _Stopping):
                return
            except BufferCorrupted:
                ahead = None
                continue
            except Exception as exc:
                ahead = None
                # The destination may have taken the batch before the buffer failed to record it
                # (deleting needs disk space too): those records are sent again, as after a crash.
                if self._buffer_trouble(f"updating the buffer: {type(exc).__name__}: {exc}"):
                    return
                continue
            if must_retry:
                ahead = None  # the retried records come first again: read from the head
                if self._wait_backoff(self._retry_delay()):
                    return
            else:
                self._backoff.reset()
                if len(rows) < batch_size and not closing:
                    try:
                        self._settle()  # the queue as it is, for whoever looks, while the sender waits
                    except BufferClosed:
                        return
                    except Exception as exc:
                        if self._buffer_trouble(f"updating the buffer: {type(exc).__name__}: {exc}"):
                            return
                        continue
                    self._idle()

    def _acknowledge(self, row_ids: list[int]) -> None:
        """Forget rows the destination confirmed, and count them sent."""
        self.buffer.delete(self.route.name, row_ids)
        self.route.metrics.add("sent", len(row_ids))

    def _acknowledge_behind(self, reader: ThreadPoolExecutor) -> None:
        """The delete of the last batch confirmed handed to the reader thread, once the one before it is done.

        A delete that failed raises here (its rows are sent again, as after a crash); the rows of
        the last batch then stay in ``_confirmed``, for :meth:`_settle`.
        """
        if self._acknowledging is not None:
            done, self._acknowledging = self._acknowledging, None
            done.result()
        if self._confirmed:
            confirmed, self._confirmed = self._confirmed, []
            self._acknowledging = reader.submit(self._acknowledge, confirmed)

    def _settle(self) -> None:
        """Every confirmed row deleted from the queue, the deletes in flight waited for; raises what they raised.

        Rows whose delete failed are forgotten here, and sent again (at least once, as after a crash).
        """
        acknowledging, self._acknowledging = self._acknowledging, None
        confirmed, self._confirmed = self._confirmed, []
        if acknowledging is not None:
            acknowledging.result()
        if confirmed:
            self._acknowledge(confirmed)

    def _settle_on_exit(self) -> None:
        try:
            self._settle()
        except BufferClosed:
            pass  # the pipeline closed the buffer: the rows are sent again at the next start
        except Exception as exc:
            what = f"updating the buffer: {type(exc).__name__}: {exc}"
            self.route.metrics.add("failed")
            self.route.metrics.set_error(what)
            self.route.failure_log.event(1, what)

    def _read_after(self, row_id: int) -> _Batch:
        """In the reader thread: the batch after ``row_id``, prepared."""
        return self._prepare(self.buffer.read_batch(self.route.name, self.route.params.batch_size, after_id=row_id))

    def _still_next(self, ahead: Future[_Batch], after_id: int) -> _Batch | None:
        """The batch read ahead after row ``after_id``, if it is still what a read from the head would give; else None.

        Called once the batch up to ``after_id`` left the queue, or is confirmed and waits for its
        delete (no record of it retried). The read ahead is still the head's then when it is full
        and its first row is still the first after ``after_id``. Rows leave a queue from its head
        (sent, dead-lettered, dropped by the size limit), so none of its rows left since the read,
        and a row committed since took an id above them all: the batch is still the first
        ``batch_size`` rows. Otherwise (a short read, a size limit that dropped its first rows)
        the head is read again: rare, and a read costs far less than a send.
        """
        batch = ahead.result()
        if len(batch.rows) < self.route.params.batch_size:
            return None
        first = self.buffer.read_batch(self.route.name, 1, after_id=after_id)
        if not first or first[0].row_id != batch.rows[0].row_id:
            return None
        return batch

    def _held(self) -> bool:
        """Whether the destination's only_when holds its records now; a change is logged once, and
        the confirmed rows are deleted before holding (raises what that raises)."""
        route = self.route
        reason = route.rules.held()
        if reason != route.held:
            if reason:
                route.logger.info(f"destination {route.name} {reason}; its records wait in the buffer")
            else:
                was = route.held.removeprefix("held: ")
                route.logger.info(f"destination {route.name} sending again (was held: {was})")
            route.held = reason
        if reason:
            self._settle()
        return bool(reason)

    def _wait_held(self) -> None:
        """Until the rules are looked at again: a condition's change, or HOLD_POLL_S for the others."""
        self.route.wakeup.wait(HOLD_POLL_S)
        self.route.wakeup.clear()
        self.route.tick_logs()

    def _idle(self) -> None:
        """Wait for batch_size records to be committed, or flush seconds."""
        self.route.pending_hint = 0
        self.route.wakeup.wait(self.settings.flush)
        self.route.wakeup.clear()

    def _buffer_trouble(self, what: str) -> bool:
        """Count and log a failed buffer operation, then back off; True when the pipeline is stopping."""
        self.route.metrics.add("failed")
        self.route.metrics.set_error(what)
        self.route.failure_log.event(1, what)
        return self._wait_backoff(self._backoff.next_delay())

    def _retry_delay(self) -> float:
        """The backoff's next delay, lengthened to the server's retry_after within scheduler_cap."""
        delay = self._backoff.next_delay()
        if self._retry_after is not None:
            delay = max(delay, min(self._retry_after, self.settings.scheduler_cap))
        return delay

    def _wait_backoff(self, delay: float) -> bool:
        if self._wait is not None:
            return self._wait(delay) or self.closing.event.is_set()
        return self.closing.event.wait(delay)

    def _prepare(self, rows: list[BufferedRow]) -> _Batch:
        """The records to send of ``rows``, and those that must not be sent; no I/O."""
        batch = _Batch(rows)
        records, sent_rows, unreadable = batch.records, batch.sent_rows, batch.unreadable
        saved = self.route.saved
        skip = saved.skipped_for(self.route.name) if saved is not None and self.route.file_fields else None
        for row in rows:
            if skip and row.record_id in skip:
                batch.evicted.append(row)  # its file was evicted before this destination had it
                continue
            if row.as_appended():
                records.append(StoredRecord(row.record_id, row.topic, row.stamp_ns, json_text=row.payload))
                sent_rows.append(row)
                continue
            try:
                data = parse_record(row.payload)
            except MalformedRecord as exc:
                # Written by an older DC (it let NaN through) or changed by hand: never sent as is.
                unreadable.append((row, f"unreadable payload in the buffer: {exc}"))
                continue
            records.append(OutgoingRecord(row.record_id, row.topic, row.stamp_ns, data, json_text=row.payload))
            sent_rows.append(row)
        return batch

    def deliver(self, rows: list[BufferedRow], prepared: _Batch | None = None, *, defer_delete: bool = False) -> bool:
        """One send() of ``rows`` (``prepared``: as :meth:`_prepare` made them); True when some must be retried.

        ``defer_delete``: a batch confirmed whole is left in ``_confirmed``, to be deleted from the
        queue while the next batch is sent (:meth:`_run`).
        """
        route, buffer = self.route, self.buffer
        batch = prepared if prepared is not None else self._prepare(rows)
        records, sent_rows, unreadable = batch.records, batch.sent_rows, batch.unreadable
        if unreadable:
            # Told only what was moved: a row the size limit dropped meanwhile has no dead letter.
            moved_ids: list[str] = []
            route.metrics.add("dead_lettered", buffer.dead_letter(route.name, unreadable, moved_ids=moved_ids))
            self._tell(moved_ids, dead_lettered=True)
            self.bound_dead_letters()
        if batch.evicted:
            self._take_out_evicted(batch.evicted)
        if not records:
            return False
        if route.pacer.active and not route.pacer.take(sum(row.size for row in sent_rows)):
            raise _Stopping
        # Until each is deleted, dead-lettered or counted failed, the size limit must not drop them:
        # one the destination confirms would be counted both dropped and sent.
        buffer.hold(route.name, [row.row_id for row in sent_rows])
        retry, waiting, reject, problem, self._retry_after = route.gate.send(
            lambda: _outcome_of(route.destination, records)
        )
        gone: set[int] = set()
        if route.saved is not None and route.file_fields and (retry or waiting or reject):
            # A file evicted while send() had its record: the record failed for want of it (no file, or
            # it vanished), which is the eviction, counted as such, not a failure nor a dead letter.
            skip = route.saved.skipped_for(route.name)
            gone = {i for i in (*retry, *waiting, *reject) if sent_rows[i].record_id in skip}
            if gone:
                retry, waiting, reject = (
                    {i: r for i, r in d.items() if i not in gone} for d in (retry, waiting, reject)
                )
                self._take_out_evicted([sent_rows[i] for i in sorted(gone)])
        again = {**waiting, **retry}  # back to the queue: failed, or not ready yet
        if again or reject or gone:
            confirmed = [
                row.row_id for i, row in enumerate(sent_rows) if i not in again and i not in reject and i not in gone
            ]
        else:
            confirmed = [row.row_id for row in sent_rows]
        # The destination answered unless everything must be retried; a refusal that names a fix is a
        # failure of the destination's set-up, whatever becomes of the records. A wait is no failure.
        if problem is not None or (retry and not confirmed):
            route.health.failed(next(iter(retry.values()), ""), problem)
        else:
            route.health.succeeded()
        if confirmed and (self._listeners or (route.saved is not None and route.file_fields)):
            done = set(confirmed)
            confirmed_ids = [row.record_id for row in sent_rows if row.row_id in done]
            if route.saved is not None and route.file_fields:
                route.saved.confirmed(route.name, confirmed_ids)
            # Told now, whatever becomes of the rest of the batch: the destination has these.
            self._tell(confirmed_ids, dead_lettered=False)
        if defer_delete and not again and not reject:
            self._confirmed += confirmed
            return False
        if confirmed:
            buffer.delete(route.name, confirmed)
            route.metrics.add("sent", len(confirmed))
        if not again and not reject:
            return False
        if retry or reject:
            route.metrics.add("failed")
            route.metrics.set_error(next(iter({**reject, **retry}.values())))
        dead: list[tuple[BufferedRow, str]] = [(sent_rows[i], reason) for i, reason in reject.items()]
        retried = 0
        if again:
            dropped: list[str] = []
            topics: Counter[str] = Counter()
            attempts = buffer.record_failure(
                route.name, [sent_rows[i].row_id for i in again], dropped_ids=dropped, dropped_topics=topics
            )
            if dropped:  # what commits during the send could not drop
                route.metrics.add_by_topic("dropped", topics)
                route.drop_log.event(
                    len(dropped),
                    f"storage_total_limit_size {route.params.storage_total_limit_size} reached, "
                    f"when_full {route.params.when_full}",
                )
                tell_dropped(self._drop_listeners, route.logger, route.name, dropped, DROP_SIZE_LIMIT)
            limit = route.params.retry_limit
            failed_again = 0
            for i, reason in again.items():
                row = sent_rows[i]
                if limit >= 0 and attempts.get(row.row_id, 0) > limit:
                    dead.append((row, f"retry_limit {limit} exhausted: {reason}"))
                else:
                    retried += 1
                    failed_again += i in retry
            route.metrics.add("retried", retried)
            if failed_again:
                route.failure_log.event(failed_again, next(iter(retry.values())))
        if dead:
            # A refused record was tried once more than its queue row counted (only retries are counted there).
            moved_ids = []
            moved = buffer.dead_letter(
                route.name, dead, tried_now={sent_rows[i].row_id for i in reject}, moved_ids=moved_ids
            )
            route.metrics.add("dead_lettered", moved)
            route.dead_letter_log.event(moved, f"{dead[0][1]}; see `dc buffer list`")
            self._tell(moved_ids, dead_lettered=True)
            self.bound_dead_letters()
        return retried > 0

    def _tell(self, record_ids: list[str], *, dead_lettered: bool) -> None:
        """The listeners told of an outcome committed (see :data:`OutcomeListener`)."""
        if not record_ids:
            return
        for listener in self._listeners:
            try:
                listener(self.route.name, record_ids, dead_lettered)
            except Exception as exc:  # a listener's bug must not make the sender send the batch again
                self.route.logger.error(
                    f"destination {self.route.name}: an outcome listener failed: {type(exc).__name__}: {exc}\n"
                    f"{traceback.format_exc()}"
                )

    def bound_dead_letters(self) -> None:
        """Delete the oldest dead letters beyond ``dead_letter_limit_size``, counted and logged."""
        route = self.route
        if route.dead_letter_max_bytes is None:
            return
        deleted = self.buffer.trim_dead_letters(route.name, route.dead_letter_max_bytes)
        if deleted:
            route.metrics.add("dead_letters_dropped", deleted)
            route.dead_letter_drop_log.event(deleted, "the newest are kept; see `dc buffer list`")

    def _take_out_evicted(self, rows: list[BufferedRow]) -> None:
        """Records naming saved files evicted before this destination had them: out of its queue, counted."""
        route = self.route
        taken = self.buffer.delete(route.name, [row.row_id for row in rows], sent=False)
        if taken == len(rows):
            route.metrics.add_by_topic("evicted", Counter(row.topic for row in rows))
        else:  # some left the queue meanwhile (a buffer set aside): which ones is not known
            route.metrics.add("evicted", taken)
        route.evict_log.event(taken, "records naming saved files evicted before this destination had them")
        assert route.saved is not None
        evicted_ids = [row.record_id for row in rows]
        route.saved.taken_out(route.name, evicted_ids)
        tell_dropped(self._drop_listeners, route.logger, route.name, evicted_ids, DROP_FILE_EVICTED)

    def _tell_evictions(self) -> bool:
        """Tell a destination that records evictions of the files evicted after it confirmed them;
        True when that failed (told again after a backoff)."""
        route = self.route
        assert route.saved is not None
        notices = route.saved.notices_for(route.name)
        if not notices:
            return False
        try:
            route.destination.files_evicted(notices)
        except Exception as exc:  # a database down, or a plugin's bug: the sender waits and tries again
            what = f"recording {len(notices)} evicted files: {type(exc).__name__}: {exc}"
            route.metrics.add("failed")
            route.metrics.set_error(what)
            route.failure_log.event(1, what)
            return True
        route.saved.told(route.name, notices)
        return False


class _Stopping(Exception):
    """The pipeline stopped while a send waited for its cap: its records stay in the queue."""


@dataclass
class _Batch:
    """Rows read from the queue and what is to be done with them."""

    rows: list[BufferedRow]
    records: list[OutgoingRecord] = field(default_factory=list)
    sent_rows: list[BufferedRow] = field(default_factory=list)  # the rows of ``records``, in order
    unreadable: list[tuple[BufferedRow, str]] = field(default_factory=list)
    evicted: list[BufferedRow] = field(default_factory=list)  # naming files evicted before they were sent


def _outcome_of(
    destination: Destination[Any], records: list[OutgoingRecord]
) -> tuple[dict[int, str], dict[int, str], dict[int, str], tuple[str, str] | None, float | None]:
    """``send(records)`` as (retry, waiting, reject, problem, retry_after): batch indexes with their
    reasons (the rest were confirmed; see SendOutcome), (what, fix) when the failure is one retrying
    cannot mend (dc_destinations.health), and the seconds the server asked to wait, when it said."""
    try:
        outcome = destination.send(records)
    except RejectedError as exc:
        return {}, {}, dict.fromkeys(range(len(records)), f"rejected: {exc}"), attention_needed(exc), None
    except RetryableError as exc:
        return dict.fromkeys(range(len(records)), str(exc)), {}, {}, attention_needed(exc), _seconds(exc.retry_after)
    except Exception as exc:
        return dict.fromkeys(range(len(records)), f"{type(exc).__name__}: {exc}"), {}, {}, attention_needed(exc), None
    if not isinstance(outcome, SendOutcome):
        return {}, {}, {}, None, None
    retry = {i: reason for i, reason in outcome.retry.items() if 0 <= i < len(records)}
    reject = {
        i: f"rejected: {reason}" for i, reason in outcome.reject.items() if 0 <= i < len(records) and i not in retry
    }
    waiting = {
        i: reason
        for i, reason in outcome.waiting.items()
        if 0 <= i < len(records) and i not in retry and i not in reject
    }
    return retry, waiting, reject, None, _seconds(outcome.retry_after) if retry else None


def _seconds(value: Any) -> float | None:
    """A plugin's retry_after as seconds; None when it gave none, or nothing a wait can use (NaN, negative)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        return None
    return float(value)
