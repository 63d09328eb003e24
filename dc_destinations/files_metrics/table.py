"""The files_metrics table: one row per file and storage, created, upgraded and written in place.

The columns are the original plugin's, plus those its documentation listed but it never created
(``ignored``, ``created_at``) and those that make a row traceable and idempotent (``record_id``,
``bucket``, ``etag``, ``verified_at``). A unique index on ``(local_path, storage_type)`` lets every
write be an upsert: a record retried ten times while it waits for its upload still has one row per
file and storage, updated in place.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import asdict, dataclass
from typing import Any

from dc_core.destination import RetryableError
from dc_destinations.pgsql.connection import MAX_IDENTIFIER

# The original's DDL, with size widened to BIGINT (a 2 GiB video overflowed INTEGER) and the new columns.
_CREATE = """CREATE TABLE IF NOT EXISTS {table} (
    id SERIAL PRIMARY KEY,
    timestamp TIMESTAMP NOT NULL,
    robot_name TEXT NOT NULL,
    robot_id TEXT NOT NULL,
    group_name TEXT NOT NULL,
    duration FLOAT8,
    local_path TEXT NOT NULL,
    remote_path TEXT NOT NULL,
    uploaded BOOLEAN NOT NULL,
    on_filesystem BOOLEAN NOT NULL,
    deleted BOOLEAN NOT NULL,
    storage_type TEXT NOT NULL,
    content_type TEXT NOT NULL,
    size BIGINT NOT NULL,
    updated_at TIMESTAMP NOT NULL,
    ignored BOOLEAN NOT NULL DEFAULT false,
    created_at TIMESTAMP NOT NULL DEFAULT (now() AT TIME ZONE 'UTC'),
    record_id TEXT,
    bucket TEXT,
    etag TEXT,
    verified_at TIMESTAMP
)"""

# What a table made by the original lacks. created_at stays nullable there: the original's rows
# have no creation time, and the time of the upgrade would be a false one.
ADDED_COLUMNS = {
    "ignored": "BOOLEAN NOT NULL DEFAULT false",
    "created_at": "TIMESTAMP",
    "record_id": "TEXT",
    "bucket": "TEXT",
    "etag": "TEXT",
    "verified_at": "TIMESTAMP",
}

_CATALOG = """SELECT to_regclass(%(t)s) IS NOT NULL,
    ARRAY(SELECT attname::text FROM pg_attribute
           WHERE attrelid = to_regclass(%(t)s) AND attnum > 0 AND NOT attisdropped),
    EXISTS (SELECT 1 FROM pg_index i
             WHERE i.indrelid = to_regclass(%(t)s) AND i.indisunique AND i.indpred IS NULL AND i.indnatts = 2
               AND ARRAY(SELECT a.attname::text FROM pg_attribute a
                          WHERE a.attrelid = i.indrelid AND a.attnum = ANY(i.indkey) ORDER BY 1)
                   = ARRAY['local_path', 'storage_type'])"""

_NOW = "(now() AT TIME ZONE 'UTC')"

# Named placeholders: psycopg sends the values apart from the statement, whatever quotes or
# semicolons a path holds. The casts give NULLs a type where the server could not infer one.
_UPSERT = f"""INSERT INTO {{table}} AS t (
    timestamp, robot_name, robot_id, group_name, duration, local_path, remote_path, uploaded,
    on_filesystem, deleted, storage_type, content_type, size, updated_at, created_at, record_id,
    bucket, etag, verified_at)
VALUES (
    %(timestamp)s, %(robot_name)s, %(robot_id)s, %(group_name)s, %(duration)s::float8, %(local_path)s,
    %(remote_path)s, %(uploaded)s, %(on_filesystem)s, false, %(storage_type)s, %(content_type)s,
    COALESCE(%(size)s::bigint, 0), {_NOW}, {_NOW}, %(record_id)s, %(bucket)s, %(etag)s::text,
    CASE WHEN %(uploaded)s THEN {_NOW} END)
ON CONFLICT (local_path, storage_type) DO UPDATE SET
    timestamp = EXCLUDED.timestamp,
    robot_name = EXCLUDED.robot_name,
    robot_id = EXCLUDED.robot_id,
    group_name = EXCLUDED.group_name,
    duration = COALESCE(EXCLUDED.duration, t.duration),
    remote_path = EXCLUDED.remote_path,
    uploaded = EXCLUDED.uploaded,
    on_filesystem = EXCLUDED.on_filesystem,
    deleted = t.deleted AND NOT EXCLUDED.on_filesystem,
    content_type = EXCLUDED.content_type,
    size = COALESCE(%(size)s::bigint, t.size),
    updated_at = EXCLUDED.updated_at,
    record_id = EXCLUDED.record_id,
    bucket = EXCLUDED.bucket,
    etag = EXCLUDED.etag,
    verified_at = EXCLUDED.verified_at"""

_MARK_DELETED = f"""UPDATE {{table}} SET deleted = true, on_filesystem = false, updated_at = {_NOW}
WHERE local_path = %(local_path)s AND storage_type = %(storage_type)s"""


@dataclass(frozen=True)
class FileRow:
    """One file in one storage as the table records it; ``None`` keeps what the row already says."""

    timestamp: dt.datetime
    robot_name: str
    robot_id: str
    group_name: str
    duration: float | None
    local_path: str
    remote_path: str
    uploaded: bool
    on_filesystem: bool
    storage_type: str
    content_type: str
    size: int | None
    record_id: str
    bucket: str
    etag: str | None

    def values(self) -> dict[str, Any]:
        return asdict(self)


class FilesTable:
    """The statements of one table, named ``schema.table`` or ``table``."""

    def __init__(self, name: str) -> None:
        from psycopg import sql

        self.name = name
        self.identifier = sql.Identifier(*name.split("."))
        index = f"{name.rsplit('.', 1)[-1]}_local_path_storage_type"[:MAX_IDENTIFIER]
        self._index = sql.Identifier(index)
        self.upsert = sql.SQL(_UPSERT).format(table=self.identifier)
        self.mark_deleted = sql.SQL(_MARK_DELETED).format(table=self.identifier)

    def prepare(self, connection: Any) -> list[str]:
        """Create the table, or add to an existing one what it lacks; returns what was done, for the log.

        Checked in the catalog first, so a role allowed to write rows but not to alter the table
        works with a table that is already complete.
        """
        import psycopg
        from psycopg import sql

        found = connection.execute(_CATALOG, {"t": self.identifier.as_string(connection)}).fetchone()
        exists, columns, indexed = (bool(found[0]), set(found[1]), bool(found[2])) if found else (False, set(), False)
        missing = [column for column in ADDED_COLUMNS if column not in columns]
        if exists and indexed and not missing:
            return []
        try:
            with connection.transaction():
                connection.execute(sql.SQL(_CREATE).format(table=self.identifier))
                for column, definition in ADDED_COLUMNS.items():
                    connection.execute(
                        sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS {} " + definition).format(
                            self.identifier, sql.Identifier(column)
                        )
                    )
                connection.execute(
                    sql.SQL("CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} (local_path, storage_type)").format(
                        self._index, self.identifier
                    )
                )
        except psycopg.errors.UniqueViolation:
            raise RetryableError(self._duplicates_message()) from None
        if not exists:
            return [f"created table {self.name}"]
        done = [f"added columns {', '.join(missing)}"] if missing else []
        if not indexed:
            done.append("added a unique index on (local_path, storage_type)")
        return [f"upgraded table {self.name} (made by the original plugin): {'; '.join(done)}"]

    def _duplicates_message(self) -> str:
        table = self.name
        return (
            f"table {table} holds several rows for the same (local_path, storage_type), left by the original"
            " plugin's retries, so its unique index cannot be created: keep one row of each, e.g."
            f" DELETE FROM {table} a USING {table} b WHERE a.local_path = b.local_path"
            " AND a.storage_type = b.storage_type AND a.id < b.id; the records wait in the buffer meanwhile"
        )
