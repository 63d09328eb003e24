"""Every question the pages ask PostgreSQL: parameterised, bounded, and served by the indexes in indexes.py.

Bounded means a page costs the same with a thousand rows or a million: plots are averaged into at
most ``POINTS`` time buckets per series (``width_bucket``), lists have a ``LIMIT``, distinct values are
read by skipping through an index rather than by scanning the table.
"""

from __future__ import annotations

import datetime as dt
import math
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from dc_dashboard import indexes, rollups
from dc_dashboard.catalog import Sources, numeric_fields, sources_of
from dc_dashboard.errors import DashboardError, first_line
from dc_dashboard.filters import Filters
from dc_dashboard.settings import PostgresSettings

POINTS = 600  # per series of a chart: more than an SVG of 900 px wide can show apart
# Points of a chart in all: without a robot filter and more than 20 robots in the table (a fleet's
# hour: 100), each robot gets fewer, wider buckets, so every robot is drawn and the page stays bounded.
CHART_POINTS = 12_000
CAMERA_PAGE = 12
EXPLORE_PAGE = 50
FILES_PAGE = 200
CATALOG_TTL_S = 30.0


@dataclass
class Series:
    label: str
    points: list[tuple[float, float]]  # (seconds since the epoch, value) or (x, y) for a trajectory


@dataclass
class Bucket:
    """A series' rows in one bucket of time: their mean time and values, and what the pages sum up."""

    robot: str
    run: str
    label: str
    when: float  # mean epoch seconds
    a: float | None  # mean of the first value (None: no row had it)
    b: float | None
    rows: int
    a_rows: int  # rows with a first value
    a_max: float | None
    a_min: float | None


@dataclass
class Trajectory:
    series: list[Series]
    map: dict[str, Any] | None = None  # the map record, with "key": its PNG in S3, when there is one
    positions: int = 0


@dataclass
class Distance:
    total_m: float
    per_run: list[tuple[str, str, float]]  # robot, run, metres in the range
    series: list[Series]


@dataclass
class SystemStats:
    cpu: list[Series]
    memory: list[Series]
    cpu_average: float | None
    cpu_max: float | None
    memory_average: float | None
    memory_max: float | None
    samples: int


@dataclass
class Inspection:
    time: dt.datetime
    robot: str
    run: str
    camera: str
    key: str  # the inspected image's key in the bucket, "" when it was not uploaded
    codes: list[dict[str, Any]]


@dataclass
class Exploration:
    """The explorer's view of one record name: its newest records and a chart per numeric field."""

    names: list[str]  # every record name of the table (at most 100)
    records: list[tuple[dt.datetime, str, str, Any]]  # time, robot, run, data: newest first
    more: bool  # older records than these exist (the page's "older" link)
    charts: list[tuple[str, list[Series]]]  # field path ("cpu.average"), a series per robot and run


@dataclass
class FilesPage:
    rows: list[dict[str, Any]]
    counts: dict[str, int]
    total_bytes: int
    more: bool


@dataclass
class Catalog:
    sources: Sources
    missing_indexes: list[str]
    row_estimate: int
    # Record name -> the JSON paths of the numbers its newest records hold (the explorer plots them).
    fields: dict[str, list[tuple[str, ...]]] = field(default_factory=dict)
    rollup_series: rollups.Found = field(default_factory=dict)  # those dc dashboard --create-rollups keeps
    read_at: float = field(default_factory=time.monotonic)

    @property
    def collected(self) -> frozenset[str]:
        """The kinds of record (catalog.KINDS) the table holds at all, whatever the filters."""
        return frozenset(kind for kind, found in self.sources.items() if found)


class Store:
    """The dashboard's reader of DC's tables; opens a connection per page (closed when the page is done)."""

    def __init__(self, settings: PostgresSettings) -> None:
        from psycopg import sql

        self.settings = settings
        self.table = sql.Identifier(*settings.table.split("."))
        self.files_table = sql.Identifier(*settings.files_table.split("."))
        self._catalog: Catalog | None = None
        self._robots: tuple[Any, list[str]] | None = None  # the page's connection, its robots

    @contextmanager
    def connection(self) -> Iterator[Any]:
        import psycopg

        try:
            with psycopg.connect(**self.settings.connect_kwargs(), autocommit=True) as connection:
                yield connection
        except psycopg.errors.UndefinedTable as exc:
            raise DashboardError(f"no such table in {self.settings.address()}: {first_line(exc)}") from None
        except psycopg.errors.QueryCanceled:
            raise DashboardError(
                f"PostgreSQL {self.settings.address()} took longer than {self.settings.statement_timeout_ms} ms;"
                " are the dashboard's indexes there? (dc dashboard --create-indexes)"
            ) from None
        except psycopg.Error as exc:
            raise DashboardError(f"PostgreSQL {self.settings.address()}: {first_line(exc)}") from None

    # -- what is there -------------------------------------------------------------------------
    def catalog(self, connection: Any) -> Catalog:
        """Record names and where each kind of measurement sits in them; read again after CATALOG_TTL_S."""
        cached = self._catalog
        if cached is not None and time.monotonic() - cached.read_at < CATALOG_TTL_S:
            return cached
        from psycopg import sql

        names = [row[0] for row in connection.execute(sql.SQL(_DISTINCT_NAMES).format(t=self.table)).fetchall()]
        latest: dict[str, list[Mapping[str, Any]]] = {}
        for name in names:
            rows = connection.execute(
                sql.SQL("SELECT data FROM {t} WHERE (data->>'name') = %s ORDER BY time DESC LIMIT 3").format(
                    t=self.table
                ),
                (name,),
            ).fetchall()
            latest[name] = [row[0] for row in rows if isinstance(row[0], dict)]
        estimate = connection.execute(
            "SELECT greatest(reltuples, 0)::bigint FROM pg_class WHERE oid = to_regclass(%s)", (self.settings.table,)
        ).fetchone()
        rows = int(estimate[0]) if estimate else 0
        if rows < 100_000:  # not analysed yet (a new table says 0): a count that stops at 100,000 rows
            bounded = sql.SQL("SELECT count(*) FROM (SELECT 1 FROM {t} LIMIT 100000) AS first_rows").format(
                t=self.table
            )
            counted = connection.execute(bounded).fetchone()
            rows = max(rows, int(counted[0]) if counted else 0)
        catalog = Catalog(
            sources=sources_of(latest),
            missing_indexes=indexes.missing(connection, self.settings),
            row_estimate=rows,
            fields={name: numeric_fields(records) for name, records in latest.items()},
            rollup_series=rollups.found(connection, self.settings.table),
        )
        self._catalog = catalog
        return catalog

    def robots(self, connection: Any) -> list[str]:
        """Read once per connection (a page): on day partitions a seek per robot is one per partition."""
        from psycopg import sql

        cached = self._robots  # pages run in threads: one read of the pair
        if cached is not None and cached[0] is connection:
            return list(cached[1])
        query = sql.SQL(_DISTINCT_ROBOTS).format(t=self.table, robot=indexes.ROBOT)
        robots = [row[0] for row in connection.execute(query).fetchall()]
        self._robots = (connection, robots)
        return list(robots)

    def runs(self, connection: Any, robot: str) -> list[str]:
        """The robot's runs (without one, those of each destination's newest 5,000 rows), newest run number
        first, at most 200."""
        from psycopg import sql

        if robot:
            query = sql.SQL(_DISTINCT_RUNS).format(t=self.table, robot=indexes.ROBOT, run=indexes.RUN)
            runs = [row[0] for row in connection.execute(query, {"robot": robot}).fetchall()]
        else:
            query = sql.SQL(_NEWEST_RUNS).format(t=self.table, run=indexes.RUN)
            runs = [row[0] for row in connection.execute(query).fetchall() if row[0] is not None]
        return sorted(runs, key=lambda r: (len(r), r), reverse=True)[:200]

    # -- pages ---------------------------------------------------------------------------------
    def trajectory(self, connection: Any, filters: Filters) -> Trajectory:
        catalog = self.catalog(connection)
        series: dict[str, list[tuple[float, float, float]]] = {}
        positions = 0
        for name, path in catalog.sources["position"]:
            for bucket in self._bucketed(connection, filters, name, rollups.charted("position", path)):
                if bucket.a is not None:
                    positions += bucket.rows
                    series.setdefault(bucket.label, []).append((bucket.when, bucket.a, bucket.b or 0.0))
        lines = [Series(label, [(x, y) for _, x, y in sorted(points)]) for label, points in sorted(series.items())]
        last = max((max(t for t, _, _ in points) for points in series.values()), default=None)
        return Trajectory(lines, self._map(connection, filters, catalog, last), positions)

    def distance(self, connection: Any, filters: Filters) -> Distance:

        catalog = self.catalog(connection)
        per_run: list[tuple[str, str, float]] = []
        series: list[Series] = []
        for name, path in catalog.sources["distance_traveled"]:
            # A run's metres, its counter's rise: from the plot's buckets (their max and min), one read of the rows.
            runs: dict[tuple[str, str], list[float]] = {}  # (robot, run) -> [max, min, newest time]
            buckets = self._bucketed(connection, filters, name, rollups.charted("distance_traveled", path))
            for bucket in buckets:
                if bucket.a_max is None or bucket.a_min is None:
                    continue
                run = runs.setdefault((bucket.robot, bucket.run), [bucket.a_max, bucket.a_min, bucket.when])
                run[0], run[1], run[2] = max(run[0], bucket.a_max), min(run[1], bucket.a_min), max(run[2], bucket.when)
            newest = sorted(runs.items(), key=lambda item: item[1][2], reverse=True)[:500]
            per_run += [(robot, run, top - low) for (robot, run), (top, low, _) in newest]
            series += _series(buckets, "a")
        return Distance(sum(m for _, _, m in per_run), per_run, series)

    def system(self, connection: Any, filters: Filters) -> SystemStats:

        catalog = self.catalog(connection)
        stats: dict[str, list[Series]] = {"cpu": [], "memory": []}
        summary: dict[str, list[tuple[float, float, int]]] = {"cpu": [], "memory": []}
        for kind in ("cpu", "memory"):
            for name, path in catalog.sources[kind]:
                # The figures from the plot's buckets: one read of the rows, not two.
                buckets = self._bucketed(connection, filters, name, rollups.charted(kind, path))
                valued = sum(b.a_rows for b in buckets)
                if valued:
                    average = sum((b.a or 0.0) * b.a_rows for b in buckets) / valued
                    top = max(b.a_max for b in buckets if b.a_max is not None)
                    summary[kind].append((average, top, sum(b.rows for b in buckets)))
                stats[kind] += _series(buckets, "a")

        def weighted(kind: str) -> tuple[float | None, float | None, int]:
            rows = summary[kind]
            n = sum(c for _, _, c in rows)
            if not n:
                return None, None, 0
            return sum(a * c for a, _, c in rows) / n, max(m for _, m, _ in rows), n

        cpu_avg, cpu_max, cpu_n = weighted("cpu")
        mem_avg, mem_max, mem_n = weighted("memory")
        return SystemStats(stats["cpu"], stats["memory"], cpu_avg, cpu_max, mem_avg, mem_max, max(cpu_n, mem_n))

    def inspections(self, connection: Any, filters: Filters) -> tuple[list[Inspection], bool]:
        """The newest camera records of the filters (before ``filters.before``), CAMERA_PAGE of them."""
        from psycopg import sql

        found: list[Inspection] = []
        code = None
        if filters.code:  # any code read whose content holds the text, any case
            code = sql.SQL(
                "EXISTS (SELECT 1 FROM jsonb_path_query(data #> %(p)s, '$.inspected.*[*].data') AS c(v)"
                " WHERE (c.v #>> '{}') ILIKE %(text)s ESCAPE '\\')"
            )
        for _, when, robot, run, record in self.newest(
            connection, filters, "camera", CAMERA_PAGE + 1, code, filters.code
        ):
            found.append(_inspection(when, robot, run, record))
        found.sort(key=lambda i: i.time, reverse=True)
        return found[:CAMERA_PAGE], len(found) > CAMERA_PAGE

    def newest(
        self,
        connection: Any,
        filters: Filters,
        kind: str,
        limit: int,
        text_condition: Any = None,
        text: str = "",
        texts: dict[str, str] | None = None,
    ) -> Iterator[tuple[str, dt.datetime, str, str, dict[str, Any]]]:
        """(record name, time, robot, run, measurement) of the newest records of ``kind`` for the filters
        (before ``filters.before``), ``limit`` per record name; ``text_condition``: an SQL condition on
        ``%(text)s``, an ILIKE pattern of ``text`` taken literally, and ``%(p)s``, the measurement's JSON
        path in the row; ``texts``: more such patterns, by parameter name."""
        from psycopg import sql

        for name, path in self.catalog(connection).sources[kind]:
            where, params = self._where(filters, name)
            if filters.before:
                where = sql.SQL("{} AND time < %(before)s").format(where)
                params["before"] = filters.before
            if text_condition is not None:
                where = sql.SQL("{} AND {}").format(where, text_condition)
                for key, value in {"text": text, **(texts or {})}.items():
                    params[key] = "%" + _like_escaped(value) + "%"
            if filters.run and not filters.robot:
                where, params, _ = self._within_run_span(connection, where, params)
            params["p"] = list(path)
            query = sql.SQL(
                "SELECT time, {robot}, {run}, data #> %(p)s FROM {t} WHERE {w} ORDER BY time DESC LIMIT %(n)s"
            ).format(robot=indexes.ROBOT, run=indexes.RUN, t=self.table, w=where)
            params["n"] = limit
            for when, robot, run, record in connection.execute(query, params).fetchall():
                if isinstance(record, dict):
                    yield name, when, robot or "", run or "", record

    def explore(self, connection: Any, filters: Filters) -> Exploration:
        """Any record name's newest records (before ``filters.before``) and its numeric fields over time."""
        from psycopg import sql

        catalog = self.catalog(connection)
        names = sorted(catalog.fields)
        if not filters.name:
            return Exploration(names, [], False, [])
        where, params = self._where(filters, filters.name)
        if filters.before:
            where = sql.SQL("{} AND time < %(before)s").format(where)
            params["before"] = filters.before
        if filters.run and not filters.robot:
            where, params, _ = self._within_run_span(connection, where, params)
        query = sql.SQL("SELECT time, {robot}, {run}, data FROM {t} WHERE {w} ORDER BY time DESC LIMIT %(n)s").format(
            robot=indexes.ROBOT, run=indexes.RUN, t=self.table, w=where
        )
        rows = connection.execute(query, {**params, "n": EXPLORE_PAGE + 1}).fetchall()
        records = [(when, robot or "", run or "", data) for when, robot, run, data in rows]
        paths = catalog.fields.get(filters.name, [])
        charts: list[tuple[str, list[Series]]] = []
        for first in range(0, len(paths), 2):  # two fields per query
            pair = paths[first : first + 2]
            series: list[list[Series]] = [[] for _ in pair]
            buckets = self._bucketed(connection, filters, filters.name, pair)
            series[0] = _series(buckets, "a")
            if len(pair) == 2:
                series[1] = _series(buckets, "b")
            charts += [(".".join(path), lines) for path, lines in zip(pair, series, strict=True)]
        return Exploration(names, records[:EXPLORE_PAGE], len(records) > EXPLORE_PAGE, charts)

    def files(self, connection: Any, filters: Filters) -> FilesPage:
        from psycopg import sql

        conditions, params = _filtered(
            filters,
            robot_column=sql.SQL("robot_name"),
            time_column=sql.SQL("timestamp"),
            run_condition=self.files_run_condition(filters, connection),
        )
        scope = sql.SQL(" AND ").join([sql.SQL("true"), *conditions])
        counts_query = sql.SQL(
            "SELECT count(*), count(*) FILTER (WHERE uploaded), count(*) FILTER (WHERE verified_at IS NOT NULL),"
            " count(*) FILTER (WHERE deleted), count(*) FILTER (WHERE NOT uploaded), coalesce(sum(size), 0)"
            " FROM {f} f WHERE {scope}"
        ).format(f=self.files_table, scope=scope)
        total, uploaded, verified, deleted, pending, size = connection.execute(counts_query, params).fetchone()
        state = {
            "uploaded": "uploaded",
            "verified": "verified_at IS NOT NULL",
            "deleted": "deleted",
            "pending": "NOT uploaded",
        }.get(filters.state)
        if state:
            scope = sql.SQL("{} AND {}").format(scope, sql.SQL(state))
        rows_query = sql.SQL(
            "SELECT timestamp, robot_name, group_name, local_path, remote_path, storage_type, content_type, size,"
            " uploaded, verified_at, deleted, on_filesystem FROM {f} f WHERE {scope}"
            " ORDER BY timestamp DESC, id DESC LIMIT %(n)s"
        ).format(f=self.files_table, scope=scope)
        cursor = connection.execute(rows_query, {**params, "n": FILES_PAGE + 1})
        columns = [c.name for c in cursor.description]
        rows = [dict(zip(columns, row, strict=True)) for row in cursor.fetchall()]
        counts = {"all": total, "uploaded": uploaded, "verified": verified, "deleted": deleted, "pending": pending}
        return FilesPage(rows[:FILES_PAGE], counts, int(size), len(rows) > FILES_PAGE)

    def files_run_condition(self, filters: Filters, connection: Any = None) -> Any:
        """The run filter of files_metrics ``f``, on ``%(run)s`` (and ``%(robot)s`` with the robot filter).
        Without a robot and with a ``connection``: bounded by the run's robots and their time spans."""
        from psycopg import sql

        # files_metrics has no run: the record that brought the file has. With a robot, that record is
        # the robot's (a file's robot_name is its record's): the run's rows of the robot are read through
        # the (robot, run, name, time) index and matched by record_id, without an index on record_id
        # (a partitioned table DC makes has none: docs/data-model.md).
        robot = sql.SQL(" AND {} = %(robot)s").format(indexes.ROBOT_OF("r")) if filters.robot else sql.SQL("")
        by_record = sql.SQL(
            "EXISTS (SELECT 1 FROM {t} r WHERE r.record_id = f.record_id AND {run} = %(run)s{robot})"
        ).format(t=self.table, run=indexes.RUN_OF("r"), robot=robot)
        if filters.robot or not filters.run or connection is None:
            return by_record
        # Without a robot, a lookup of each file's record read the files of every run (9.3 s for a
        # fleet's run of 2 hours on 25 M rows; a partitioned table, without an index on record_id, hashed
        # the whole table). A robot runs one run at a time, and a file's timestamp is its record's time
        # (files_metrics and the records table take it from the record): the run's files are each robot's
        # files between its first and last row of the run — ranges of files_metrics' (robot, timestamp)
        # index. A file without a robot name (a group record's: the robot is one level down) is still
        # matched by its record, within the run's whole span.
        spans = self.run_spans(connection, filters.run)
        if not spans:
            return sql.SQL("false")
        ranges = [
            sql.SQL("(f.robot_name = {} AND f.timestamp BETWEEN {} AND {})").format(
                sql.Literal(robot_name), sql.Literal(_utc(low)), sql.Literal(_utc(high))
            )
            for robot_name, (low, high) in sorted(spans.items())
        ]
        low = min(low for low, _ in spans.values())
        high = max(high for _, high in spans.values())
        unnamed = sql.SQL(
            "(f.robot_name = '' AND f.timestamp BETWEEN {low} AND {high} AND EXISTS (SELECT 1 FROM {t} r"
            " WHERE r.record_id = f.record_id AND {run} = %(run)s AND r.time BETWEEN {r_low} AND {r_high}))"
        ).format(
            t=self.table,
            run=indexes.RUN_OF("r"),
            low=sql.Literal(_utc(low)),
            high=sql.Literal(_utc(high)),
            r_low=sql.Literal(low),  # as the records table holds it (timestamptz: with its zone)
            r_high=sql.Literal(high),
        )
        # The whole span too: the newest files first through the (timestamp) index then stop at the
        # run's end, not at the newest file of the table (1.6 s, the OR tried on every file since).
        return sql.SQL("(f.timestamp BETWEEN {} AND {} AND ({}))").format(
            sql.Literal(_utc(low)), sql.Literal(_utc(high)), sql.SQL(" OR ").join([*ranges, unnamed])
        )

    def run_spans(self, connection: Any, run: str) -> dict[str, tuple[dt.datetime, dt.datetime]]:
        """Each robot's first and last row of run ``run``: a seek per robot and record name at each end
        in the (robot, run, name, time) index (the robots themselves by skipping through it)."""
        from psycopg import sql

        names = sorted(self.catalog(connection).fields)
        if not names:
            return {}
        query = sql.SQL(
            "SELECT r.robot, min(s.low), max(s.high) FROM unnest(%(robots)s::text[]) AS r(robot)"
            " CROSS JOIN unnest(%(names)s::text[]) AS n(name)"
            " CROSS JOIN LATERAL (SELECT min(time) AS low, max(time) AS high FROM {t}"
            "   WHERE {robot} = r.robot AND {run} = %(run)s AND (data->>'name') = n.name) AS s"
            " GROUP BY r.robot HAVING min(s.low) IS NOT NULL"
        ).format(t=self.table, robot=indexes.ROBOT, run=indexes.RUN)
        params = {"robots": self.robots(connection), "names": names, "run": run}
        return {robot: (low, high) for robot, low, high in connection.execute(query, params).fetchall()}

    def last_stored(self, connection: Any) -> dict[str, dt.datetime | None]:
        """Per destination (the ``tag`` column): the time of its newest row."""
        from psycopg import sql

        query = sql.SQL(_LAST_PER_TAG).format(t=self.table)
        return {tag: when for tag, when in connection.execute(query).fetchall()}

    def files_by_storage(self, connection: Any) -> list[dict[str, Any]]:
        from psycopg import sql

        query = sql.SQL(
            "SELECT storage_type, max(verified_at) AS last_verified, max(updated_at) AS last_update,"
            " count(*) FILTER (WHERE NOT uploaded) AS pending, count(*) FILTER (WHERE deleted) AS deleted"
            " FROM {f} GROUP BY storage_type ORDER BY 1 LIMIT 20"
        ).format(f=self.files_table)
        cursor = connection.execute(query)
        columns = [c.name for c in cursor.description]
        return [dict(zip(columns, row, strict=True)) for row in cursor.fetchall()]

    # -- helpers -------------------------------------------------------------------------------
    def _where(self, filters: Filters, name: str) -> tuple[Any, dict[str, Any]]:
        from psycopg import sql

        parts, params = _filtered(
            filters,
            robot_column=indexes.ROBOT,
            time_column=sql.SQL("time"),
            run_condition=sql.SQL("{} = %(run)s").format(indexes.RUN),
        )
        return sql.SQL(" AND ").join([sql.SQL("(data->>'name') = %(name)s"), *parts]), {"name": name, **params}

    def _within_run_span(
        self, connection: Any, where: Any, params: dict[str, Any]
    ) -> tuple[Any, dict[str, Any], tuple[Any, ...] | None]:
        """For every robot's run N (a run filter without a robot): ``where`` bounded by the span of the rows
        it matches, and that span (first, last time; None or (None, None) when no row). The span takes a seek
        per robot at each end of the (robot, run, name, time) index; the bound makes what is read next a range
        of the (name, time) index. Without them PostgreSQL walked that index in from the table's ends to
        the run (9.6 s for the positions of a fleet's run on 25 M rows)."""
        from psycopg import sql

        span_query = sql.SQL(
            "SELECT min(s.low), max(s.high) FROM unnest(%(robots)s::text[]) AS r(robot) CROSS JOIN LATERAL"
            " (SELECT min(time) AS low, max(time) AS high FROM {t} WHERE {w} AND {robot} = r.robot) AS s"
        ).format(t=self.table, w=where, robot=indexes.ROBOT)
        span = connection.execute(span_query, {**params, "robots": self.robots(connection)}).fetchone()
        if not span or span[0] is None:
            return where, params, span
        bounded = sql.SQL("{} AND time BETWEEN %(span_low)s AND %(span_high)s").format(where)
        return bounded, {**params, "span_low": span[0], "span_high": span[1]}, span

    def _bucketed(self, connection: Any, filters: Filters, name: str, paths: list[tuple[str, ...]]) -> list[Bucket]:
        """The rows of record ``name`` (two values at ``paths``) averaged per robot and run over at most
        POINTS buckets of time, fewer when the robots are many (CHART_POINTS in all): PostgreSQL reduces
        them, a few thousand rows come back whatever the rows read."""
        from psycopg import sql

        where, params = self._where(filters, name)
        span: tuple[Any, ...] | None
        if filters.run and not filters.robot:
            where, params, span = self._within_run_span(connection, where, params)
        else:
            span = connection.execute(
                sql.SQL("SELECT min(time), max(time) FROM {t} WHERE {w}").format(t=self.table, w=where), params
            ).fetchone()
        if not span or span[0] is None:
            return []
        low, high = (_epoch(t) for t in span)
        values: list[sql.Composable] = []
        for i, path in enumerate(paths[:2]):
            # A key at a time (-> … ->>), not the path operator #>>: 10-20 % less of the query's time on
            # a fleet's hour of positions (360,000 rows, two values each).
            keys = [sql.Placeholder(f"p{i}_{k}") for k in range(len(path))]
            params.update({f"p{i}_{k}": key for k, key in enumerate(path)})
            steps = sql.SQL("").join(sql.SQL(" -> {}::text").format(key) for key in keys[:-1])
            values.append(sql.SQL("(data{} ->> {}::text)::float8").format(steps, keys[-1]))
        while len(values) < 2:
            values.append(sql.SQL("NULL::float8"))
        # A robot's runs share the time axis, so a chart holds about (robots x buckets) points: without a
        # robot filter, every robot of the table in CHART_POINTS, a robot alone POINTS.
        robots = 1 if filters.robot else max(len(self.robots(connection)), 1)
        buckets = max(1, min(POINTS, CHART_POINTS // robots))
        series = None if filters.robot else self.catalog(connection).rollup_series.get(_series_key(name, paths))
        if series is not None and (high + 0.001 - low) / buckets >= 0.95 * series.seconds:
            rolled = self._rolled_up(connection, filters, series, (low, high), buckets, where, params, values)
            if rolled is not None:
                return rolled
        params.update(low=low, high=high + 0.001, buckets=buckets)
        # Each row's values once (OFFSET 0 keeps the subquery, else each aggregate extracts them again).
        query = sql.SQL(
            "SELECT robot, run, sum(t) / count(*), avg(a), avg(b), count(*), count(a), max(a), min(a)"
            " FROM (SELECT {robot} AS robot, {run} AS run, extract(epoch FROM time)::float8 AS t, {a} AS a, {b} AS b"
            "   FROM {t} WHERE {w} OFFSET 0) AS row_values"
            " GROUP BY robot, run, width_bucket(t, %(low)s, %(high)s, %(buckets)s) LIMIT 20000"
        ).format(robot=indexes.ROBOT, run=indexes.RUN, a=values[0], b=values[1], t=self.table, w=where)
        return _buckets(connection.execute(query, params).fetchall())

    def _rolled_up(
        self,
        connection: Any,
        filters: Filters,
        series: rollups.Series,
        span: tuple[float, float],
        buckets: int,
        where: Any,
        params: dict[str, Any],
        values: list[Any],
    ) -> list[Bucket] | None:
        """The buckets of _bucketed from the rollup (no robot filter): each chart bucket a whole number of
        rollup buckets on their grid (multiples of its width since the epoch, about the width asked), the
        rows of the range's partial rollup buckets at its ends read from the table. None: the range holds
        no whole rollup bucket."""
        from psycopg import sql

        low, high = span
        width = series.seconds
        # A chart bucket up to 5 % narrower than asked: a fleet's hour is 120 rollup buckets, not 60.
        chart = width * max(1, math.ceil((high + 0.001 - low) / buckets / width - 0.05))
        # Whole rollup buckets within the filters' range and the rows' span ([first, last) in epoch s).
        first = math.floor(low / width) * width
        if filters.start is not None:
            first = max(first, math.ceil(_epoch(filters.start) / width) * width)
        last = math.floor(high / width) * width + width
        if filters.end is not None:
            last = min(last, math.floor(_epoch(filters.end) / width) * width)
        if first >= last:
            return None
        rollup = sql.Identifier(*rollups.names(self.settings.table)["_rollup"].split("."))
        run = sql.SQL(" AND run = %(run)s") if filters.run else sql.SQL("")
        params.update(series=series.id, first=first, last=last, chart=chart)
        params.update(first_time=_naive_utc(first), last_time=_naive_utc(last))
        query = sql.SQL(
            "SELECT robot, run, sum(time_sum) / sum(rows), sum(a_sum) / nullif(sum(a_rows), 0),"
            " sum(b_sum) / nullif(sum(b_rows), 0), sum(rows), sum(a_rows), max(a_max), min(a_min) FROM ("
            "  SELECT robot, run, floor(bucket / %(chart)s::float8) AS k, rows, time_sum, a_rows, a_sum, a_min,"
            "   a_max, b_rows, b_sum FROM {rollup}"
            "  WHERE series = %(series)s AND bucket >= %(first)s AND bucket < %(last)s{run}"
            "  UNION ALL"
            "  SELECT robot, run, floor(t / %(chart)s), 1, t, (a IS NOT NULL)::int, coalesce(a, 0), a, a,"
            "   (b IS NOT NULL)::int, coalesce(b, 0)"
            "  FROM (SELECT coalesce({robot}, '') AS robot, coalesce({run_of}, '') AS run,"
            "    extract(epoch FROM time)::float8 AS t, {a} AS a, {b} AS b"
            "   FROM {t} WHERE {w} AND (time < %(first_time)s OR time >= %(last_time)s) OFFSET 0) AS ends"
            " ) AS parts GROUP BY robot, run, k LIMIT 20000"
        ).format(
            rollup=rollup, run=run, robot=indexes.ROBOT, run_of=indexes.RUN, a=values[0], b=values[1],
            t=self.table, w=where,
        )  # fmt: skip
        return _buckets(connection.execute(query, params).fetchall())

    def _map(self, connection: Any, filters: Filters, catalog: Catalog, last: float | None) -> dict[str, Any] | None:
        """The newest map of the robot saved before the last point drawn (or before the range's end)."""
        from psycopg import sql

        for name, path in catalog.sources["map"]:
            where, params = self._where(Filters(robot=filters.robot), name)
            until = filters.end or (dt.datetime.fromtimestamp(last, dt.UTC).replace(tzinfo=None) if last else None)
            if until:
                where = sql.SQL("{} AND time <= %(until)s").format(where)
                params["until"] = until
            params["p"] = list(path)
            query = sql.SQL("SELECT data #> %(p)s FROM {t} WHERE {w} ORDER BY time DESC LIMIT 1").format(
                t=self.table, w=where
            )
            row = connection.execute(query, params).fetchone()
            if row is None and until:  # the first map came after the range: better than none
                params.pop("until")
                where, _ = self._where(Filters(robot=filters.robot), name)
                query = sql.SQL("SELECT data #> %(p)s FROM {t} WHERE {w} ORDER BY time DESC LIMIT 1").format(
                    t=self.table, w=where
                )
                row = connection.execute(query, params).fetchone()
            if row and isinstance(row[0], dict):
                record = dict(row[0])
                record["key"] = _remote_key(record, "png")
                return record
        return None


def _buckets(found: list[tuple[Any, ...]]) -> list[Bucket]:
    """Bucket rows (robot, run, mean time, mean a, mean b, rows, rows with a, max a, min a) as the pages use them."""
    out = []
    # Sorted here: an ORDER BY made PostgreSQL sort every row (360,000: 0.8 s, on disk) to aggregate
    # in order, where a hash of the buckets needs no sort.
    found = sorted(found, key=lambda row: (row[0] or "", row[1] or "", row[2]))
    for robot, run, when, a, b, rows, a_rows, top, bottom in found:
        robot, run = robot or "", run or ""
        out.append(
            Bucket(
                robot, run, f"{robot or '?'} run {run or '?'}", float(when), _float(a), _float(b),
                int(rows), int(a_rows), _float(top), _float(bottom),
            )
        )  # fmt: skip
    return out


def _series(buckets: list[Bucket], value: str) -> list[Series]:
    """A series per label of the buckets holding ``value`` ("a" or "b"), in the buckets' order."""
    found: dict[str, Series] = {}
    for bucket in buckets:
        if bucket.a is not None:  # a bucket is drawn when its first value is there (the second: 0 without)
            point = (bucket.when, float(getattr(bucket, value) or 0.0))
            found.setdefault(bucket.label, Series(bucket.label, [])).points.append(point)
    return list(found.values())


def _float(value: Any) -> float | None:
    return float(value) if value is not None else None


def _inspection(when: dt.datetime, robot: str, run: str, record: dict[str, Any]) -> Inspection:
    inspected = record.get("inspected")
    codes = inspected.get("barcode", []) if isinstance(inspected, dict) else []
    return Inspection(
        time=when,
        robot=robot or str(record.get("robot_name", "")),
        run=run or str(record.get("run_id", "")),
        camera=str(record.get("camera_name", "")),
        key=_remote_key(record, "inspected"),
        codes=[c for c in codes if isinstance(c, dict)][:50],
    )


def _remote_key(record: dict[str, Any], file_key: str) -> str:
    """The file's key in the bucket, from ``remote_paths.<remote key>.<file key>`` (first remote key that has it)."""
    remote = record.get("remote_paths")
    if isinstance(remote, dict):
        for paths in remote.values():
            if isinstance(paths, dict) and isinstance(paths.get(file_key), str):
                return str(paths[file_key])
    return ""


def _like_escaped(text: str) -> str:
    """``text`` matched literally inside an ILIKE pattern (ESCAPE '\\')."""
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def _utc(value: dt.datetime) -> dt.datetime:
    """UTC without a zone, as files_metrics' timestamp column holds it."""
    return value.astimezone(dt.UTC).replace(tzinfo=None) if value.tzinfo is not None else value


def _naive_utc(epoch: float) -> dt.datetime:
    """As the filters' times are: UTC without a zone (the dashboard's sessions are in UTC)."""
    return dt.datetime.fromtimestamp(epoch, dt.UTC).replace(tzinfo=None)


def _series_key(name: str, paths: list[tuple[str, ...]]) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
    """The rollup's key of a chart of record ``name`` drawing the values at ``paths`` (one or two)."""
    return name, tuple(paths[0]), tuple(paths[1]) if len(paths) > 1 else ()


def _epoch(value: dt.datetime) -> float:
    return value.replace(tzinfo=dt.UTC).timestamp() if value.tzinfo is None else value.timestamp()


# Distinct values by skipping through an index: one index probe per value, not a scan of the table.
_DISTINCT_NAMES = """
WITH RECURSIVE names(name) AS (
    (SELECT (data->>'name') FROM {t} WHERE (data->>'name') IS NOT NULL ORDER BY 1 LIMIT 1)
    UNION ALL
    SELECT (SELECT (data->>'name') FROM {t} WHERE (data->>'name') > names.name ORDER BY 1 LIMIT 1)
    FROM names WHERE names.name IS NOT NULL
)
SELECT name FROM names WHERE name IS NOT NULL LIMIT 100"""

_DISTINCT_ROBOTS = """
WITH RECURSIVE robots(robot) AS (
    (SELECT {robot} FROM {t} WHERE {robot} IS NOT NULL ORDER BY 1 LIMIT 1)
    UNION ALL
    SELECT (SELECT {robot} FROM {t} WHERE {robot} > robots.robot ORDER BY 1 LIMIT 1)
    FROM robots WHERE robots.robot IS NOT NULL
)
SELECT robot FROM robots WHERE robot IS NOT NULL LIMIT 500"""

_DISTINCT_RUNS = """
WITH RECURSIVE runs(run) AS (
    (SELECT {run} FROM {t} WHERE {robot} = %(robot)s AND {run} IS NOT NULL ORDER BY {run} LIMIT 1)
    UNION ALL
    SELECT (SELECT {run} FROM {t} WHERE {robot} = %(robot)s AND {run} > runs.run ORDER BY {run} LIMIT 1)
    FROM runs WHERE runs.run IS NOT NULL
)
SELECT run FROM runs WHERE run IS NOT NULL LIMIT 1000"""

# The newest rows of each destination (tag) through the (tag, time) index: no index orders the whole
# table by time (BRIN cannot), and a sort of every row took 20 s on 7.6 M rows.
_NEWEST_RUNS = """
WITH RECURSIVE tags(tag) AS (
    (SELECT tag FROM {t} WHERE tag IS NOT NULL ORDER BY tag LIMIT 1)
    UNION ALL
    SELECT (SELECT tag FROM {t} WHERE tag > tags.tag ORDER BY tag LIMIT 1) FROM tags WHERE tags.tag IS NOT NULL
)
SELECT DISTINCT {run} FROM (SELECT tag FROM tags WHERE tag IS NOT NULL LIMIT 50) AS found
CROSS JOIN LATERAL (SELECT data FROM {t} WHERE tag = found.tag ORDER BY time DESC LIMIT 5000) AS newest"""

_LAST_PER_TAG = """
WITH RECURSIVE tags(tag) AS (
    (SELECT tag FROM {t} WHERE tag IS NOT NULL ORDER BY tag LIMIT 1)
    UNION ALL
    SELECT (SELECT tag FROM {t} WHERE tag > tags.tag ORDER BY tag LIMIT 1) FROM tags WHERE tags.tag IS NOT NULL
)
SELECT tag, (SELECT max(time) FROM {t} WHERE tag = tags.tag) FROM tags WHERE tag IS NOT NULL LIMIT 50"""


def _filtered(
    filters: Filters, *, robot_column: Any, time_column: Any, run_condition: Any
) -> tuple[list[Any], dict[str, Any]]:
    """The conditions the dashboard's filters set (robot, run, time range) and their query parameters.

    ``robot_column`` and ``time_column`` are the table's columns (psycopg.sql), ``run_condition`` the
    whole condition on ``%(run)s``: the tables name them differently, the filters mean the same on each.
    """
    from psycopg import sql

    conditions: list[sql.Composable] = []
    params: dict[str, Any] = {}
    if filters.robot:
        conditions.append(sql.SQL("{} = %(robot)s").format(robot_column))
        params["robot"] = filters.robot
    if filters.run:
        conditions.append(run_condition)
        params["run"] = filters.run
    if filters.start:
        conditions.append(sql.SQL("{} >= %(start)s").format(time_column))
        params["start"] = filters.start
    if filters.end:
        conditions.append(sql.SQL("{} <= %(end)s").format(time_column))
        params["end"] = filters.end
    return conditions, params
