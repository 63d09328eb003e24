"""FilesMetrics destination: a PostgreSQL row per file a record names and per storage that should hold it.

It uploads nothing: the MinIO destination (or any uploader) receives the same records and stores
the files named by ``src_fields`` at the keys named by ``upload_fields``. For each such file and
each storage of ``file_storage``, FilesMetrics asks the storage whether it holds the file — same
size and same ETag as the local copy, not merely a key — and upserts the file's row: ``uploaded``
says what was verified, ``on_filesystem`` whether the local copy exists. A record whose files are
not all stored yet is retried (the uploader may simply not have got there); once every storage
verified every file, ``delete_when_sent`` deletes the local copies and the rows say ``deleted``.

A file that is neither on disk nor in a storage can never be uploaded: its record goes to the dead
letters, naming the path. A storage or PostgreSQL that cannot be reached retries the batch; the
rows are upserted on ``(local_path, storage_type)``, so retries add no duplicate.
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from dc_core.confined_files import ConfinementParams, OpenedFile, delete_opened
from dc_core.destination import Destination, OutgoingRecord, ProbeResult, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import compat_param, param
from dc_destinations.content_types import content_type
from dc_destinations.files_metrics.media import DurationProbe, is_video
from dc_destinations.files_metrics.table import FileRow, FilesTable
from dc_destinations.object_files import (
    FilePair,
    NoLocalFile,
    ObjectStoreParams,
    RecordFiles,
    StoreUnavailable,
    file_pairs,
    probe_bucket,
    store_where,
    verify_stored,
)
from dc_destinations.pgsql import record_time
from dc_destinations.pgsql.connection import (
    KeptConnection,
    PostgresServerParams,
    is_record_error,
    keep_database,
    probe_table,
    require_psycopg,
    table_problem,
)

STORAGES = ("minio", "s3")
DB_TYPES = ("pgsql",)


def _storages_problem(storages: list[str]) -> str | None:
    expected = 'a non-empty list of "minio" and "s3", each at most once'
    if not storages or len(set(storages)) != len(storages) or any(s not in STORAGES for s in storages):
        return expected
    return None


@dataclass(frozen=True, kw_only=True, repr=False)
class StorageSection(ObjectStoreParams):
    input_names: list[str] = compat_param([], "records come from the destination's inputs")


@dataclass(frozen=True, kw_only=True, repr=False)
class S3Section(StorageSection):
    endpoint: str = param(
        "", doc="Store address: host:port (http or https by use_ssl) or a URL; empty: AWS's endpoint of region"
    )


# The defaults of `minio` and `s3`, told apart by identity: a section the YAML does not give is one
# of these very objects, while one given (even empty) is a new one. That is how "listed in
# file_storage but not configured" and "configured but not listed" are found from the parsed values.
_MINIO_NOT_GIVEN = StorageSection()
_S3_NOT_GIVEN = S3Section()


def _minio_not_given() -> StorageSection:
    return _MINIO_NOT_GIVEN


def _s3_not_given() -> S3Section:
    return _S3_NOT_GIVEN


@dataclass(frozen=True, kw_only=True)
class FilesMetricsDatabaseParams(PostgresServerParams):
    table: str = param(
        "files_metrics", check=table_problem, doc='Table of the rows ("schema.table" accepted); created if absent'
    )
    time_format: str = compat_param("double", "`timestamp` comes from timestamp_key or the record's stamp")
    time_key: str = compat_param("date", "`timestamp` comes from timestamp_key or the record's stamp")


@dataclass(frozen=True, kw_only=True)
class FilesMetricsParams(ConfinementParams):
    file_storage: list[str] = param(
        check=_storages_problem, doc='Storages whose copies are checked: "minio", "s3" or both, each with its section'
    )
    db_type: str = param("pgsql", choices=DB_TYPES, doc="Database of the table: only pgsql")
    delete_when_sent: bool = param(False, doc="Delete the local files once every storage holds them, verified")
    missing_wait: float = param(
        1.0,
        minimum=0.0,
        maximum=60.0,
        doc="Seconds a file neither on disk nor stored is looked for again before its record is dead-lettered",
    )
    plugin_path: str = compat_param("", "there is no Go plugin to load")
    minio: StorageSection = param(default_factory=_minio_not_given, doc="The MinIO storage, if file_storage lists it")
    s3: S3Section = param(default_factory=_s3_not_given, doc="The S3 storage, if file_storage lists it")
    pgsql: FilesMetricsDatabaseParams = param(
        default_factory=FilesMetricsDatabaseParams, doc="The PostgreSQL server and table"
    )

    def __post_init__(self) -> None:
        for name in STORAGES:
            listed = name in self.file_storage
            section = self.section(name)
            given = section is not _MINIO_NOT_GIVEN and section is not _S3_NOT_GIVEN
            if listed and not given:
                raise ConfigError(name, f'section missing: file_storage lists "{name}"')
            if not listed and given:
                raise ConfigError(
                    name, f'"{name}" is not in file_storage: add it there, or remove the section (it would be unused)'
                )
            if listed and not section.src_fields:
                raise ConfigError(f"{name}.src_fields", "expected at least one field naming a file to track")

    def section(self, storage: str) -> StorageSection:
        section: StorageSection = getattr(self, storage)
        return section


@dataclass(frozen=True)
class _Store:
    name: str
    section: StorageSection
    client: Any  # boto3 S3 client


@dataclass
class _Plan:
    """What one record's files call for: the rows to write, and why it cannot be confirmed yet or ever."""

    rows: list[FileRow] = field(default_factory=list)
    waiting: list[str] = field(default_factory=list)  # on disk, not stored yet: no failure, look again later
    unsure: list[str] = field(default_factory=list)  # a store cannot say, or holds another object: retry
    missing: list[str] = field(default_factory=list)  # files neither on disk nor stored: reject, after a wait
    refused: list[str] = field(default_factory=list)  # what the record names is no file: reject at once
    opened: dict[str, OpenedFile] = field(default_factory=dict)  # local path -> the file checked and open

    def close(self) -> None:
        for opened in self.opened.values():
            opened.close()


class FilesMetrics(Destination[FilesMetricsParams]):
    """Track in PostgreSQL which storage verified each file a record names; delete it once all did."""

    def __init__(self, context: Any, params: FilesMetricsParams) -> None:
        super().__init__(context, params)
        self._database: KeptConnection | None = None  # made by on_configure, connected by the first batch
        self._table: FilesTable | None = None
        self._stores: list[_Store] = []
        self._probe = DurationProbe(context.logger)
        self._files_deleted = 0
        self._files = RecordFiles(context)
        self.address = ""

    def __repr__(self) -> str:
        return f"FilesMetrics({self.context.name!r}, {self.address or self.params.pgsql.host!r})"

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        require_psycopg(self.context.name, "FilesMetrics")
        self._files.configure(self.params)
        table = FilesTable(self.params.pgsql.table)
        self._table = table
        self._database = keep_database(
            self,
            self.params.pgsql.server(),
            prepare=self._prepare_table,
            prepared=f"table {table.name}",
            section=f"destination_server.{self.context.name}.pgsql",
        )
        self.address = self._database.address
        self._stores = [
            _Store(storage, section, section.client(self.context.logger, f"{self.context.name}.{storage}"))
            for storage, section in ((s, self.params.section(s)) for s in self.params.file_storage)
        ]

    def probe(self) -> ProbeResult:
        """The table's database (as PgSQL's probe) and every storage's bucket; the first failure."""
        assert self._database is not None and self._table is not None, "probe() before on_configure()"
        results = [probe_table(self._database, self._table.identifier, self._table.name)]
        results += [
            probe_bucket(s.client, s.section.bucket, f"{s.name}: {store_where(s.section.bucket, s.client)}")
            for s in self._stores
        ]
        failed = [r for r in results if not r.ok]
        if failed:
            return failed[0]
        return ProbeResult(True, "; ".join(r.reason for r in results))

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a database that is down
        # must not hold up activation.
        storages = ", ".join(f"{s.name} (bucket {s.section.bucket})" for s in self._stores)
        self.context.logger.info(
            f"tracking the files of {storages} in table {self.params.pgsql.table} of {self.address}"
        )

    def on_cleanup(self) -> None:
        super().on_cleanup()
        self._stores = []

    # A file DC evicted before it was stored gets its row, with evicted true: the record is confirmed.
    records_evictions = True

    def files_evicted(self, files: Mapping[str, Sequence[str]]) -> None:
        """Files DC evicted after their rows were written: those rows (of the records that named them,
        by record id, so another robot's row of the same path is left alone) say so."""
        database = self._database
        assert database is not None and self._table is not None, "files_evicted() before on_configure()"
        statement = self._table.mark_evicted
        rows = [{"local_path": path, "record_ids": list(ids)} for path, ids in files.items()]

        def mark(connection: Any) -> None:
            with connection.transaction(), connection.cursor() as cursor:
                cursor.executemany(statement, rows)

        database.run(mark)

    def file_fields(self) -> list[str]:
        """Every storage's src_fields: a record is confirmed once every storage verified its files."""
        return list(dict.fromkeys(f for s in self.params.file_storage for f in self.params.section(s).src_fields))

    def counters(self) -> dict[str, int]:
        return {"files_deleted": self._files_deleted, "files_refused": self._files.refused}

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        return self._files.batch(functools.partial(self._send, batch))

    def _send(self, batch: Sequence[OutgoingRecord], plans: list[_Plan]) -> SendOutcome | None:
        database = self._database
        assert database is not None, "send() before on_configure()"
        durations: dict[str, float | None] = {}
        # Every storage is asked before anything is written: one that cannot be reached retries the
        # whole batch (StoreUnavailable), leaving the table as it was.
        planned_at = time.monotonic()
        plans.extend(self._plan(record, durations) for record in batch)
        if any(plan.missing for plan in plans):
            # A measurement may write its file just after publishing the record: look once more.
            time.sleep(max(0.0, self.params.missing_wait - (time.monotonic() - planned_at)))
            for i, record in enumerate(batch):
                if plans[i].missing:
                    plans[i].close()
                    plans[i] = self._plan(record, durations)
        outcome = SendOutcome()
        writes = [(i, plan.rows) for i, plan in enumerate(plans) if plan.rows]
        if writes:
            outcome.reject.update(database.run(lambda connection: self._write(database, connection, writes)))
        gone: list[FileRow] = []
        for i, plan in enumerate(plans):
            if i in outcome.reject:
                continue
            if plan.refused or plan.missing:
                outcome.reject[i] = "; ".join(plan.refused + plan.missing)
            elif plan.unsure:
                outcome.retry[i] = "; ".join(plan.unsure + plan.waiting)
            elif plan.waiting:
                # The upload is another destination's (MinIO, S3Files): until it is done, the record waits.
                outcome.waiting[i] = "; ".join(plan.waiting)
            elif self.params.delete_when_sent:
                problems = self._delete(plan, gone)
                if problems:
                    outcome.retry[i] = "; ".join(problems)
        if gone:
            database.run(lambda connection: self._mark_deleted(connection, gone))
        return outcome if outcome.retry or outcome.reject or outcome.waiting else None

    def _plan(self, record: OutgoingRecord, durations: dict[str, float | None]) -> _Plan:
        plan = _Plan()
        for store in self._stores:
            for pair in file_pairs(record.data, store.section):
                self._plan_file(record, store, pair, plan, durations)
        return plan

    def _plan_file(
        self, record: OutgoingRecord, store: _Store, pair: FilePair, plan: _Plan, durations: dict[str, float | None]
    ) -> None:
        bucket = store.section.bucket
        usable, opened = self._files.open(pair, plan.refused, plan.opened.get(pair.local_path))
        if not usable or pair.key is None:
            return
        if opened is not None:
            plan.opened[pair.local_path] = opened
        size = opened.size if opened is not None else None
        on_filesystem = size is not None
        try:
            local = opened if opened is not None else NoLocalFile(pair.local_path)
            verification = verify_stored(store.client, bucket, pair.key, local)
        except StoreUnavailable:
            raise  # the whole store: every record of the batch waits for it
        except RetryableError as exc:
            plan.unsure.append(f"{store.name} cannot tell whether it holds {pair.key}: {exc}")
            return
        mime_type = content_type(pair.local_path)
        duration = None
        if on_filesystem and is_video(mime_type):
            if pair.local_path not in durations:
                durations[pair.local_path] = self._probe.duration(pair.local_path)
            duration = durations[pair.local_path]
        data = record.data
        evicted = not on_filesystem and not verification.verified and self.evicted_file(pair.local_path)
        plan.rows.append(
            FileRow(
                timestamp=record_time(record, self.params.pgsql.timestamp_key),
                robot_name=_text(data.get("robot_name")),
                robot_id=_text(data.get("id")),
                group_name=_text(data.get("name")),
                duration=duration,
                local_path=pair.local_path,
                # The URI every S3 client reads (aws s3, boto3, DuckDB), whichever storage_type holds it.
                remote_path=f"s3://{bucket}/{pair.key}",
                uploaded=verification.verified,
                on_filesystem=on_filesystem,
                storage_type=store.name,
                content_type=mime_type,
                size=size if on_filesystem else verification.size,
                record_id=record.record_id,
                bucket=bucket,
                etag=verification.etag if verification.verified else None,
                evicted=evicted,
            )
        )
        if verification.verified or evicted:
            return  # an evicted file's row says so: there is nothing left to wait for
        if on_filesystem and verification.size is None:
            plan.waiting.append(f"waiting for {store.name} to store {pair.key}: {verification.reason}")
        elif on_filesystem:
            # A stored object unlike the file is no upload under way: shown as a failure until it is mended.
            plan.unsure.append(f"{store.name} holds another {pair.key}: {verification.reason}")
        else:
            # Nobody can upload a file that is gone: waiting would last for ever.
            plan.missing.append(
                f"no file {pair.local_path} ({pair.src_field}), and {store.name} does not hold it"
                f" (bucket {bucket}: {verification.reason})"
            )

    def _write(
        self, database: KeptConnection, connection: Any, writes: list[tuple[int, list[FileRow]]]
    ) -> dict[int, str]:
        import psycopg

        assert self._table is not None
        upsert = self._table.upsert
        try:
            with connection.transaction(), connection.cursor() as cursor:
                cursor.executemany(upsert, [row.values() for _, rows in writes for row in rows])
            return {}
        except psycopg.Error as exc:
            if not is_record_error(exc):
                raise
            if len(writes) == 1:
                return {writes[0][0]: database.refusal(exc, "the record's rows")}
        # Whose rows did the server refuse? Each record again in its own savepoint, in one transaction.
        refused: dict[int, str] = {}
        with connection.transaction():
            for index, rows in writes:
                try:
                    with connection.transaction(), connection.cursor() as cursor:
                        cursor.executemany(upsert, [row.values() for row in rows])
                except psycopg.Error as exc:
                    if not is_record_error(exc):
                        raise
                    refused[index] = database.refusal(exc, "the record's rows")
        return refused

    def _delete(self, plan: _Plan, gone: list[FileRow]) -> list[str]:
        """Delete the plan's local files; the rows of those now gone join ``gone``. Returns the failures."""
        kept: dict[str, str] = {}
        for path in dict.fromkeys(row.local_path for row in plan.rows):
            opened = plan.opened.get(path)
            if opened is None:
                continue  # not there when planned: deleted by an earlier attempt whose rows could not be updated
            try:
                if not delete_opened(opened):
                    continue  # gone since, or the name holds another file now: not the one verified
            except OSError as exc:
                kept[path] = f"cannot delete {path}: {exc.strerror or exc}"
                continue
            self._files_deleted += 1
            self.context.logger.debug(f"deleted {path}: stored and verified in {', '.join(self.params.file_storage)}")
        gone.extend(row for row in plan.rows if row.local_path not in kept and not row.evicted)
        return list(kept.values())

    def _mark_deleted(self, connection: Any, gone: list[FileRow]) -> None:
        assert self._table is not None
        with connection.transaction(), connection.cursor() as cursor:
            cursor.executemany(
                self._table.mark_deleted,
                [
                    {"local_path": row.local_path, "storage_type": row.storage_type, "robot_name": row.robot_name}
                    for row in gone
                ],
            )

    def _prepare_table(self, connection: Any) -> None:
        assert self._table is not None
        for change in self._table.prepare(connection):
            self.context.logger.info(f"{change} in {self.address}")


def _text(value: Any) -> str:
    """A record value as the table's TEXT columns hold it: absent is empty (the original panicked)."""
    if value is None:
        return ""
    return value if isinstance(value, str) else json.dumps(value, ensure_ascii=False)
