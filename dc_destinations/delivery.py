"""Durable delivery: group-committed intake into the SQLite buffer, one sender thread per destination.

``submit`` runs on the server's main thread (its intake): it only puts the record on an in-memory
hand-off queue.
A writer thread takes everything waiting there (up to ``commit_batch_size``) and writes it in one
transaction — a group commit — so the cost of a commit is shared by all the records that arrived
meanwhile. A record is durable once its group commit is done (see :meth:`DeliveryPipeline.flush_intake`
and docs/delivery.md for the loss window of each ``storage_sync``).

Each destination has its own queue and sender thread, so a slow or dead destination never delays
another: the sender reads the oldest rows of its queue in batches, calls ``send``, deletes what was
confirmed, dead-letters what was refused and backs off exponentially (full jitter) when something
must be retried.
"""

from __future__ import annotations

import contextlib
import os
import queue
import sqlite3
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, RejectedError, RetryableError, SendOutcome
from dc_core.http_status import StatusServer, start_status_server
from dc_core.logs import BurstLog, Logger
from dc_core.paths import expand_env
from dc_core.records import MalformedRecord, parse_record
from dc_destinations.backoff import Backoff
from dc_destinations.buffer import (
    FILE_NAME,
    AppendResult,
    BufferClosed,
    BufferCorrupted,
    BufferedRow,
    PendingRecord,
    Quarantine,
    QueueLimit,
    SqliteBuffer,
    default_storage_dir,
)
from dc_destinations.metrics import DestinationMetrics, prometheus_text
from dc_destinations.settings import (
    DeliveryParams,
    DestinationDeliveryParams,
    check_destination_params,
    parse_size,
)

__all__ = ["DeliveryPipeline", "new_record_id", "uuid7"]


class _Uuid7Source:
    """RFC 9562 UUIDv7: 48-bit Unix milliseconds, then a 12-bit counter that keeps ids from one
    process increasing within a millisecond, then 62 random bits.

    The random bits come from the operating system's CSPRNG, read 4 KiB at a time: one getrandom()
    per id was a system call on the intake's hot path, where each one also lets the writer thread
    take the GIL. A forked child forgets the pool, so parent and child never share bits.
    """

    _POOL_BYTES = 4096

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last_ms = -1
        self._counter = 0
        self._pool = b""
        self._pool_pos = 0
        os.register_at_fork(after_in_child=self._forget_pool)

    def _forget_pool(self) -> None:
        self._pool, self._pool_pos = b"", 0

    def _random_bits(self, bits: int) -> int:
        """``bits`` (at most 64) random bits; call with the lock held."""
        if self._pool_pos + 8 > len(self._pool):
            self._pool, self._pool_pos = os.urandom(self._POOL_BYTES), 0
        word = int.from_bytes(self._pool[self._pool_pos : self._pool_pos + 8], "big")
        self._pool_pos += 8
        return word >> (64 - bits)

    def next(self) -> uuid.UUID:
        with self._lock:
            ms = time.time_ns() // 1_000_000
            if ms > self._last_ms:
                self._last_ms = ms
                self._counter = self._random_bits(11)  # top bit clear leaves room to count up
            else:
                self._counter += 1
                if self._counter > 0xFFF:  # 4,096 ids in one millisecond: borrow the next one
                    self._last_ms += 1
                    self._counter = 0
            ms, counter = self._last_ms, self._counter
            random62 = self._random_bits(62)
        value = (ms & 0xFFFF_FFFF_FFFF) << 80 | 0x7 << 76 | counter << 64 | 0b10 << 62 | random62
        return uuid.UUID(int=value)


_UUID7 = _Uuid7Source()


def uuid7() -> uuid.UUID:
    return _UUID7.next()


def new_record_id() -> str:
    """A fresh ``record_id``: a UUIDv7 string, time-ordered, for sinks to deduplicate on."""
    return str(_UUID7.next())


_STOP = object()


@dataclass(frozen=True)
class _Handoff:
    """One received record: its copies for each destination and its hop key, committed together."""

    records: list[tuple[_Route, OutgoingRecord]]
    seen: tuple[str, int, int] | None


@dataclass
class _CommitBatch:
    """The records of one group commit by destination, with their hop keys."""

    by_destination: dict[str, list[PendingRecord]] = field(default_factory=dict)
    limits: dict[str, QueueLimit] = field(default_factory=dict)
    seen: list[tuple[str, int, int]] = field(default_factory=list)
    committed: list[tuple[str, str]] = field(default_factory=list)  # (destination, record_id), as they came

    def add(self, route: _Route, record: PendingRecord) -> None:
        self.by_destination.setdefault(route.name, []).append(record)
        self.limits[route.name] = route.limit
        self.committed.append((route.name, record.record_id))

    @property
    def count(self) -> int:
        return len(self.committed)


def _may_pass(exc: Exception) -> bool:
    """Whether a failed commit is the disk's or the system's (retry it) rather than its records' own."""
    return isinstance(exc, (sqlite3.OperationalError, OSError, MemoryError, BufferClosed))


@dataclass
class _Route:
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
    wakeup: threading.Event = field(default_factory=threading.Event)
    pending_hint: int = 0
    thread: threading.Thread | None = None

    def tick_logs(self) -> None:
        self.drop_log.tick()
        self.failure_log.tick()
        self.dead_letter_log.tick()
        self.dead_letter_drop_log.tick()
        self.malformed_log.tick()


class DeliveryPipeline:
    """The delivery layer of ``destination_server``; see the module documentation.

    ``seen_window``: how many hop keys (see :meth:`submit_record`) the buffer keeps per topic.
    ``clock``, ``wait`` (called with each backoff delay; returns True to give up because the
    pipeline is stopping) and ``uniform`` (the jitter draw) exist for tests.
    """

    def __init__(
        self,
        settings: DeliveryParams,
        destinations: Mapping[str, tuple[Destination[Any], DestinationDeliveryParams]],
        logger: Logger,
        *,
        seen_window: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        wait: Callable[[float], bool] | None = None,
        uniform: Callable[[float, float], float] | None = None,
    ) -> None:
        self.settings = settings
        self.logger = logger
        self._seen_window = seen_window
        self._clock = clock
        self._wait = wait
        self._uniform = uniform
        self._routes: dict[str, _Route] = {}
        for name, (destination, params) in destinations.items():
            check_destination_params(params, f"destination_server.{name}")
            max_bytes = parse_size(params.storage_total_limit_size)
            self._routes[name] = _Route(
                name=name,
                destination=destination,
                params=params,
                limit=QueueLimit(max_bytes=max_bytes, drop_oldest=params.when_full == "drop_oldest"),
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
            )
        self._intake_drop_log = BurstLog(logger.error, "delivery intake: records dropped")
        self._commit_log = BurstLog(logger.error, "delivery buffer: group commit failed, retrying")
        self._intake: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._accepting = False
        self._buffer: SqliteBuffer | None = None
        self._writer: threading.Thread | None = None
        self._closing = threading.Event()
        self._deadline = float("inf")
        self._quarantined = 0
        # (since, error) while group commits fail for a reason that may pass (disk full, I/O error).
        self._commit_error: tuple[float, str] | None = None
        self._last_log_tick = 0.0
        self._commit_listeners: list[Callable[[Sequence[tuple[str, str]]], None]] = []
        self._status: StatusServer | None = None
        self._sections: dict[str, Callable[[], Any]] = {}
        self.storage_file: Path | None = None

    # -- lifecycle ----------------------------------------------------------------------------------

    def start(self) -> None:
        """Open (or recover) the buffer, start the writer and one sender per destination."""
        if self._writer is not None:
            return
        directory = self._storage_dir()
        self.storage_file = directory / FILE_NAME
        self._buffer = SqliteBuffer(
            self.storage_file, synchronous=self.settings.storage_sync, on_quarantine=self._on_quarantine
        )
        self._buffer.ensure_queues(list(self._routes))
        for route in self._routes.values():  # a limit lowered since the last run applies at once
            self._bound_dead_letters(route, self._buffer)
        backlog = {name: self._buffer.stats(name).rows for name in self._routes}
        self.logger.info(
            f"delivery buffer {self.storage_file} (storage_sync={self.settings.storage_sync}: "
            + _SYNC_PROMISE[self.settings.storage_sync]
            + "); backlog: "
            + (", ".join(f"{name} {rows}" for name, rows in backlog.items()) or "none")
        )
        self._closing.clear()
        self._deadline = float("inf")
        self._intake = queue.SimpleQueue()
        self._accepting = True
        self._writer = threading.Thread(target=self._write_loop, name="dc-delivery-writer", daemon=True)
        self._writer.start()
        for route in self._routes.values():
            route.wakeup.clear()
            route.thread = threading.Thread(
                target=self._send_loop, args=(route,), name=f"dc-sender-{route.name}", daemon=True
            )
            route.thread.start()
        if self.settings.http_server:
            self._start_status_server()

    def stop(self, grace: float) -> None:
        """Stop intake, commit what was submitted, deliver for up to ``grace`` s, leave the rest on disk."""
        if self._writer is None:
            return
        self._accepting = False
        self._intake.put(_STOP)
        self._writer.join()
        self._writer = None
        self._deadline = self._clock() + grace
        self._closing.set()
        for route in self._routes.values():
            route.wakeup.set()
        for route in self._routes.values():
            if route.thread is not None:
                route.thread.join(timeout=max(self._deadline - self._clock(), 0.0) + 1.0)
                if route.thread.is_alive():
                    self.logger.warning(
                        f"destination {route.name}: send() still running after the {grace:g} s grace; "
                        "its batch stays in the buffer and will be sent again"
                    )
                route.thread = None
        if self._status is not None:
            self._status.stop()
            self._status = None
        left = {}
        if self._buffer is not None:
            for name in self._routes:
                with contextlib.suppress(BufferClosed, BufferCorrupted):
                    left[name] = self._buffer.stats(name).rows
            self._buffer.close()
        for route in self._routes.values():
            route.tick_logs()
        pending = {name: rows for name, rows in left.items() if rows}
        if pending:
            self.logger.info(
                "delivery stopped; left in the buffer for the next start: "
                + ", ".join(f"{name} {rows}" for name, rows in pending.items())
            )

    # -- intake ---------------------------------------------------------------------------------

    def submit(self, destination: str, record: OutgoingRecord) -> None:
        """Hand a record over for ``destination``; never blocks. Durable after its group commit."""
        route = self._routes[destination]
        if not self._accepting:
            route.metrics.add("received")
            route.metrics.add("dropped")
            self._intake_drop_log.event(1, "the delivery pipeline is not running")
            return
        if self._intake.qsize() >= self.settings.intake_queue_limit:
            route.metrics.add("received")
            route.metrics.add("dropped")
            self._intake_drop_log.event(
                1,
                f"{self.settings.intake_queue_limit} records already wait for the disk (intake_queue_limit)",
            )
            return
        self._intake.put((route, record))

    def submit_record(
        self, deliveries: Sequence[tuple[str, OutgoingRecord]], seen: tuple[str, int, int] | None = None
    ) -> bool:
        """Hand over the copies of one record, and its hop key, to be committed in one transaction.

        Never blocks. Returns False when the record was dropped (counted for each destination):
        its key is then not written either, so a replay of the record is delivered. With no
        deliveries, only the key is written (a record that reaches no destination was handled too).
        """
        routes = [(self._routes[name], record) for name, record in deliveries]
        reason = None
        if not self._accepting:
            reason = "the delivery pipeline is not running"
        elif self._intake.qsize() >= self.settings.intake_queue_limit:
            reason = f"{self.settings.intake_queue_limit} records already wait for the disk (intake_queue_limit)"
        if reason is not None:
            for route, _ in routes:
                route.metrics.add("received")
                route.metrics.add("dropped")
            if routes:
                self._intake_drop_log.event(len(routes), reason)
            return False
        self._intake.put(_Handoff(routes, seen))
        return True

    def hop_keys(self) -> list[tuple[str, int, int]]:
        """The hop keys kept in the buffer, oldest first (empty before :meth:`start`)."""
        if self._buffer is None or self._buffer.closed:
            return []
        try:
            return self._buffer.seen_keys()
        except (BufferClosed, BufferCorrupted):
            return []

    def flush_intake(self, timeout: float | None = None) -> bool:
        """Wait until every record submitted before this call is committed; False on timeout."""
        if self._writer is None:
            return False
        done = threading.Event()
        self._intake.put(done)
        return done.wait(timeout)

    def add_commit_listener(self, listener: Callable[[Sequence[tuple[str, str]]], None]) -> None:
        """Call ``listener`` on the writer thread with ``(destination, record_id)`` of each group commit."""
        self._commit_listeners.append(listener)

    def _write_loop(self) -> None:
        limit = self.settings.commit_batch_size
        while True:
            try:
                first = self._intake.get(timeout=0.5)
            except queue.Empty:
                self._tick_logs()
                continue
            items = [first]
            self._take_waiting(items, limit)
            if len(items) < limit and self.settings.commit_interval > 0 and first is not _STOP:
                # Let a trickle of records gather into one commit: at robot rates this turns a
                # commit (and, with storage_sync full, an fsync) per record into a few per second.
                time.sleep(self.settings.commit_interval)
                self._take_waiting(items, limit)
            stop = False
            records: list[Any] = []
            markers: list[threading.Event] = []
            for item in items:
                if item is _STOP:
                    stop = True
                elif isinstance(item, threading.Event):
                    markers.append(item)
                else:
                    records.append(item)
            if records:
                self._commit(records)
            self._tick_logs()
            for marker in markers:
                marker.set()
            if stop:
                # Whatever was submitted before the stop is committed before the writer ends.
                self._drain_after_stop()
                return

    def _take_waiting(self, items: list[Any], limit: int) -> None:
        while len(items) < limit:
            try:
                items.append(self._intake.get_nowait())
            except queue.Empty:
                return

    def _drain_after_stop(self) -> None:
        while True:
            try:
                item = self._intake.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, threading.Event):
                item.set()
            elif item is not _STOP:
                self._commit([item])

    def _commit(self, items: list[Any]) -> None:
        """One group commit of intake items: ``(route, record)`` pairs and :class:`_Handoff` s."""
        handoffs = [item if isinstance(item, _Handoff) else _Handoff([item], None) for item in items]
        batch = self._storable(handoffs)
        assert self._buffer is not None
        while True:
            try:
                result = self._buffer.append(
                    batch.by_destination, batch.limits, seen=batch.seen, seen_window=self._seen_window
                )
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
                if self._closing.wait(1.0) or not self._accepting:
                    for name, records in batch.by_destination.items():
                        self._routes[name].metrics.add("received", len(records))
                        self._routes[name].metrics.add("dropped", len(records))
                    self.logger.error(f"delivery buffer: {batch.count} records lost at shutdown: {exc}")
                    return
        self._commit_error = None
        self._account(batch, result)

    def _storable(self, handoffs: list[_Handoff]) -> _CommitBatch:
        """What of ``handoffs`` the buffer can hold; a record that is not valid UTF-8 JSON is counted apart."""
        batch = _CommitBatch()
        for handoff in handoffs:
            if handoff.seen is not None:
                batch.seen.append(handoff.seen)
            for route, record in handoff.records:
                try:
                    pending = PendingRecord(record.record_id, record.topic, record.stamp_ns, record.to_json())
                    pending.size  # noqa: B018 - encodes the payload: a lone surrogate fails here, not in append
                except (MalformedRecord, UnicodeError, ValueError, TypeError, RecursionError) as exc:
                    self._not_storable(route, record.record_id, f"{type(exc).__name__}: {exc}")
                    continue
                batch.add(route, pending)
        return batch

    def _commit_apart(self, handoffs: list[_Handoff], exc: Exception) -> None:
        """Commit each received record alone after ``exc`` failed their group commit."""
        if len(handoffs) > 1:
            for handoff in handoffs:
                self._commit([handoff])
            return
        (handoff,) = handoffs
        for route, record in handoff.records:
            self._not_storable(route, record.record_id, f"the buffer refused it: {type(exc).__name__}: {exc}")
        if handoff.seen is not None:
            self._commit([_Handoff([], handoff.seen)])  # handled: a replay of it is not reported as new

    def _not_storable(self, route: _Route, record_id: str, reason: str) -> None:
        route.metrics.add("received")
        route.metrics.add("malformed")
        route.malformed_log.event(1, f"record {record_id}: {reason}")

    def _commit_failed(self, batch: _CommitBatch, exc: Exception) -> None:
        error = f"committing to the buffer: {type(exc).__name__}: {exc}"
        if self._commit_error is None:
            self._commit_error = (self._clock(), error)
        else:
            self._commit_error = (self._commit_error[0], error)
        self._commit_log.event(batch.count, f"{type(exc).__name__}: {exc}")
        for name in batch.by_destination:
            metrics = self._routes[name].metrics
            metrics.add("failed")
            metrics.set_error(error)

    def _account(self, batch: _CommitBatch, result: AppendResult) -> None:
        """Counters, drop logs and sender wake-ups after a group commit."""
        for name, records in batch.by_destination.items():
            route = self._routes[name]
            route.metrics.add("received", len(records))
            dropped_newest = result.dropped_newest.get(name, 0)
            dropped_oldest = result.dropped_oldest.get(name, 0)
            if dropped_newest or dropped_oldest:
                route.metrics.add("dropped", dropped_newest + dropped_oldest)
                route.drop_log.event(
                    dropped_newest + dropped_oldest,
                    f"storage_total_limit_size {route.params.storage_total_limit_size} reached, "
                    f"when_full {route.params.when_full}",
                )
            route.pending_hint += result.appended.get(name, 0)
            if route.pending_hint >= route.params.batch_size:
                route.wakeup.set()
        if self._commit_listeners:
            committed = batch.committed
            for listener in self._commit_listeners:
                try:
                    listener(committed)
                except Exception as exc:
                    self.logger.error(f"delivery commit listener failed: {exc}")

    # -- senders --------------------------------------------------------------------------------

    def _send_loop(self, route: _Route) -> None:
        backoff = Backoff(self.settings.scheduler_base, self.settings.scheduler_cap, self._uniform)
        assert self._buffer is not None
        buffer = self._buffer
        batch_size = route.params.batch_size
        while True:
            closing = self._closing.is_set()
            if closing and self._clock() >= self._deadline:
                return
            try:
                rows = buffer.read_batch(route.name, batch_size)
            except BufferCorrupted:
                continue
            except BufferClosed:
                return
            except Exception as exc:  # disk full, I/O error: the sender waits and tries again, never dies
                if self._buffer_trouble(route, backoff, f"reading the buffer: {type(exc).__name__}: {exc}"):
                    return
                continue
            if not rows:
                if closing:
                    return
                route.pending_hint = 0
                route.wakeup.wait(self.settings.flush)
                route.wakeup.clear()
                route.tick_logs()
                continue
            try:
                must_retry = self._deliver(route, buffer, rows)
            except BufferClosed:
                return
            except BufferCorrupted:
                continue
            except Exception as exc:
                # The destination may have taken the batch before the buffer failed to record it
                # (deleting needs disk space too): those records are sent again, as after a crash.
                if self._buffer_trouble(route, backoff, f"updating the buffer: {type(exc).__name__}: {exc}"):
                    return
                continue
            if must_retry:
                delay = backoff.next_delay()
                if self._wait_backoff(delay):
                    return
            else:
                backoff.reset()
                if len(rows) < batch_size and not closing:
                    route.pending_hint = 0
                    route.wakeup.wait(self.settings.flush)
                    route.wakeup.clear()

    def _buffer_trouble(self, route: _Route, backoff: Backoff, what: str) -> bool:
        """Count and log a failed buffer operation, then back off; True when the pipeline is stopping."""
        route.metrics.add("failed")
        route.metrics.set_error(what)
        route.failure_log.event(1, what)
        return self._wait_backoff(backoff.next_delay())

    def _wait_backoff(self, delay: float) -> bool:
        if self._wait is not None:
            return self._wait(delay) or self._closing.is_set()
        return self._closing.wait(delay)

    def _deliver(self, route: _Route, buffer: SqliteBuffer, rows: list[BufferedRow]) -> bool:
        """One send() of ``rows``; returns True when some of them must be retried."""
        records: list[OutgoingRecord] = []
        sent_rows: list[BufferedRow] = []
        unreadable: list[tuple[BufferedRow, str]] = []
        for row in rows:
            try:
                data = parse_record(row.payload)
            except MalformedRecord as exc:
                # Written by an older DC (it let NaN through) or changed by hand: never sent as is.
                unreadable.append((row, f"unreadable payload in the buffer: {exc}"))
                continue
            records.append(OutgoingRecord(row.record_id, row.topic, row.stamp_ns, data, json_text=row.payload))
            sent_rows.append(row)
        if unreadable:
            route.metrics.add("dead_lettered", buffer.dead_letter(route.name, unreadable))
            self._bound_dead_letters(route, buffer)
        if not records:
            return False
        retry: dict[int, str] = {}
        reject: dict[int, str] = {}
        try:
            outcome = route.destination.send(records)
        except RejectedError as exc:
            reject = dict.fromkeys(range(len(records)), f"rejected: {exc}")
        except RetryableError as exc:
            retry = dict.fromkeys(range(len(records)), str(exc))
        except Exception as exc:
            retry = dict.fromkeys(range(len(records)), f"{type(exc).__name__}: {exc}")
        else:
            if isinstance(outcome, SendOutcome):
                retry = {i: reason for i, reason in outcome.retry.items() if 0 <= i < len(records)}
                reject = {
                    i: f"rejected: {reason}"
                    for i, reason in outcome.reject.items()
                    if 0 <= i < len(records) and i not in retry
                }
        confirmed = [row.row_id for i, row in enumerate(sent_rows) if i not in retry and i not in reject]
        if confirmed:
            buffer.delete(route.name, confirmed)
            route.metrics.add("sent", len(confirmed))
        if not retry and not reject:
            return False
        route.metrics.add("failed")
        first_error = next(iter({**reject, **retry}.values()))
        route.metrics.set_error(first_error)
        dead: list[tuple[BufferedRow, str]] = [(sent_rows[i], reason) for i, reason in reject.items()]
        retried = 0
        if retry:
            attempts = buffer.record_failure(route.name, [sent_rows[i].row_id for i in retry])
            limit = route.params.retry_limit
            for i, reason in retry.items():
                row = sent_rows[i]
                if limit >= 0 and attempts.get(row.row_id, 0) > limit:
                    dead.append((row, f"retry_limit {limit} exhausted: {reason}"))
                else:
                    retried += 1
            route.metrics.add("retried", retried)
            if retried:
                route.failure_log.event(retried, first_error)
        if dead:
            moved = buffer.dead_letter(route.name, dead)
            route.metrics.add("dead_lettered", moved)
            route.dead_letter_log.event(moved, f"{dead[0][1]}; see `dc buffer list`")
            self._bound_dead_letters(route, buffer)
        return retried > 0

    def _bound_dead_letters(self, route: _Route, buffer: SqliteBuffer) -> None:
        if route.dead_letter_max_bytes is None:
            return
        deleted = buffer.trim_dead_letters(route.name, route.dead_letter_max_bytes)
        if deleted:
            route.metrics.add("dead_letters_dropped", deleted)
            route.dead_letter_drop_log.event(deleted, "the newest are kept; see `dc buffer list`")

    # -- storage ------------------------------------------------------------------------------------

    def _storage_dir(self) -> Path:
        configured = self.settings.storage_path.strip()
        if not configured:
            directory = default_storage_dir()
            directory.mkdir(parents=True, exist_ok=True)
            return directory
        directory = Path(os.path.expanduser(expand_env(configured, "destination_server.flb.storage_path")))
        try:
            directory.mkdir(parents=True, exist_ok=True)
            if not os.access(directory, os.W_OK | os.X_OK):
                raise PermissionError(f"{directory} is not writable")
        except OSError as exc:
            fallback = default_storage_dir()
            self.logger.error(f"flb.storage_path {directory} cannot be used ({exc}); buffering in {fallback} instead")
            fallback.mkdir(parents=True, exist_ok=True)
            return fallback
        return directory

    def _on_quarantine(self, quarantine: Quarantine) -> None:
        self._quarantined += 1
        self.logger.error(
            f"delivery buffer was unreadable ({quarantine.reason}); moved aside to {quarantine.moved_to} "
            "and replaced by an empty one — records in it were not delivered"
        )

    def _tick_logs(self) -> None:
        """Let bursts of log-worthy events end with their summary line (the writer calls this)."""
        now = self._clock()
        if now - self._last_log_tick < 0.5:
            return
        self._last_log_tick = now
        self._intake_drop_log.tick()
        self._commit_log.tick()
        for route in self._routes.values():
            route.tick_logs()

    # -- observability ------------------------------------------------------------------------------

    def metrics(self) -> dict[str, dict[str, Any]]:
        """Per destination: counters since start, what waits in the buffer, the last error."""
        out: dict[str, dict[str, Any]] = {}
        now_ns = time.time_ns()
        for name, route in self._routes.items():
            values = route.metrics.snapshot()
            values.update(buffered=None, buffered_bytes=None, dead_letters=None, oldest_pending_age_s=None)
            if self._buffer is not None and not self._buffer.closed:
                try:
                    stats = self._buffer.stats(name)
                except (BufferClosed, BufferCorrupted):
                    pass
                else:
                    values.update(
                        buffered=stats.rows,
                        buffered_bytes=stats.bytes,
                        dead_letters=stats.dead_letters,
                        oldest_pending_age_s=(
                            max(now_ns - stats.oldest_enqueued_ns, 0) / 1e9
                            if stats.oldest_enqueued_ns is not None
                            else 0.0
                        ),
                    )
            out[name] = values
        return out

    def buffer_metrics(self) -> dict[str, Any]:
        """The buffer as a whole: file, sync mode, corrupt files set aside, records awaiting commit,
        and while group commits fail, since how long and why."""
        failing = self._commit_error
        return {
            "path": str(self.storage_file) if self.storage_file else None,
            "storage_sync": self.settings.storage_sync,
            "quarantined": self._quarantined,
            "intake_pending": self._intake.qsize(),
            "running": self._writer is not None and self._writer.is_alive(),
            "commit_error": failing[1] if failing else "",
            "commit_failing_s": round(self._clock() - failing[0], 3) if failing else 0.0,
        }

    def add_metrics_section(self, name: str, supplier: Callable[[], Any]) -> None:
        """Add ``name: supplier()`` to the JSON of ``/api/v1/metrics`` (e.g. the server's intake counters)."""
        self._sections[name] = supplier

    def status_document(self) -> dict[str, Any]:
        """What ``/api/v1/metrics`` serves."""
        document: dict[str, Any] = {"destinations": self.metrics(), "buffer": self.buffer_metrics()}
        for name, supplier in self._sections.items():
            document[name] = supplier()
        return document

    def healthy(self) -> bool:
        """Writer and senders alive, and records reaching the disk (a failing group commit keeps
        every new record in memory only)."""
        if self._writer is None or not self._writer.is_alive() or self._commit_error is not None:
            return False
        return all(route.thread is not None and route.thread.is_alive() for route in self._routes.values())

    def prometheus(self) -> str:
        return prometheus_text(self.metrics(), self.buffer_metrics())

    @property
    def http_address(self) -> tuple[str, int] | None:
        return self._status.address if self._status is not None else None

    def _start_status_server(self) -> None:
        self._status = start_status_server(
            self.logger,
            self.settings.http_listen,
            self.settings.http_port,
            health=self.healthy,
            metrics=self.status_document,
            prometheus=self.prometheus,
        )


_SYNC_PROMISE = {
    "normal": "committed records survive a crash of the process, a power cut may lose the last ones",
    "full": "committed records survive a crash of the process and a power cut",
}
