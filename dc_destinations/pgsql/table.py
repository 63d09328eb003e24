"""The records table of the PgSQL destination: its shape, creating it, and its time partitions.

A table DC creates has typed columns a data team queries without digging into ``data``:
``time timestamptz NOT NULL``, ``name``, ``robot_name`` and ``run_id bigint`` (filled by DC at insert
from the record's top-level keys), an index on ``(robot_name, name, time)`` and a BRIN index on
``time``; with ``partition_by`` it is partitioned by range of ``time`` (a partition a UTC day or ISO
week), partitions made ahead and dropped after ``retention_days``.

A table that exists is used as it is: one of the original's shape (``tag, time timestamp, data,
record_id``) keeps getting those four columns, and DC says once how to migrate it
(docs/data-model.md); it never changes its columns' types or partitions it by itself.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from typing import Any

from dc_core.destination import ConfigurationProblem
from dc_destinations.pgsql.connection import MAX_IDENTIFIER

PARTITION_BY = ("none", "day", "week")
# Partitions made beyond the current one: records of the next periods never wait for a partition,
# and a robot whose clock runs a little ahead still finds one.
PARTITIONS_AHEAD = 2
MIGRATION_DOC = "docs/data-model.md#migrating-a-table-of-the-originals-shape"
LATEST_SUFFIX = "_latest"

LEGACY_COLUMNS = ("tag", "time", "data", "record_id")
TYPED_COLUMNS = ("tag", "time", "data", "record_id", "name", "robot_name", "run_id")
# A typed table DC makes has it; one made before it (or by hand) is typed without it.
VALUE_COLUMN = "value"
# The types of the columns a binary COPY may write, as format_type spells them, per column.
_BINARY_TYPES = {
    "tag": ("character varying", "text"),
    "time": ("timestamp without time zone", "timestamp with time zone"),
    "data": ("jsonb",),
    "record_id": ("text",),
    "name": ("text",),
    "robot_name": ("text",),
    "run_id": ("bigint",),
    "value": ("double precision",),
}
_COPY_TYPES = {
    "character varying": "varchar",
    "text": "text",
    "timestamp without time zone": "timestamp",
    "timestamp with time zone": "timestamptz",
    "jsonb": "jsonb",
    "bigint": "int8",
    "double precision": "float8",
}

_CATALOG = """SELECT c.relkind,
    ARRAY(SELECT ARRAY[attname::text, format_type(atttypid, atttypmod)] FROM pg_attribute
           WHERE attrelid = c.oid AND attnum > 0 AND NOT attisdropped),
    ARRAY(SELECT ARRAY(SELECT a.attname::text FROM unnest(i.indkey) WITH ORDINALITY AS k (attnum, n)
                        JOIN pg_attribute a ON a.attrelid = i.indrelid AND a.attnum = k.attnum
                        WHERE k.n <= i.indnkeyatts ORDER BY 1)::text
           FROM pg_index i WHERE i.indrelid = c.oid AND i.indisunique AND i.indpred IS NULL)
FROM pg_class c WHERE c.oid = to_regclass(%(t)s)"""


@dataclass(frozen=True)
class TableShape:
    """What the catalog says of an existing table; ``columns``: name -> type as format_type writes it."""

    partitioned: bool
    columns: dict[str, str]
    unique_keys: frozenset[str]  # each unique index's key columns (not INCLUDEd ones), sorted, as a text[] prints

    @property
    def typed(self) -> bool:
        """DC's shape for new tables: the typed columns are there and time has its zone."""
        return all(c in self.columns for c in TYPED_COLUMNS) and self.columns["time"] == "timestamp with time zone"

    @property
    def written(self) -> tuple[str, ...]:
        if not self.typed:
            return LEGACY_COLUMNS
        return (*TYPED_COLUMNS, VALUE_COLUMN) if self.has_value else TYPED_COLUMNS

    @property
    def has_value(self) -> bool:
        return self.columns.get(VALUE_COLUMN) == "double precision"

    @property
    def conflict_key(self) -> str | None:
        """The unique index a retried batch meets: record_id alone, with time in a partitioned table, or
        with the team's key (create_typed)."""
        for key in ("{record_id}", "{record_id,time}"):
            if key in self.unique_keys:
                return key.strip("{}").replace(",", ", ")
        if "{name,record_id,robot_name,time}" in self.unique_keys:
            return "robot_name, name, time, record_id"  # a partitioned table DC made on PostgreSQL 15+
        return None

    def copy_types(self) -> list[str] | None:
        """The types of a binary COPY of the written columns; None when a type calls for a text COPY."""
        written = self.written
        if any(self.columns.get(c) not in _BINARY_TYPES[c] for c in written):
            return None
        return [_COPY_TYPES[self.columns[c]] for c in written]


def read_shape(connection: Any, table: Any) -> TableShape | None:
    found = connection.execute(_CATALOG, {"t": table.as_string(connection)}).fetchone()
    if found is None:
        return None
    relkind, columns, unique = found
    return TableShape(relkind == "p", {name: kind for name, kind in columns}, frozenset(unique))


def create_typed(
    connection: Any, table: Any, name: str, partition_by: str, *, latest: bool = True, run_index: bool = True
) -> None:
    """The table of DC's shape, with its indexes (``run_index``: with the run's; ``latest``: with its
    latest-row table), in one transaction (IF NOT EXISTS: several robots may make it at once)."""
    from psycopg import sql

    base = name.rsplit(".", 1)[-1]
    partitioned = partition_by != "none"
    with connection.transaction():
        connection.execute(
            sql.SQL(
                "CREATE TABLE IF NOT EXISTS {} (tag text, time timestamptz NOT NULL, data jsonb,"
                " record_id text NOT NULL, name text, robot_name text, run_id bigint, value double precision)"
                + (" PARTITION BY RANGE (time)" if partitioned else "")
            ).format(table)
        )
        if partitioned and connection.info.server_version >= 150000:
            # A unique index of a partitioned table must hold the partition key, time: then one btree
            # is both the team's (robot_name, name, time) index and the key a retried batch meets.
            # Robot and name come from the record's text, the same in every copy of it; time, like
            # the (record_id, time) key it replaces, from its stamp or timestamp_key (a copy stored
            # twice by NATS and ingested with two stamps is two rows, in both). NULLS NOT DISTINCT:
            # a record without robot or name is met too. One btree and its disk space where two were;
            # the CPU per insert measured the same within the noise (docs/performance.md). value
            # INCLUDEd: an aggregate of a measurement's value_keys number is an index-only scan.
            connection.execute(
                sql.SQL(
                    "CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} (robot_name, name, time, record_id) INCLUDE (value)"
                    " NULLS NOT DISTINCT"
                ).format(_index_name(base, "robot_name_time"), table)
            )
        else:
            # Not partitioned: record_id alone is unique, whatever time a copy of the record carries.
            unique = "record_id, time" if partitioned else "record_id"
            connection.execute(
                sql.SQL("CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} (" + unique + ")").format(
                    _index_name(base, "record_id"), table
                )
            )
            connection.execute(
                sql.SQL("CREATE INDEX IF NOT EXISTS {} ON {} (robot_name, name, time) INCLUDE (value)").format(
                    _index_name(base, "robot_name_time"), table
                )
            )
        # The path of a robot in a run (and anything else asked by run) reads only that run's rows.
        # A btree whose keys land all over it, as the team's: the largest part of the insert's cost
        # after that one (docs/performance.md), hence run_index for a team that never asks by run.
        if run_index:
            connection.execute(
                sql.SQL("CREATE INDEX IF NOT EXISTS {} ON {} (robot_name, run_id, name, time)").format(
                    _index_name(base, "robot_run_time"), table
                )
            )
        connection.execute(
            sql.SQL("CREATE INDEX IF NOT EXISTS {} ON {} USING brin (time)").format(
                _index_name(base, "time_brin"), table
            )
        )
        if latest and connection.info.server_version >= 140000:  # CREATE OR REPLACE TRIGGER
            create_latest(connection, table, name)


def latest_name(name: str, suffix: str = LATEST_SUFFIX) -> str:
    """The latest-row table of records table ``name`` ("schema.table" kept), or another object named after it
    with ``suffix``, within PostgreSQL's identifier length."""
    schema, dot, base = name.rpartition(".")
    return f"{schema}{dot}{base[: MAX_IDENTIFIER - len(suffix)]}{suffix}"


def create_latest(connection: Any, table: Any, name: str) -> None:
    """Each robot's latest record of each measurement, one row a pair, kept by a trigger of the records table.

    The question "what did each robot last say" answered from a table of a row per pair: a skip
    scan of the records table probes each of its partitions once per pair and reads a heap page
    per row found (45-105 ms at 100 robots x 1 day; docs/data-model.md). A statement trigger
    rather than the destination's own upsert: no round trip more per batch (a robot's link may be
    slow), the rows a statement really inserted (not those ON CONFLICT skipped or the server
    refused), whoever inserts them (dc ingest, a backfill).
    """
    from psycopg import sql

    def identifier(suffix: str) -> Any:
        return sql.Identifier(*latest_name(name, suffix).split("."))

    latest = identifier(LATEST_SUFFIX)
    # Fill factor 70: an upsert rewrites a row in place of itself on the same page (a HOT update,
    # the key's index untouched) as long as the page has room.
    connection.execute(
        sql.SQL(
            "CREATE TABLE IF NOT EXISTS {} (robot_name text NOT NULL, name text NOT NULL,"
            " time timestamptz NOT NULL, data jsonb, record_id text NOT NULL, PRIMARY KEY (robot_name, name))"
            " WITH (fillfactor = 70)"
        ).format(latest)
    )
    # The pairs in one order: two statements upserting the same pairs at once wait for each other
    # rather than deadlock. A row is replaced by a record as late or later only (a robot's backlog
    # delivered after newer records replaces nothing).
    body = sql.SQL(
        "BEGIN INSERT INTO {} AS l (robot_name, name, time, data, record_id)"
        " SELECT DISTINCT ON (robot_name, name) robot_name, name, time, data, record_id FROM dc_inserted"
        " WHERE robot_name IS NOT NULL AND name IS NOT NULL ORDER BY robot_name, name, time DESC"
        " ON CONFLICT (robot_name, name) DO UPDATE"
        " SET time = EXCLUDED.time, data = EXCLUDED.data, record_id = EXCLUDED.record_id"
        " WHERE l.time <= EXCLUDED.time; RETURN NULL; END"
    ).format(latest)
    function = identifier("_keep_latest")
    # SET search_path FROM CURRENT: the session that inserts (any role, any search_path) upserts
    # into the latest-row table of the records table's schema, the one current here.
    connection.execute(
        sql.SQL(
            "CREATE OR REPLACE FUNCTION {}() RETURNS trigger LANGUAGE plpgsql SET search_path FROM CURRENT AS {}"
        ).format(function, sql.Literal(body.as_string(connection)))
    )
    connection.execute(
        sql.SQL(
            "CREATE OR REPLACE TRIGGER keep_latest AFTER INSERT ON {} REFERENCING NEW TABLE AS dc_inserted"
            " FOR EACH STATEMENT EXECUTE FUNCTION {}()"
        ).format(table, function)
    )


def has_latest(connection: Any, name: str) -> bool:
    found = connection.execute("SELECT to_regclass(%s)", (latest_identifier(name).as_string(connection),))
    return found.fetchone()[0] is not None


def latest_identifier(name: str) -> Any:
    from psycopg import sql

    return sql.Identifier(*latest_name(name).split("."))


def add_record_id(connection: Any, table: Any, name: str, partitioned: bool) -> None:
    """A table made by the original (or by hand) gets the record_id column and unique index it lacks
    (with time in a partitioned table, whose unique indexes must hold the partition key)."""
    from psycopg import sql

    with connection.transaction():
        connection.execute(sql.SQL("ALTER TABLE {} ADD COLUMN IF NOT EXISTS record_id text").format(table))
        connection.execute(
            sql.SQL(
                "CREATE UNIQUE INDEX IF NOT EXISTS {} ON {} ("
                + ("record_id, time" if partitioned else "record_id")
                + ")"
            ).format(_index_name(name.rsplit(".", 1)[-1], "record_id"), table)
        )


def _index_name(base: str, suffix: str) -> Any:
    from psycopg import sql

    return sql.Identifier(f"{base}_{suffix}"[:MAX_IDENTIFIER])


def not_partitioned_problem(name: str, address: str) -> ConfigurationProblem:
    return ConfigurationProblem(
        f"table {name} of {address} is not partitioned, and partition_by asks DC to manage its partitions",
        fix=f"migrate the table as {MIGRATION_DOC} shows (a partitioned copy, then a rename), "
        "or set partition_by: none",
    )


def legacy_hint(name: str) -> str:
    return (
        f"table {name} has the original's shape (time without time zone, robot and run only inside data): "
        f"used as it is; {MIGRATION_DOC} shows how to migrate it to typed columns, indexes and partitions"
    )


# -- partitions ------------------------------------------------------------------------------------


def period_start(moment: dt.datetime, partition_by: str) -> dt.date:
    """The first UTC day of the partition holding ``moment`` (naive: UTC)."""
    day = (moment.astimezone(dt.UTC) if moment.tzinfo else moment).date()
    return day - dt.timedelta(days=day.weekday()) if partition_by == "week" else day


def period_end(start: dt.date, partition_by: str) -> dt.date:
    return start + dt.timedelta(days=7 if partition_by == "week" else 1)


class Partitions:
    """The partitions DC keeps for one table: which exist, making the missing, dropping the expired.

    Only partitions named ``<table>_pYYYYMMDD`` are DC's: one made by hand (or by pg_partman)
    under another name is never dropped, and one covering a period already counts as that period's.
    """

    def __init__(self, name: str, partition_by: str, retention_days: int) -> None:
        self.schema, _, base = name.rpartition(".")
        self.prefix = f"{base[: MAX_IDENTIFIER - 10]}_p"
        self.partition_by = partition_by
        self.retention_days = retention_days
        self.known: set[dt.date] = set()
        self.made: list[str] = []  # names made by the last ensure(), for the log
        self.dropped: list[str] = []  # names dropped by the last expire(), for the log
        self.dropped_before: dt.date | None = None  # the end of the latest period expire() dropped

    def _identifier(self, start: dt.date) -> Any:
        from psycopg import sql

        name = f"{self.prefix}{start:%Y%m%d}"
        return sql.Identifier(self.schema, name) if self.schema else sql.Identifier(name)

    def ensure(self, connection: Any, table: Any, starts: set[dt.date]) -> None:
        """Make the partitions of ``starts`` that are not known to exist."""
        import psycopg
        from psycopg import sql

        self.made = []
        for start in sorted(starts - self.known):
            end = period_end(start, self.partition_by)
            statement = sql.SQL("CREATE TABLE IF NOT EXISTS {} PARTITION OF {} FOR VALUES FROM ({}) TO ({})").format(
                self._identifier(start), table, sql.Literal(f"{start} 00:00:00+00"), sql.Literal(f"{end} 00:00:00+00")
            )
            try:
                with connection.transaction():
                    connection.execute(statement)
                self.made.append(f"{self.prefix}{start:%Y%m%d}")
            except (psycopg.errors.DuplicateTable, psycopg.errors.UniqueViolation):
                pass  # another robot made it at the same moment
            except psycopg.errors.InvalidObjectDefinition as exc:
                # "would overlap partition …": a partition made by someone else covers the period.
                if "overlap" not in str(exc):
                    raise
            self.known.add(start)

    def ahead(self, today: dt.date) -> set[dt.date]:
        start = period_start(dt.datetime.combine(today, dt.time()), self.partition_by)
        step = dt.timedelta(days=7 if self.partition_by == "week" else 1)
        return {start + step * n for n in range(PARTITIONS_AHEAD + 1)}

    def expire(self, connection: Any, table: Any, today: dt.date) -> None:
        """Drop DC's partitions whose whole period is older than ``retention_days`` (0: keep all)."""
        from psycopg import sql

        self.dropped = []
        self.dropped_before = None
        if not self.retention_days:
            return
        horizon = today - dt.timedelta(days=self.retention_days)
        children = connection.execute(
            "SELECT c.relname::text FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid"
            " WHERE i.inhparent = to_regclass(%s)",
            (table.as_string(connection),),
        ).fetchall()
        pattern = re.compile(re.escape(self.prefix) + r"(\d{8})")
        for (child,) in children:
            match = pattern.fullmatch(child)
            if match is None:
                continue
            start = dt.datetime.strptime(match.group(1), "%Y%m%d").date()
            if period_end(start, self.partition_by) > horizon:
                continue
            with connection.transaction():
                connection.execute(sql.SQL("DROP TABLE IF EXISTS {}").format(self._identifier(start)))
            self.known.discard(start)
            self.dropped.append(child)
            end = period_end(start, self.partition_by)
            self.dropped_before = max(end, self.dropped_before or end)
