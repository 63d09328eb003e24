"""The indexes the dashboard's queries need, how to tell they are there, and ``dc dashboard --create-indexes``.

The robot and the run of a row are where DC puts them: top-level ``robot_name`` and ``run_id`` in a
measurement's record, one level down in a group's (each member carries them). The expressions below
say exactly that, and the queries use them verbatim, so PostgreSQL matches them to the expression
indexes. ``jsonb_path_query_first`` is immutable, as an index expression must be.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from psycopg import sql

from dc_dashboard.errors import first_line
from dc_dashboard.settings import PostgresSettings

_MAX_IDENTIFIER = 63


def _expression(key: str, alias: str = "") -> sql.SQL:
    data = f"{alias}.data" if alias else "data"
    return sql.SQL(f"COALESCE({data}->>'{key}', jsonb_path_query_first({data}, '$.*.{key}') #>> '{{}}')")


ROBOT = _expression("robot_name")
RUN = _expression("run_id")


def RUN_OF(alias: str) -> sql.SQL:
    return _expression("run_id", alias)


def ROBOT_OF(alias: str) -> sql.SQL:
    return _expression("robot_name", alias)


@dataclass(frozen=True)
class Index:
    suffix: str
    on_files: bool
    columns: sql.Composable
    why: str


INDEXES = (
    Index(
        "dash_name_time", False, sql.SQL("((data->>'name'), time)"), "record names, newest rows of a name, time ranges"
    ),
    Index(
        "dash_robot_name_time",
        False,
        sql.SQL("(({}), (data->>'name'), time)").format(ROBOT),
        "the robot filter, the list of robots",
    ),
    Index(
        "dash_robot_run_name_time",
        False,
        sql.SQL("(({}), ({}), (data->>'name'), time)").format(ROBOT, RUN),
        "the run filter, the list of a robot's runs",
    ),
    Index("dash_tag_time", False, sql.SQL("(tag, time)"), "newest row per destination (health page)"),
    Index("dash_robot_timestamp", True, sql.SQL("(robot_name, timestamp)"), "files of a robot in a time range"),
    Index("dash_timestamp", True, sql.SQL("(timestamp)"), "newest files, all robots"),
)


ROBOT_INDEX = INDEXES[1]  # its first column's statistics say each robot's share of the rows (dc_dashboard.fleet)


def table_and_name(settings: PostgresSettings, index: Index) -> tuple[str, str]:
    table = settings.files_table if index.on_files else settings.table
    return table, f"{table.rsplit('.', 1)[-1]}_{index.suffix}"[:_MAX_IDENTIFIER]


def statements(settings: PostgresSettings, partitioned: frozenset[str] = frozenset()) -> list[sql.Composed]:
    """CREATE INDEX CONCURRENTLY: DC keeps inserting while they are built. PostgreSQL builds an index of
    a ``partitioned`` table (PgSQL's ``partition_by``) only without CONCURRENTLY: each partition is locked
    against writes while its part is built (the records wait in DC's buffer meanwhile)."""
    out = []
    for index in INDEXES:
        table, name = table_and_name(settings, index)
        how = "CREATE INDEX IF NOT EXISTS" if table in partitioned else "CREATE INDEX CONCURRENTLY IF NOT EXISTS"
        out.append(
            sql.SQL(how + " {} ON {} {}").format(sql.Identifier(name), sql.Identifier(*table.split(".")), index.columns)
        )
    return out


def _partitioned(connection: Any, settings: PostgresSettings) -> frozenset[str]:
    """Which of the two tables are partitioned (relkind 'p')."""
    rows = connection.execute(
        "SELECT t FROM unnest(ARRAY[%s, %s]) AS t JOIN pg_class c ON c.oid = to_regclass(t) WHERE c.relkind = 'p'",
        (settings.table, settings.files_table),
    ).fetchall()
    return frozenset(row[0] for row in rows)


def missing(connection: Any, settings: PostgresSettings) -> list[str]:
    """Names of the dashboard's indexes not (validly) built on the existing tables."""
    wanted = []
    for index in INDEXES:
        table, name = table_and_name(settings, index)
        wanted.append((table, name))
    rows = connection.execute(
        "SELECT c.relname, i.indisvalid FROM pg_index i JOIN pg_class c ON c.oid = i.indexrelid"
        " WHERE i.indrelid = ANY(ARRAY[to_regclass(%s), to_regclass(%s)])",
        (settings.table, settings.files_table),
    ).fetchall()
    present = {name for name, valid in rows if valid}
    tables = {
        t
        for t, exists in connection.execute(
            "SELECT t, to_regclass(t) IS NOT NULL FROM unnest(ARRAY[%s, %s]) AS t",
            (settings.table, settings.files_table),
        ).fetchall()
        if exists
    }
    return [name for table, name in wanted if table in tables and name not in present]


def create(settings: PostgresSettings, say: Any = print) -> int:
    """Build the missing indexes (each table that exists); 0 when all are there afterwards."""
    import psycopg

    try:
        with psycopg.connect(**{**settings.connect_kwargs(), "options": ""}, autocommit=True) as connection:
            todo = set(missing(connection, settings))
            partitioned = _partitioned(connection, settings)
            for index, statement in zip(INDEXES, statements(settings, partitioned), strict=True):
                table, name = table_and_name(settings, index)
                if name not in todo:
                    continue
                # An earlier, interrupted CONCURRENTLY build leaves an invalid index that IF NOT EXISTS would keep.
                drop = "DROP INDEX IF EXISTS {}" if table in partitioned else "DROP INDEX CONCURRENTLY IF EXISTS {}"
                connection.execute(sql.SQL(drop).format(sql.Identifier(*table.split(".")[:-1], name)))
                say(f"creating index {name} on {table} ({index.why}) ...")
                connection.execute(statement)
            left = missing(connection, settings)
    except psycopg.Error as exc:
        say(f"dc dashboard: PostgreSQL {settings.address()}: {first_line(exc)}")
        return 2
    say("indexes: all present" if not left else f"indexes still missing: {', '.join(left)}")
    return 0 if not left else 1
