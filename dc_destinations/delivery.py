"""Durable delivery for destination_server: the buffer, its group commits and one sender per destination.

:class:`DeliveryPipeline` puts the parts together and is what the server talks to:

- dc_destinations.commit — records handed over on the main thread reach the disk in group commits;
- dc_destinations.sender — how each destination's ``send()`` is called, retried and dead-lettered;
- dc_destinations.buffer — the SQLite buffer (behind the ``Buffer`` protocol);
- dc_destinations.storage — where the buffer lives;
- dc_destinations.metrics — the counters, served over HTTP with the buffer's state.

Each destination has its own queue and sender thread, so a slow or dead destination never delays
another.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dc_core.confined_files import ConfinementParams
from dc_core.destination import Destination, OutgoingRecord
from dc_core.http_status import StatusServer, start_status_server
from dc_core.logs import BurstLog, Logger
from dc_core.supervision import Supervisor
from dc_destinations.buffer import (
    FILE_NAME,
    BufferClosed,
    BufferCorrupted,
    Quarantine,
    SalvageStopped,
    SqliteBuffer,
)
from dc_destinations.commit import CommitListener, GroupCommitter, HopKey, Received
from dc_destinations.disk_budget import FileCandidate, RecordClass, Step, budget_plan
from dc_destinations.health import FAILING
from dc_destinations.links import LinuxNetwork, Network, link_buckets, warn_missing_interfaces
from dc_destinations.metrics import prometheus_text
from dc_destinations.record_ids import new_record_id, uuid7
from dc_destinations.saved_files import FILE_NAME as SAVED_FILES_NAME
from dc_destinations.saved_files import SavedFiles
from dc_destinations.sender import (
    DROP_DISK_BUDGET,
    DROP_INTAKE,
    Closing,
    DropListener,
    OutcomeListener,
    Route,
    Sender,
    tell_dropped,
)
from dc_destinations.settings import (
    DeliveryParams,
    DestinationDeliveryParams,
    budget_limits,
    by_measurement,
    check_destination_params,
    link_rates,
)
from dc_destinations.storage import (
    SYNC_PROMISE,
    BufferLock,
    legacy_storage_dir,
    storage_dir,
    waiting_in,
)

__all__ = ["DeliveryPipeline", "new_record_id", "uuid7"]


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
        supervisor: Supervisor | None = None,
        network: Network | None = None,
        saved_files_roots: Sequence[str] = (),
    ) -> None:
        """``saved_files_roots``: where DC's measurements save files (besides the file destinations'
        ``allowed_roots``): the files the disk budget weighs and may delete are those in these folders."""
        self.settings = settings
        self._saved_files_roots = [
            *saved_files_roots,
            *(
                root
                for destination, _ in destinations.values()
                if isinstance(destination.params, ConfinementParams)
                for root in destination.params.allowed_roots
            ),
        ]
        self.logger = logger
        # The writer, the senders and the status server run under its rule (dc_core.supervision).
        self.supervisor = supervisor if supervisor is not None else Supervisor(logger)
        self._seen_window = seen_window
        self._clock = clock
        self._wait = wait
        self._uniform = uniform
        self._closing = Closing()
        self._routes: dict[str, Route] = {}
        # The network only_when reads: the kernel's unless a test gives its own (dc_destinations.links).
        network = network if network is not None else LinuxNetwork()
        links = link_buckets(link_rates(settings, "destination_server.flb"), settings.burst_s)
        for name, (destination, params) in destinations.items():
            check_destination_params(params, f"destination_server.{name}", settings.links)
            route = Route.of(
                name,
                destination,
                params,
                logger,
                network=network,
                links=links,
                burst_s=settings.burst_s,
                stop=self._closing.event,
            )
            warn_missing_interfaces(route.rules, name, logger)
            self._routes[name] = route
        # The disk budget over the buffer's records and DC's saved files (dc_destinations.saved_files).
        self._limits = budget_limits(settings, "destination_server.flb")
        self._file_fields = {name: route.file_fields for name, route in self._routes.items() if route.file_fields}
        self._saved: SavedFiles | None = None
        # Made with the ledger at start: nothing here may need the logger before (a tool claims the storage alone).
        self._budget_log: BurstLog | None = None
        self._buffer: SqliteBuffer | None = None
        self._committer: GroupCommitter | None = None
        self._listeners: list[CommitListener] = []
        self._outcome_listeners: list[OutcomeListener] = []
        self._drop_listeners: list[DropListener] = []
        # Set before start: called on the writer thread with the hop keys of each successful commit.
        self.on_seen_committed: Callable[[list[HopKey]], None] | None = None
        self._quarantined = 0
        self._salvage_thread: threading.Thread | None = None
        self._salvaging: Path | None = None
        self._salvage_started: set[str] = set()
        self._lost_unknown = 0
        # The last integrity check of the buffer file: (wall-clock time, "ok" or what it found), and
        # whether the file in use is damaged (cleared when it is set aside).
        self._check_lock = threading.Lock()
        self._last_check: tuple[float, str] | None = None
        self._damaged = False
        self._last_log_tick = 0.0
        # The size of the buffer's filesystem as last read (a budget in percent of it), and the budget
        # as DC accounts it (records waiting + saved files) after each admission and the evictions it
        # made necessary: the last total, the most, and how many checks left it over the budget.
        self._filesystem_bytes: int | None = None
        self._budget_held = self._budget_most = self._budget_left_over = self._budget_failed = 0
        self._budget_failed_log: BurstLog | None = None
        self._status: StatusServer | None = None
        # (server, ROS domain id, namespace) under which the server writes its metrics address down.
        self.metrics_announce_as: tuple[str, int, str] | None = None
        self._sections: dict[str, Callable[[], Any]] = {}
        self._prometheus_sections: list[Callable[[], str]] = []
        self.storage_file: Path | None = None
        self._lock: BufferLock | None = None
        self._lock_taken_by_start = False

    # -- lifecycle ----------------------------------------------------------------------------------

    def claim_storage(self, namespace: str = "/") -> Path:
        """Find the buffer file and take its lock (dc_destinations.storage): the server does it at
        configure, so that a buffer owned by another process fails configure, with the owner named.
        :meth:`release_storage` gives it back."""
        if self._lock is not None and self._lock.held:
            assert self.storage_file is not None
            return self.storage_file
        storage_file = storage_dir(self.settings, self.logger, namespace) / FILE_NAME
        lock = BufferLock(storage_file)
        lock.acquire()
        self.storage_file, self._lock = storage_file, lock
        if not self.settings.storage_path.strip():
            self._mention_legacy_backlog()
        return storage_file

    def release_storage(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def _mention_legacy_backlog(self) -> None:
        legacy = legacy_storage_dir() / FILE_NAME
        waiting = waiting_in(legacy)
        if waiting:
            self.logger.warning(
                f"{waiting} records of an earlier DC wait in {legacy}, the default buffer before buffers were "
                f"separated by ROS domain and namespace; to deliver them, run once with flb.storage_path: "
                f'"{legacy.parent}"'
            )

    def start(self) -> None:
        """Open (or recover) the buffer, start the writer and one sender per destination."""
        if self._committer is not None and self._committer.started:
            return
        if self._lock is None or not self._lock.held:
            self.claim_storage()
            self._lock_taken_by_start = True
        assert self.storage_file is not None
        buffer = SqliteBuffer(
            self.storage_file,
            synchronous=self.settings.storage_sync,
            on_quarantine=self._on_quarantine,
            on_salvage_start=self._on_salvage_start,
            defer_salvage=True,
        )
        self._buffer = buffer
        # Before the senders start: a file found damaged now is set aside before anything reads it
        # (and salvaged beside delivery, below).
        self.check_buffer(repair=True)
        buffer.ensure_queues(list(self._routes))
        # Queues whose records have priorities by input topic are counted per topic, under a budget only.
        budgeted = self._limits.budget_bytes is not None or self._limits.budget_fraction is not None
        buffer.track_topics([name for name, route in self._routes.items() if route.per_topic_retention and budgeted])
        if self._limits.active:
            saved = SavedFiles(
                self.storage_file.parent / SAVED_FILES_NAME,
                self.settings.retention_priorities,
                self.logger,
                keep_run_ends=self.settings.keep_run_ends,
                records_evictions=[n for n, r in self._routes.items() if r.destination.records_evictions],
                roots=self._saved_files_roots,
            )
            saved.open()
            self._saved = saved
            self._budget_log = BurstLog(self.logger.warning, "disk budget")
            self._budget_failed_log = BurstLog(
                self.logger.error, "delivery buffer: keeping the disk budget failed, tried again at the next check"
            )
            for route in self._routes.values():
                route.saved = saved
                route.destination.__dict__["_dc_evicted"] = saved.is_evicted
        self._closing.reset()
        senders = {
            name: Sender(
                route,
                buffer,
                self.settings,
                self._closing,
                clock=self._clock,
                wait=self._wait,
                uniform=self._uniform,
                listeners=self._outcome_listeners,
                drop_listeners=self._drop_listeners,
            )
            for name, route in self._routes.items()
        }
        for sender in senders.values():  # a limit lowered since the last run applies at once
            sender.bound_dead_letters()
        backlog = {name: buffer.stats(name).rows for name in self._routes}
        self.logger.info(
            f"delivery buffer {self.storage_file} (storage_sync={self.settings.storage_sync}: "
            + SYNC_PROMISE[self.settings.storage_sync]
            + "); backlog: "
            + (", ".join(f"{name} {rows}" for name, rows in backlog.items()) or "none")
        )
        self._committer = GroupCommitter(
            self._routes,
            buffer,
            self.settings,
            self._closing,
            self.logger,
            seen_window=self._seen_window,
            clock=self._clock,
            tick_logs=self._tick_logs,
            supervisor=self.supervisor,
            drop_listeners=self._drop_listeners,
        )
        for listener in self._listeners:
            self._committer.add_listener(listener)
        self._committer.on_seen_committed = self.on_seen_committed
        self._committer.after_append = lambda: self._keep_budget(tick=False)
        self._committer.start()
        for name, sender in senders.items():
            route = self._routes[name]
            route.wakeup.clear()
            route.destination.stopping.clear()
            route.thread = self.supervisor.start_thread(sender.run, name=f"dc-sender-{name}")
        pending = buffer.pending_salvage()
        if pending is not None:
            # Beside delivery, not in this transition: ~0.75 s per 100,000 records.
            self._salvage_thread = self.supervisor.start_thread(
                lambda: self._salvage(buffer, pending), name="dc-salvage"
            )
        if self.settings.http_server:
            self._start_status_server()

    def stop(self, grace: float) -> None:
        """Stop intake, commit what was submitted, deliver for up to ``grace`` s, leave the rest on disk.

        What waits in memory is committed first, even if the writer died; what cannot be is counted
        and logged with its number (dc_destinations.commit.GroupCommitter.stop)."""
        if self._committer is None or not self._committer.started:
            return
        self._committer.stop()
        self._closing.deadline = self._clock() + grace
        self._closing.event.set()
        if self._salvage_thread is not None:  # it stops after its current transaction
            self._salvage_thread.join(timeout=max(grace, 1.0) + 10.0)
            self._salvage_thread = None
        for route in self._routes.values():
            route.wakeup.set()
        for route in self._routes.values():
            if route.thread is not None:
                route.thread.join(timeout=max(self._closing.deadline - self._clock(), 0.0) + 1.0)
                if route.thread.is_alive():
                    route.destination.stopping.set()  # a send that waits (a rate's slot) returns now
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
        if self._saved is not None:
            self._saved.close()
            self._saved.tick_logs()
        self._committer.intake_drop_log.tick()
        self._committer.commit_log.tick()
        self._committer.after_append_log.tick()
        if self._budget_failed_log is not None:
            self._budget_failed_log.tick()
        for route in self._routes.values():
            route.tick_logs()
        pending = {name: rows for name, rows in left.items() if rows}
        if pending:
            self.logger.info(
                "delivery stopped; left in the buffer for the next start: "
                + ", ".join(f"{name} {rows}" for name, rows in pending.items())
            )
        # The stopped committer stays: records handed over from now on are counted as dropped.
        if self._lock_taken_by_start:
            self.release_storage()
            self._lock_taken_by_start = False

    def between_sends(self, name: str, hook: Callable[[], None]) -> bool:
        """``hook()`` (the destination ``name``'s deactivate or cleanup) never while its ``send`` runs.

        Now, and True, unless a ``send`` still runs past the stop's grace: then False, and ``hook``
        runs on the sender's thread as soon as that ``send`` returns (dc_destinations.sender.Gate).
        """
        route = self._routes.get(name)
        if route is None:
            hook()
            return True
        return route.gate.run(hook)

    # -- intake ---------------------------------------------------------------------------------

    def submit(self, destination: str, record: OutgoingRecord) -> None:
        """Hand a record over for ``destination``; never blocks. Durable after its group commit."""
        self.submit_record([(destination, record)])

    def submit_record(self, deliveries: Sequence[tuple[str, OutgoingRecord]], seen: HopKey | None = None) -> bool:
        """See :meth:`dc_destinations.commit.GroupCommitter.submit_record`."""
        return self.submit_records([(deliveries, seen)])

    def submit_records(self, received: Sequence[Received]) -> bool:
        """See :meth:`dc_destinations.commit.GroupCommitter.submit_records`."""
        if self._committer is None:
            for deliveries, _ in received:
                for name, record in deliveries:
                    self._routes[name].metrics.add("received")
                    self._routes[name].metrics.add_by_topic("dropped", {record.topic: 1})
                    tell_dropped(self._drop_listeners, self.logger, name, [record.record_id], DROP_INTAKE)
            return False
        saved = self._saved
        if saved is not None:
            for deliveries, _ in received:
                saved.note(deliveries, self._file_fields)
        return self._committer.submit_records(received)

    def conditions(self) -> list[str]:
        """The DC conditions some destination's only_when reads (the server subscribes to them)."""
        return sorted({name for route in self._routes.values() for name in route.rules.params.conditions})

    def set_condition(self, name: str, value: bool) -> None:
        """A condition's state heard on dc/condition/<name>: the senders it holds look again at once."""
        for route in self._routes.values():
            if route.rules.condition_changed(name, value):
                route.wakeup.set()

    def hop_keys(self) -> list[HopKey]:
        """The hop keys kept in the buffer, oldest first (empty before :meth:`start`)."""
        if self._buffer is None or self._buffer.closed:
            return []
        try:
            return self._buffer.seen_keys()
        except (BufferClosed, BufferCorrupted):
            return []

    def hop_loss_totals(self) -> dict[str, tuple[int, int]]:
        """Per topic, the records every run counted lost before destination_server, and in how many
        gaps (empty before :meth:`start`)."""
        if self._buffer is None or self._buffer.closed:
            return {}
        try:
            return self._buffer.hop_loss_totals()
        except (BufferClosed, BufferCorrupted):
            return {}

    def flush_intake(self, timeout: float | None = None) -> bool:
        """Wait until every record submitted before this call is committed; False on timeout."""
        return self._committer is not None and self._committer.flush(timeout)

    def add_commit_listener(self, listener: CommitListener) -> None:
        """Call ``listener`` on the writer thread with ``(destination, record_id)`` of each group commit."""
        self._listeners.append(listener)
        if self._committer is not None:
            self._committer.add_listener(listener)

    def add_outcome_listener(self, listener: OutcomeListener) -> None:
        """Call ``listener`` on the senders' threads with the records each destination confirmed, and with
        those dead-lettered once their dead letters are committed (dc_destinations.sender.OutcomeListener).
        Before :meth:`start`."""
        self._outcome_listeners.append(listener)

    def add_drop_listener(self, listener: DropListener) -> None:
        """Call ``listener`` with the records that leave a destination's queue, or never reach it, with
        no outcome: dropped by its size limit, evicted by the disk budget, refused at the intake…
        (dc_destinations.sender.DropListener, with the reason). Each is counted as it always was
        (``dropped``, ``evicted``, ``malformed``). Before :meth:`start`."""
        self._drop_listeners.append(listener)

    # -- storage ------------------------------------------------------------------------------------

    def _on_salvage_start(self, moved_to: Path, reason: str) -> None:
        self._salvage_started.add(moved_to.name)
        self.logger.error(
            f"delivery buffer is damaged ({reason}); moved aside to {moved_to}; salvaging its readable records "
            "into a new buffer"
        )

    def _salvage(self, buffer: SqliteBuffer, source: Path) -> None:
        """The salvage thread: a damaged file set aside at this start (or one an earlier run did not
        finish) copied into the buffer while delivery runs; stopped with delivery, resumed at the next start."""
        self._salvaging = source
        if all(q.moved_to != source for q in buffer.quarantines) and source.name not in self._salvage_started:
            self.logger.warning(f"delivery buffer: going on with the salvage of {source} (set aside earlier)")
        try:
            buffer.salvage_pending(stop=self._closing.event.is_set)
        except (SalvageStopped, BufferClosed):
            self.logger.warning(
                f"delivery buffer: the salvage of {source} stops with delivery; the next start goes on with it"
            )
        except Exception as exc:
            self.logger.error(
                f"delivery buffer: the salvage of {source} failed ({type(exc).__name__}: {exc}); the next start "
                f"tries again\n{traceback.format_exc()}"
            )
        finally:
            self._salvaging = None

    def _on_quarantine(self, quarantine: Quarantine) -> None:
        """Count what the salvage of a damaged file put back and lost, and say it in one line."""
        self._quarantined += 1
        with self._check_lock:
            self._damaged = False  # the file in use is a new one
        report = quarantine.salvage
        if report is not None:
            for name, count in report.recovered.items():
                if name in self._routes:
                    self._routes[name].metrics.add("salvaged", count)
            for name, count in report.lost.items():
                if name in self._routes:
                    self._routes[name].metrics.add("lost_to_damage", count)
                else:
                    self._lost_unknown += count
        numbers = report.summary() if report is not None else "nothing salvaged"
        failed = f"; salvage stopped: {quarantine.salvage_error}" if quarantine.salvage_error else ""
        self.logger.error(
            f"delivery buffer salvaged from {quarantine.moved_to} into the new buffer: {numbers}{failed} (records "
            f"already delivered may be delivered again, with the same record_id; `dc buffer salvage "
            f"{quarantine.moved_to}` reads the file again)"
        )

    def check_buffer(self, *, repair: bool = False) -> str:
        """``PRAGMA quick_check`` of the buffer file: "ok" or what is damaged, kept for health and metrics.

        Runs on the caller's thread on a connection of its own (the server calls it from its worker
        about hourly: ``buffer_check_interval``). Damage is logged once when found; with ``repair``
        (at start, before anything is read from the file) the file is set aside at once, to be
        salvaged beside delivery.
        While running, a damaged file is set aside when an operation meets the damage or at the next
        start; until then the health endpoint answers 503 and ``buffer_damaged`` is true.
        """
        buffer = self._buffer
        if buffer is None or buffer.closed:
            return "not open"
        try:
            result = buffer.quick_check()
        except sqlite3.Error as exc:
            self.logger.warning(f"delivery buffer {buffer.path}: integrity check could not run: {exc}")
            return f"not checked: {exc}"
        with self._check_lock:
            self._last_check = (time.time(), result)
            newly = result != "ok" and not self._damaged
            self._damaged = result != "ok"
        if result == "ok":
            return result
        if repair:  # _on_quarantine says it, with the numbers
            with contextlib.suppress(BufferClosed):
                buffer.set_aside(f"integrity check: {result}", defer=True)
        elif newly:
            self.logger.error(
                f"delivery buffer {buffer.path} is damaged: {result}. It is set aside and its readable records "
                "salvaged when delivery meets the damage or at the next start: restart destination_server to do "
                "it now"
            )
        return result

    def _tick_logs(self) -> None:
        """Let bursts of log-worthy events end with their summary line (the writer calls this)."""
        now = self._clock()
        if now - self._last_log_tick < 0.5:
            return
        self._last_log_tick = now
        self._keep_budget()
        if self._committer is not None:
            self._committer.intake_drop_log.tick()
            self._committer.commit_log.tick()
            self._committer.after_append_log.tick()
        for route in self._routes.values():
            route.tick_logs()

    def _keep_budget(self, *, tick: bool = True) -> None:
        """Keep the buffer's records and the saved files within flb.disk_budget and the free space above
        disk_free_floor (dc_destinations.disk_budget), each eviction counted and logged once per burst.

        On the writer thread, at each admission: after each group commit, within Buffer.exclusive
        (``tick`` False: the files its records name taken in with it; the budget only, on the
        filesystem's size as last read), and twice a second (the ledger written, the filesystem and
        the free-space floor read)."""
        buffer, saved = self._buffer, self._saved
        if not self._limits.active or buffer is None or buffer.closed or self.storage_file is None:
            return
        try:
            if tick:
                if saved is not None:
                    saved.tick()
                    saved.tick_logs()
                if self._budget_log is not None:
                    self._budget_log.tick()
                if self._budget_failed_log is not None:
                    self._budget_failed_log.tick()
                disk = os.statvfs(self.storage_file.parent)
                self._filesystem_bytes = disk.f_blocks * disk.f_frsize
            elif self._filesystem_bytes is None and self._limits.budget_fraction is not None:
                return  # before the first tick: a budget in percent of the filesystem is not known yet
            elif saved is not None:
                saved.take_in()
            budget = self._limits.budget(self._filesystem_bytes or 0)
            short = self._under_floor() if tick else []
            if budget is None and not short:
                return
            # One SELECT of the queues' own totals: cheap enough for every group commit.
            queued = {name: n for name, n in buffer.queued_bytes().items() if name in self._routes}
            total = sum(queued.values()) + (saved.total_bytes if saved is not None else 0)
            over = total - (budget or 0)
            if (budget is None or over <= 0) and not short:
                self._budget_kept(total, budget)
                return
            # Only when something must go: the list of files is walked (tens of thousands on a long run).
            files = saved.candidates() if saved is not None else []
            steps = []
            if budget is not None and over > 0:
                if saved is not None:
                    saved.too_large(budget)
                steps = budget_plan(self._record_classes(buffer, queued), files, over)
            if short and not any(step.kind == "file" for step in steps):
                steps = self._floor_steps(short, files)
            for step in steps:
                if step.kind == "records":
                    given = buffer.evict_oldest_among(
                        dict(step.parts), step.nbytes, with_ids=bool(self._drop_listeners)
                    )
                    for name, gone in given.items():
                        route = self._routes[name]
                        route.metrics.add_by_topic("evicted", gone.by_topic)
                        of = ", ".join(f"{measurement} {n}" for measurement, n in by_measurement(gone.by_topic).items())
                        route.evict_log.event(gone.records, f"{gone.bytes} bytes: {of}; see `dc status`")
                        tell_dropped(self._drop_listeners, self.logger, name, gone.record_ids, DROP_DISK_BUDGET)
                elif saved is not None:
                    evicted = saved.evict(step.name)
                    if evicted is not None:
                        unsent = f"not yet delivered to {', '.join(evicted.unsent_to)}" if evicted.unsent_to else ""
                        saved.evict_log.event(
                            1, f"{step.name} ({evicted.freed} bytes, measurement {evicted.measurement}) {unsent}"
                        )
            if budget is not None:
                total = sum(n for name, n in buffer.queued_bytes().items() if name in self._routes)
                self._budget_kept(total + (saved.total_bytes if saved is not None else 0), budget)
        except (BufferClosed, BufferCorrupted):
            return
        except (sqlite3.Error, OSError) as exc:  # a full disk: tried at the next check; the commit says it too
            # Counted and logged once per burst: this runs after every group commit, and a fault that lasts
            # would otherwise write a line per commit.
            self._budget_failed += 1
            if self._budget_failed_log is not None:
                self._budget_failed_log.event(1, f"{type(exc).__name__}: {exc}")

    def _budget_kept(self, held: int, budget: int | None) -> None:
        """The total the budget holds after a check (each admission's, the tick's) and its evictions, for
        the metrics: over it only while what the order would give up next is records in a send() (left
        alone: the destination may confirm them) or a file that could not be deleted."""
        if budget is None:
            return
        self._budget_held = held
        self._budget_most = max(self._budget_most, held)
        if held > budget:
            self._budget_left_over += 1

    def _record_classes(self, buffer: SqliteBuffer, queued: Mapping[str, int]) -> list[RecordClass]:
        """What waits in the queues, by destination and retention priority: a destination with
        ``retention_priorities`` by input topic (its queue counted per topic), the others whole."""
        classes = []
        for name, size in queued.items():
            route = self._routes[name]
            if not route.per_topic_retention:
                classes.append(RecordClass(name, None, route.params.retention_priority, size))
                continue
            topics: dict[int, list[str]] = {}
            weights: dict[int, int] = {}
            for topic, nbytes in buffer.queued_topics(name).items():
                priority = route.retention_of(topic)
                topics.setdefault(priority, []).append(topic)
                weights[priority] = weights.get(priority, 0) + nbytes
            classes += [RecordClass(name, tuple(topics[p]), p, weights[p]) for p in sorted(topics)]
        return classes

    def _under_floor(self) -> list[tuple[str, int, int, int]]:
        """(folder, device, free bytes, floor) of each filesystem under disk_free_floor: the buffer's and
        those of the folders saved files are in (the save folder, the file destinations' allowed_roots)."""
        limits = self._limits
        if (limits.floor_bytes is None and limits.floor_fraction is None) or self.storage_file is None:
            return []
        short = []
        seen: set[int] = set()
        for folder in (str(self.storage_file.parent), *self._saved_files_roots):
            try:
                device = os.stat(folder).st_dev
                if device in seen:
                    continue
                seen.add(device)
                disk = os.statvfs(folder)
            except OSError:
                continue  # a save folder not made yet holds no file
            floor = self._limits.floor(disk.f_blocks * disk.f_frsize)
            free = disk.f_bavail * disk.f_frsize
            if floor is not None and free < floor:
                short.append((folder, device, free, floor))
        return short

    def _floor_steps(
        self,
        short: list[tuple[str, int, int, int]],
        files: list[FileCandidate],
    ) -> list[Step]:
        """The saved files to evict, by the budget's order, to bring each filesystem in ``short`` back
        above the floor: only files on that filesystem free space there."""
        steps: list[Step] = []
        for folder, device, free, floor in short:
            here = [f for f in files if _device(f.path) == device]
            plan = budget_plan([], here, floor - free)
            if not plan and self._budget_log is not None:
                self._budget_log.event(
                    1,
                    f"{free} bytes free on the filesystem of {folder}, under disk_free_floor ({floor}), and no "
                    "saved file left to evict there",
                )
            steps += plan
        return steps

    # -- observability ------------------------------------------------------------------------------

    def metrics(self) -> dict[str, dict[str, Any]]:
        """Per destination: counters since start, what waits in the buffer, the last error, and the
        plugin's own counters (``plugin``: its ``counters()``)."""
        out: dict[str, dict[str, Any]] = {}
        now_ns = time.time_ns()
        for name, route in self._routes.items():
            values = route.metrics.snapshot()
            values.update(buffered=None, buffered_bytes=None, dead_letters=None, oldest_pending_age_s=None)
            values["plugin"] = _plugin_counters(route)
            values["health"] = route.health.snapshot()
            values["held"] = route.held
            values["files_evicted"] = self._saved.files_evicted(name) if self._saved is not None else 0
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
        committer = self._committer
        failing = committer.failing if committer is not None else None
        with self._check_lock:
            last_check, damaged = self._last_check, self._damaged
        return {
            "path": str(self.storage_file) if self.storage_file else None,
            "storage_sync": self.settings.storage_sync,
            "quarantined": self._quarantined,
            "lost_to_damage_unknown": self._lost_unknown,
            "buffer_damaged": damaged,
            "salvaging": str(self._salvaging) if self._salvaging is not None else None,
            "last_check_time": last_check[0] if last_check else None,
            "last_check_result": last_check[1] if last_check else "",
            "intake_pending": committer.waiting if committer is not None else 0,
            "intake_pending_bytes": committer.waiting_bytes if committer is not None else 0,
            "running": committer is not None and committer.running,
            "commit_error": failing[1] if failing else "",
            "commit_failing_s": round(self._clock() - failing[0], 3) if failing else 0.0,
        }

    def add_metrics_section(self, name: str, supplier: Callable[[], Any]) -> None:
        """Add ``name: supplier()`` to the JSON of ``/api/v1/metrics`` (e.g. the server's intake counters)."""
        self._sections[name] = supplier

    def add_prometheus_section(self, render: Callable[[], str]) -> None:
        """Append ``render()`` (Prometheus text, e.g. the server's hop counters) to ``/api/v1/metrics/prometheus``."""
        self._prometheus_sections.append(render)

    def status_document(self) -> dict[str, Any]:
        """What ``/api/v1/metrics`` serves."""
        document: dict[str, Any] = {
            "destinations": self.metrics(),
            "buffer": self.buffer_metrics(),
            "threads": self.supervisor.metrics(),
        }
        if self._saved is not None:
            document["saved_files"] = self._saved.snapshot()
        budget = self._limits.budget(self._filesystem_bytes or 0)
        if budget is not None and (self._filesystem_bytes is not None or self._limits.budget_fraction is None):
            document["disk_budget"] = {
                "budget": budget,
                "held": self._budget_held,
                "most_held": self._budget_most,
                "checks_left_over": self._budget_left_over,
                "checks_failed": self._budget_failed + (self._committer.after_append_failed if self._committer else 0),
            }
        for name, supplier in self._sections.items():
            document[name] = supplier()
        return document

    def healthy(self) -> bool:
        """Writer and senders alive, no thread of the server died, records reaching the disk (a failing
        group commit keeps every new record in memory only), and the buffer file undamaged at its last check."""
        return not self.unhealthy_reason()

    def unhealthy_reason(self) -> str:
        """Why :meth:`healthy` is False ("" while healthy)."""
        committer = self._committer
        if committer is None or not committer.running:
            return "the buffer writer is not running"
        if committer.failing is not None:
            return f"records cannot be committed to the buffer: {committer.failing[1]}"
        if self._damaged:
            return "the buffer file was found damaged at its last check"
        if self.supervisor.unhealthy_reason:
            return self.supervisor.unhealthy_reason
        dead = [name for name in self._routes if not self.sender_alive(name)]
        return f"sender thread of {', '.join(dead)} not running" if dead else ""

    def sender_alive(self, name: str) -> bool:
        thread = self._routes[name].thread
        return thread is not None and thread.is_alive()

    def destination_health(self) -> dict[str, dict[str, Any]]:
        """Per destination: ok, retrying or failing, and while not ok since when and why (dc_destinations.health)."""
        return {name: route.health.snapshot() for name, route in self._routes.items()}

    def check_health(self) -> None:
        """Log a destination that became failing by time alone (its sender may be waiting out a long backoff)."""
        for route in self._routes.values():
            route.health.check()

    def health_document(self) -> dict[str, Any]:
        """What ``/api/v1/health`` serves: ``status`` ok, degraded (a destination failing) or error
        (see :meth:`healthy`), and each destination's state."""
        destinations = self.destination_health()
        for name, route in self._routes.items():
            if route.held:  # not a fault: what its only_when asks, said so that nobody looks for one
                destinations[name] = {**destinations[name], "held": route.held}
        if not self.healthy():
            status = "error"
        elif any(state["state"] == FAILING for state in destinations.values()):
            status = "degraded"
        else:
            status = "ok"
        return {"status": status, "destinations": destinations}

    def prometheus(self) -> str:
        sections = "".join(render() for render in self._prometheus_sections)
        return prometheus_text(self.metrics(), self.buffer_metrics()) + sections + self.supervisor.prometheus()

    @property
    def http_address(self) -> tuple[str, int] | None:
        return self._status.address if self._status is not None else None

    def _start_status_server(self) -> None:
        self._status = start_status_server(
            self.logger,
            self.settings.http_listen,
            self.settings.http_port,
            health=self.health_document,
            metrics=self.status_document,
            prometheus=self.prometheus,
            supervisor=self.supervisor,
            announce_as=self.metrics_announce_as,
        )


def _device(path: str) -> int | None:
    """The filesystem ``path`` is on; None when it cannot be read (gone: the eviction will say so)."""
    try:
        return os.stat(path).st_dev
    except OSError:
        return None


def _plugin_counters(route: Route) -> dict[str, int]:
    """A destination plugin's own counters; a plugin whose counters() fails has none shown (never a 500)."""
    try:
        return dict(route.destination.counters())
    except Exception:
        return {}
