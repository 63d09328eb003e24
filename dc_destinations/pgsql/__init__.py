"""PgSQL destination: each record a row ``(tag, time, data jsonb, record_id)`` of a PostgreSQL table.

The table is the original's (Fluent Bit's ``pgsql`` output: ``tag``, ``time``, ``data``) plus a
``record_id`` column with a unique index: a batch inserted again after a failure whose outcome was
unknown (the connection died during COMMIT) adds nothing twice (``ON CONFLICT DO NOTHING``), so the
buffer's at-least-once delivery becomes exactly one row per record.

A batch is one ``COPY`` of its rows straight into the table, outside any transaction block: the
statement is its own transaction, committed before the server answers it, so a batch is all in
or all out, and it costs the server what a plain COPY does. It fails on the unique index when a
record of it is there already (a batch sent again after the connection died during its commit, or
a record twice in the batch): the batch is then inserted the careful way, in one transaction:
``COPY`` into a temporary table of the session (emptied at each commit), then ``INSERT … SELECT …
ON CONFLICT DO NOTHING`` from it, which adds only the rows not there yet. When the server refuses
the batch because of its data (a JSON jsonb cannot hold, a value a constraint forbids), the batch
is inserted again row by row, each row in its own savepoint: the refused rows go to the dead
letters with the server's message, the others are committed. A role that may not create temporary
tables uses psycopg's pipelined ``executemany`` for the careful way, and a table COPY may not load
(row-level security) gets the careful way for every batch. Lost or refused connections, a server
shutting down, wrong credentials and anything else are retried: they are about the server, not the
records. The password is never logged nor part of an error message. Connecting, keeping the
connection and wording its failures live in ``connection.py``, which the FilesMetrics destination
shares.
"""

from __future__ import annotations

import datetime as dt
import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, SendOutcome
from dc_core.params import compat_param, param
from dc_core.records import MalformedRecord
from dc_destinations.pgsql.connection import (
    MAX_IDENTIFIER,
    KeptConnection,
    PostgresServerParams,
    is_record_error,
    keep_database,
    one_line,
    probe_table,
    require_psycopg,
    table_problem,
)

_EPOCH = dt.datetime(1970, 1, 1)
_COLUMNS = ("tag", "time", "data", "record_id")
# A batch's rows: (index in the batch, the values of _COLUMNS).
_Rows = list[tuple[int, tuple[str, dt.datetime, str, str]]]
# The column types of a table DC creates (a `tag` of type text too): a COPY into such a table can be
# binary, which costs the client and the server about half the CPU of text (docs/performance.md).
# Any other types (a table made by hand: json, timestamptz, varchar(n)) get text, converted by the
# server as an INSERT's values would be.
_BINARY_TYPES = (
    ("character varying", "text"),
    ("timestamp without time zone",),
    ("jsonb",),
    ("text",),
)


@dataclass(frozen=True, kw_only=True, repr=False)
class PgSQLParams(PostgresServerParams):
    table: str = param("dc", check=table_problem, doc='Table of the rows ("schema.table" accepted); created if absent')
    async_: bool = compat_param(
        False, "each batch is written by the destination's own sender thread", aliases=("async",)
    )
    min_pool_size: int | str = compat_param("1", "DC keeps one connection per destination")
    max_pool_size: int | str = compat_param("4", "DC keeps one connection per destination")
    cockroachdb: bool = compat_param(False, "DC writes PostgreSQL's SQL whatever the server")

    def __repr__(self) -> str:
        # Written by hand: the generated repr would show `async_`, and the password must stay out.
        shown = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if k != "password")
        return f"PgSQLParams({shown})"


class PgSQL(Destination[PgSQLParams]):
    """Insert each record as a row (tag, time, data jsonb, record_id) of a PostgreSQL table, once."""

    def __init__(self, context: Any, params: PgSQLParams) -> None:
        super().__init__(context, params)
        self._database: KeptConnection | None = None  # made by on_configure, connected by the first batch
        self._insert: Any = None
        self._load: Any = None  # COPY straight into the table, as text
        self._load_binary: Any = None  # the same, binary
        self._stage: Any = None  # COPY into the staging table, then the INSERT … SELECT from it
        self._move: Any = None
        # Whether the current connection has its staging table (a temporary table lives as long as
        # its session, so it is made again with every new connection).
        self._staging = False
        # Whether the table takes a COPY: tried again on every new connection (a table's row-level
        # security may have been switched off meanwhile); and whether it may be binary.
        self._direct = False
        self._binary = False
        self.address = ""

    def __repr__(self) -> str:
        return f"PgSQL({self.context.name!r}, {self.address or self.params.host!r})"

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        require_psycopg(self.context.name, "PgSQL")
        from psycopg import sql

        self._database = keep_database(
            self,
            self.params.server(),
            prepare=self._prepare_table,
            prepared=f"table {self.params.table}",
            section=f"destination_server.{self.context.name}",
        )
        self.address = self._database.address
        self._insert = sql.SQL(
            "INSERT INTO {} (tag, time, data, record_id) VALUES (%s, %s, %s::jsonb, %s)"
            " ON CONFLICT (record_id) DO NOTHING"
        ).format(self._table())
        self._load = sql.SQL("COPY {} (tag, time, data, record_id) FROM STDIN").format(self._table())
        self._load_binary = sql.SQL("COPY {} (tag, time, data, record_id) FROM STDIN (FORMAT BINARY)").format(
            self._table()
        )
        staging = self._staging_table()
        self._stage = sql.SQL("COPY {} (tag, time, data, record_id) FROM STDIN").format(staging)
        self._move = sql.SQL(
            "INSERT INTO {} (tag, time, data, record_id) SELECT tag, time, data, record_id FROM {}"
            " ON CONFLICT (record_id) DO NOTHING"
        ).format(self._table(), staging)

    def probe(self) -> ProbeResult:
        assert self._database is not None, "probe() before on_configure()"
        return probe_table(self._database, self._table(), self.params.table)

    def on_activate(self) -> None:
        # The connection opens with the first batch, in the sender's thread: a database that is down
        # must not hold up activation.
        self.context.logger.info(f"inserting into table {self.params.table} of {self.address}")

    # -- sending -----------------------------------------------------------------------------------
    def send(self, batch: Sequence[OutgoingRecord]) -> SendOutcome | None:
        assert self._database is not None, "send() before on_configure()"
        database = self._database
        tag = self.context.name
        rows: _Rows = []
        rejected: dict[int, str] = {}
        for i, record in enumerate(batch):
            try:
                rows.append(
                    (i, (tag, record_time(record, self.params.timestamp_key), record.to_json(), record.record_id))
                )
            except MalformedRecord as exc:
                rejected[i] = f"not valid JSON: {exc}"
        if rows:
            rejected.update(database.run(lambda connection: self._insert_rows(database, connection, rows)))
        return SendOutcome(reject=rejected) if rejected else None

    def _insert_rows(self, database: KeptConnection, connection: Any, rows: _Rows) -> dict[int, str]:
        import psycopg

        if self._direct:
            try:
                # The connection is in autocommit: this COPY commits alone, before its answer.
                with (
                    connection.cursor() as cursor,
                    cursor.copy(self._load_binary if self._binary else self._load) as copy,
                ):
                    if self._binary:
                        copy.set_types(["varchar", "timestamp", "jsonb", "text"])
                    for _, values in rows:
                        copy.write_row(values)
                return {}
            except psycopg.errors.UniqueViolation:
                pass  # some rows are there already: the way that skips them
            except psycopg.errors.FeatureNotSupported as exc:
                self._direct = False
                self.context.logger.warning(
                    f"table {self.params.table} of {self.address} takes no COPY ({one_line(str(exc))}): "
                    "inserting with INSERT … ON CONFLICT, which costs the server more CPU"
                )
            except psycopg.Error as exc:
                if not is_record_error(exc):
                    raise
                return self._refused(database, connection, rows, exc)
        try:
            with connection.transaction(), connection.cursor() as cursor:
                if self._staging:
                    with cursor.copy(self._stage) as copy:
                        for _, values in rows:
                            copy.write_row(values)
                    cursor.execute(self._move)
                else:
                    cursor.executemany(self._insert, [values for _, values in rows])
            return {}
        except psycopg.Error as exc:
            if not is_record_error(exc):
                raise
            return self._refused(database, connection, rows, exc)

    def _refused(self, database: KeptConnection, connection: Any, rows: _Rows, exc: Exception) -> dict[int, str]:
        """The server refused a record of the batch: which one, when it is alone; else each row on its own."""
        if len(rows) == 1:
            return {rows[0][0]: database.refusal(exc)}
        return self._insert_one_by_one(database, connection, rows)

    def _insert_one_by_one(self, database: KeptConnection, connection: Any, rows: _Rows) -> dict[int, str]:
        """Which rows does the server refuse? Each again in its own savepoint, in one transaction."""
        import psycopg

        rejected: dict[int, str] = {}
        with connection.transaction():
            for index, values in rows:
                try:
                    with connection.transaction():
                        connection.execute(self._insert, values)
                except psycopg.Error as exc:
                    if not is_record_error(exc):
                        raise
                    rejected[index] = database.refusal(exc)
        return rejected

    # -- table -------------------------------------------------------------------------------------
    def _prepare_table(self, connection: Any) -> None:
        self._staging = self._direct = self._binary = False
        self._ensure_table(connection)
        types = self._column_types(connection)
        self._staging = self._make_staging_table(connection, types)
        self._direct = True
        self._binary = len(types) == len(_COLUMNS) and all(
            types[column] in allowed for column, allowed in zip(_COLUMNS, _BINARY_TYPES, strict=True)
        )
        if self._binary:
            connection.adapters.register_dumper(None, json_text_binary_dumper())

    def _ensure_table(self, connection: Any) -> None:
        """The table, its record_id column and their unique index, created when missing.

        Checked in the catalog first: a role allowed to insert into an existing table but not to
        create anything still works.
        """
        from psycopg import sql

        table = self._table()
        name = self.params.table
        found = connection.execute(
            """SELECT to_regclass(%(t)s) IS NOT NULL,
                      EXISTS (SELECT 1 FROM pg_index i JOIN pg_attribute a
                                ON a.attrelid = i.indrelid AND a.attnum = i.indkey[0]
                               WHERE i.indrelid = to_regclass(%(t)s) AND i.indisunique AND i.indnatts = 1
                                 AND a.attname = 'record_id')""",
            {"t": table.as_string(connection)},
        ).fetchone()
        if found is not None and found[1]:
            return
        index = sql.Identifier(f"{name.rsplit('.', 1)[-1]}_record_id"[:MAX_IDENTIFIER])
        with connection.transaction():
            connection.execute(
                sql.SQL(
                    "CREATE TABLE IF NOT EXISTS {} (tag varchar, time timestamp, data jsonb, record_id text)"
                ).format(table)
            )
            # A table made by the original (or by hand) gets the column and index it lacks.
            connection.execute(sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS record_id text").format(table))
            connection.execute(sql.SQL("CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} (record_id)").format(index, table))
        self.context.logger.info(f"table {name} ready in {self.address} (tag, time, data, record_id)")

    def _column_types(self, connection: Any) -> dict[str, str]:
        """The types of the table's four columns (those it has), as ``format_type`` writes them."""
        return dict(
            connection.execute(
                """SELECT attname, format_type(atttypid, atttypmod) FROM pg_attribute
                    WHERE attrelid = to_regclass(%s) AND attnum > 0 AND NOT attisdropped
                      AND attname IN ('tag', 'time', 'data', 'record_id')""",
                (self._table().as_string(connection),),
            ).fetchall()
        )

    def _make_staging_table(self, connection: Any, found: dict[str, str]) -> bool:
        """This session's staging table, with the types of the table's four columns; False if not allowed.

        The types come from the catalog rather than ``CREATE TABLE … AS SELECT`` from the table,
        which would need the right to read it; a table made by hand with other types (``json``,
        ``varchar(n)``) refuses in COPY what it would refuse in an INSERT, and the row-by-row pass
        finds which rows.
        """
        import psycopg
        from psycopg import sql

        if any(column not in found for column in _COLUMNS):
            return False  # a table without them: the INSERT says what is wrong, as it always did
        definition = sql.SQL(", ").join(
            sql.SQL("{} {}").format(sql.Identifier(column), sql.SQL(found[column])) for column in _COLUMNS
        )
        try:
            connection.execute(
                sql.SQL("CREATE TEMPORARY TABLE {} ({}) ON COMMIT DELETE ROWS").format(
                    self._staging_table(), definition
                )
            )
        except psycopg.errors.InsufficientPrivilege as exc:
            self.context.logger.warning(
                f"no temporary table allowed in {self.address} ({one_line(str(exc))}): "
                "inserting with INSERT … VALUES, which costs the client more CPU"
            )
            return False
        return True

    def _table(self) -> Any:
        from psycopg import sql

        return sql.Identifier(*self.params.table.split("."))

    def _staging_table(self) -> Any:
        from psycopg import sql

        # An unqualified name finds a temporary table first: the staging table must never take
        # the name of the table it feeds.
        name = "dc_staging" if self.params.table.rsplit(".", 1)[-1] != "dc_staging" else "dc_staging_2"
        return sql.Identifier("pg_temp", name)


@functools.cache
def json_text_binary_dumper() -> type:
    """psycopg dumper of JSON text (a str) as jsonb's binary form: a version byte, then the text.

    Made at first use: psycopg is an optional dependency. Registered for jsonb's oid only, it is
    what ``set_types`` picks for the data column, and nothing else uses it.
    """
    from psycopg import postgres
    from psycopg.adapt import Dumper
    from psycopg.pq import Format

    class JsonTextBinaryDumper(Dumper):
        format = Format.BINARY
        oid = postgres.types["jsonb"].oid

        def dump(self, obj: Any) -> bytes:
            return b"\x01" + str(obj).encode("utf-8")

    return JsonTextBinaryDumper


def record_time(record: OutgoingRecord, timestamp_key: str = "") -> dt.datetime:
    """The record's time as a naive UTC timestamp: ``timestamp_key``'s value when readable, else its stamp.

    The value may be epoch seconds (``time_format: double``) or ISO 8601 text (UTC without an offset).
    """
    if timestamp_key:
        value = record.data.get(timestamp_key)
        try:
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                return _EPOCH + dt.timedelta(seconds=float(value))
            if isinstance(value, str):
                moment = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
                if moment.tzinfo is not None:
                    moment = moment.astimezone(dt.UTC).replace(tzinfo=None)
                return moment
        except (ValueError, OverflowError):
            pass  # unreadable: the stamp, rather than refusing a record for its time
    return _EPOCH + dt.timedelta(microseconds=record.stamp_ns // 1000)
