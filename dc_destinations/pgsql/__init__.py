"""PgSQL destination: each record a row of a PostgreSQL table, once.

A table DC creates has typed columns (``time timestamptz``, ``name``, ``robot_name``, ``run_id
bigint`` beside the original's ``tag`` and ``data jsonb``), the indexes a data team's queries need,
and optionally time partitions (table.py). A table that exists is used as it is: one of the
original's shape (Fluent Bit's ``pgsql`` output: ``tag``, ``time``, ``data``) gets only the
``record_id`` column and its unique index, the rest being a documented migration. A unique index
holding ``record_id`` (with robot, name and time in a partitioned table DC makes) makes a batch inserted again
after a failure whose outcome was unknown (the connection died during COMMIT) add nothing twice
(``ON CONFLICT DO NOTHING``), so the buffer's at-least-once delivery becomes exactly one row per record.

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
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import orjson

from dc_core.destination import Destination, OutgoingRecord, ProbeResult, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import compat_param, param
from dc_core.records import MalformedRecord
from dc_destinations.pgsql.connection import (
    KeptConnection,
    PostgresServerParams,
    is_record_error,
    keep_database,
    one_line,
    probe_table,
    require_psycopg,
    table_problem,
)
from dc_destinations.pgsql.table import (
    PARTITION_BY,
    TYPED_COLUMNS,
    Partitions,
    TableShape,
    add_record_id,
    create_typed,
    has_latest,
    latest_identifier,
    legacy_hint,
    not_partitioned_problem,
    period_start,
    read_shape,
)

_EPOCH = dt.datetime(1970, 1, 1)
_EPOCH_UTC = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
# A batch's rows: (index in the batch, the values of the columns written).
_Rows = list[tuple[int, tuple[Any, ...]]]
# A batch's records to insert: (index in the batch, the record, its JSON text).
_Pending = list[tuple[int, OutgoingRecord, str]]
# Partitions are made ahead and expired at most this often, besides at every new connection.
_MAINTENANCE_S = 3600.0
_INT8 = 2**63


@dataclass(frozen=True, kw_only=True, repr=False)
class PgSQLParams(PostgresServerParams):
    table: str = param("dc", check=table_problem, doc='Table of the rows ("schema.table" accepted); created if absent')
    partition_by: str = param(
        "none",
        choices=PARTITION_BY,
        doc="A table DC creates, partitioned by range of time: a partition per UTC day or ISO week; none: one table",
    )
    retention_days: int = param(
        0,
        minimum=0,
        maximum=36500,
        doc="Partitions whose whole period is older than this many days are dropped; 0: kept for ever",
    )
    value_keys: dict[str, str] = param(
        default_factory=dict,
        doc="Measurement name -> the top-level key of its records whose number DC writes in column value (a table"
        " DC creates has it, in its (robot_name, name, time) index): an aggregate of it reads the index only",
    )
    run_index: bool = param(
        True,
        doc="A table DC creates gets the index (robot_name, run_id, name, time): what is asked by run reads that"
        " run's rows only; false: none (inserts cost the server less, a query by run reads the robot's rows)",
    )
    latest_table: bool = param(
        False,
        doc="A table DC creates gets <table>_latest, each robot's latest record of each measurement, kept by a"
        " trigger of the table (PostgreSQL 14+): worth it with partition_by, whose skip scan probes each partition;"
        " false: not made (the trigger costs every insert; a plain table's skip scan answers)",
    )
    async_: bool = compat_param(
        False, "each batch is written by the destination's own sender thread", aliases=("async",)
    )
    min_pool_size: int | str = compat_param("1", "DC keeps one connection per destination")
    max_pool_size: int | str = compat_param("4", "DC keeps one connection per destination")
    cockroachdb: bool = compat_param(False, "DC writes PostgreSQL's SQL whatever the server")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.retention_days and self.partition_by == "none":
            raise ConfigError(
                "retention_days", "retention drops whole partitions: set partition_by (day or week), or 0 here"
            )

    def __repr__(self) -> str:
        # Written by hand: the generated repr would show `async_`, and the password must stay out.
        shown = ", ".join(f"{k}={v!r}" for k, v in vars(self).items() if k != "password")
        return f"PgSQLParams({shown})"


class PgSQL(Destination[PgSQLParams]):
    """Insert each record as a row (tag, time, data jsonb, record_id, name, robot_name, run_id) of a PostgreSQL
    table, once."""

    def __init__(self, context: Any, params: PgSQLParams) -> None:
        super().__init__(context, params)
        self._database: KeptConnection | None = None  # made by on_configure, connected by the first batch
        # The statements of the table's shape, made by _prepare_table on every new connection.
        self._shape: TableShape | None = None
        self._insert: Any = None
        self._load: Any = None  # COPY straight into the table, as text
        self._load_binary: Any = None  # the same, binary
        self._copy_types: list[str] | None = None
        self._stage: Any = None  # COPY into the staging table, then the INSERT … SELECT from it
        self._move: Any = None
        self._latest = False  # whether the table has its latest-row table (partitions expire in it too)
        # Whether the current connection has its staging table (a temporary table lives as long as
        # its session, so it is made again with every new connection).
        self._staging = False
        # Whether the table takes a COPY: tried again on every new connection (a table's row-level
        # security may have been switched off meanwhile); and whether it may be binary.
        self._direct = False
        self._binary = False
        self._partitions: Partitions | None = None
        self._maintained_at = 0.0
        self._hinted = False  # the hint to migrate a table of the original's shape: once
        self._run_id_told = False
        self._value_told = False
        self.address = ""

    def __repr__(self) -> str:
        return f"PgSQL({self.context.name!r}, {self.address or self.params.host!r})"

    # -- lifecycle -------------------------------------------------------------------------------
    def on_configure(self) -> None:
        require_psycopg(self.context.name, "PgSQL")
        p = self.params
        self._database = keep_database(
            self,
            p.server(),
            prepare=self._prepare_table,
            prepared=f"table {p.table}",
            section=f"destination_server.{self.context.name}",
        )
        self.address = self._database.address
        if p.partition_by != "none":
            self._partitions = Partitions(p.table, p.partition_by, p.retention_days)

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
        pending: _Pending = []
        rejected: dict[int, str] = {}
        for i, record in enumerate(batch):
            try:
                pending.append((i, record, record.to_json()))
            except MalformedRecord as exc:
                rejected[i] = f"not valid JSON: {exc}"
        if pending:
            rejected.update(database.run(lambda connection: self._insert_rows(database, connection, pending)))
        return SendOutcome(reject=rejected) if rejected else None

    def _rows(self, pending: _Pending) -> _Rows:
        """The values of the table's written columns, per record.

        Only a typed table reads the record's ``data``: a record from the buffer holds its JSON text
        and parses it on first read, which a table of the original's shape never needs.
        """
        shape = self._shape
        assert shape is not None, "rows before the table was prepared"
        tag, key = self.context.name, self.params.timestamp_key
        # The original's column holds UTC without a zone: a naive value, which no session time zone
        # shifts (an aware one would be converted to the session's zone).
        aware = shape.columns.get("time") != "timestamp without time zone"
        if not shape.typed:
            return [(i, (tag, record_time(r, key, aware), text, r.record_id)) for i, r, text in pending]
        rows: _Rows = []
        run_id = self._run_id
        value_keys = self.params.value_keys if shape.has_value else None
        for i, record, text in pending:
            data = _top_level(record, text)
            name, robot = data.get("name"), data.get("robot_name")
            values: tuple[Any, ...] = (
                tag,
                record_time(record, key, aware)
                if key
                else _EPOCH_UTC + dt.timedelta(microseconds=record.stamp_ns // 1000),
                text,
                record.record_id,
                name if isinstance(name, str) else None,
                robot if isinstance(robot, str) else None,
                run_id(data.get("run_id")),
            )
            if value_keys is not None:
                values = (*values, _number(data.get(value_keys[name]) if name in value_keys else None))
            rows.append((i, values))
        return rows

    def _run_id(self, value: Any) -> int | None:
        """A record's run_id as the bigint column holds it: DC's counter; None for anything else."""
        if isinstance(value, str) and value.isascii() and value.isdigit():
            number = int(value)
        elif isinstance(value, int) and not isinstance(value, bool):
            number = value
        else:
            if value is not None and not self._run_id_told:
                self._run_id_told = True
                self.context.logger.warning(
                    f"run_id {str(value)[:40]!r} is not a counter: the run_id column stays NULL for such records"
                    " (data->>'run_id' holds it); the measurement server's run_id.counter gives counters"
                )
            return None
        return number if -_INT8 <= number < _INT8 else None

    def _insert_rows(self, database: KeptConnection, connection: Any, pending: _Pending) -> dict[int, str]:
        import psycopg

        rows = self._rows(pending)  # here: the shape is that of the table this connection prepared
        if self._partitions is not None:
            self._maintain_partitions(connection, {self._period(values[1]) for _, values in rows})
        if self._direct:
            try:
                # The connection is in autocommit: this COPY commits alone, before its answer.
                with (
                    connection.cursor() as cursor,
                    cursor.copy(self._load_binary if self._binary else self._load) as copy,
                ):
                    if self._binary:
                        copy.set_types(self._copy_types)
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

    def _period(self, moment: dt.datetime) -> dt.date:
        return period_start(moment, self.params.partition_by)

    def _maintain_partitions(self, connection: Any, starts: set[dt.date]) -> None:
        """The partitions of the batch's times made when missing; those ahead made and the expired dropped
        at most every _MAINTENANCE_S (and on every new connection)."""
        partitions = self._partitions
        assert partitions is not None
        now = time.monotonic()
        if not self._maintained_at or now - self._maintained_at >= _MAINTENANCE_S:
            today = dt.datetime.now(dt.UTC).date()
            partitions.expire(connection, self._table(), today)
            if partitions.dropped:
                self.context.logger.info(
                    f"dropped partitions {', '.join(partitions.dropped)} of table {self.params.table}"
                    f" (older than retention_days {self.params.retention_days})"
                )
                self._expire_latest(connection, partitions.dropped_before)
            starts = starts | partitions.ahead(today)
            self._maintained_at = now
        if starts - partitions.known:
            partitions.ensure(connection, self._table(), starts)
            if partitions.made:
                self.context.logger.info(f"made partitions {', '.join(partitions.made)} of table {self.params.table}")

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
        """The table made or checked, and the statements of its shape, on every new connection.

        Checked in the catalog first: a role allowed to insert into an existing table but not to
        create anything still works.
        """
        self._staging = self._direct = self._binary = False
        p = self.params
        table = self._table()
        shape = read_shape(connection, table)
        if shape is None:
            create_typed(connection, table, p.table, p.partition_by, latest=p.latest_table, run_index=p.run_index)
            self.context.logger.info(
                f"table {p.table} ready in {self.address} ({', '.join(TYPED_COLUMNS)}"
                + (f"; partitioned by {p.partition_by})" if p.partition_by != "none" else ")")
            )
            shape = read_shape(connection, table)
            assert shape is not None
        elif shape.conflict_key is None:
            # A table made by the original, or by hand: the column and index that make a retried
            # batch add nothing twice.
            add_record_id(connection, table, p.table, shape.partitioned)
            self.context.logger.info(f"table {p.table} of {self.address}: record_id column and unique index added")
            shape = read_shape(connection, table)
            assert shape is not None
        if not shape.typed and not self._hinted:
            self._hinted = True
            self.context.logger.warning(legacy_hint(p.table))
        if p.partition_by != "none" and not shape.partitioned:
            raise not_partitioned_problem(p.table, self.address)
        self._shape = shape
        self._statements(shape)
        self._latest = shape.typed and has_latest(connection, p.table)
        if p.value_keys and not shape.has_value and not self._value_told:
            self._value_told = True
            self.context.logger.warning(
                f"table {p.table} of {self.address} has no value column (double precision): value_keys unused;"
                " docs/data-model.md#a-measurements-value-in-the-index says how to add it"
            )
        self._staging = self._make_staging_table(connection, shape)
        self._direct = True
        self._copy_types = shape.copy_types()
        self._binary = self._copy_types is not None
        if self._binary:
            connection.adapters.register_dumper(None, json_text_binary_dumper())
        self._maintained_at = 0.0  # partitions checked again on a new connection

    def _statements(self, shape: TableShape) -> None:
        from psycopg import sql

        table, staging = self._table(), self._staging_table()
        columns = sql.SQL(", ").join(map(sql.Identifier, shape.written))
        key = shape.conflict_key or "record_id"
        conflict = sql.SQL(" ON CONFLICT (" + key + ") DO NOTHING")
        values = sql.SQL(", ").join(
            sql.SQL("%s::jsonb") if column == "data" else sql.SQL("%s") for column in shape.written
        )
        self._insert = sql.SQL("INSERT INTO {} ({}) VALUES ({})").format(table, columns, values) + conflict
        self._load = sql.SQL("COPY {} ({}) FROM STDIN").format(table, columns)
        self._load_binary = sql.SQL("COPY {} ({}) FROM STDIN (FORMAT BINARY)").format(table, columns)
        self._stage = sql.SQL("COPY {} ({}) FROM STDIN").format(staging, columns)
        move = sql.SQL("INSERT INTO {} ({}) SELECT {} FROM {}")
        self._move = move.format(table, columns, columns, staging) + conflict

    def _expire_latest(self, connection: Any, before: dt.date | None) -> None:
        """The latest-row table's rows of dropped partitions removed with them: it answers what the
        records table holds."""
        from psycopg import sql

        if not self._latest or before is None:
            return
        with connection.transaction():
            connection.execute(
                sql.SQL("DELETE FROM {} WHERE time < {}").format(
                    latest_identifier(self.params.table), sql.Literal(f"{before} 00:00:00+00")
                )
            )

    def _make_staging_table(self, connection: Any, shape: TableShape) -> bool:
        """This session's staging table, with the types of the table's written columns; False if not allowed.

        The types come from the catalog rather than ``CREATE TABLE … AS SELECT`` from the table,
        which would need the right to read it; a table made by hand with other types (``json``,
        ``varchar(n)``) refuses in COPY what it would refuse in an INSERT, and the row-by-row pass
        finds which rows.
        """
        import psycopg
        from psycopg import sql

        found = shape.columns
        written = shape.written
        if any(column not in found for column in written) or shape.conflict_key is None:
            return False  # a table without them: the INSERT says what is wrong, as it always did
        definition = sql.SQL(", ").join(
            sql.SQL("{} {}").format(sql.Identifier(column), sql.SQL(found[column])) for column in written
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


def _top_level(record: OutgoingRecord, text: str) -> dict[str, Any]:
    """The record's top-level keys, for the typed columns: its ``data`` when parsed already, else its JSON
    text read by orjson alone.

    A record from the buffer parses its text on first read, with checks that keep every value as
    DC would write it back (parse_record): a third of the typed table's insert cost, for three
    strings and a counter that read the same either way (an integer beyond 64 bits, which orjson
    reads as a float, is not a counter the column holds in both).
    """
    data = record.__dict__.get("data")
    if data is not None:
        return data  # type: ignore[no-any-return]
    try:
        found = orjson.loads(text)
    except orjson.JSONDecodeError:
        return record.data  # what is wrong with it, said the usual way
    return found if isinstance(found, dict) else record.data


def _number(value: Any) -> float | None:
    """A JSON number as float8 holds it; None for anything else (a bool is no number here)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) < 1.7e308:
        return float(value)
    return None


def record_time(record: OutgoingRecord, timestamp_key: str = "", aware: bool = False) -> dt.datetime:
    """The record's time as a naive UTC timestamp (``aware``: with its UTC zone): ``timestamp_key``'s value
    when readable, else its stamp.

    The value may be epoch seconds (``time_format: double``) or ISO 8601 text (UTC without an offset).
    """
    if timestamp_key:
        moment = _keyed_time(record, timestamp_key)
        if moment is not None:
            return moment.replace(tzinfo=dt.UTC) if aware else moment
    # Made from the right epoch at once: a replace() per row was a measurable part of the insert's CPU.
    return (_EPOCH_UTC if aware else _EPOCH) + dt.timedelta(microseconds=record.stamp_ns // 1000)


def _keyed_time(record: OutgoingRecord, timestamp_key: str) -> dt.datetime | None:
    """``timestamp_key``'s value as a naive UTC timestamp; None when absent or unreadable (the stamp then,
    rather than refusing a record for its time)."""
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
        pass
    return None
