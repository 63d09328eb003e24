"""DC's saved files (camera images, maps, recordings) under the disk budget: the one place that knows them.

Measurements write files and name them in their records (``local_paths``, and whatever field a
file destination's ``src_fields`` reads); destinations that carry files (MinIO, FilesMetrics:
:meth:`dc_core.destination.Destination.file_fields`) upload and verify them. This ledger learns of
each file from the records destination_server receives, learns from the senders which file
destination confirmed which record, and keeps per file: its size, measurement, run, retention
priority (``flb.retention_priorities``) and which file destinations still owe it. A file every one
of them confirmed is *delivered and verified* (MinIO confirms a record once its objects are
verified, FilesMetrics once every storage holds them intact).

The pipeline (dc_destinations.delivery) asks it, on the writer thread, for the files to weigh
against the budget, and has it evict those the plan (dc_destinations.disk_budget) gives up. An
eviction deletes the file and is counted per measurement (``evicted``, ``evicted_unsent``) and per
file destination that had not delivered it (``files_evicted``). A record of such a destination that
names an evicted file is then taken out of that destination's queue, counted ``evicted``, unless the
destination records evictions itself (FilesMetrics writes the file's row with ``evicted``). Such a
destination is also told of a file evicted after it confirmed it (``notices_for``, on its sender's
thread: FilesMetrics then marks the rows it wrote of that file evicted, off the filesystem).

What it knows is kept in a small SQLite file beside the buffer, so that the files saved before a
restart still count. Counters are since start, as the delivery counters.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import sqlite3
import stat
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dc_core.confined_files import Confinement, FileRefused
from dc_core.destination import OutgoingRecord
from dc_core.logs import BurstLog, Logger
from dc_core.records import measurement_of
from dc_destinations.disk_budget import FileCandidate
from dc_destinations.record_fields import field_value

FILE_NAME = "saved_files.sqlite3"
# Ticks (twice a second) a file named by a record is looked for before it is taken as never written.
_LOOKS = 20

_SCHEMA = """
CREATE TABLE IF NOT EXISTS files (
    path TEXT PRIMARY KEY, size INTEGER NOT NULL, measurement TEXT NOT NULL, run_id TEXT NOT NULL,
    seq INTEGER NOT NULL, run_index INTEGER NOT NULL, priority INTEGER NOT NULL,
    destinations TEXT NOT NULL, owed TEXT NOT NULL, records TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    measurement TEXT NOT NULL, run_id TEXT NOT NULL, produced INTEGER NOT NULL,
    PRIMARY KEY (measurement, run_id));
CREATE TABLE IF NOT EXISTS evicted (path TEXT PRIMARY KEY, records TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS notices (
    destination TEXT NOT NULL, path TEXT NOT NULL, records TEXT NOT NULL, PRIMARY KEY (destination, path));
"""
# Added since the first ledgers: (destination, record_id) that confirmed the file, of the destinations
# that record evictions (they are told when it is evicted later).
_ADDED = {"told": "TEXT NOT NULL DEFAULT '[]'"}


@dataclass
class SavedFile:
    path: str
    size: int
    measurement: str
    run_id: str
    seq: int  # order of registration, over all files: oldest first
    run_index: int  # 0 for the first file of its measurement and run
    priority: int
    destinations: set[str]  # the file destinations that deliver it
    owed: set[str]  # those that have not confirmed it yet
    records: set[tuple[str, str]]  # (destination, record_id) naming it, not confirmed yet
    # (destination, record_id) that confirmed it, of the destinations that record evictions.
    told: set[tuple[str, str]] = field(default_factory=set)

    @property
    def delivered(self) -> bool:
        """Delivered and verified by every destination that carries it; a file none carries is the only copy."""
        return bool(self.destinations) and not self.owed


@dataclass
class _Noted:
    record_id: str
    measurement: str
    run_id: str
    paths: dict[str, set[str]]  # path -> file destinations that carry it
    looks: int = 0


@dataclass
class _Counts:
    produced: int = 0
    produced_bytes: int = 0
    delivered: int = 0
    evicted: int = 0
    evicted_unsent: int = 0
    evicted_bytes: int = 0


@dataclass
class Evicted:
    """What one eviction did, for the pipeline's log line."""

    freed: int
    measurement: str
    unsent_to: list[str] = field(default_factory=list)


def record_files(data: Mapping[str, Any], fields_by_destination: Mapping[str, Sequence[str]]) -> dict[str, set[str]]:
    """The files a record names: path -> the file destinations (of ``fields_by_destination``) that carry it.

    Every string under ``local_paths`` (at the top, or in a group's member records) is a saved file;
    a file destination's ``src_fields`` may name more."""
    found: dict[str, set[str]] = {}
    for holder in (data, *(v for v in data.values() if isinstance(v, dict))):
        local = holder.get("local_paths")
        if isinstance(local, dict):
            for value in local.values():
                if isinstance(value, str) and value:
                    found.setdefault(value, set())
    for destination, fields in fields_by_destination.items():
        for dotted in fields:
            value = field_value(data, dotted)
            if isinstance(value, str) and value:
                found.setdefault(value, set()).add(destination)
    return found


class SavedFiles:
    """The ledger of DC's saved files; see the module documentation.

    ``note`` runs on the main thread, ``confirmed`` on the senders', ``tick``, ``candidates`` and
    ``evict`` on the writer's, ``snapshot`` on the status server's: one lock guards the state, and
    the first two only queue what they learn.
    """

    def __init__(
        self,
        path: Path | None,
        priorities: Mapping[str, int],
        logger: Logger,
        *,
        keep_run_ends: int = 0,
        records_evictions: Iterable[str] = (),
        roots: Sequence[str] = (),
    ) -> None:
        self.path = path
        # Anything on the ROS graph can publish a record: only DC's own files, in these folders and
        # owned by this user, are weighed and ever deleted (dc_core.confined_files, as the uploads).
        self._confinement = Confinement(roots)
        self.refused = 0
        self.priorities = dict(priorities)
        self.keep_run_ends = keep_run_ends
        self.logger = logger
        # Destinations that record an evicted file themselves: their records are sent, not taken out.
        self.records_evictions = set(records_evictions)
        self._lock = threading.Lock()
        self._files: dict[str, SavedFile] = {}
        self._by_record: dict[str, set[str]] = collections.defaultdict(set)  # record id -> paths it names
        self._runs: dict[tuple[str, str], int] = {}
        self._evicted: dict[str, set[tuple[str, str]]] = {}  # path -> (destination, record_id) to settle
        self._skip: dict[str, set[str]] = collections.defaultdict(set)  # destination -> record ids to take out
        # destination -> path -> record ids whose rows must say the file was evicted (records_evictions).
        self._notices: dict[str, dict[str, set[str]]] = collections.defaultdict(dict)
        self._dirty_notices: set[tuple[str, str]] = set()
        self._inbox: collections.deque[_Noted] = collections.deque()
        self._confirmations: collections.deque[tuple[str, list[str]]] = collections.deque()
        self._waiting: list[_Noted] = []
        self._seq = 0
        self._bytes = 0
        self._counts: dict[str, _Counts] = collections.defaultdict(_Counts)
        self._files_evicted: dict[str, int] = collections.defaultdict(int)
        self._dirty: set[str] = set()
        self._dirty_runs: set[tuple[str, str]] = set()
        self._dirty_evicted: set[str] = set()
        self._db: sqlite3.Connection | None = None
        self.evict_log = BurstLog(
            logger.warning, "saved files evicted to keep DC within flb.disk_budget / disk_free_floor"
        )
        self.failure_log = BurstLog(logger.warning, "saved files that could not be evicted")
        self.too_large_log = BurstLog(logger.error, "saved files larger than the whole disk budget")
        self.refused_log = BurstLog(
            logger.warning, "files named by records left out of the disk budget (never evicted): not DC's to delete"
        )

    # -- durable state ---------------------------------------------------------------------------

    def open(self) -> None:
        """Load what an earlier run left (a damaged file is set aside: its files are no longer counted)."""
        if self.path is None:
            return
        try:
            self._db = self._connect()
            self._load()
        except sqlite3.DatabaseError as exc:
            if self._db is not None:
                self._db.close()
            aside = self.path.with_name(self.path.name + ".damaged")
            with contextlib.suppress(OSError):
                os.replace(self.path, aside)
            self.logger.error(
                f"saved files ledger {self.path} unreadable ({exc}): set aside as {aside}; the files it listed "
                "no longer count in the disk budget (delete them by hand if they are not needed)"
            )
            self._files.clear()
            self._db = self._connect()

    def _connect(self) -> sqlite3.Connection:
        assert self.path is not None
        db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        db.execute("PRAGMA journal_mode=WAL")
        db.executescript(_SCHEMA)
        columns = {row[1] for row in db.execute("PRAGMA table_info(files)")}
        for column, definition in _ADDED.items():
            if column not in columns:
                db.execute(f"ALTER TABLE files ADD COLUMN {column} {definition}")
        return db

    def _load(self) -> None:
        assert self._db is not None
        for row in self._db.execute(
            "SELECT path, size, measurement, run_id, seq, run_index, priority, destinations, owed, records, told "
            "FROM files"
        ):
            path, size, measurement, run_id, seq, run_index, priority, destinations, owed, records, told = row
            self._files[path] = SavedFile(
                path,
                int(size),
                measurement,
                run_id,
                int(seq),
                int(run_index),
                int(priority),
                set(json.loads(destinations)),
                set(json.loads(owed)),
                {(d, r) for d, r in json.loads(records)},
                {(d, r) for d, r in json.loads(told)},
            )
            for _, record_id in self._files[path].records:
                self._by_record[record_id].add(path)
            self._bytes += int(size)
            self._seq = max(self._seq, int(seq))
        for measurement, run_id, produced in self._db.execute("SELECT measurement, run_id, produced FROM runs"):
            self._runs[(measurement, run_id)] = int(produced)
        for path, records in self._db.execute("SELECT path, records FROM evicted"):
            pending = {(d, r) for d, r in json.loads(records)}
            self._evicted[path] = pending
            for destination, record_id in pending:
                if destination not in self.records_evictions:
                    self._skip[destination].add(record_id)
        for destination, path, records in self._db.execute("SELECT destination, path, records FROM notices"):
            self._notices[destination][path] = set(json.loads(records))

    def _persist(self) -> None:
        db = self._db
        if db is None or not (self._dirty or self._dirty_runs or self._dirty_evicted or self._dirty_notices):
            return
        files = [(p, self._files.get(p)) for p in self._dirty]
        evicted = [(p, self._evicted.get(p)) for p in self._dirty_evicted]
        runs = [(m, r, self._runs[(m, r)]) for m, r in self._dirty_runs]
        notices = [(d, p, self._notices.get(d, {}).get(p)) for d, p in self._dirty_notices]
        self._dirty, self._dirty_runs, self._dirty_evicted = set(), set(), set()
        self._dirty_notices = set()
        try:
            db.execute("BEGIN")
            db.executemany("DELETE FROM files WHERE path = ?", [(p,) for p, f in files if f is None])
            db.executemany(
                "INSERT OR REPLACE INTO files (path, size, measurement, run_id, seq, run_index, priority, "
                "destinations, owed, records, told) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (
                        f.path,
                        f.size,
                        f.measurement,
                        f.run_id,
                        f.seq,
                        f.run_index,
                        f.priority,
                        json.dumps(sorted(f.destinations)),
                        json.dumps(sorted(f.owed)),
                        json.dumps(sorted(f.records)),
                        json.dumps(sorted(f.told)),
                    )
                    for _, f in files
                    if f is not None
                ],
            )
            db.executemany("INSERT OR REPLACE INTO runs VALUES (?, ?, ?)", runs)
            db.executemany("DELETE FROM evicted WHERE path = ?", [(p,) for p, e in evicted if not e])
            db.executemany(
                "INSERT OR REPLACE INTO evicted VALUES (?, ?)", [(p, json.dumps(sorted(e))) for p, e in evicted if e]
            )
            db.executemany(
                "DELETE FROM notices WHERE destination = ? AND path = ?", [(d, p) for d, p, n in notices if not n]
            )
            db.executemany(
                "INSERT OR REPLACE INTO notices VALUES (?, ?, ?)",
                [(d, p, json.dumps(sorted(n))) for d, p, n in notices if n],
            )
            db.execute("COMMIT")
        except sqlite3.Error as exc:  # a full disk: kept in memory, written at a later tick
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            self._dirty |= {p for p, _ in files}
            self._dirty_runs |= {(m, r) for m, r, _ in runs}
            self._dirty_evicted |= {p for p, _ in evicted}
            self._dirty_notices |= {(d, p) for d, p, _ in notices}
            self.failure_log.event(1, f"the ledger {self.path} could not be written: {exc}")

    def close(self) -> None:
        with self._lock:
            self._take_in()
            self._persist()
            if self._db is not None:
                self._db.close()
                self._db = None

    # -- what the other threads tell ------------------------------------------------------------------

    def note(self, deliveries: Sequence[tuple[str, OutgoingRecord]], file_fields: Mapping[str, Sequence[str]]) -> None:
        """The copies of one received record (main thread): its files, queued for the writer's tick."""
        if not deliveries:
            return
        record = deliveries[0][1]
        carrying = {name: file_fields[name] for name, _ in deliveries if file_fields.get(name)}
        paths = record_files(record.data, carrying)
        if not paths:
            return
        data = record.data
        name = data.get("name")
        measurement = name if isinstance(name, str) and name else measurement_of(record.topic)
        run_id = data.get("run_id")
        self._inbox.append(_Noted(record.record_id, measurement, str(run_id) if run_id is not None else "", paths))

    def confirmed(self, destination: str, record_ids: list[str]) -> None:
        """A file destination confirmed these records (sender thread)."""
        if record_ids:
            self._confirmations.append((destination, record_ids))

    def skipped_for(self, destination: str) -> set[str]:
        """Record ids of ``destination`` whose files were evicted before it delivered them: to take out."""
        with self._lock:
            return set(self._skip.get(destination, ()))

    def taken_out(self, destination: str, record_ids: Iterable[str]) -> None:
        """The sender took these records out of ``destination``'s queue, counted ``evicted``."""
        done = set(record_ids)
        with self._lock:
            self._skip[destination] -= done
            self._settle_evicted({(destination, r) for r in done})

    def notices_for(self, destination: str) -> dict[str, list[str]]:
        """Files evicted after ``destination`` (one that records evictions) confirmed records naming
        them: path -> those record ids. It says so where it recorded them, then calls :meth:`told`."""
        with self._lock:
            return {path: sorted(ids) for path, ids in self._notices.get(destination, {}).items()}

    def told(self, destination: str, paths: Iterable[str]) -> None:
        """``destination`` recorded the eviction of these files."""
        with self._lock:
            notices = self._notices.get(destination, {})
            for path in paths:
                if notices.pop(path, None) is not None:
                    self._dirty_notices.add((destination, path))

    def _notify(self, destination: str, path: str, record_ids: Iterable[str]) -> None:
        self._notices[destination].setdefault(path, set()).update(record_ids)
        self._dirty_notices.add((destination, path))

    def is_evicted(self, path: str) -> bool:
        """True when DC evicted ``path`` before every destination delivered it (FilesMetrics asks)."""
        with self._lock:
            return path in self._evicted

    # -- the writer's tick ------------------------------------------------------------------------

    def tick(self) -> None:
        """Take in what was noted and confirmed since the last tick, and write it down."""
        with self._lock:
            self._take_in()
            self._persist()

    def take_in(self) -> None:
        """Weigh the files noted since (after each group commit, with the records naming them), without
        writing them down or looking again for those not written yet: the next :meth:`tick` does both."""
        with self._lock:
            while self._inbox:
                self._register(self._inbox.popleft())

    def _take_in(self) -> None:
        noted, self._waiting = self._waiting, []
        while self._inbox:
            noted.append(self._inbox.popleft())
        for item in noted:
            self._register(item)
        while self._confirmations:
            destination, record_ids = self._confirmations.popleft()
            self._confirm(destination, record_ids)

    def _register(self, noted: _Noted) -> None:
        missing = {}
        for path, destinations in noted.paths.items():
            known = self._files.get(path)
            records = {(d, noted.record_id) for d in destinations}
            if records:
                self._by_record[noted.record_id].add(path)
            if known is not None:  # named again by another record
                known.destinations |= destinations
                known.owed |= destinations
                known.records |= records
                self._dirty.add(path)
                continue
            try:
                size = self._own_file(path).st_size
            except FileNotFoundError:
                missing[path] = destinations
                continue
            except FileRefused as exc:
                self.refused += 1
                self.refused_log.event(1, str(exc))
                continue
            except OSError:
                continue  # not DC's to weigh (no access): the destination says what it cannot read
            run = (noted.measurement, noted.run_id)
            run_index = self._runs.get(run, 0)
            self._runs[run] = run_index + 1
            self._dirty_runs.add(run)
            self._seq += 1
            self._files[path] = SavedFile(
                path,
                size,
                noted.measurement,
                noted.run_id,
                self._seq,
                run_index,
                self.priorities.get(noted.measurement, 0),
                set(destinations),
                set(destinations),
                records,
            )
            self._bytes += size
            self._dirty.add(path)
            counts = self._counts[noted.measurement]
            counts.produced += 1
            counts.produced_bytes += size
        if missing and noted.looks < _LOOKS:  # the measurement may write it just after publishing
            self._waiting.append(_Noted(noted.record_id, noted.measurement, noted.run_id, missing, noted.looks + 1))

    def _confirm(self, destination: str, record_ids: list[str]) -> None:
        keys = {(destination, r) for r in record_ids}
        telling = destination in self.records_evictions
        for path, settled in self._settle_evicted(keys).items():
            if telling:  # it may have found the file still there, in a send() as DC evicted it: told again
                self._notify(destination, path, (r for _, r in settled))
        # Records of a file evicted in a send() that confirmed them anyway: nothing left to take out.
        self._skip[destination] -= set(record_ids)
        for record_id in record_ids:
            for path in list(self._by_record.get(record_id, ())):
                saved = self._files.get(path)
                if saved is None or (destination, record_id) not in saved.records:
                    continue
                saved.records.discard((destination, record_id))
                if telling:
                    saved.told.add((destination, record_id))
                if not any(d == record_id for _, d in saved.records):
                    self._by_record[record_id].discard(path)
                    if not self._by_record[record_id]:
                        del self._by_record[record_id]
                if not any(d == destination for d, _ in saved.records):
                    saved.owed.discard(destination)
                self._dirty.add(path)
                if saved.delivered and not saved.records:
                    self._counts[saved.measurement].delivered += 1
                    if not os.path.exists(path):  # deleted once sent (delete_when_sent): off the disk
                        self._forget(saved)

    def _settle_evicted(self, keys: set[tuple[str, str]]) -> dict[str, set[tuple[str, str]]]:
        """Forget these (destination, record_id) of the evicted files that awaited them; returns which, per path."""
        settled = {}
        for path in [p for p, pending in self._evicted.items() if pending & keys]:
            settled[path] = self._evicted[path] & keys
            self._evicted[path] -= keys
            self._dirty_evicted.add(path)
            if not self._evicted[path]:
                del self._evicted[path]
        return settled

    def _forget(self, saved: SavedFile) -> None:
        self._files.pop(saved.path, None)
        for _, record_id in saved.records:
            paths = self._by_record.get(record_id)
            if paths is not None:
                paths.discard(saved.path)
                if not paths:
                    del self._by_record[record_id]
        self._bytes -= saved.size
        self._dirty.add(saved.path)

    # -- the budget ------------------------------------------------------------------------------

    @property
    def total_bytes(self) -> int:
        with self._lock:
            return self._bytes

    def candidates(self) -> list[FileCandidate]:
        """Every file weighed against the budget, with what the plan needs to know of it."""
        ends = self.keep_run_ends
        with self._lock:
            return [
                FileCandidate(
                    f.path,
                    f.size,
                    f.priority,
                    f.delivered,
                    ends > 0
                    and (f.run_index < ends or self._runs.get((f.measurement, f.run_id), 0) - f.run_index <= ends),
                    f.seq,
                )
                for f in self._files.values()
            ]

    def tick_logs(self) -> None:
        for log in (self.evict_log, self.failure_log, self.too_large_log, self.refused_log):
            log.tick()

    def _own_file(self, path: str) -> os.stat_result:
        """The status of ``path`` if it is a regular file of this user inside the roots; FileRefused if not."""
        real = self._confinement.check_path(path)
        status = os.lstat(real)
        if not stat.S_ISREG(status.st_mode) or status.st_uid != self._confinement.uid:
            raise FileRefused(f"{path} is not a regular file of DC's user")
        return status

    def too_large(self, budget: int) -> None:
        """Say, once per file, which saved files alone are larger than the whole budget."""
        with self._lock:
            large = [f for f in self._files.values() if f.size > budget]
        for saved in large:
            self.too_large_log.event(
                1,
                f"{saved.path} ({saved.size} bytes, measurement {saved.measurement}) is larger than the whole "
                f"disk budget ({budget} bytes): raise flb.disk_budget above the largest file a measurement saves",
            )

    def evict(self, path: str) -> Evicted | None:
        """Delete ``path`` and count it; None when it could not be (kept, said once per burst)."""
        with self._lock:
            saved = self._files.get(path)
            if saved is None:
                return None
            try:
                # Checked again: a folder of the path may have been swapped for a link since it was weighed.
                self._own_file(path)
                os.unlink(path)
            except FileRefused as exc:
                self.failure_log.event(1, str(exc))
                return None
            except FileNotFoundError:  # deleted by someone else (delete_when_sent, an operator): not DC's eviction
                self._forget(saved)
                return Evicted(saved.size, saved.measurement)
            except OSError as exc:
                self.failure_log.event(1, f"{path}: {exc.strerror or exc}")
                return None
            self._forget(saved)
            counts = self._counts[saved.measurement]
            counts.evicted += 1
            counts.evicted_bytes += saved.size
            unsent = sorted(saved.owed) if saved.destinations else []
            if not saved.delivered:
                counts.evicted_unsent += 1
            for destination in unsent:
                self._files_evicted[destination] += 1
            for destination, record_id in saved.told:  # its rows say the file is on the filesystem
                self._notify(destination, path, (record_id,))
            pending = {key for key in saved.records if key[0] in saved.owed}
            if pending:
                self._evicted[path] = pending
                self._dirty_evicted.add(path)
                for destination, record_id in pending:
                    if destination not in self.records_evictions:
                        self._skip[destination].add(record_id)
            return Evicted(saved.size, saved.measurement, unsent)

    # -- observability ---------------------------------------------------------------------------

    def files_evicted(self, destination: str) -> int:
        with self._lock:
            return self._files_evicted.get(destination, 0)

    def snapshot(self) -> dict[str, Any]:
        """Per measurement: files produced, delivered, evicted (and of those, unsent), on disk now."""
        with self._lock:
            on_disk: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0])
            for saved in self._files.values():
                on_disk[saved.measurement][0] += 1
                on_disk[saved.measurement][1] += saved.size
            measurements = {}
            for name in sorted(set(self._counts) | set(on_disk)):
                counts = self._counts[name]
                measurements[name] = {
                    "retention_priority": self.priorities.get(name, 0),
                    "produced": counts.produced,
                    "produced_bytes": counts.produced_bytes,
                    "delivered": counts.delivered,
                    "evicted": counts.evicted,
                    "evicted_unsent": counts.evicted_unsent,
                    "evicted_bytes": counts.evicted_bytes,
                    "kept": on_disk[name][0],
                    "kept_bytes": on_disk[name][1],
                }
            return {
                "refused": self.refused,
                "files": len(self._files),
                "bytes": self._bytes,
                "measurements": measurements,
                "files_evicted": dict(self._files_evicted),
            }
