"""The durable delivery buffer: one SQLite database (WAL), one queue table per destination.

A record is a row of its destination's queue until the destination confirms it (then the row is
deleted) or refuses it for good (then it moves to ``dead_letters`` with the error text). The
``queues`` table keeps, in the same transactions as the rows, each queue's row count and bytes (so
the size limit and start-up never scan the queue) and lifetime totals for ``dc status``.

All access goes through one connection guarded by a lock: the writer thread's group commits and
the senders' reads and deletes are short, and ``send()`` itself runs outside the lock. Other
processes (``dc buffer``) open their own connection; WAL lets them work while the server runs.

``hop_seen`` keeps the keys (topic, source timestamp, sequence number) of the newest records that
arrived over DDS, written in the same transaction as the records: a record replayed from a
publisher's history after a restart is recognised as already buffered (dc_destinations.hop).
``hop_losses`` keeps, per topic, the records every run counted lost before destination_server,
added in the group commit after the count: a run killed later does not take its count with it.

A database that SQLite reports as corrupt or not a database is moved aside (renamed with a
``.corrupt-<UTC time>`` suffix) and replaced by a new one, at start-up or whenever an operation
meets the corruption, and every row still readable in the old file (queued records with their
``record_id``, dead letters, hop keys) is put back into the new one (dc_destinations.salvage):
collection goes on, a record already delivered may be delivered again (at-least-once), what could
not be read is counted, and the old file is kept for inspection and ``dc buffer salvage``.
"""

from __future__ import annotations

import heapq
import json
import os
import re
import sqlite3
import threading
import time
import zlib
from collections import Counter
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, closing, contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

from dc_core.errors import DcError
from dc_core.private_files import make_folders, private_database
from dc_destinations.salvage import UNKNOWN, DamagedReader, SalvageReport, open_damaged

FILE_NAME = "delivery.sqlite3"
SCHEMA_VERSION = 3  # 2: queues.dead_bytes; 3: q_<n>.payload_crc

_SQLITE_CORRUPT = 11
_SALVAGING = "salvaging"  # meta key: the set-aside file being salvaged into this buffer
_SQLITE_NOTADB = 26

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS queues (
    name TEXT PRIMARY KEY,
    qid INTEGER NOT NULL UNIQUE,
    rows INTEGER NOT NULL DEFAULT 0,
    bytes INTEGER NOT NULL DEFAULT 0,
    received INTEGER NOT NULL DEFAULT 0,
    sent INTEGER NOT NULL DEFAULT 0,
    dropped INTEGER NOT NULL DEFAULT 0,
    dead_lettered INTEGER NOT NULL DEFAULT 0,
    dead_bytes INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS dead_letters (
    id INTEGER PRIMARY KEY,
    destination TEXT NOT NULL,
    record_id TEXT NOT NULL,
    topic TEXT NOT NULL,
    stamp_ns INTEGER NOT NULL,
    enqueued_ns INTEGER NOT NULL,
    failed_ns INTEGER NOT NULL,
    attempts INTEGER NOT NULL,
    error TEXT NOT NULL,
    size INTEGER NOT NULL,
    payload TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS dead_letters_by_destination ON dead_letters (destination, id);
CREATE TABLE IF NOT EXISTS hop_seen (
    id INTEGER PRIMARY KEY,
    topic TEXT NOT NULL,
    source_ns INTEGER NOT NULL,
    seq INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS hop_seen_by_topic ON hop_seen (topic, id);
CREATE TABLE IF NOT EXISTS hop_losses (
    topic TEXT PRIMARY KEY,
    missing INTEGER NOT NULL DEFAULT 0,
    gaps INTEGER NOT NULL DEFAULT 0
);
"""

# queues.dead_bytes is the size of a destination's dead letters, kept by triggers so that every
# way of adding or removing one (the sender, `dc buffer replay|purge`, an older DC) keeps it right
# and dead_letter_limit_size needs no scan. Created after the schema-1 migration below.
_DEAD_BYTES_TRIGGERS = """
CREATE TRIGGER IF NOT EXISTS dead_letter_added AFTER INSERT ON dead_letters BEGIN
    UPDATE queues SET dead_bytes = dead_bytes + NEW.size WHERE name = NEW.destination;
END;
CREATE TRIGGER IF NOT EXISTS dead_letter_removed AFTER DELETE ON dead_letters BEGIN
    UPDATE queues SET dead_bytes = dead_bytes - OLD.size WHERE name = OLD.destination;
END;
"""

_QUEUE_COLUMNS = "id, record_id, topic, stamp_ns, enqueued_ns, attempts, size, payload, payload_crc"
_DEAD_COLUMNS = "id, destination, record_id, topic, stamp_ns, enqueued_ns, failed_ns, attempts, error, size, payload"


class DeliveryBufferError(DcError):
    """Base of the buffer's own errors."""


class BufferCorrupted(DeliveryBufferError):
    """The database was corrupt: it has been moved aside and replaced; the operation was not done."""


class BufferClosed(DeliveryBufferError):
    """The buffer was closed (the pipeline stopped) while an operation was pending."""


class PendingRecord:
    """A record on its way into a queue: its text, encoded once.

    ``checked``: the payload is DC JSON for certain (dc_core.records' rule); it is stored with its
    CRC and sent without being parsed again (:meth:`BufferedRow.as_appended`). A payload that is
    not valid Unicode (a lone surrogate) raises ``UnicodeEncodeError`` here, before any commit.

    A slotted class computing everything at construction, not a frozen dataclass with cached
    properties: the writer thread builds one per record (0.35 us with its row, against 1.3). Read-only by use.
    """

    __slots__ = ("checked", "crc", "encoded", "payload", "record_id", "size", "stamp_ns", "topic")

    def __init__(self, record_id: str, topic: str, stamp_ns: int, payload: str, checked: bool = False) -> None:
        self.record_id = record_id
        self.topic = topic
        self.stamp_ns = stamp_ns
        self.payload = payload
        self.checked = checked
        self.encoded = encoded = payload.encode("utf-8")
        self.size = len(encoded)
        self.crc = zlib.crc32(encoded) if checked else None

    def __repr__(self) -> str:
        return f"PendingRecord(record_id={self.record_id!r}, topic={self.topic!r}, size={self.size})"


class BufferedRow(NamedTuple):
    """One row of a destination's queue, as read back.

    A named tuple, not a frozen dataclass: the sender reads one per record (0.13 us against 0.65).
    """

    row_id: int
    record_id: str
    topic: str
    stamp_ns: int
    enqueued_ns: int
    attempts: int
    size: int
    payload: str
    # CRC-32 of the payload's UTF-8 as append() stored it, for a payload known to be DC JSON
    # (PendingRecord.checked); None for any other row, and for rows an older DC or a replayed dead
    # letter wrote.
    payload_crc: int | None = None

    def as_appended(self) -> bool:
        """True when the payload is DC JSON for certain: the very text that append() was given as checked.

        Such a payload needs no parse before it is sent. A row written by an older DC (which let
        NaN through) or from a text nobody checked has no CRC; a payload changed since, by hand or
        on the disk, no longer matches its CRC: those are parsed. A CRC costs ~0.2 us a record,
        the parse ~5.
        """
        return self.payload_crc is not None and zlib.crc32(self.payload.encode("utf-8")) == self.payload_crc


@dataclass(frozen=True)
class DeadLetter:
    id: int
    destination: str
    record_id: str
    topic: str
    stamp_ns: int
    enqueued_ns: int
    failed_ns: int
    attempts: int
    error: str
    size: int
    payload: str


@dataclass(frozen=True)
class QueueLimit:
    max_bytes: int | None
    drop_oldest: bool


@dataclass
class AppendResult:
    """Per destination: rows written, and records dropped by the size limit (counts, and their record_ids)."""

    appended: dict[str, int] = field(default_factory=dict)
    dropped_newest: dict[str, int] = field(default_factory=dict)
    dropped_oldest: dict[str, int] = field(default_factory=dict)
    # Whoever must know that a record left its queue undelivered (``dc ingest`` hands its message
    # back to the stream) needs which ones; filled only when some were dropped.
    dropped_ids: dict[str, list[str]] = field(default_factory=dict)
    # How many of each input topic were dropped (counted per measurement); filled only when some were.
    dropped_topics: dict[str, Counter[str]] = field(default_factory=dict)


class Evicted(NamedTuple):
    """What :meth:`Buffer.evict_oldest` deleted: records, bytes, their record_ids when asked for, and
    how many records of each input topic."""

    records: int
    bytes: int
    record_ids: list[str]
    by_topic: dict[str, int]


@dataclass(frozen=True)
class QueueStats:
    destination: str
    rows: int
    bytes: int
    oldest_enqueued_ns: int | None
    dead_letters: int
    received_total: int
    sent_total: int
    dropped_total: int
    dead_lettered_total: int


@dataclass(frozen=True)
class Quarantine:
    """A database file set aside because SQLite found it corrupt.

    ``salvage``: what of it was put back into the new buffer and what was lost (partial when the
    salvage failed, with ``salvage_error`` saying why).
    """

    moved_to: Path
    reason: str
    salvage: SalvageReport | None = None
    salvage_error: str = ""


def is_corruption(exc: BaseException) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)
    return (
        isinstance(exc, sqlite3.DatabaseError) and code is not None and code & 0xFF in (_SQLITE_CORRUPT, _SQLITE_NOTADB)
    )


def _now_ns() -> int:
    return time.time_ns()


class Buffer(Protocol):
    """What delivery (dc_destinations.delivery, .commit, .sender) and `dc buffer` need of a buffer.

    :class:`SqliteBuffer` is the one DC ships; tests/test_buffer.py is the suite a buffer must
    pass. Every method is thread-safe and atomic (a crash leaves an operation done or not done);
    an operation on a closed buffer raises :class:`BufferClosed`, one that met corruption (the
    store was set aside and replaced) raises :class:`BufferCorrupted` and was not done.
    """

    @property
    def closed(self) -> bool: ...
    def close(self) -> None: ...
    def exclusive(self) -> AbstractContextManager[None]:
        """Within it, the calling thread's operations are the only ones: what they change is seen by
        the others all at once (the group commit and the disk budget's eviction after it)."""

    def ensure_queues(self, destinations: Sequence[str]) -> None:
        """Create the queues that do not exist yet."""

    def append(
        self,
        records: Mapping[str, Sequence[PendingRecord]],
        limits: Mapping[str, QueueLimit] | None = None,
        *,
        now_ns: int | None = None,
        seen: Sequence[tuple[str, int, int]] = (),
        seen_window: int | None = None,
        hop_losses: Sequence[tuple[str, int, int]] = (),
    ) -> AppendResult:
        """Write records of several queues, their hop keys and the hop's losses (topic, records, gaps:
        added to its lifetime totals) at once (one group commit).

        A payload given as ``checked`` is sent, as long as it is unchanged, without being parsed
        again (:meth:`BufferedRow.as_appended`).
        """

    def seen_keys(self) -> list[tuple[str, int, int]]:
        """The hop keys kept, oldest first."""

    def hop_loss_totals(self) -> dict[str, tuple[int, int]]:
        """Per topic, the records counted lost before destination_server and in how many gaps, by every run."""

    def read_batch(self, destination: str, limit: int, *, after_id: int = 0) -> list[BufferedRow]:
        """The oldest ``limit`` rows of a queue; with ``after_id``, of those whose ``row_id`` is greater."""

    def delete(self, destination: str, row_ids: Sequence[int], *, sent: bool = True) -> int:
        """Forget confirmed rows (``sent`` False: evicted unsent); returns how many were there."""

    def record_failure(
        self,
        destination: str,
        row_ids: Sequence[int],
        *,
        dropped_ids: list[str] | None = None,
        dropped_topics: Counter[str] | None = None,
    ) -> dict[int, int]:
        """One more failed attempt for each row; returns their attempt counts. Those the size limit
        dropped while they were held (:meth:`hold`) are deleted now, their record_ids added to
        ``dropped_ids`` and their input topics to ``dropped_topics`` (counted in the queue's ``dropped``)."""

    def hold(self, destination: str, row_ids: Sequence[int]) -> None:
        """These rows are in a ``send()``: the size limit drops none of them before the destination
        answered (a record it confirms would be counted both dropped and sent). One the limit chose
        meanwhile goes when :meth:`record_failure` counts its send failed; confirmed, :meth:`delete`
        takes it as sent; dead-lettered, it is a dead letter."""

    def release(self, destination: str, row_ids: Sequence[int] | None = None) -> None:
        """Rows held by :meth:`hold` no longer are (None: every row of the queue): the size limit
        may drop them again, and those it chose meanwhile stay in the queue."""

    def dead_letter(
        self,
        destination: str,
        failures: Sequence[tuple[BufferedRow, str]],
        *,
        now_ns: int | None = None,
        tried_now: Collection[int] = (),
        moved_ids: list[str] | None = None,
    ) -> int:
        """Move rows to the dead letters with their error text; returns how many moved. ``tried_now``: rows
        whose failed attempt the queue has not counted yet (refused at once), counted in the dead letter's.
        ``moved_ids``: given, the record_ids of the rows moved are added to it (not those the size
        limit dropped meanwhile)."""

    def queued_bytes(self) -> dict[str, int]:
        """Bytes of records waiting per destination."""

    def evict_oldest(self, destination: str, nbytes: int, *, with_ids: bool = False) -> Evicted:
        """Delete a queue's oldest records, at least ``nbytes``: (records, bytes, and with ``with_ids``
        their record_ids) deleted."""

    def evict_oldest_among(
        self, parts: Mapping[str, Collection[str] | None], nbytes: int, *, with_ids: bool = False
    ) -> dict[str, Evicted]:
        """Delete the oldest records of several queues taken together, at least ``nbytes`` (all there
        are, if fewer), oldest first by when they were committed; of each queue only those of the input
        topics given (None: all). What each queue gave, per destination."""

    def track_topics(self, destinations: Collection[str]) -> None:
        """Keep :meth:`queued_topics` quick for these queues (and only these: it costs on their commits)."""

    def queued_topics(self, destination: str) -> dict[str, int]:
        """Bytes of records waiting in a queue per input topic."""

    def trim_dead_letters(self, destination: str, max_bytes: int) -> int:
        """Delete the oldest dead letters of a queue beyond ``max_bytes``; returns how many."""

    def stats(self, destination: str) -> QueueStats:
        """What waits in a queue, its dead letters and lifetime totals."""

    # What `dc buffer` does with the dead letters.
    def list_dead_letters(
        self, destination: str | None = None, *, limit: int = 100, after_id: int = 0
    ) -> list[DeadLetter]:
        """Dead letters oldest first, ``limit`` at a time after ``after_id``."""

    def get_dead_letter(self, dead_letter_id: int) -> DeadLetter | None: ...
    def replay_dead_letters(
        self, destination: str | None = None, ids: Sequence[int] | None = None, *, now_ns: int | None = None
    ) -> int:
        """Move dead letters back to the end of their queues, attempts reset; returns how many."""

    def purge_dead_letters(self, destination: str | None = None, ids: Sequence[int] | None = None) -> int:
        """Delete dead letters; returns how many."""


class SqliteBuffer:
    """Thread-safe access to the buffer database; see the module documentation."""

    def __init__(
        self,
        path: Path,
        *,
        synchronous: str = "normal",
        on_quarantine: Callable[[Quarantine], None] | None = None,
        on_salvage_start: Callable[[Path, str], None] | None = None,
        defer_salvage: bool = False,
        repair: bool = True,
    ) -> None:
        """Open (creating it if needed) the database at ``path``.

        With ``repair`` (the server), a corrupt database is moved aside and replaced; without it
        (operator tools), corruption raises :class:`BufferCorrupted` and the file is left alone.
        """
        self.path = Path(path)
        self.repair = repair
        self.synchronous = synchronous.upper()
        self._on_quarantine = on_quarantine
        self._on_salvage_start = on_salvage_start
        self._lock = threading.RLock()
        self._qids: dict[str, int] = {}
        self._seen_since_prune: Counter[str] = Counter()
        # Per destination: the largest row id read_batch handed out, and after a set-aside, the id
        # new rows must stay above. A sender may hold rows read from the old file; once it deletes
        # them (delivered) or dead-letters them, those ids must name the same records or none: a
        # record lost to the damage must never lend its id to a new one.
        self._max_read: dict[str, int] = {}
        self._id_floor: dict[str, int] = {}
        self.quarantines: list[Quarantine] = []
        # The queues named by track_topics, and of those counted by queued_topics: their rows per
        # input topic, [rows, bytes], kept by every change of the queue in this process from then on
        # and counted again from the table whenever they may be wrong (a transaction rolled back; a
        # change made elsewhere: `dc buffer replay`, a salvage), which queued_topics sees from the
        # queue's own totals. Until the disk budget first needs them, their commits pay nothing.
        self._tracked: set[str] = set()
        self._by_topic: dict[str, dict[str, list[int]]] = {}
        # Per destination: the ids of the rows in a send() now (hold), and of those the size limit
        # chose meanwhile, left to the send's outcome: deleted as dropped only if it failed.
        self._held: dict[str, set[int]] = {}
        self._doomed: dict[str, set[int]] = {}
        self._conn: sqlite3.Connection | None = None
        try:
            self._conn = self._connect()
        except sqlite3.DatabaseError as exc:
            if not is_corruption(exc):
                raise
            if not repair:
                raise BufferCorrupted(f"buffer {self.path} is corrupt ({exc})") from exc
            self._set_aside(str(exc), defer=defer_salvage)

    # -- connection ---------------------------------------------------------------------------

    def _connect(self) -> sqlite3.Connection:
        make_folders(self.path.parent)
        private_database(self.path)
        conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=10.0)
        try:
            conn.execute("PRAGMA journal_mode=WAL").fetchone()
            conn.execute(f"PRAGMA synchronous={self.synchronous}")
            conn.executescript(_SCHEMA)
            _migrate(conn)
            conn.executescript(_DEAD_BYTES_TRIGGERS)
            # Touch every queue's head so that a damaged file is found now rather than mid-delivery.
            qids = dict(conn.execute("SELECT name, qid FROM queues").fetchall())
            for qid in qids.values():
                _ensure_queue_table(conn, qid)
                conn.execute(f"SELECT {_QUEUE_COLUMNS} FROM q_{qid} ORDER BY id LIMIT 1").fetchall()
        except BaseException:
            conn.close()
            raise
        self._qids = qids
        self._by_topic = {}
        return conn

    def _set_aside(self, reason: str, *, defer: bool = False) -> Quarantine | None:
        """Move the damaged file aside, open a new one and salvage the old one into it.

        Called without a connection. With ``defer`` only the hop keys are copied now and the
        records wait for :meth:`salvage_pending` (the server runs it beside delivery: a salvage
        takes ~0.75 s per 100,000 records, too long for a lifecycle transition); without it (an
        operation met the damage) everything is copied now, rows keeping their ids, so that a
        batch a sender read from the old file is still deleted once delivered. A salvage that
        fails or stops leaves its progress in the new buffer (meta ``salvaging``), where the next
        :meth:`salvage_pending` goes on with it; the new buffer is open either way.
        """
        moved_to = self._move_aside()
        self._conn = conn = self._connect()
        self._id_floor.update(self._max_read)
        progress: dict[str, Any] = {"file": str(moved_to), "reason": reason, "done": {}, "found": {}, "dead": 0}
        conn.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (_SALVAGING, json.dumps(progress)))
        if self._on_salvage_start is not None:
            self._on_salvage_start(moved_to, reason)

        def writing() -> AbstractContextManager[sqlite3.Connection]:
            return _plain_transaction(conn)

        with suppress(Exception):  # the hop keys are a help against duplicates, never a condition
            self._salvage_hop_keys(progress, writing)
        if defer:
            return None
        return self._finish_salvage(progress, keep_ids=True, writing=writing)

    def _move_aside(self) -> Path:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}")
        n = 1
        while target.exists():
            n += 1
            target = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{n}")
        for suffix in ("", "-wal", "-shm"):
            source = Path(f"{self.path}{suffix}")
            if source.exists():
                os.replace(source, Path(f"{target}{suffix}"))
        return target

    def pending_salvage(self) -> Path | None:
        """The set-aside file whose salvage into this buffer is not done (deferred, stopped or failed)."""
        progress = self._salvage_progress()
        return Path(progress["file"]) if progress is not None else None

    def _salvage_progress(self) -> dict[str, Any] | None:
        with self._locked() as conn:
            row = conn.execute("SELECT value FROM meta WHERE key = ?", (_SALVAGING,)).fetchone()
        if row is None:
            return None
        try:
            progress = json.loads(row[0])
            if not isinstance(progress, dict) or not isinstance(progress.get("file"), str):
                raise ValueError(row[0])
        except ValueError:
            return {"file": str(row[0]), "reason": "", "done": {}, "found": {}, "dead": 0}
        return progress

    def salvage_pending(self, stop: Callable[[], bool] | None = None) -> Quarantine | None:
        """Go on with the salvage :meth:`pending_salvage` names, beside delivery; None when there is none.

        Copies in transactions of a few thousand rows, each taking the buffer's lock only for its
        write. ``stop`` is asked between them: a salvage stopped (the server stopping) raises
        :class:`SalvageStopped` and goes on from there the next time. The new rows go to the end of
        their queues (delivery may have added records meanwhile).
        """
        progress = self._salvage_progress()
        if progress is None:
            return None
        return self._finish_salvage(progress, keep_ids=False, writing=self._transaction, stop=stop)

    def _finish_salvage(
        self,
        progress: dict[str, Any],
        *,
        keep_ids: bool,
        writing: Callable[[], AbstractContextManager[sqlite3.Connection]],
        stop: Callable[[], bool] | None = None,
    ) -> Quarantine:
        moved_to = Path(progress["file"])
        report = SalvageReport(moved_to)
        error = ""
        try:
            self._salvage_into(report, progress, keep_ids=keep_ids, writing=writing, stop=stop)
            with writing() as conn:
                conn.execute("DELETE FROM meta WHERE key = ?", (_SALVAGING,))
        except (SalvageStopped, BufferClosed):
            raise
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
        quarantine = Quarantine(moved_to=moved_to, reason=progress["reason"], salvage=report, salvage_error=error)
        self.quarantines.append(quarantine)
        if self._on_quarantine is not None:
            self._on_quarantine(quarantine)
        return quarantine

    def set_aside(self, reason: str, *, defer: bool = False) -> Quarantine | None:
        """Set the file aside and salvage it (the integrity check found damage); see :meth:`_set_aside`."""
        with self._lock:
            if self._conn is None:
                raise BufferClosed(f"buffer {self.path} is closed")
            with suppress(sqlite3.Error):
                self._conn.close()
            self._conn = None
            return self._set_aside(reason, defer=defer)

    def quick_check(self) -> str:
        """``PRAGMA quick_check`` of the file on a connection of its own: "ok", or what is damaged.

        Its own connection: under WAL the writer and the senders go on meanwhile, where the
        buffer's connection would hold its lock for the whole check.

        Raises :class:`sqlite3.Error` when the check could not run (a lock held too long, no file):
        that says nothing of damage, and a sound file must never be set aside for it.
        """
        try:
            with closing(open_damaged(self.path)) as conn:
                found = [str(row[0]) for row in conn.execute("PRAGMA quick_check(5)")]
        except sqlite3.DatabaseError as exc:
            if not is_corruption(exc):
                raise
            return f"{type(exc).__name__}: {exc}"
        return "ok" if found == ["ok"] else " ".join(" ".join(found).split())  # one log line

    def salvage(self, source: Path) -> SalvageReport:
        """Put every readable row of the (damaged) buffer file ``source`` into this buffer.

        Queued records go to the end of their destination's queue with their ``record_id``, dead
        letters to the dead letters; the source is only read.
        """
        if Path(source).resolve() == self.path.resolve():
            raise DeliveryBufferError(f"{source} is this buffer itself")
        report = SalvageReport(Path(source))
        progress: dict[str, Any] = {"file": str(source), "reason": "", "done": {}, "found": {}, "dead": 0}
        self._salvage_into(report, progress, keep_ids=False, writing=self._transaction, track=False)
        return report

    def _salvage_hop_keys(
        self, progress: dict[str, Any], writing: Callable[[], AbstractContextManager[sqlite3.Connection]]
    ) -> None:
        """The hop keys of the old file, in their order, before delivery starts: the records a
        publisher replays from its history are then recognised."""
        with closing(open_damaged(Path(progress["file"]))) as source:
            reader = DamagedReader(source)
            if "hop_seen" not in reader.tables():
                return
            keys = [row[1:] for row in reader.rows("hop_seen", "topic, source_ns, seq") if _is_hop_key(row[1:])]
            # The lifetime totals of losses go with them (a help, as the keys: what cannot be read is not counted).
            losses = (
                [row[1:] for row in reader.rows("hop_losses", "topic, missing, gaps") if _is_hop_key(row[1:])]
                if "hop_losses" in reader.tables()
                else []
            )
        with writing() as conn:
            conn.executemany("INSERT INTO hop_seen (topic, source_ns, seq) VALUES (?, ?, ?)", keys)
            conn.executemany("INSERT OR REPLACE INTO hop_losses (topic, missing, gaps) VALUES (?, ?, ?)", losses)

    def _salvage_into(
        self,
        report: SalvageReport,
        progress: dict[str, Any],
        *,
        keep_ids: bool,
        writing: Callable[[], AbstractContextManager[sqlite3.Connection]],
        stop: Callable[[], bool] | None = None,
        track: bool = True,
    ) -> None:
        """Copy what ``report.source`` still holds after ``progress``, in transactions of a few
        thousand rows; with ``track``, each one records in meta how far it got."""
        with closing(open_damaged(report.source)) as source:
            reader = DamagedReader(source)
            tables = reader.tables()
            names: dict[int, str] = {}
            expected: dict[str, int] = {}
            totals: dict[str, tuple[int, int, int, int]] = {}
            if "queues" in tables:
                for row in reader.rows("queues", "name, qid, rows, received, sent, dropped, dead_lettered"):
                    _rowid, name, qid, rows, *counts = row
                    if isinstance(name, str) and isinstance(qid, int):
                        names[qid] = name
                        expected[name] = int(rows) if isinstance(rows, int) else 0
                        totals[name] = tuple(int(c) if isinstance(c, int) else 0 for c in counts)  # type: ignore[assignment]
            # Without a whole queues table, what was in the queues it lost cannot be counted.
            report.lost_unknown_count = "queues" not in tables or reader.damaged_spots > 0
            copy = _Copy(progress, writing, stop, track)
            for table in sorted(t for t in tables if re.fullmatch(r"q_\d+", t)):
                name = names.get(int(table[2:]))
                if name is None:
                    unplaced = sum(1 for _ in reader.rows(table, "id"))
                    if unplaced:
                        report.lost[UNKNOWN] = report.lost.get(UNKNOWN, 0) + unplaced
                    continue
                self._salvage_queue(reader, table, name, copy, keep_ids)
            found: dict[str, int] = progress["found"]
            report.recovered = {name: n for name, n in found.items() if n}
            for name, rows in expected.items():
                lost = rows - found.get(name, 0)
                if lost > 0:
                    report.lost[name] = report.lost.get(name, 0) + lost
            if not progress["done"].get("totals"):
                with writing() as conn:
                    for name, (received, sent, dropped, dead_lettered) in totals.items():
                        # The lifetime totals carry over, so that `dc buffer stats` keeps the history.
                        conn.execute(
                            "UPDATE queues SET received = received + ?, sent = sent + ?, dropped = dropped + ?, "
                            "dead_lettered = dead_lettered + ? WHERE qid = ?",
                            (received, sent, dropped, dead_lettered, self._qid(conn, name)),
                        )
                    progress["done"]["totals"] = 1
                    copy.record(conn)
            if "dead_letters" in tables:
                self._salvage_dead_letters(reader, report, copy, keep_ids)
            report.dead_letters_recovered = int(progress["dead"])
            report.damaged_spots = reader.damaged_spots

    def _salvage_queue(self, reader: DamagedReader, table: str, name: str, copy: _Copy, keep_ids: bool) -> None:
        """Copy a queue's readable rows to ``name``'s queue, counted in ``copy.progress["found"]``."""
        with copy.writing() as conn:
            qid = self._qid(conn, name)
            keep_ids = keep_ids and conn.execute(f"SELECT 1 FROM q_{qid} LIMIT 1").fetchone() is None
        has_crc = "payload_crc" in {column[1] for column in reader.conn.execute(f"PRAGMA table_info({table})")}
        crc = "payload_crc" if has_crc else "NULL"
        # The size computed again from the payload, so that the queue's byte count stays exact; a
        # damaged page can read as rows of the wrong types, which are no records any more (counted
        # lost with the unreadable ones). Checked by SQLite rather than row by row in Python.
        columns = f"record_id, topic, stamp_ns, enqueued_ns, attempts, length(CAST(payload AS BLOB)), payload, {crc}"
        records_only = (
            "typeof(record_id) = 'text' AND typeof(topic) = 'text' AND typeof(stamp_ns) = 'integer' "
            "AND typeof(enqueued_ns) = 'integer' AND typeof(attempts) = 'integer' AND typeof(payload) = 'text' "
            f"AND typeof({crc}) IN ('integer', 'null')"
        )
        insert = (
            f"INSERT INTO q_{qid} ({'id, ' if keep_ids else ''}record_id, topic, stamp_ns, enqueued_ns, attempts, "
            f"size, payload, payload_crc) VALUES ({'?, ' if keep_ids else ''}?, ?, ?, ?, ?, ?, ?, ?)"
        )
        found = copy.progress["found"]
        chunk: list[tuple[Any, ...]] = []

        def flush() -> None:
            if not chunk:
                return
            with copy.writing() as conn:
                conn.executemany(insert, [row if keep_ids else row[1:] for row in chunk])
                conn.execute(
                    "UPDATE queues SET rows = rows + ?, bytes = bytes + ? WHERE qid = ?",
                    (len(chunk), sum(int(row[-3]) for row in chunk), qid),
                )
                found[name] = found.get(name, 0) + len(chunk)
                copy.progress["done"][table] = int(chunk[-1][0])
                copy.record(conn)
            chunk.clear()
            copy.check_stop()

        after = int(copy.progress["done"].get(table, _NO_ROWID))
        for row in reader.rows(table, columns, records_only, after=after):
            chunk.append(row)
            if len(chunk) >= 2000:
                flush()
        flush()

    def _salvage_dead_letters(self, reader: DamagedReader, report: SalvageReport, copy: _Copy, keep_ids: bool) -> None:
        with copy.writing() as conn:
            keep_ids = keep_ids and conn.execute("SELECT 1 FROM dead_letters LIMIT 1").fetchone() is None
        spots = reader.damaged_spots
        columns = _DEAD_COLUMNS.removeprefix("id, ")
        insert = (
            f"INSERT INTO dead_letters ({'id, ' if keep_ids else ''}{columns}) "
            f"VALUES ({'?, ' if keep_ids else ''}?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
        )
        chunk: list[tuple[Any, ...]] = []

        def flush() -> None:
            with copy.writing() as conn:
                for row in chunk:
                    self._qid(conn, str(row[1]))
                    conn.execute(insert, row if keep_ids else row[1:])
                copy.progress["dead"] += len(chunk)
                copy.progress["done"]["dead_letters"] = int(chunk[-1][0])
                copy.record(conn)
            chunk.clear()
            copy.check_stop()

        after = int(copy.progress["done"].get("dead_letters", _NO_ROWID))
        for row in reader.rows("dead_letters", columns, after=after):
            if not _is_dead_letter(row):
                report.dead_letters_damaged = True  # read, but no longer a dead letter
                continue
            chunk.append(row)
            if len(chunk) >= 500:  # dead letters can be large (dead_letter_limit_size): few in memory
                flush()
        if chunk:
            flush()
        if reader.damaged_spots > spots:
            report.dead_letters_damaged = True

    @contextmanager
    def _locked(self) -> Iterator[sqlite3.Connection]:
        """The connection, under the lock; corruption found here resets the database."""
        with self._lock:
            if self._conn is None:
                raise BufferClosed(f"buffer {self.path} is closed")
            try:
                yield self._conn
            except sqlite3.DatabaseError as exc:
                if not is_corruption(exc):
                    raise
                if not self.repair:
                    raise BufferCorrupted(f"buffer {self.path} is corrupt ({exc})") from exc
                self._reset_after_corruption(str(exc))
                raise BufferCorrupted(f"buffer {self.path} was corrupt ({exc}); moved aside") from exc

    def _reset_after_corruption(self, reason: str) -> None:
        assert self._conn is not None
        with suppress(sqlite3.Error):
            self._conn.close()
        self._conn = None
        self._set_aside(reason)

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        with self._lock:  # reentrant: the operations inside take it again
            yield

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._locked() as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                self._by_topic.clear()  # they may hold what was rolled back
                if conn.in_transaction:
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    @property
    def closed(self) -> bool:
        return self._conn is None

    # -- queues -------------------------------------------------------------------------------

    def _qid(self, conn: sqlite3.Connection, destination: str) -> int:
        qid = self._qids.get(destination)
        if qid is not None:
            return qid
        row = conn.execute("SELECT qid FROM queues WHERE name=?", (destination,)).fetchone()
        if row is None:
            qid = conn.execute("SELECT coalesce(max(qid), 0) + 1 FROM queues").fetchone()[0]
            conn.execute("INSERT INTO queues (name, qid) VALUES (?, ?)", (destination, qid))
        else:
            qid = row[0]
        _ensure_queue_table(conn, qid)
        if destination in self._tracked:
            conn.execute(f"CREATE INDEX IF NOT EXISTS q_{qid}_by_topic ON q_{qid} (topic)")
        self._qids[destination] = int(qid)
        return int(qid)

    def track_topics(self, destinations: Collection[str]) -> None:
        """Keep :meth:`queued_topics` quick for these queues and index their rows by topic, so that an
        eviction of some topics seeks their oldest rows rather than walking the queue; the index of
        any other queue is dropped: it costs on every commit and delete of its queue."""
        with self._transaction() as conn:
            self._tracked = set(destinations)
            for name, qid in conn.execute("SELECT name, qid FROM queues").fetchall():
                if name in self._tracked:
                    conn.execute(f"CREATE INDEX IF NOT EXISTS q_{qid}_by_topic ON q_{qid} (topic)")
                else:
                    conn.execute(f"DROP INDEX IF EXISTS q_{qid}_by_topic")
                    self._by_topic.pop(name, None)
            for name in self._tracked:
                self._qid(conn, name)

    def queued_topics(self, destination: str) -> dict[str, int]:
        """Bytes of records waiting in a queue per input topic: kept as they change for a queue of
        :meth:`track_topics` once counted, counted from the table otherwise (a scan of the queue)."""
        with self._locked() as conn:
            qid = self._qids.get(destination)
            if qid is None:
                return {}
            rows, size = conn.execute("SELECT rows, bytes FROM queues WHERE qid = ?", (qid,)).fetchone()
            counts = self._by_topic.get(destination)
            if (
                counts is None
                or sum(c[0] for c in counts.values()) != rows
                or sum(c[1] for c in counts.values()) != size
            ):
                counts = {
                    str(topic): [int(n), int(total)]
                    for topic, n, total in conn.execute(
                        f"SELECT topic, count(*), sum(size) FROM q_{qid} GROUP BY topic"
                    )
                }
                if destination in self._tracked:
                    self._by_topic[destination] = counts
            return {topic: c[1] for topic, c in counts.items()}

    def ensure_queues(self, destinations: Sequence[str]) -> None:
        with self._transaction() as conn:
            for destination in destinations:
                self._qid(conn, destination)

    def destinations(self) -> list[str]:
        with self._locked() as conn:
            return [row[0] for row in conn.execute("SELECT name FROM queues ORDER BY name")]

    def append(
        self,
        records: Mapping[str, Sequence[PendingRecord]],
        limits: Mapping[str, QueueLimit] | None = None,
        *,
        now_ns: int | None = None,
        seen: Sequence[tuple[str, int, int]] = (),
        seen_window: int | None = None,
        hop_losses: Sequence[tuple[str, int, int]] = (),
    ) -> AppendResult:
        """Write the records of several destinations in one transaction (a group commit).

        ``seen`` are the hop keys (topic, source_ns, seq) of the records handled by this commit,
        kept with them so that a record is never known as seen without being buffered; each topic
        keeps about its newest ``seen_window`` keys (all of them with ``None``). ``hop_losses``
        (topic, records, gaps) are added to the topics' lifetime totals.
        """
        enqueued = _now_ns() if now_ns is None else now_ns
        result = AppendResult()
        with self._transaction() as conn:
            if seen:
                self._remember_seen(conn, seen, seen_window)
            if hop_losses:
                conn.executemany(
                    "INSERT INTO hop_losses (topic, missing, gaps) VALUES (?, ?, ?) ON CONFLICT (topic) "
                    "DO UPDATE SET missing = missing + excluded.missing, gaps = gaps + excluded.gaps",
                    hop_losses,
                )
            for destination, batch in records.items():
                if not batch:
                    continue
                qid = self._qid(conn, destination)
                limit = (limits or {}).get(destination, QueueLimit(None, True))
                rows = [(r.record_id, r.topic, r.stamp_ns, enqueued, r.size, r.payload, r.crc) for r in batch]
                dropped_newest = dropped_oldest = 0
                counts = self._by_topic.get(destination)
                if limit.max_bytes is not None:
                    dropped: list[str] = []
                    topics: Counter[str] = Counter()
                    rows, dropped_newest, dropped_oldest = self._apply_limit(
                        conn, destination, qid, rows, limit, dropped, topics
                    )
                    if dropped:
                        result.dropped_ids[destination] = dropped
                        result.dropped_topics[destination] = topics
                insert = (
                    f"INSERT INTO q_{qid} (record_id, topic, stamp_ns, enqueued_ns, size, payload, payload_crc) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)"
                )
                if rows and destination in self._id_floor:
                    self._first_above_floor(conn, destination, qid, insert, rows[0])
                    conn.executemany(insert, rows[1:])
                else:
                    conn.executemany(insert, rows)
                if counts is not None:
                    _count_rows(counts, [(row[1], row[4]) for row in rows], 1)
                added_bytes = sum(row[4] for row in rows)
                conn.execute(
                    "UPDATE queues SET rows = rows + ?, bytes = bytes + ?, received = received + ?, "
                    "dropped = dropped + ? WHERE qid = ?",
                    (len(rows), added_bytes, len(batch), dropped_newest + dropped_oldest, qid),
                )
                result.appended[destination] = len(rows)
                if dropped_newest:
                    result.dropped_newest[destination] = dropped_newest
                if dropped_oldest:
                    result.dropped_oldest[destination] = dropped_oldest
        return result

    def _first_above_floor(
        self, conn: sqlite3.Connection, destination: str, qid: int, insert: str, values: tuple[object, ...]
    ) -> None:
        """Insert one row with an id above the destination's floor (see ``_id_floor``): the rows
        after it follow it. Once the queue's ids are above the floor it is forgotten."""
        floor = self._id_floor[destination]
        top = int(conn.execute(f"SELECT coalesce(max(id), 0) FROM q_{qid}").fetchone()[0])
        if top >= floor:
            del self._id_floor[destination]
            conn.execute(insert, values)
            return
        with_id = insert.replace(" (record_id,", " (id, record_id,", 1).replace("VALUES (", "VALUES (?, ", 1)
        conn.execute(with_id, (floor + 1, *values))

    def _remember_seen(
        self, conn: sqlite3.Connection, keys: Sequence[tuple[str, int, int]], window: int | None
    ) -> None:
        conn.executemany("INSERT INTO hop_seen (topic, source_ns, seq) VALUES (?, ?, ?)", keys)
        if window is None:
            return
        # Pruning scans `window` index entries: do it once per quarter window of new keys, so a
        # topic holds between `window` and 1.25 x `window` keys.
        for topic, count in Counter(key[0] for key in keys).items():
            self._seen_since_prune[topic] += count
            if self._seen_since_prune[topic] >= max(window // 4, 1):
                self._seen_since_prune[topic] = 0
                conn.execute(
                    "DELETE FROM hop_seen WHERE topic = ? AND id <= "
                    "(SELECT id FROM hop_seen WHERE topic = ? ORDER BY id DESC LIMIT 1 OFFSET ?)",
                    (topic, topic, window),
                )

    def seen_keys(self) -> list[tuple[str, int, int]]:
        """The hop keys kept in the buffer, oldest first."""
        with self._locked() as conn:
            rows = conn.execute("SELECT topic, source_ns, seq FROM hop_seen ORDER BY id").fetchall()
        return [(str(topic), int(source_ns), int(seq)) for topic, source_ns, seq in rows]

    def hop_loss_totals(self) -> dict[str, tuple[int, int]]:
        """Per topic, the records counted lost before destination_server and in how many gaps, by every run."""
        with self._locked() as conn:
            rows = conn.execute("SELECT topic, missing, gaps FROM hop_losses ORDER BY topic").fetchall()
        return {str(topic): (int(missing), int(gaps)) for topic, missing, gaps in rows}

    def _apply_limit(
        self,
        conn: sqlite3.Connection,
        destination: str,
        qid: int,
        rows: list[_QueueRow],
        limit: QueueLimit,
        dropped: list[str],
        topics: Counter[str],
    ) -> tuple[list[_QueueRow], int, int]:
        """Rows that fit, records dropped from the batch, rows deleted from the queue head; the
        record_ids of both added to ``dropped``, their input topics to ``topics``."""
        assert limit.max_bytes is not None
        max_bytes = limit.max_bytes

        def drop(row: _QueueRow) -> None:
            dropped.append(str(row[0]))
            topics[str(row[1])] += 1

        # A record bigger than the whole limit can never fit: it is dropped whatever the policy.
        fitting = [row for row in rows if row[4] <= max_bytes]
        for row in rows:
            if row[4] > max_bytes:
                drop(row)
        dropped_newest = len(rows) - len(fitting)
        used = conn.execute("SELECT bytes FROM queues WHERE qid=?", (qid,)).fetchone()[0]
        if not limit.drop_oldest:
            kept: list[_QueueRow] = []
            for row in fitting:
                if used + row[4] <= max_bytes:
                    kept.append(row)
                    used += row[4]
                else:
                    dropped_newest += 1
                    drop(row)
            return kept, dropped_newest, 0
        incoming = sum(row[4] for row in fitting)
        # Within one batch, newer records win over older ones of the same batch too.
        while fitting and incoming > max_bytes:
            gone = fitting.pop(0)
            incoming -= gone[4]
            dropped_newest += 1
            drop(gone)
        need = used + incoming - max_bytes
        dropped_oldest = 0
        if need > 0:
            head = self._drop_head(conn, destination, qid, need)
            dropped.extend(record_id for record_id, _topic in head)
            topics.update(topic for _record_id, topic in head)
            dropped_oldest = len(head)
        return fitting, dropped_newest, dropped_oldest

    def _drop_head(self, conn: sqlite3.Connection, destination: str, qid: int, need: int) -> list[tuple[str, str]]:
        """Delete a queue's oldest rows, at least ``need`` bytes of them (all there are, if fewer); their
        (record_id, input topic). Not counted here.

        A row held in a send() is only marked: the destination may confirm it, and a record must never
        be counted both dropped and sent. It goes, counted dropped, if its send fails
        (:meth:`record_failure`); meanwhile the queue stands above its limit by those rows."""
        held = self._held.get(destination)
        if held:
            doomed = _head_ids(conn, qid, need)
            chosen = [row_id for row_id in doomed if row_id not in held]
            self._doomed.setdefault(destination, set()).update(row_id for row_id in doomed if row_id in held)
            return self._delete_head_rows(conn, destination, qid, chosen)
        _count, _freed, last_id = _walk_head(conn, qid, need, after=-1)
        if last_id is None:
            return []
        return self._delete_head_rows(conn, destination, qid, None, last_id)

    def _delete_head_rows(
        self, conn: sqlite3.Connection, destination: str, qid: int, row_ids: list[int] | None, last_id: int = 0
    ) -> list[tuple[str, str]]:
        """Delete rows of the queue's head, ``row_ids`` (None: every row up to ``last_id``), kept out of
        the counts per topic; their (record_id, input topic)."""
        args: tuple[object, ...]
        if row_ids is None:
            where, args = "id <= ?", (last_id,)
        elif row_ids:
            where, args = "id IN (SELECT value FROM json_each(?))", (json.dumps(row_ids),)
        else:
            return []
        deleted = conn.execute(f"DELETE FROM q_{qid} WHERE {where} RETURNING record_id, topic, size", args).fetchall()
        counts = self._by_topic.get(destination)
        if counts is not None:
            _count_rows(counts, [(topic, size) for _id, topic, size in deleted], -1)
        conn.execute(
            "UPDATE queues SET rows = rows - ?, bytes = bytes - ? WHERE qid = ?",
            (len(deleted), sum(int(size) for _id, _topic, size in deleted), qid),
        )
        if deleted and destination in self._max_read:
            # The head dropped may be the whole queue, rows a sender read with it: SQLite would give
            # their ids to the new rows, and that sender's delete of its confirmed rows would then
            # delete new records unsent.
            self._id_floor[destination] = max(self._id_floor.get(destination, 0), self._max_read[destination])
        return [(str(record_id), str(topic)) for record_id, topic, _size in deleted]

    def read_batch(self, destination: str, limit: int, *, after_id: int = 0) -> list[BufferedRow]:
        """The oldest ``limit`` rows of a queue after ``after_id`` (memory bounded by ``limit``, whatever the
        backlog)."""
        with self._locked() as conn:
            qid = self._qids.get(destination)
            if qid is None:
                return []
            rows = conn.execute(
                f"SELECT {_QUEUE_COLUMNS} FROM q_{qid} WHERE id > ? ORDER BY id LIMIT ?", (after_id, limit)
            ).fetchall()
        if rows and rows[-1][0] > self._max_read.get(destination, 0):
            self._max_read[destination] = rows[-1][0]
        return list(map(BufferedRow._make, rows))

    def delete(self, destination: str, row_ids: Sequence[int], *, sent: bool = True) -> int:
        """Delete confirmed rows; returns how many were still there (the size limit may have dropped some).
        ``sent`` False: rows evicted unsent, not added to the queue's lifetime ``sent``."""
        if not row_ids:
            return 0
        with self._transaction() as conn:
            qid = self._qid(conn, destination)
            counts = self._by_topic.get(destination)
            sizes = conn.execute(
                f"DELETE FROM q_{qid} WHERE id IN (SELECT value FROM json_each(?)) "
                + ("RETURNING topic, size" if counts is not None else "RETURNING size"),
                (json.dumps(list(row_ids)),),
            ).fetchall()
            total = sum(row[-1] for row in sizes)
            if counts is not None:
                _count_rows(counts, sizes, -1)
            conn.execute(
                "UPDATE queues SET rows = rows - ?, bytes = bytes - ?, sent = sent + ? WHERE qid = ?",
                (len(sizes), total, len(sizes) if sent else 0, qid),
            )
            if self._held.get(destination):
                self.release(destination, row_ids)
        return len(sizes)

    def record_failure(
        self,
        destination: str,
        row_ids: Sequence[int],
        *,
        dropped_ids: list[str] | None = None,
        dropped_topics: Counter[str] | None = None,
    ) -> dict[int, int]:
        """Count one more failed attempt for each row; returns the rows' attempt counts. Those the size
        limit chose while their send ran (:meth:`hold`) are deleted now, counted dropped, their
        record_ids added to ``dropped_ids``, their input topics to ``dropped_topics``."""
        if not row_ids:
            return {}
        with self._transaction() as conn:
            qid = self._qid(conn, destination)
            rows = conn.execute(
                f"UPDATE q_{qid} SET attempts = attempts + 1 WHERE id IN (SELECT value FROM json_each(?)) "
                "RETURNING id, attempts",
                (json.dumps(list(row_ids)),),
            ).fetchall()
            doomed = self._doomed.get(destination)
            if doomed:
                gone = self._delete_head_rows(conn, destination, qid, sorted(doomed.intersection(row_ids)))
                conn.execute("UPDATE queues SET dropped = dropped + ? WHERE qid = ?", (len(gone), qid))
                if dropped_ids is not None:
                    dropped_ids.extend(record_id for record_id, _topic in gone)
                if dropped_topics is not None:
                    dropped_topics.update(topic for _record_id, topic in gone)
            self.release(destination, row_ids)
        return {int(row_id): int(attempts) for row_id, attempts in rows}

    def hold(self, destination: str, row_ids: Sequence[int]) -> None:
        """Keep these rows from the size limit while they are in a send(); see :class:`Buffer`."""
        with self._lock:
            self._held.setdefault(destination, set()).update(row_ids)

    def release(self, destination: str, row_ids: Sequence[int] | None = None) -> None:
        with self._lock:
            for rows in (self._held.get(destination), self._doomed.get(destination)):
                if rows:
                    if row_ids is None:
                        rows.clear()
                    else:
                        rows.difference_update(row_ids)

    def dead_letter(
        self,
        destination: str,
        failures: Sequence[tuple[BufferedRow, str]],
        *,
        now_ns: int | None = None,
        tried_now: Collection[int] = (),
        moved_ids: list[str] | None = None,
    ) -> int:
        """Move rows to the dead-letter table with their error text; returns how many moved (their
        record_ids added to ``moved_ids`` when given)."""
        if not failures:
            return 0
        failed = _now_ns() if now_ns is None else now_ns
        moved = 0
        with self._transaction() as conn:
            qid = self._qid(conn, destination)
            for row, error in failures:
                gone = conn.execute(f"DELETE FROM q_{qid} WHERE id = ? RETURNING attempts", (row.row_id,)).fetchone()
                if gone is None:
                    continue  # dropped by the size limit meanwhile
                counts = self._by_topic.get(destination)
                if counts is not None:
                    _count_rows(counts, [(row.topic, row.size)], -1)
                conn.execute(
                    f"INSERT INTO dead_letters ({_DEAD_COLUMNS.removeprefix('id, ')}) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        destination,
                        row.record_id,
                        row.topic,
                        row.stamp_ns,
                        row.enqueued_ns,
                        failed,
                        gone[0] + (row.row_id in tried_now),
                        error,
                        row.size,
                        row.payload,
                    ),
                )
                conn.execute(
                    "UPDATE queues SET rows = rows - 1, bytes = bytes - ?, dead_lettered = dead_lettered + 1 "
                    "WHERE qid = ?",
                    (row.size, qid),
                )
                moved += 1
                if moved_ids is not None:
                    moved_ids.append(row.record_id)
            if self._held.get(destination):
                self.release(destination, [row.row_id for row, _error in failures])
        return moved

    def queued_bytes(self) -> dict[str, int]:
        """Bytes of records waiting in each destination's queue, from the queues' own totals (no scan)."""
        with self._locked() as conn:
            return {str(name): int(size) for name, size in conn.execute("SELECT name, bytes FROM queues")}

    def evict_oldest(self, destination: str, nbytes: int, *, with_ids: bool = False) -> Evicted:
        """Delete the oldest records of ``destination``'s queue, at least ``nbytes`` of them (all there
        are, if fewer): (records, bytes, and with ``with_ids`` their record_ids) deleted. They are not
        counted as sent or dropped here.

        Rows a sender has read are left alone: they may be in a send() now, and are counted sent or
        dead-lettered when it returns; the oldest of the others go."""
        record_ids: list[str] = []
        by_topic: dict[str, int] = {}
        with self._transaction() as conn:
            qid = self._qid(conn, destination)
            first = self._max_read.get(destination, 0)
            count, freed, last_id = _walk_head(conn, qid, nbytes, after=first)
            if last_id is not None:
                # Counted by topic in SQLite: the range may be a whole queue (dc ingest empties its own).
                per_topic = conn.execute(
                    f"SELECT topic, count(*), sum(size) FROM q_{qid} WHERE id > ? AND id <= ? GROUP BY topic",
                    (first, last_id),
                ).fetchall()
                by_topic = {str(topic): int(n) for topic, n, _size in per_topic}
                counts = self._by_topic.get(destination)
                if counts is not None:
                    for topic, n, size in per_topic:
                        _count_rows(counts, [(topic, size)], -1, n)
                delete = f"DELETE FROM q_{qid} WHERE id > ? AND id <= ?"
                if with_ids:
                    deleted = conn.execute(delete + " RETURNING record_id", (first, last_id)).fetchall()
                    record_ids = [str(record_id) for (record_id,) in deleted]
                else:
                    conn.execute(delete, (first, last_id))
                conn.execute("UPDATE queues SET rows = rows - ?, bytes = bytes - ? WHERE qid = ?", (count, freed, qid))
        return Evicted(count, freed, record_ids, by_topic)

    def evict_oldest_among(
        self, parts: Mapping[str, Collection[str] | None], nbytes: int, *, with_ids: bool = False
    ) -> dict[str, Evicted]:
        """Delete the oldest records of several queues taken together, at least ``nbytes`` of them (all
        there are, if fewer): oldest by their commit time across the queues; of each queue only the
        records of the input topics given (None: all of them). Per destination, what it gave; not
        counted as sent or dropped here.

        Rows a sender has read are left alone, as by :meth:`evict_oldest`. Deleted a few thousand at
        a time, so that memory does not grow with what is evicted."""
        gone: dict[str, tuple[int, int, list[str], Counter[str]]] = {}
        freed = 0
        with self._transaction() as conn:
            heads = []
            for destination, topics in parts.items():
                qid = self._qid(conn, destination)
                after = self._max_read.get(destination, 0)
                for topic in (None,) if topics is None else sorted(topics):
                    heads.append((destination, qid, after, topic))
            while freed < nbytes:
                # Each round from the heads again: the rows taken by the round before are gone.
                chosen: dict[str, list[int]] = {}
                oldest = heapq.merge(
                    *(_oldest(conn, qid, after, topic, destination) for destination, qid, after, topic in heads)
                )
                for taken, (_enqueued, row_id, size, destination) in enumerate(oldest, 1):
                    chosen.setdefault(destination, []).append(row_id)
                    freed += size
                    if freed >= nbytes or taken >= 4096:
                        break
                if not chosen:
                    break
                for destination, row_ids in chosen.items():
                    qid = self._qids[destination]
                    deleted = conn.execute(
                        f"DELETE FROM q_{qid} WHERE id IN (SELECT value FROM json_each(?)) "
                        "RETURNING record_id, topic, size",
                        (json.dumps(row_ids),),
                    ).fetchall()
                    size = sum(int(row[2]) for row in deleted)
                    conn.execute(
                        "UPDATE queues SET rows = rows - ?, bytes = bytes - ? WHERE qid = ?", (len(deleted), size, qid)
                    )
                    counts = self._by_topic.get(destination)
                    if counts is not None:
                        _count_rows(counts, [(topic, n) for _id, topic, n in deleted], -1)
                    records, nbytes_gone, ids, by_topic = gone.get(destination, (0, 0, [], Counter()))
                    if with_ids:
                        ids.extend(str(row[0]) for row in deleted)
                    by_topic.update(str(row[1]) for row in deleted)
                    gone[destination] = (records + len(deleted), nbytes_gone + size, ids, by_topic)
        return {
            destination: Evicted(records, size, ids, dict(by_topic))
            for destination, (records, size, ids, by_topic) in gone.items()
        }

    def trim_dead_letters(self, destination: str, max_bytes: int) -> int:
        """Delete the oldest dead letters of ``destination`` until theirs fit in ``max_bytes``.

        Returns how many. Reads their total from ``queues.dead_bytes`` and walks only the oldest
        ones it deletes: no scan of them all.
        """
        with self._transaction() as conn:
            row = conn.execute("SELECT dead_bytes FROM queues WHERE name = ?", (destination,)).fetchone()
            total = int(row[0]) if row is not None else 0
            excess = total - max_bytes
            if excess <= 0:
                return 0
            doomed: list[int] = []
            for letter_id, size in conn.execute(
                "SELECT id, size FROM dead_letters WHERE destination = ? ORDER BY id", (destination,)
            ):
                doomed.append(int(letter_id))
                excess -= int(size)
                if excess <= 0:
                    break
            conn.execute("DELETE FROM dead_letters WHERE id IN (SELECT value FROM json_each(?))", (json.dumps(doomed),))
        return len(doomed)

    def stats(self, destination: str) -> QueueStats:
        with self._locked() as conn:
            row = conn.execute(
                "SELECT qid, rows, bytes, received, sent, dropped, dead_lettered FROM queues WHERE name=?",
                (destination,),
            ).fetchone()
            dead = conn.execute("SELECT count(*) FROM dead_letters WHERE destination=?", (destination,)).fetchone()[0]
            if row is None:
                return QueueStats(destination, 0, 0, None, dead, 0, 0, 0, 0)
            qid, rows, size, received, sent, dropped, dead_lettered = row
            head = conn.execute(f"SELECT enqueued_ns FROM q_{qid} ORDER BY id LIMIT 1").fetchone()
        return QueueStats(
            destination, rows, size, head[0] if head else None, dead, received, sent, dropped, dead_lettered
        )

    # -- dead letters ---------------------------------------------------------------------------

    def list_dead_letters(
        self, destination: str | None = None, *, limit: int = 100, after_id: int = 0
    ) -> list[DeadLetter]:
        with self._locked() as conn:
            if destination is None:
                rows = conn.execute(
                    f"SELECT {_DEAD_COLUMNS} FROM dead_letters WHERE id > ? ORDER BY id LIMIT ?",
                    (after_id, limit),
                ).fetchall()
            else:
                rows = conn.execute(
                    f"SELECT {_DEAD_COLUMNS} FROM dead_letters WHERE destination = ? AND id > ? ORDER BY id LIMIT ?",
                    (destination, after_id, limit),
                ).fetchall()
        return [DeadLetter(*row) for row in rows]

    def get_dead_letter(self, dead_letter_id: int) -> DeadLetter | None:
        with self._locked() as conn:
            row = conn.execute(f"SELECT {_DEAD_COLUMNS} FROM dead_letters WHERE id = ?", (dead_letter_id,)).fetchone()
        return DeadLetter(*row) if row else None

    def _select_dead(self, destination: str | None, ids: Sequence[int] | None) -> tuple[str, tuple[object, ...]]:
        clauses: list[str] = []
        args: list[object] = []
        if destination is not None:
            clauses.append("destination = ?")
            args.append(destination)
        if ids is not None:
            clauses.append("id IN (SELECT value FROM json_each(?))")
            args.append(json.dumps(list(ids)))
        return (" WHERE " + " AND ".join(clauses) if clauses else ""), tuple(args)

    def replay_dead_letters(
        self, destination: str | None = None, ids: Sequence[int] | None = None, *, now_ns: int | None = None
    ) -> int:
        """Move dead letters back to the end of their queues, attempts reset; returns how many."""
        enqueued = _now_ns() if now_ns is None else now_ns
        where, args = self._select_dead(destination, ids)
        moved = 0
        with self._transaction() as conn:
            rows = conn.execute(f"SELECT {_DEAD_COLUMNS} FROM dead_letters{where} ORDER BY id", args).fetchall()
            for row in rows:
                letter = DeadLetter(*row)
                qid = self._qid(conn, letter.destination)
                insert = (
                    f"INSERT INTO q_{qid} (record_id, topic, stamp_ns, enqueued_ns, size, payload) "
                    "VALUES (?, ?, ?, ?, ?, ?)"
                )
                values = (letter.record_id, letter.topic, letter.stamp_ns, enqueued, letter.size, letter.payload)
                if letter.destination in self._id_floor:
                    self._first_above_floor(conn, letter.destination, qid, insert, values)
                else:
                    conn.execute(insert, values)
                conn.execute("UPDATE queues SET rows = rows + 1, bytes = bytes + ? WHERE qid = ?", (letter.size, qid))
                conn.execute("DELETE FROM dead_letters WHERE id = ?", (letter.id,))
                moved += 1
        return moved

    def purge_dead_letters(self, destination: str | None = None, ids: Sequence[int] | None = None) -> int:
        where, args = self._select_dead(destination, ids)
        with self._transaction() as conn:
            return int(conn.execute(f"DELETE FROM dead_letters{where}", args).rowcount)


@contextmanager
def _plain_transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield conn
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    conn.execute("COMMIT")


_NO_ROWID = -(2**63) - 1  # progress of a table not begun: every rowid is above it


def _count_rows(counts: dict[str, list[int]], rows: Iterable[Sequence[Any]], sign: int, n: int = 1) -> None:
    """Add (``sign`` 1) or take off (-1) rows of (topic, size) to the rows and bytes per topic ``counts``;
    ``n``: each stands for that many rows (size their total)."""
    for topic, size in rows:
        count = counts.get(topic)
        if count is None:
            counts[topic] = count = [0, 0]
        count[0] += sign * n
        count[1] += sign * size
        if count[0] <= 0:
            del counts[topic]


def _oldest(
    conn: sqlite3.Connection, qid: int, after: int, topic: str | None, destination: str
) -> Iterator[tuple[int, int, int, str]]:
    """(commit time, row id, size, ``destination``) of queue ``qid``'s rows after ``after``, of ``topic``
    only unless None, in their order, read 512 at a time."""
    while True:
        if topic is None:
            rows = conn.execute(
                f"SELECT enqueued_ns, id, size FROM q_{qid} WHERE id > ? ORDER BY id LIMIT 512", (after,)
            ).fetchall()
        else:
            rows = conn.execute(
                f"SELECT enqueued_ns, id, size FROM q_{qid} WHERE topic = ? AND id > ? ORDER BY id LIMIT 512",
                (topic, after),
            ).fetchall()
        if not rows:
            return
        for enqueued, row_id, size in rows:
            yield int(enqueued), int(row_id), int(size), destination
        after = rows[-1][1]


def _head_ids(conn: sqlite3.Connection, qid: int, need: int) -> list[int]:
    """The ids of the oldest rows of queue ``qid`` whose sizes reach ``need`` (all of them if fewer),
    read 512 at a time."""
    doomed: list[int] = []
    freed = 0
    after = -1
    while freed < need:
        head = conn.execute(f"SELECT id, size FROM q_{qid} WHERE id > ? ORDER BY id LIMIT 512", (after,)).fetchall()
        if not head:
            break
        for row_id, size in head:
            doomed.append(int(row_id))
            freed += int(size)
            if freed >= need:
                break
        after = head[-1][0]
    return doomed


def _walk_head(conn: sqlite3.Connection, qid: int, need: int, *, after: int) -> tuple[int, int, int | None]:
    """The oldest rows of queue ``qid`` after id ``after`` whose sizes reach ``need`` (all of them if
    fewer): (rows, bytes, last row id), read 512 at a time so that memory does not grow with the queue."""
    count = freed = 0
    last_id = None
    while freed < need:
        head = conn.execute(f"SELECT id, size FROM q_{qid} WHERE id > ? ORDER BY id LIMIT 512", (after,)).fetchall()
        if not head:
            break
        for row_id, size in head:
            freed += int(size)
            count += 1
            last_id = row_id
            if freed >= need:
                break
        after = head[-1][0]
    return count, freed, last_id


class SalvageStopped(DeliveryBufferError):
    """A salvage asked to stop (the server stopping); the next one goes on from where it was."""


class _Copy:
    """How a salvage writes: its transactions, its progress (kept in meta with each one), when to stop."""

    def __init__(
        self,
        progress: dict[str, Any],
        writing: Callable[[], AbstractContextManager[sqlite3.Connection]],
        stop: Callable[[], bool] | None,
        track: bool,
    ) -> None:
        self.progress = progress
        self.writing = writing
        self._stop = stop
        self._track = track

    def record(self, conn: sqlite3.Connection) -> None:
        if self._track:
            conn.execute("UPDATE meta SET value = ? WHERE key = ?", (json.dumps(self.progress), _SALVAGING))

    def check_stop(self) -> None:
        if self._stop is not None and self._stop():
            raise SalvageStopped("stopped before it was done")


def _migrate(conn: sqlite3.Connection) -> None:
    """Bring a buffer written by an older DC to SCHEMA_VERSION (in one transaction: a second
    process opening the file meanwhile finds it migrated)."""
    if _schema_version(conn) == SCHEMA_VERSION:
        return
    conn.execute("BEGIN IMMEDIATE")
    try:
        row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
        columns = {column[1] for column in conn.execute("PRAGMA table_info(queues)")}
        if "dead_bytes" not in columns:  # schema 1
            conn.execute("ALTER TABLE queues ADD COLUMN dead_bytes INTEGER NOT NULL DEFAULT 0")
            conn.execute(
                "UPDATE queues SET dead_bytes = "
                "(SELECT coalesce(sum(size), 0) FROM dead_letters WHERE destination = queues.name)"
            )
        if row is None or int(row[0]) < SCHEMA_VERSION:  # a newer DC's number stays
            conn.execute("INSERT OR REPLACE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise


def _schema_version(conn: sqlite3.Connection) -> int | None:
    row = conn.execute("SELECT value FROM meta WHERE key='schema_version'").fetchone()
    return int(row[0]) if row is not None else None


_QUEUE_DDL = (
    "id INTEGER PRIMARY KEY, record_id TEXT NOT NULL, topic TEXT NOT NULL, stamp_ns INTEGER NOT NULL, "
    "enqueued_ns INTEGER NOT NULL, attempts INTEGER NOT NULL DEFAULT 0, size INTEGER NOT NULL, "
    "payload TEXT NOT NULL, payload_crc INTEGER"
)
# (record_id, topic, stamp_ns, enqueued_ns, size, payload, payload_crc) as append() inserts them.
_QueueRow = tuple[str, str, int, int, int, str, int | None]


def _ensure_queue_table(conn: sqlite3.Connection, qid: int) -> None:
    """A queue's table, with the columns of this schema.

    Checked at every start rather than once by the schema migration: an older DC run on this
    buffer since creates the table of a new destination without ``payload_crc``.
    """
    conn.execute(f"CREATE TABLE IF NOT EXISTS q_{qid} ({_QUEUE_DDL})")
    columns = {column[1] for column in conn.execute(f"PRAGMA table_info(q_{qid})")}
    if "payload_crc" not in columns:
        try:
            conn.execute(f"ALTER TABLE q_{qid} ADD COLUMN payload_crc INTEGER")
        except sqlite3.OperationalError as exc:
            if "duplicate column" not in str(exc):  # another process added it meanwhile
                raise


def _is_dead_letter(row: tuple[object, ...]) -> bool:
    _id, destination, record_id, topic, stamp_ns, enqueued_ns, failed_ns, attempts, error, size, payload = row
    return all(isinstance(v, str) for v in (destination, record_id, topic, error, payload)) and all(
        isinstance(v, int) for v in (stamp_ns, enqueued_ns, failed_ns, attempts, size)
    )


def _is_hop_key(key: tuple[object, ...]) -> bool:
    topic, source_ns, seq = key
    return isinstance(topic, str) and isinstance(source_ns, int) and isinstance(seq, int)
