"""Pre-averaged buckets of the charted measurements, kept by a trigger: ``dc dashboard --create-rollups``.

A chart of every robot's hour reads every row it plots (360,000 positions for 100 robots), ~2 µs a
row for its JSON values: over 0.5 s whatever the plan (docs/fleet.md). ``<table>_rollup`` holds, per
series (a record name and the one or two values a chart draws of it), robot, run and ``SECONDS`` of
time, the rows' count, the sum of their times and the count, sum, min and max of the values: a
chart's bucket of whole rollup buckets is their sums added up, the same means as from the rows.

An AFTER INSERT statement trigger with the statement's rows (``REFERENCING NEW TABLE``) adds them
in the inserting transaction: rows delivered hours late (a robot back from an outage) are counted,
whoever writes (the PgSQL destination's COPY or INSERT, ``dc ingest``, a backfill); a rolled-back
insert leaves nothing; rows a retried batch's ``ON CONFLICT DO NOTHING`` skipped are not in the
statement's rows, so not counted twice. Rows deleted or partitions dropped are not taken out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from psycopg import sql

from dc_dashboard import indexes

SECONDS = 30  # a rollup bucket: a fleet's hour of 100 robots is 120 of them per robot (CHART_POINTS)
# What the charts draw of each kind of measurement (catalog.KINDS): the paths below the measurement's.
CHARTED: dict[str, tuple[tuple[str, ...], ...]] = {
    "position": (("x",), ("y",)),
    "distance_traveled": (("distance_traveled",),),
    "cpu": (("average",),),
    "memory": (("used",),),
}
_MAX_IDENTIFIER = 63


def charted(kind: str, path: tuple[str, ...]) -> list[tuple[str, ...]]:
    """The JSON paths in the row of the values a chart of ``kind`` draws, its measurement at ``path``."""
    return [(*path, *value) for value in CHARTED[kind]]


def names(table: str) -> dict[str, str]:
    """The rollup's objects, named after the records table ("schema.table" kept), within 63 characters."""
    schema, dot, base = table.rpartition(".")
    return {
        suffix: f"{schema}{dot}{base[: _MAX_IDENTIFIER - len(suffix)]}{suffix}"
        for suffix in ("_rollup", "_rollup_series", "_roll_up")
    }


def identifier(qualified: str) -> sql.Identifier:
    return sql.Identifier(*qualified.split("."))


@dataclass(frozen=True)
class Series:
    id: int
    seconds: int


Found = dict[tuple[str, tuple[str, ...], tuple[str, ...]], Series]  # (name, a path, b path or ()) -> series


def found(connection: Any, table: str) -> Found:
    """The series rolled up for records table ``table``: none when ``--create-rollups`` was not run, or
    when its trigger is gone or disabled (the rollup would miss the rows since)."""
    series = names(table)["_rollup_series"]
    exists = connection.execute(
        "SELECT to_regclass(%s) IS NOT NULL AND EXISTS (SELECT 1 FROM pg_trigger WHERE tgrelid = to_regclass(%s)"
        " AND tgname = 'dc_roll_up' AND tgenabled <> 'D')",
        (series, table),
    ).fetchone()
    if not exists or not exists[0]:
        return {}
    rows = connection.execute(sql.SQL("SELECT id, name, a, b, seconds FROM {}").format(identifier(series)))
    return {(name, tuple(a), tuple(b)): Series(int(i), int(s)) for i, name, a, b, s in rows.fetchall()}


def value_of(path: str) -> sql.Composable:
    """The number at JSON path ``s.<path>`` of the inserted row ``n``; NULL when absent or not a number
    (a string must not fail the robot's insert)."""
    return sql.SQL("CASE WHEN jsonb_typeof(n.data #> s.{p}) = 'number' THEN (n.data #>> s.{p})::float8 END").format(
        p=sql.Identifier(path)
    )


def guarded_value(path: str) -> sql.Composable:
    """As value_of, a number beyond float8's range (JSON allows it) NULL rather than an error."""
    return sql.SQL(
        "CASE WHEN jsonb_typeof(n.data #> s.{p}) = 'number' AND abs((n.data #> s.{p})::numeric) < 1e300"
        " THEN (n.data #>> s.{p})::float8 END"
    ).format(p=sql.Identifier(path))


def upsert(rollup: Any, series: Any, source: Any, value: Any, only: Any = None) -> sql.Composed:
    """Rows of ``source`` (aliased n) added to the rollup: grouped first (ON CONFLICT may touch a key
    once a statement), in key order (two inserting transactions wait for each other, not deadlock)."""
    return sql.SQL(
        "INSERT INTO {rollup} AS r (series, bucket, robot, run, rows, time_sum, a_rows, a_sum, a_min, a_max,"
        " b_rows, b_sum)"
        " SELECT s.id, (floor(v.t / s.seconds) * s.seconds)::bigint, v.robot, v.run, count(*), sum(v.t),"
        "  count(v.a), coalesce(sum(v.a), 0), min(v.a), max(v.a), count(v.b), coalesce(sum(v.b), 0)"
        " FROM {source} n JOIN {series} s ON s.name = (n.data->>'name'){only}"
        " CROSS JOIN LATERAL (SELECT extract(epoch FROM n.time)::float8 AS t, coalesce({robot}, '') AS robot,"
        "  coalesce({run}, '') AS run, {a} AS a, {b} AS b) AS v"
        " GROUP BY 1, 2, 3, 4 ORDER BY 1, 2, 3, 4"
        " ON CONFLICT (series, bucket, robot, run) DO UPDATE SET rows = r.rows + EXCLUDED.rows,"
        "  time_sum = r.time_sum + EXCLUDED.time_sum, a_rows = r.a_rows + EXCLUDED.a_rows,"
        "  a_sum = r.a_sum + EXCLUDED.a_sum, a_min = least(r.a_min, EXCLUDED.a_min),"
        "  a_max = greatest(r.a_max, EXCLUDED.a_max), b_rows = r.b_rows + EXCLUDED.b_rows,"
        "  b_sum = r.b_sum + EXCLUDED.b_sum"
    ).format(
        rollup=rollup,
        source=source,
        series=series,
        only=only if only is not None else sql.SQL(""),
        robot=indexes.ROBOT_OF("n"),
        run=indexes.RUN_OF("n"),
        a=value("a"),
        b=value("b"),
    )


def wanted(catalog_sources: dict[str, list[tuple[str, tuple[str, ...]]]]) -> list[tuple[str, list[str], list[str]]]:
    """(record name, a path, b path or []) of every chart the pages draw, from the catalog's sources."""
    out = []
    for kind in CHARTED:
        for name, path in catalog_sources.get(kind, []):
            paths = charted(kind, path)
            out.append((name, list(paths[0]), list(paths[1]) if len(paths) > 1 else []))
    return out
