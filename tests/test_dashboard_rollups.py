"""The dashboard's rollup (dc dashboard --create-rollups) against a real PostgreSQL: the charts of every
robot drawn from it show the means the rows give on the same bucket edges, rows inserted after it was
built (late, by INSERT or COPY) counted, a rolled-back insert and a retried batch's skipped rows not."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers import postgres
from dc_dashboard import indexes, rollup_setup, rollups
from dc_dashboard.filters import Filters
from dc_dashboard.queries import Store
from dc_dashboard.settings import PostgresSettings
from tests.destination_helpers import running_postgres

T0 = dt.datetime(2026, 3, 1, 12, 0, 0)  # UTC
MINUTES = 360  # a row of each record a minute per robot: 600 buckets of 6 h are 36 s, the rollup's 30 s fit


@pytest.fixture(scope="module")
def server() -> Iterator[PostgresSettings]:
    reason = postgres.missing_reason()
    if reason is not None:
        pytest.fail(reason)  # make test-deps installs it: a skip would hide a missing dependency
    with running_postgres("dc-pg-rollup-") as running:
        yield PostgresSettings(
            port=running.port, user=running.user, password=running.password, database=running.database
        )


def _record(name: str, robot: str, run: str, i: int) -> dict[str, Any]:
    """A row's data as DC stores it: position, cpu and memory in groups (robot and run one level down)."""
    meta = {"robot_name": robot, "run_id": run}
    n = int(robot[1:])
    if name == "robot":
        position = {"x": i * 0.37 + n, "y": math.sin(i / 9), "yaw": 0.0, **meta}
        return {"name": "robot", "position": position, "speed": {"computed": 0.5, **meta}, "date": 0}
    if name == "system":
        # Some cpu rows without their number: counted as rows, not in the mean.
        average = None if i % 17 == 5 else float((i * 13 + n) % 100)
        memory = {"used": 30.0 + n + i % 7, **meta}
        return {"name": "system", "cpu": {"average": average, "processes": 9, **meta}, "memory": memory, "date": 0}
    return {"name": "distance_traveled", "distance_traveled": i * 1.5, **meta}


def _rows(robot: str, offset_s: int) -> list[tuple[dt.datetime, str, str]]:
    """A robot's rows: 6 h, run 1 then run 2 (r1) or run 1 alone, at an offset off the rollup's grid."""
    out = []
    for i in range(MINUTES):
        run = "2" if robot == "r1" and i >= MINUTES // 2 else "1"
        when = T0 + dt.timedelta(minutes=i, seconds=offset_s)
        for name in ("robot", "system", "distance_traveled"):
            out.append((when, f"{robot}-{name}-{i}", json.dumps(_record(name, robot, run, i))))
    return out


def _table(server: PostgresSettings, table: str, partitioned: bool) -> PostgresSettings:
    """Records table ``table`` (DC's shape: plain, or by day as partition_by: day makes it) with rows of
    three robots, the dashboard's indexes, and its rollup built."""
    import psycopg
    from psycopg import sql

    settings = dataclasses.replace(server, table=table, files_table=f"{table}_files")
    with psycopg.connect(**server.connect_kwargs(), autocommit=True) as connection:
        name = sql.Identifier(table)
        if partitioned:
            connection.execute(
                sql.SQL(
                    "CREATE TABLE {} (tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL)"
                    " PARTITION BY RANGE (time)"
                ).format(name)
            )
            for day in (T0.date(), T0.date() + dt.timedelta(days=1)):
                connection.execute(
                    sql.SQL("CREATE TABLE {} PARTITION OF {} FOR VALUES FROM ({}) TO ({})").format(
                        sql.Identifier(f"{table}_p{day:%Y%m%d}"), name, sql.Literal(f"{day} 00:00Z"),
                        sql.Literal(f"{day + dt.timedelta(days=1)} 00:00Z"),
                    )
                )  # fmt: skip
            connection.execute(sql.SQL("CREATE UNIQUE INDEX ON {} (record_id, time)").format(name))
        else:
            connection.execute(
                sql.SQL("CREATE TABLE {} (tag varchar, time timestamp, data jsonb, record_id text)").format(name)
            )
            connection.execute(sql.SQL("CREATE UNIQUE INDEX ON {} (record_id)").format(name))
        rows = _rows("r1", 7) + _rows("r2", 13) + _rows("r3", 44)
        with connection.cursor() as cursor:
            cursor.executemany(
                sql.SQL("INSERT INTO {} VALUES ('pg', %s, %s::jsonb, %s)").format(name),
                [(when, data, record_id) for when, record_id, data in rows],
            )
    assert indexes.create(settings, say=lambda text: None) == 0
    assert rollup_setup.create(settings, say=lambda text: None) == 0
    return settings


def _later_rows(settings: PostgresSettings) -> None:
    """What arrives after the rollup was built: a robot's position delivered late (INSERT), a robot never
    seen before (COPY), a retried batch whose row is there already, a transaction rolled back."""
    import psycopg
    from psycopg import sql

    table = sql.Identifier(settings.table)
    late = T0 + dt.timedelta(hours=2, seconds=3)  # the middle of the range: a whole bucket, not an edge
    with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
        record = _record("robot", "r2", "1", 5000)
        connection.execute(
            sql.SQL("INSERT INTO {} VALUES ('pg', %s, %s::jsonb, 'late-1')").format(table), (late, json.dumps(record))
        )
        with connection.cursor() as cursor:
            copy = sql.SQL("COPY {} (tag, time, data, record_id) FROM STDIN").format(table)
            with cursor.copy(copy) as writing:
                for i in range(3):
                    for name in ("robot", "system"):
                        data = json.dumps(_record(name, "r4", "7", 100 + i))
                        writing.write_row(("pg", late + dt.timedelta(minutes=i), data, f"r4-{name}-{i}"))
        # A batch sent again (its answer lost): ON CONFLICT skipped the row, the statement inserted nothing.
        retried = json.dumps(_record("system", "r1", "1", 999))
        connection.execute(
            sql.SQL("INSERT INTO {} VALUES ('pg', %s, %s::jsonb, 'r1-system-3') ON CONFLICT DO NOTHING").format(table),
            (T0 + dt.timedelta(minutes=3, seconds=7), retried),
        )
        with pytest.raises(psycopg.errors.UniqueViolation), connection.transaction():
            connection.execute(
                sql.SQL("INSERT INTO {} VALUES ('pg', %s, %s::jsonb, 'gone')").format(table),
                (late, json.dumps(_record("robot", "r3", "1", 7000))),
            )
            # Fails after the row above went in, and its statement's rollup was added: both undone.
            connection.execute(sql.SQL("INSERT INTO {} VALUES ('pg', %s, '{{}}', 'late-1')").format(table), (late,))


def _expected(
    settings: PostgresSettings, name: str, paths: list[tuple[str, ...]], width: int, start: Any, end: Any
) -> dict[str, list[tuple[float, float | None, float | None]]]:
    """The rows' means (time, a, b) per robot and run in buckets of ``width`` s from the epoch, in Python
    from every row of the table in [start, end]: what the chart must show."""
    import psycopg
    from psycopg import sql

    query = sql.SQL(
        "SELECT extract(epoch FROM time)::float8, data FROM {} WHERE data->>'name' = %s AND time >= %s AND time <= %s"
    ).format(sql.Identifier(settings.table))
    with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
        rows = connection.execute(query, (name, start, end)).fetchall()
    buckets: dict[tuple[str, str, int], list[tuple[float, Any, Any]]] = {}

    def at(data: Any, path: tuple[str, ...]) -> Any:
        for key in path:
            data = data.get(key) if isinstance(data, dict) else None
        return data

    for t, data in rows:
        member = at(data, paths[0][:-1]) or data
        key = (member.get("robot_name", ""), member.get("run_id", ""), math.floor(t / width))
        buckets.setdefault(key, []).append((t, at(data, paths[0]), at(data, paths[1]) if len(paths) > 1 else None))
    out: dict[str, list[tuple[float, float | None, float | None]]] = {}
    for (robot, run, _), found in sorted(buckets.items()):
        a = [v[1] for v in found if v[1] is not None]
        b = [v[2] for v in found if v[2] is not None]
        point = (
            sum(v[0] for v in found) / len(found),
            sum(a) / len(a) if a else None,
            sum(b) / len(b) if b else None,
        )
        out.setdefault(f"{robot} run {run}", []).append(point)
    return out


@pytest.mark.parametrize("partitioned", [False, True], ids=["plain", "by-day"])
def test_the_charts_of_every_robot_from_the_rollup_show_the_rows_means_late_rows_counted(
    server: PostgresSettings, partitioned: bool
) -> None:
    import psycopg

    settings = _table(server, "dc_days" if partitioned else "dc_plain", partitioned)
    _later_rows(settings)
    store = Store(settings)
    start, end = T0 + dt.timedelta(seconds=95), T0 + dt.timedelta(hours=5, seconds=17)
    everything = (T0 - dt.timedelta(days=1), T0 + dt.timedelta(days=1))
    # Without a robot: 600 buckets over the rows' 6 h are 36 s, rounded to 60 (two rollup buckets); the
    # range start-end (not on the grid: its partial buckets' rows come from the table) 30 s.
    with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
        catalog = store.catalog(connection)
        assert len(catalog.rollup_series) == 4, catalog.rollup_series
        for filters, width, (low, high) in (
            (Filters(), 60, everything),
            (Filters(start=start, end=end), 30, (start, end)),
            (Filters(run="1"), 60, everything),
        ):
            trajectory = store.trajectory(connection, filters)
            expected = _expected(settings, "robot", [("position", "x"), ("position", "y")], width, low, high)
            if filters.run:
                expected = {label: points for label, points in expected.items() if label.endswith("run 1")}
            assert [s.label for s in trajectory.series] == sorted(expected)
            for series in trajectory.series:
                want = [v for _, a, b in expected[series.label] for v in (a, b)]
                assert _flat(series.points) == pytest.approx(want, rel=1e-12), (filters, series.label)
            system = store.system(connection, filters)
            for charts, path in ((system.cpu, ("cpu", "average")), (system.memory, ("memory", "used"))):
                expected = _expected(settings, "system", [path], width, low, high)
                if filters.run:
                    expected = {label: points for label, points in expected.items() if label.endswith("run 1")}
                assert [s.label for s in charts] == sorted(expected)
                for series in charts:
                    want = [v for t, a, _ in expected[series.label] if a is not None for v in (t, a)]
                    assert _flat(series.points) == pytest.approx(want, rel=1e-12), (filters, path, series.label)
        # The late row, the new robot's COPY, not the retried nor the rolled-back rows: 4 robots' rows.
        assert store.trajectory(connection, Filters()).positions == 3 * MINUTES + 1 + 3
        assert store.system(connection, Filters()).samples == 3 * MINUTES + 3
        # A run's metres, its counter's rise, from the rollup's max and min: 179, 179, 359 and 359 rows of 1.5 m.
        assert store.distance(connection, Filters()).total_m == pytest.approx((179 + 179 + 359 + 359) * 1.5)
        assert store.trajectory(connection, Filters(robot="r2")).positions == MINUTES + 1  # from the rows
        # Its trigger disabled, the rollup would miss the rows inserted since: the pages read the rows.
        connection.execute(f"ALTER TABLE {settings.table} DISABLE TRIGGER dc_roll_up")
        assert rollups.found(connection, settings.table) == {}
        connection.execute(f"ALTER TABLE {settings.table} ENABLE TRIGGER dc_roll_up")
        assert len(rollups.found(connection, settings.table)) == 4


def _flat(points: list[tuple[float, float]]) -> list[float]:
    return [v for point in points for v in point]


def test_a_value_that_is_no_float_does_not_fail_the_insert_its_row_is_counted_without_it(
    server: PostgresSettings,
) -> None:
    import psycopg

    system = {"name": "system", "cpu": {"average": 12.5, "processes": 3, "robot_name": "r1", "run_id": "1"}}
    with psycopg.connect(**server.connect_kwargs(), autocommit=True) as connection:
        connection.execute("CREATE TABLE dc_odd (tag text, time timestamptz NOT NULL, data jsonb, record_id text)")
        connection.execute("INSERT INTO dc_odd VALUES ('pg', %s, %s, 'first')", (T0, json.dumps(system)))
        # As an operator makes it: the command, its password in the environment (not on the command line).
        made = subprocess.run(
            [str(Path(sys.executable).with_name("dc")), "dashboard", "--create-rollups", "--pg-host", server.host,
             "--pg-port", str(server.port), "--pg-user", server.user, "--pg-database", server.database,
             "--table", "dc_odd", "--files-table", "dc_odd_files"],
            env={**os.environ, "DC_POSTGRES_PASSWORD": server.password}, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert made.returncode == 0, made.stderr
        assert "rollups: 1 series, 1 new" in made.stdout, made.stdout
        # A number beyond float8 (JSON has no bound: 1e400 fails a float8 cast) and a string, in one
        # statement with a good row; then each alone.
        member = '"processes": 3, "robot_name": "r1", "run_id": "1"'
        rows = [f'{{"name": "system", "cpu": {{"average": {v}, {member}}}}}' for v in ("1e400", '"n/a"', "7.5")]
        connection.execute(
            "INSERT INTO dc_odd SELECT 'pg', %s, d::jsonb, 'odd' || n FROM unnest(%s::text[]) WITH ORDINALITY AS r(d, n)",
            (T0 + dt.timedelta(seconds=1), rows),
        )
        for n, data in enumerate(rows[:2]):
            connection.execute("INSERT INTO dc_odd VALUES ('pg', %s, %s::jsonb, %s)", (T0, data, f"alone{n}"))
        counted = connection.execute("SELECT sum(rows), sum(a_rows), sum(a_sum) FROM dc_odd_rollup").fetchone()
    assert counted == (6, 2, 20.0)
