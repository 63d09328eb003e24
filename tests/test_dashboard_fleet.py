"""The dashboard's Fleet page (dc_dashboard.fleet) against a real PostgreSQL: robots, last seen,
records today, failing destinations from each robot's newest health record."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
from collections.abc import Iterator
from typing import Any

import pytest

from dc_bringup.local_servers import postgres
from dc_dashboard import fleet, indexes
from dc_dashboard.filters import Filters
from dc_dashboard.queries import Store
from dc_dashboard.server import Dashboard
from dc_dashboard.settings import DashboardSettings, PostgresSettings, S3Settings
from tests.destination_helpers import running_postgres

NOW = dt.datetime(2026, 11, 26, 15, 0, 0)  # UTC


def health(robot: str, **states: dict[str, Any]) -> dict[str, Any]:
    """A health record as the StringStamped measurement forwards dc/destination_health."""
    return {**states, "name": fleet.HEALTH_RECORD, "robot_name": robot, "run_id": "1", "date": 0}


def cpu(robot: str) -> dict[str, Any]:
    return {"name": "cpu", "average": 12.0, "processes": 200, "robot_name": robot, "run_id": "1", "date": 0}


ROWS: list[tuple[dt.timedelta, dict[str, Any]]] = [
    # r1: three cpu rows today, two yesterday; an older health record all ok, the newest says pg fails.
    *[(-dt.timedelta(minutes=m), cpu("r1")) for m in (10, 60, 120)],
    *[(-dt.timedelta(days=1, minutes=m), cpu("r1")) for m in (0, 30)],
    (-dt.timedelta(hours=3), health("r1", pg={"state": "ok"}, s3={"state": "ok"})),
    (
        -dt.timedelta(minutes=5),
        health(
            "r1",
            pg={"state": "failing", "reason": "password authentication failed", "fix": "check the password"},
            s3={"state": "ok"},
        ),
    ),
    # r2: nothing today; its newest health record has pg retrying.
    (-dt.timedelta(days=1, hours=2), cpu("r2")),
    (-dt.timedelta(days=1, hours=1), health("r2", pg={"state": "retrying", "reason": "timeout"})),
    # r4: last seen three days ago (found by the second look, in the whole table).
    (-dt.timedelta(days=3), cpu("r4")),
    # r3: group records (the robot one level down), no health record at all.
    *[
        (-dt.timedelta(minutes=m), {"name": "system", "cpu": {"average": 3.0, "robot_name": "r3"}, "date": 0})
        for m in (30, 40)
    ],
]


def rows_today(connection: Any, table: str) -> dict[str, int]:
    """Each robot's rows of ``table`` since midnight (of NOW), counted."""
    from psycopg import sql

    query = sql.SQL("SELECT data->>'robot_name', count(*) FROM {} WHERE time >= %s GROUP BY 1")
    return dict(connection.execute(query.format(sql.Identifier(table)), (NOW.replace(hour=0, tzinfo=dt.UTC),)))


@pytest.fixture(scope="module")
def database() -> Iterator[PostgresSettings]:
    import psycopg

    from dc_destinations.files_metrics.table import FilesTable

    reason = postgres.missing_reason()
    if reason is not None:
        pytest.fail(reason)  # make test-deps installs it: a skip would hide a missing dependency
    with running_postgres("dc-pg-fleet-") as server:
        settings = PostgresSettings(
            port=server.port, user=server.user, password=server.password, database=server.database, table="dc"
        )
        with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
            # timestamptz, as PgSQL's typed tables have it (the pages show UTC without a zone)
            connection.execute("CREATE TABLE dc (tag text, time timestamptz, data jsonb, record_id text)")
            with connection.cursor() as cursor:
                cursor.executemany(
                    "INSERT INTO dc VALUES ('flb_pgsql', %s, %s::jsonb, %s)",
                    [
                        ((NOW + delta).replace(tzinfo=dt.UTC), json.dumps(r), str(n))
                        for n, (delta, r) in enumerate(ROWS)
                    ],
                )
            FilesTable("files_metrics").prepare(connection)
        assert indexes.create(settings, say=lambda text: None) == 0
        yield settings


def test_the_fleet_overview_gives_each_robot_its_last_row_records_today_and_failing_destinations(
    database: PostgresSettings,
) -> None:
    import psycopg

    store = Store(database)
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        rows, estimated = fleet.overview(store, connection, Filters(), NOW)
        only, _ = fleet.overview(store, connection, Filters(robot="r2"), NOW)
    assert not estimated, "a few rows today: counted"
    assert [r.robot for r in rows] == ["r1", "r3", "r2", "r4"], "most recently seen first"
    r1, r3, r2, r4 = rows
    assert (r4.last_seen, r4.records_today, r4.health_at) == (NOW - dt.timedelta(days=3), 0, None)
    assert (r1.last_seen, r1.records_today) == (NOW - dt.timedelta(minutes=5), 5)  # 3 cpu + 2 health today
    assert r1.failing == [("pg", "password authentication failed — check the password")]
    assert r1.health_at == NOW - dt.timedelta(minutes=5) and r1.retrying == []
    assert (r2.last_seen, r2.records_today, r2.failing, r2.retrying) == (
        NOW - dt.timedelta(days=1, hours=1),
        0,
        [],
        ["pg"],
    )
    assert (r3.last_seen, r3.records_today, r3.health_at) == (NOW - dt.timedelta(minutes=30), 2, None)
    assert [r.robot for r in only] == ["r2"]

    html = fleet.page(rows, NOW)
    assert 'id="stat-robots"><span class="value">4<' in html
    assert 'id="stat-seen-last-hour"><span class="value">2<' in html
    assert 'id="stat-records-today"><span class="value">7<' in html
    assert 'id="stat-failing-robots"><span class="value">1<' in html
    assert "r1: destination pg failing: password authentication failed — check the password" in html
    row = html.split('<tr data-robot="r1">')[1].split("</tr>")[0]
    assert "<td>2026-11-26 14:55:00</td><td class=num>5 min</td><td class=num>5</td>" in row
    assert '<span class="health failing" title="password authentication failed — check the password">pg</span>' in row
    assert '<span class="health retrying">pg retrying</span>' in html.split('<tr data-robot="r2">')[1]


def test_the_fleet_figures_are_index_seeks(database: PostgresSettings) -> None:
    import psycopg

    store = Store(database)
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("SET enable_seqscan = off")  # the table is tiny: would the indexes serve it?
        plans: list[str] = []
        original = connection.execute

        def explained(query: Any, params: Any = None) -> Any:
            from psycopg import sql

            if isinstance(query, sql.Composed) and "LATERAL" in query.as_string(connection):
                plans.append(str(original(sql.SQL("EXPLAIN ") + query, params).fetchall()))
            return original(query, params)

        connection.execute = explained  # type: ignore[method-assign,assignment]
        fleet.overview(store, connection, Filters(), NOW)
    assert len(plans) == 4, plans  # last seen since yesterday, then r4 in the whole table; counts; health
    for plan in plans:
        assert "dc_dash_robot_name_time" in plan or "dc_dash_robot_run_name_time" in plan, plan
    assert all("Seq Scan" not in plan for plan in plans), plans


def test_the_fleet_page_is_served_and_in_the_navigation(database: PostgresSettings) -> None:
    dashboard = Dashboard(DashboardSettings(dataclasses.replace(database), S3Settings()))
    status, html = dashboard.render("/fleet", "")
    assert status == 200, html
    assert 'id="fleet-table"' in html and '<tr data-robot="r1">' in html
    assert '<a href="/fleet" class="active">Fleet</a>' in html


def test_above_the_bound_the_records_today_are_the_planners_estimates_and_said_so(
    database: PostgresSettings,
) -> None:
    import psycopg

    big = dataclasses.replace(database, table="dc_big")
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("CREATE TABLE dc_big (tag text, time timestamptz, data jsonb, record_id text)")
        # r1 a row every 10 s since 6:00 yesterday (half of them today), r2 every 30 s today only.
        connection.execute(
            "INSERT INTO dc_big SELECT 'pg', t, jsonb_build_object('name', 'cpu', 'robot_name', robot), NULL"
            " FROM (VALUES ('r1', 10), ('r2', 30)) AS r(robot, every),"
            " generate_series(%(now)s - CASE robot WHEN 'r1' THEN interval '33 hours' ELSE interval '15 hours' END,"
            "                 %(now)s, every * interval '1 s') AS t",
            {"now": NOW.replace(tzinfo=dt.UTC)},
        )
        counted = rows_today(connection, "dc_big")
    assert indexes.create(big, say=lambda text: None) == 0  # the robot expression's statistics come with its index
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("ANALYZE dc_big")
        store = Store(big)
        rows, estimated = fleet.overview(store, connection, Filters(), NOW, exact_up_to=1000)
        exact, counted_flag = fleet.overview(store, connection, Filters(), NOW)
    assert estimated and not counted_flag
    assert {r.robot: r.records_today for r in exact} == counted
    for row in rows:
        assert abs(row.records_today - counted[row.robot]) <= 0.2 * counted[row.robot], (row, counted)
    html = fleet.page(rows, NOW, estimated)
    assert 'id="estimated"' in html and "are estimates" in html
    assert "<td class=num>\u2248" in html.split('<tr data-robot="r1">')[1]


def test_on_day_partitions_every_robots_estimate_is_one_read_of_the_statistics_not_a_plan_per_robot(
    database: PostgresSettings,
) -> None:
    """An EXPLAIN per robot plans over every partition (100 robots x 30 days: 1.6 s): the robots' shares
    come from the robot index's statistics of each partition instead, still within 20 % of the count."""
    import psycopg

    parted = dataclasses.replace(database, table="dc_days")
    day = NOW.replace(hour=0, tzinfo=dt.UTC)
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute(
            "CREATE TABLE dc_days (tag text, time timestamptz, data jsonb, record_id text) PARTITION BY RANGE (time)"
        )
        for n in range(-3, 2):  # three days back, today, and tomorrow's made ahead (empty)
            low, high = (f"{day + dt.timedelta(days=d):%Y-%m-%d}" for d in (n, n + 1))
            connection.execute(
                f"CREATE TABLE dc_days_{n + 3} PARTITION OF dc_days FOR VALUES FROM ('{low}') TO ('{high}')"
            )
        # r1..r5 a row every 20 s for 3 days (r5 only since this morning), at different rates today.
        connection.execute(
            "INSERT INTO dc_days SELECT 'pg', t, jsonb_build_object('name', 'cpu', 'robot_name', 'r' || r), NULL"
            " FROM generate_series(1, 5) AS r,"
            " generate_series(%(now)s - CASE WHEN r = 5 THEN interval '14 hours' ELSE interval '70 hours' END,"
            "                 %(now)s, interval '20 s') AS t",
            {"now": NOW.replace(tzinfo=dt.UTC)},
        )
        counted = rows_today(connection, "dc_days")
    assert indexes.create(parted, say=lambda text: None) == 0
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("ANALYZE dc_days")
        explained: list[str] = []
        original = connection.execute

        def counting(query: Any, params: Any = None) -> Any:
            from psycopg import sql

            text = query.as_string(connection) if isinstance(query, sql.Composable) else str(query)
            if text.startswith("EXPLAIN"):
                explained.append(text)
            return original(query, params)

        connection.execute = counting  # type: ignore[method-assign,assignment]
        rows, estimated = fleet.overview(Store(parted), connection, Filters(), NOW, exact_up_to=1000)
    assert estimated
    assert len(explained) == 1, explained  # the rows today, whether to estimate: one plan, whatever the robots
    assert {r.robot for r in rows} == set(counted)
    for row in rows:
        assert abs(row.records_today - counted[row.robot]) <= 0.2 * counted[row.robot], (row, counted)
