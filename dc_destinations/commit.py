"""From the server's intake to the disk: a hand-off queue and a writer thread doing group commits.

``submit_records`` runs on the server's main thread: it only puts the records its intake took
at one wake-up on an in-memory hand-off queue, in one piece. The writer thread takes everything
waiting there (up to ``commit_batch_size`` records, and the rest of the last piece: a piece is
never split) and writes it in one transaction — a group commit — so the cost of a commit is
shared by all the records that arrived meanwhile. A record is durable once its group commit is
done (see :meth:`GroupCommitter.flush` and docs/delivery.md for the loss window of each
``storage_sync``).

One record never stops the others: a record that is not valid UTF-8 JSON is counted apart, and a
commit that fails because of what is in its records is split per received record. A commit that
fails on the disk (full, I/O error) is retried every second, visibly (``failed``, ``last_error``,
:attr:`GroupCommitter.failing`).

What waits in memory is never lost without a count (:meth:`GroupCommitter.stop`): at a stop it is
committed, by the writer or, if the writer died (dc_core.supervision), by the stopping thread, for
up to :data:`STOP_COMMIT_WAIT_S`; what cannot be committed is counted as ``dropped`` of its
destinations and logged in one line with its number.
"""

from __future__ import annotations

import queue
import sqlite3
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dc_core.destination import OutgoingRecord
from dc_core.logs import BurstLog, Logger
from dc_core.records import MalformedRecord
from dc_core.supervision import Supervisor
from dc_destinations.buffer import AppendResult, Buffer, BufferClosed, BufferCorrupted, PendingRecord, QueueLimit
from dc_destinations.hop import HopLosses
from dc_destinations.sender import (
    DROP_INTAKE,
    DROP_NOT_COMMITTED,
    DROP_NOT_STORABLE,
    DROP_SIZE_LIMIT,
    Closing,
    DropListener,
    Route,
    tell_dropped,
)
from dc_destinations.settings import DeliveryParams

HopKey = tuple[str, int, int]
CommitListener = Callable[[Sequence[tuple[str, str]]], None]

_STOP = object()
# The longest a stop waits for the writer to commit what waits in memory (a disk that hangs rather
# than fails): what is still not committed then is counted as dropped and logged.
STOP_COMMIT_WAIT_S = 10.0

Received = tuple[Sequence[tuple[str, OutgoingRecord]], HopKey | HopLosses | None]
"""One received record as routing gave it: its copies by destination name, and its hop key (or, with
no copies, the hop's losses since the last hand-over)."""


@dataclass
class _CommitBatch:
    """The records of one group commit by destination, with their hop keys."""

    by_destination: dict[str, list[PendingRecord]] = field(default_factory=dict)
    limits: dict[str, QueueLimit] = field(default_factory=dict)
    seen: list[HopKey] = field(default_factory=list)
    hop_losses: list[HopLosses] = field(default_factory=list)
    # (destination, record_id) as they came, for commit listeners: None (not built) when none listens.
    committed: list[tuple[str, str]] | None = None
    count: int = 0

    def add(self, route: Route, record: PendingRecord) -> None:
        records = self.by_destination.get(route.name)
        if records is None:
            records = self.by_destination[route.name] = []
            self.limits[route.name] = route.limit
        records.append(record)
        self.count += 1
        if self.committed is not None:
            self.committed.append((route.name, record.record_id))


class _Handoff(list[Received]):
    """The records of one submit, as the writer takes them, with the bytes of their JSON."""

    nbytes = 0


class _IntakeQueue(queue.SimpleQueue[Any]):
    """The hand-off queue, counting the bytes of the records taken off it (``intake_queue_limit_bytes``).

    Counted where the writer takes them, whichever way it does: the writer loop stays as it is.
    """

    def __init__(self) -> None:
        self.taken_bytes = 0

    def get(self, block: bool = True, timeout: float | None = None) -> Any:
        item = super().get(block, timeout)
        self.taken_bytes += getattr(item, "nbytes", 0)
        return item

    def get_nowait(self) -> Any:
        return self.get(False)


def _received_bytes(received: Sequence[Received]) -> int:
    """Bytes of the JSON text of every copy of these records (what they hold in memory, roughly)."""
    total = 0
    for copies, _ in received:
        for _, record in copies:
            text = record.json_text
            if text is None:  # made by hand (tests, a plugin's own records): not serialised by routing
                try:
                    text = record.to_json()
                except MalformedRecord:
                    continue  # counted apart as malformed by the writer
            total += len(text)
    return total


def _may_pass(exc: Exception) -> bool:
    """Whether a failed commit is the disk's or the system's (retry it) rather than its records' own."""
    return isinstance(exc, (sqlite3.OperationalError, OSError, MemoryError, BufferClosed))


class GroupCommitter:
    """The hand-off queue and the writer thread; see the module documentation."""

    def __init__(
        self,
        routes: Mapping[str, Route],
        buffer: Buffer,
        settings: DeliveryParams,
        closing: Closing,
        logger: Logger,
        *,
        supervisor: Supervisor,
        seen_window: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        tick_logs: Callable[[], None] = lambda: None,
        drop_listeners: Sequence[DropListener] = (),
    ) -> None:
        self._routes = routes
        # Told of each record dropped for a destination (dc_destinations.sender.DropListener).
        self._drop_listeners = drop_listeners
        # The pipeline's: the writer thread runs under the same rule as the senders (dc_core.supervision).
        self._supervisor = supervisor
        self._buffer = buffer
        self.settings = settings
        self._closing = closing
        self.logger = logger
        self._seen_window = seen_window
        self._clock = clock
        self._tick_logs = tick_logs
        self._intake = _IntakeQueue()
        self._limit_bytes = settings.intake_limit_bytes
        self._submitted_bytes = 0  # taken: counted by the queue
        # Records submitted and taken by the writer, each counted by one side: their difference is
        # what waits in memory (intake_queue_limit).
        self._submitted = 0
        self._taken = 0
        self._submit_lock = threading.Lock()
        self._accepting = False
        self._writer: threading.Thread | None = None
        self._listeners: list[CommitListener] = []
        # Called with the hop keys of each group commit once it succeeded (destination_server's acks).
        self.on_seen_committed: Callable[[list[HopKey]], None] | None = None
        # Called on the writer thread right after each group commit, within Buffer.exclusive (the
        # pipeline keeps the disk budget there): must not wait for another thread.
        self.after_append: Callable[[], None] = lambda: None
        self.intake_drop_log = BurstLog(logger.error, "delivery intake: records dropped")
        self.commit_log = BurstLog(logger.error, "delivery buffer: group commit failed, retrying")
        # What follows a commit (the disk budget) failing for a reason it does not handle itself: a bug,
        # logged with its traceback once per burst and counted, never taken for a failure of the commit.
        self.after_append_log = BurstLog(logger.error, "delivery: the disk budget after a group commit failed")
        self.after_append_failed = 0
        # (since, error) while group commits fail for a reason that may pass (disk full, I/O error).
        self.failing: tuple[float, str] | None = None
        # The records of the commit being written (the writer's), and those a dead writer held then.
        self._in_hand: list[Received] = []
        self._orphaned: list[Received] = []
        # Records that could not be committed at the stop, and why (one log line at the end of stop()).
        self._lost_at_stop = 0
        self._lost_reason = ""

    # -- the server's side ------------------------------------------------------------------------

    def start(self) -> None:
        self._intake = _IntakeQueue()
        self._submitted = self._taken = self._submitted_bytes = 0
        self._accepting = True
        self._in_hand, self._orphaned = [], []
        self._lost_at_stop, self._lost_reason = 0, ""
        self._writer = self._supervisor.start_thread(
            self._write_loop, name="dc-delivery-writer", on_failure=self._writer_failed
        )

    def stop(self, timeout: float | None = None) -> int:
        """Refuse new records, commit what was submitted, end the writer; returns how many records were lost.

        Waits up to ``timeout`` seconds (:data:`STOP_COMMIT_WAIT_S` when None) for the writer. If it
        died, what it held and what waits for it are committed here. Records that cannot be
        committed (the disk is full, the writer did not finish in time) are counted as ``dropped``
        of their destinations and logged in one line with their number.
        """
        writer = self._writer
        if writer is None:
            return 0
        self._accepting = False
        self._intake.put(_STOP)
        wait = STOP_COMMIT_WAIT_S if timeout is None else timeout
        writer.join(wait)
        self._writer = None
        if writer.is_alive():
            # Still committing (a disk that hangs): what it has not taken yet is counted lost here.
            # It may yet commit its batch in hand; that batch is then delivered, at least once.
            left = self._take_all()
            self._taken += len(left)
            self._lose(left, f"the writer did not finish within {wait:g} s")
        else:
            # A writer that died left its batch and the queue: committed here if the disk allows.
            leftovers, self._orphaned = self._orphaned, []
            leftovers += self._take_all()
            if leftovers:
                self.logger.warning(f"delivery buffer: committing {len(leftovers)} records the writer left behind")
                self._taken += len(leftovers)
                try:
                    self._commit(leftovers)
                except Exception as exc:  # the writer's own failure again, most likely
                    self._lose(leftovers, f"{type(exc).__name__}: {exc}")
        lost = self._lost_at_stop
        if lost:
            self.logger.error(
                f"delivery buffer: {lost} records held in memory could not be committed at the stop and are lost"
                f" ({self._lost_reason}); counted as dropped"
            )
        return lost

    @property
    def started(self) -> bool:
        """Started and not stopped yet (its writer may have died meanwhile)."""
        return self._writer is not None

    @property
    def running(self) -> bool:
        return self._writer is not None and self._writer.is_alive()

    @property
    def waiting(self) -> int:
        """Records handed over and not taken by the writer yet."""
        return self._submitted - self._taken

    @property
    def waiting_bytes(self) -> int:
        """Bytes of the records handed over and not taken by the writer yet."""
        return self._submitted_bytes - self._intake.taken_bytes

    def submit_record(self, deliveries: Sequence[tuple[str, OutgoingRecord]], seen: HopKey | None = None) -> bool:
        """Hand over the copies of one record, and its hop key, to be committed in one transaction.

        Never blocks. Returns False when the record was dropped (counted for each destination):
        its key is then not written either, so a replay of the record is delivered. With no
        deliveries, only the key is written (a record that reaches no destination was handled too).
        """
        return self.submit_records([(deliveries, seen)])

    def submit_records(self, received: Sequence[Received]) -> bool:
        """:meth:`submit_record` for several records at once, all kept or all dropped: one hand-off.

        Each record's copies and key are still committed together, and all of these records in the
        same group commit.
        """
        reason = None
        nbytes = _received_bytes(received) if self._limit_bytes is not None else 0
        if not self._accepting:
            reason = "the delivery pipeline is not running"
        elif self.waiting >= self.settings.intake_queue_limit:
            reason = f"{self.settings.intake_queue_limit} records already wait for the disk (intake_queue_limit)"
        elif self._limit_bytes is not None and self.waiting_bytes + nbytes > self._limit_bytes:
            reason = (
                f"{self.waiting_bytes} bytes of records wait for the disk, {nbytes} more would pass "
                f"intake_queue_limit_bytes ({self.settings.intake_queue_limit_bytes})"
            )
        if reason is not None:
            dropped = self._count_dropped(received, DROP_INTAKE)
            if dropped:
                self.intake_drop_log.event(dropped, reason)
            return False
        if received:
            # Taken as they are: the destinations are looked up by the writer thread, not here.
            handoffs = _Handoff(received)
            handoffs.nbytes = nbytes
            with self._submit_lock:  # several threads may submit
                self._submitted += len(handoffs)
                self._submitted_bytes += nbytes
            self._intake.put(handoffs)
        return True

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every record submitted before this call is committed; False on timeout."""
        if self._writer is None:
            return False
        done = threading.Event()
        self._intake.put(done)
        return done.wait(timeout)

    def add_listener(self, listener: CommitListener) -> None:
        """Call ``listener`` on the writer thread with ``(destination, record_id)`` of each group commit.

        Used by tests only: the per-record list is built only while a listener exists (from the next
        group commit on), so delivery without one pays nothing for it.
        """
        self._listeners.append(listener)

    def _take_all(self) -> list[Received]:
        """Every hand-off still on the queue (markers set, the stop marker skipped)."""
        taken: list[Received] = []
        while True:
            try:
                item = self._intake.get_nowait()
            except queue.Empty:
                return taken
            if isinstance(item, threading.Event):
                item.set()
            elif item is not _STOP:
                taken.extend(item)

    def _writer_failed(self, exc: BaseException) -> None:
        """On the dying writer (dc_core.supervision): its batch in hand waits for the stop with the queue."""
        self._orphaned.extend(self._in_hand)
        self._taken -= len(self._in_hand)  # waiting again: intake_pending shows it
        self._in_hand = []

    def _lose(self, handoffs: Sequence[Received], reason: str) -> None:
        """Count the copies of ``handoffs`` as received and dropped; the stop logs their number once."""
        self._add_lost(self._count_dropped(handoffs, DROP_NOT_COMMITTED), reason)

    def _count_dropped(self, received: Sequence[Received], why: str) -> int:
        """Count each copy of ``received`` as received and dropped at its destination, the drop
        listeners told ``why``; how many were."""
        dropped = 0
        ids: dict[str, list[str]] = {}
        topics: dict[str, Counter[str]] = {}
        for copies, _ in received:
            for name, record in copies:
                route = self._routes.get(name)
                if route is not None:
                    route.metrics.add("received")
                    topics.setdefault(name, Counter())[record.topic] += 1
                    dropped += 1
                    if self._drop_listeners:
                        ids.setdefault(name, []).append(record.record_id)
        for name, counts in topics.items():
            self._routes[name].metrics.add_by_topic("dropped", counts)
        for name, record_ids in ids.items():
            tell_dropped(self._drop_listeners, self.logger, name, record_ids, why)
        return dropped

    def _add_lost(self, count: int, reason: str) -> None:
        # The writer and a stop that gave up waiting for it may both count.
        with self._submit_lock:
            self._lost_at_stop += count
            self._lost_reason = self._lost_reason or reason

    # -- the writer thread ------------------------------------------------------------------------

    def _write_loop(self) -> None:
        limit = self.settings.commit_batch_size
        while True:
            try:
                first = self._intake.get(timeout=0.5)
            except queue.Empty:
                self._tick_logs()
                continue
            items = [first]
            if self._take_waiting(items, limit) < limit and self.settings.commit_interval > 0 and first is not _STOP:
                # Let a trickle of records gather into one commit: at robot rates this turns a
                # commit (and, with storage_sync full, an fsync) per record into a few per second.
                time.sleep(self.settings.commit_interval)
                self._take_waiting(items, limit)
            stop = False
            handoffs: list[Received] = []
            markers: list[threading.Event] = []
            for item in items:
                if item is _STOP:
                    stop = True
                elif isinstance(item, threading.Event):
                    markers.append(item)
                else:
                    handoffs.extend(item)
            self._taken += len(handoffs)
            if handoffs:
                self._in_hand = handoffs
                self._commit(handoffs)
                self._in_hand = []
            self._tick_logs()
            for marker in markers:
                marker.set()
            if stop:
                # Whatever was submitted before the stop is committed before the writer ends.
                self._drain_after_stop()
                return

    def _take_waiting(self, items: list[Any], limit: int) -> int:
        """Add what waits on the queue to ``items`` until they hold ``limit`` records; returns how many they hold."""
        records = sum(len(item) for item in items if isinstance(item, list))
        while records < limit:
            try:
                item = self._intake.get_nowait()
            except queue.Empty:
                break
            items.append(item)
            if isinstance(item, list):
                records += len(item)
        return records

    def _drain_after_stop(self) -> None:
        while True:
            try:
                item = self._intake.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, threading.Event):
                item.set()
            elif item is not _STOP:
                self._taken += len(item)
                self._in_hand = item
                self._commit(item)
                self._in_hand = []

    def _commit(self, handoffs: list[Received]) -> None:
        """One group commit of received records."""
        batch = self._storable(handoffs)
        while True:
            try:
                result = self._append(batch)
                break
            except BufferCorrupted:
                continue  # the buffer was replaced by an empty one: write the batch there
            except Exception as exc:
                if not _may_pass(exc):
                    # Something in the records themselves: find it, so that one record never holds up
                    # the others (a group commit retried forever stalled every destination).
                    self._commit_apart(handoffs, exc)
                    return
                # Disk full, I/O error: keep the batch and try again, visibly.
                self._commit_failed(batch, exc)
                # At a stop, one attempt: waiting for space would only make the stop wait.
                if not self._accepting or self._closing.event.wait(1.0):
                    # Stopping: counted here, logged once with the total by stop().
                    for name, records in batch.by_destination.items():
                        self._routes[name].metrics.add("received", len(records))
                        self._routes[name].metrics.add_by_topic("dropped", Counter(r.topic for r in records))
                        tell_dropped(
                            self._drop_listeners, self.logger, name, [r.record_id for r in records], DROP_NOT_COMMITTED
                        )
                    self._add_lost(batch.count, f"{type(exc).__name__}: {exc}")
                    return
        self.failing = None
        self._account(batch, result)

    def _append(self, batch: _CommitBatch) -> AppendResult:
        """The group commit, counted, and what must follow it before anyone reads the buffer again:
        the disk budget (``after_append``), so that no reader ever sees the records of a commit
        without the evictions they made necessary."""
        with self._buffer.exclusive():
            result = self._buffer.append(
                batch.by_destination,
                batch.limits,
                seen=batch.seen,
                seen_window=self._seen_window,
                hop_losses=batch.hop_losses,
            )
            # Counted before anything they made necessary: received = sent + evicted + dropped + buffered
            # holds at every reading, even for records evicted by the commit that brought them.
            for name, records in batch.by_destination.items():
                metrics = self._routes[name].metrics
                metrics.add("received", len(records))
                metrics.add_by_topic("dropped", result.dropped_topics.get(name, {}))
            try:
                self.after_append()
            except Exception:  # never taken for a failure of the commit: that would commit its records again
                self.after_append_failed += 1
                self.after_append_log.event(1, traceback.format_exc())
        return result

    def _storable(self, handoffs: list[Received]) -> _CommitBatch:
        """What of ``handoffs`` the buffer can hold; a record that is not valid UTF-8 JSON is counted apart."""
        batch = _CommitBatch(committed=[] if self._listeners else None)
        routes = self._routes
        for copies, seen in handoffs:
            if isinstance(seen, HopLosses):
                batch.hop_losses.append(seen)
            elif seen is not None:
                batch.seen.append(seen)
            for name, record in copies:
                route = routes.get(name)
                if route is None:
                    self._unknown_destination(name, record.record_id)
                    continue
                try:
                    # Encodes the payload: a lone surrogate fails here, not in the commit.
                    pending = PendingRecord(
                        record.record_id, record.topic, record.stamp_ns, record.to_json(), record.text_follows_rule
                    )
                except (MalformedRecord, UnicodeError, ValueError, TypeError, RecursionError) as exc:
                    self._not_storable(route, record.record_id, f"{type(exc).__name__}: {exc}")
                    continue
                batch.add(route, pending)
        return batch

    def _commit_apart(self, handoffs: list[Received], exc: Exception) -> None:
        """Commit each received record alone after ``exc`` failed their group commit."""
        if len(handoffs) > 1:
            for handoff in handoffs:
                self._commit([handoff])
            return
        ((copies, seen),) = handoffs
        for name, record in copies:
            route = self._routes.get(name)
            if route is not None:
                self._not_storable(route, record.record_id, f"the buffer refused it: {type(exc).__name__}: {exc}")
        if seen is not None:
            self._commit([([], seen)])  # handled: a replay of it is not reported as new

    def _unknown_destination(self, name: str, record_id: str) -> None:
        # A caller's mistake (the server routes only to its destinations), never a reason to stop
        # the writer: said, and the record's other copies are committed.
        self.logger.error(f"delivery intake: record {record_id} submitted for {name!r}, not a destination here")

    def _not_storable(self, route: Route, record_id: str, reason: str) -> None:
        route.metrics.add("received")
        route.metrics.add("malformed")
        route.malformed_log.event(1, f"record {record_id}: {reason}")
        tell_dropped(self._drop_listeners, self.logger, route.name, [record_id], DROP_NOT_STORABLE)

    def _commit_failed(self, batch: _CommitBatch, exc: Exception) -> None:
        error = f"committing to the buffer: {type(exc).__name__}: {exc}"
        since = self.failing[0] if self.failing is not None else self._clock()
        self.failing = (since, error)
        # Counted before it is logged: whoever reads the log line finds the counters saying it too.
        for name in batch.by_destination:
            metrics = self._routes[name].metrics
            metrics.add("failed")
            metrics.set_error(error)
        self.commit_log.event(batch.count, f"{type(exc).__name__}: {exc}")

    def _account(self, batch: _CommitBatch, result: AppendResult) -> None:
        """Drop logs, listeners and sender wake-ups after a group commit (counted by :meth:`_append`)."""
        for name in batch.by_destination:
            route = self._routes[name]
            dropped_newest = result.dropped_newest.get(name, 0)
            dropped_oldest = result.dropped_oldest.get(name, 0)
            if dropped_newest or dropped_oldest:
                route.drop_log.event(
                    dropped_newest + dropped_oldest,
                    f"storage_total_limit_size {route.params.storage_total_limit_size} reached, "
                    f"when_full {route.params.when_full}",
                )
                tell_dropped(self._drop_listeners, self.logger, name, result.dropped_ids.get(name, []), DROP_SIZE_LIMIT)
            route.pending_hint += result.appended.get(name, 0)
            if route.pending_hint >= route.params.batch_size:
                route.wakeup.set()
        for listener in self._listeners:
            try:
                listener(batch.committed or [])
            except Exception as exc:
                self.logger.error(f"delivery commit listener failed: {exc}")
        if batch.seen and self.on_seen_committed is not None:
            try:
                self.on_seen_committed(batch.seen)
            except Exception as exc:
                self.logger.error(f"delivery: acknowledging committed records failed: {exc!r}")
