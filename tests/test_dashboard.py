"""`dc dashboard`: its queries against a real PostgreSQL with known rows, its pages, and the whole thing in
headless Chromium over what the tb3_pgsql_minio demo stored, as a user sees it."""

from __future__ import annotations

import datetime as dt
import http.client
import io
import json
import os
import secrets
import shutil
import socket
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from dc_bringup.local_servers import postgres, seaweedfs
from dc_bringup.local_servers.processes import free_port
from dc_bringup.local_servers.run import environment
from dc_dashboard import catalog, charts, indexes
from dc_dashboard.filters import Filters
from dc_dashboard.objects import image_type
from dc_dashboard.queries import Store
from dc_dashboard.server import Dashboard
from dc_dashboard.settings import DashboardSettings, PostgresSettings, S3Settings
from tests.bringup_util import BIN, REPO, Bringup
from tests.destination_helpers import running_postgres

T0 = dt.datetime(2026, 3, 1, 12, 0, 0)
ARTIFACTS = REPO / "test-artifacts" / "dashboard"


# -- pure --------------------------------------------------------------------------------------------


def test_filters_round_trip_through_the_query_string_and_bad_values_are_said() -> None:
    filters = Filters.parse("robot=C3PO&run=2&start=2026-03-01T12:00&end=2026-03-01T13:00:30&state=deleted")
    assert (filters.robot, filters.run, filters.state) == ("C3PO", "2", "deleted")
    assert Filters.parse(filters.query().lstrip("?")) == filters
    assert filters.scope().query() == "?robot=C3PO&run=2&start=2026-03-01T12%3A00%3A00&end=2026-03-01T13%3A00%3A30"
    bad = Filters.parse("start=yesterday&end=2026-01-01&state=lost")
    assert bad.start is None and bad.state == "" and len(bad.problems) == 2


def test_measurements_are_found_by_their_shape_alone_or_in_groups() -> None:
    robot_group = {"name": "robot", "position": {"x": 1.0, "y": 2.0, "yaw": 0.1}, "speed": {"computed": 0.0}}
    system_group = {"name": "system", "cpu": {"average": 3.0, "processes": 9}, "memory": {"used": 40.0}}
    map_record = {"name": "map", "resolution": 0.05, "origin": {"x": 0, "y": 0, "yaw": 0}, "width": 2, "height": 2}
    found = catalog.sources_of({"robot": [robot_group], "system": [system_group], "map": [map_record]})
    assert found["position"] == [("robot", ("position",))]
    assert found["cpu"] == [("system", ("cpu",))] and found["memory"] == [("system", ("memory",))]
    assert found["map"] == [("map", ())]  # its origin is not a position


def test_charts_draw_every_series_and_say_when_there_is_nothing() -> None:
    from dc_dashboard.queries import Series

    svg = charts.time_chart([Series("a", [(0.0, 1.0), (60.0, 2.0)])], chart_id="c", unit="%")
    assert svg.count('class="series"') == 1 and 'data-points="2"' in svg
    assert "nothing stored" in charts.time_chart([], chart_id="c", unit="%")
    assert charts.nice_ticks(0, 100) == [0, 20, 40, 60, 80, 100]
    assert image_type(b"\x89PNG\r\n\x1a\n...") == "image/png" and image_type(b"<svg") is None


def test_the_health_page_shows_each_destinations_last_delivery_from_the_metrics() -> None:
    from dc_dashboard.health import ServerHealth
    from dc_dashboard.pages import health

    delivered = dt.datetime(2026, 11, 25, 10, 0, 5, tzinfo=dt.UTC).timestamp()
    server = ServerHealth("destination_server", "http://x/api/v1/metrics")
    server.destinations = {
        "pg": {
            "sent": 4,
            "last_delivery": delivered,
            "last_error": "timeout",
            "last_error_time": delivered - 5,
            "health": {"state": "failing", "for_s": 300.0, "reason": "password authentication failed", "fix": "check"},
        },
        "s3": {"sent": 0, "last_delivery": None, "last_error": "", "health": {"state": "ok"}},
    }
    # The newest row's time is the record's own (simulated time, here): shown apart, labelled as such.
    page = health([server], {"pg": dt.datetime(2023, 11, 14, 22, 0)}, [], [], [], now=delivered + 12)
    pg, s3 = page.split("<tr><td>pg</td>")[1], page.split("<tr><td>s3</td>")[1]
    assert "<td class=delivered>2026-11-25 10:00:05</td><td>2023-11-14 22:00:00</td>" in pg
    assert "<td>2026-11-25 10:00:00: timeout</td>" in pg
    assert s3.startswith('<td><span class="health ok">ok</span></td><td class=num>')
    assert "<td class=delivered>\u2013</td>" in s3
    # A failing destination: its state in the table, and a notice with the reason and the fix above it.
    assert pg.startswith('<td><span class="health failing" title="password authentication failed — check">')
    assert "destination_server: destination pg failing: password authentication failed — check" in page
    assert 'id="stat-last-delivery"><span class="value">12 s ago' in page
    assert "last delivery" in page and "newest row's record time" in page


# -- queries against a real PostgreSQL -------------------------------------------------------------------


# -- the HTTP server on its own: Host allow-list, timeouts, connection cap (no PostgreSQL needed) ----------


@pytest.fixture(params=["roomy"])
def dashboard_server(request: pytest.FixtureRequest) -> Iterator[Any]:
    """A dashboard without a database; ``tight``: two connections at once, idle ones closed after 1 s."""
    from dc_dashboard.server import make_server

    # Roomy for the tests of other things: on a loaded machine the handler of the previous request may
    # still hold its slot when the next one comes, and a third request would be answered busy.
    limits: dict[str, Any] = {"max_connections": 2, "timeout": 1.0} if request.param == "tight" else {}
    server = make_server(
        DashboardSettings(PostgresSettings(), S3Settings()),
        "127.0.0.1",
        0,
        quiet=True,
        extra_hosts=["robot.example.org"],
        **limits,
    )
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5.0)


def _status_for_host(server: Any, host: str | None, path: str = "/favicon.ico") -> tuple[int, str]:
    """Status and body of GET ``path`` sent with this Host header (None: without one)."""
    connection = http.client.HTTPConnection("127.0.0.1", server.server_address[1], timeout=5)
    try:
        connection.putrequest("GET", path, skip_host=True)
        if host is not None:
            connection.putheader("Host", host)
        connection.endheaders()
        reply = connection.getresponse()
        return reply.status, reply.read().decode()
    finally:
        connection.close()


def test_requests_for_another_host_are_refused_dns_rebinding(dashboard_server: Any) -> None:
    port = dashboard_server.server_address[1]
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", "LOCALHOST", f"[::1]:{port}", "robot.example.org"):
        assert _status_for_host(dashboard_server, host)[0] == 204, host
    # A rebinding page's own name (pointed at 127.0.0.1 by its DNS), or none at all: nothing rendered.
    refused: list[str | None] = [f"attacker.example:{port}", "127.0.0.1.attacker.example", "", None]
    for name in refused:
        status, body = _status_for_host(dashboard_server, name, "/")
        assert status == 421, name
        assert "--allowed-host" in body and "<html" not in body


@pytest.mark.parametrize("dashboard_server", ["tight"], indirect=True)
def test_an_idle_connection_does_not_hold_the_dashboard_and_excess_ones_are_refused(dashboard_server: Any) -> None:
    port = dashboard_server.server_address[1]
    with socket.create_connection(("127.0.0.1", port)):
        started = time.monotonic()
        assert _status_for_host(dashboard_server, "127.0.0.1")[0] == 204
        assert time.monotonic() - started < 2.0
    # As many silent connections as it serves at once: the next one is refused at once, and counted.
    idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(2)]
    try:
        deadline = time.monotonic() + 5.0
        while dashboard_server.refused == 0:
            assert time.monotonic() < deadline, "never refused beyond max_connections"
            status, body = _status_for_host(dashboard_server, "127.0.0.1")
            assert status in (204, 503) and (status == 204 or "busy" in body)
        # The silent ones are timed out after 1 s: served again while they are still open.
        deadline = time.monotonic() + 5.0
        while _status_for_host(dashboard_server, "127.0.0.1")[0] != 204:
            assert time.monotonic() < deadline, "the idle connections were never timed out"
    finally:
        for sock in idle:
            sock.close()


def test_allowed_hosts_default_to_the_listening_address_and_loopback() -> None:
    from dc_dashboard.server import allowed_hosts

    assert allowed_hosts("127.0.0.1") == {"127.0.0.1", "localhost", "::1"}
    assert allowed_hosts("192.0.2.7", ["Robot.Example.org."]) == {
        "192.0.2.7", "127.0.0.1", "localhost", "::1", "robot.example.org"
    }  # fmt: skip
    assert socket.gethostname().lower() in allowed_hosts("0.0.0.0")


def _run_rows(robot: str, run: str, start: dt.datetime, seconds: int, cpu: float) -> list[tuple[Any, ...]]:
    """One row per second of each kind the demo stores, shaped as DC stores them (groups carry robot and run below)."""
    meta = {"robot_name": robot, "run_id": run}
    rows: list[dict[str, Any]] = []
    for i in range(seconds):
        position: dict[str, Any] = {"x": float(i), "y": 1.0, "yaw": 0.0, "name": "position", **meta}
        rows.append({"name": "robot", "position": position, "speed": {"computed": 1.0, "name": "speed", **meta}})
        rows.append(
            {
                "name": "system",
                "cpu": {"average": cpu, "processes": 5, "sorted": [], **meta},
                "memory": {"used": 30.0, **meta},
            }
        )
        rows.append({"name": "distance_traveled", "distance_traveled": float(i), **meta})
    rows = [{**r, "date": 0} for r in rows]
    timed: list[tuple[dt.datetime, dict[str, Any]]] = [
        (start + dt.timedelta(seconds=i // 3), r) for i, r in enumerate(rows)
    ]
    key = f"{robot}/inspected/{run}.jpg"
    camera: dict[str, Any] = {"name": "front_camera", "camera_name": "front_camera", **meta, "remote_paths": {"minio": {"inspected": key}},
              "inspected": {"barcode": [{"data": f"PAL-{robot}-{run}", "type": "CODE128", "top": 0, "left": 0, "width": 5, "height": 5}]}}  # fmt: skip
    timed.append((start + dt.timedelta(seconds=2), camera))
    map_record: dict[str, Any] = {"name": "map", "resolution": 0.5, "origin": {"x": -1.0, "y": -1.0, "yaw": 0.0}, "width": 40, "height": 10,
                  **meta, "remote_paths": {"minio": {"png": f"{robot}/map.png"}}}  # fmt: skip
    timed.append((start, map_record))
    return [("flb_pgsql", when, json.dumps(r), f"{robot}-{run}-{n}") for n, (when, r) in enumerate(timed)]


@pytest.fixture(scope="module")
def database() -> Iterator[PostgresSettings]:
    import psycopg

    from dc_destinations.files_metrics.table import FilesTable

    reason = postgres.missing_reason()
    if reason is not None:
        pytest.fail(reason)  # make test-deps installs it: a skip would hide a missing dependency
    with running_postgres("dc-pg-dash-") as server:
        settings = PostgresSettings(
            port=server.port, user=server.user, password=server.password, database=server.database
        )
        rows = (
            _run_rows("C3PO", "1", T0, 10, cpu=10.0)  # 9 m
            + _run_rows("C3PO", "2", T0 + dt.timedelta(hours=1), 5, cpu=50.0)  # 4 m
            + _run_rows("R2D2", "1", T0, 20, cpu=30.0)  # 19 m
        )
        with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
            connection.execute("CREATE TABLE dc (tag varchar, time timestamp, data jsonb, record_id text)")
            connection.execute("CREATE UNIQUE INDEX dc_record_id ON dc (record_id)")
            with connection.cursor() as cursor:
                cursor.executemany("INSERT INTO dc VALUES (%s, %s, %s::jsonb, %s)", rows)
            FilesTable("files_metrics").prepare(connection)
            files = [
                # robot, record_id (its run's camera row), uploaded, verified, deleted
                ("C3PO", "C3PO-1-30", True, True, True),
                ("C3PO", "C3PO-2-15", True, True, False),
                ("C3PO", "C3PO-2-16", False, False, False),
                ("R2D2", "R2D2-1-60", True, True, True),
            ]
            for i, (robot, record_id, uploaded, verified, deleted) in enumerate(files):
                connection.execute(
                    "INSERT INTO files_metrics (timestamp, robot_name, robot_id, group_name, local_path, remote_path,"
                    " uploaded, on_filesystem, deleted, storage_type, content_type, size, updated_at, record_id,"
                    " bucket, verified_at) VALUES (%s, %s, '', 'front_camera', %s, %s, %s, %s, %s, 'minio',"
                    " 'image/jpeg', 100, now(), %s, 'b', %s)",
                    (T0 + dt.timedelta(minutes=i), robot, f"/d/{i}.jpg", f"minio://b/{i}.jpg", uploaded,
                     not deleted, deleted, record_id, T0 if verified else None),
                )  # fmt: skip
        yield settings


def test_the_numbers_follow_the_robot_run_and_time_filters(database: PostgresSettings) -> None:
    store = Store(database)
    with store.connection() as connection:
        assert store.robots(connection) == ["C3PO", "R2D2"]
        assert store.runs(connection, "C3PO") == ["2", "1"]

        def metres(**filters: Any) -> float:
            return round(store.distance(connection, Filters(**filters)).total_m, 6)

        assert metres() == 32.0
        assert metres(robot="C3PO") == 13.0
        assert metres(robot="C3PO", run="2") == 4.0
        assert metres(robot="R2D2", start=T0, end=T0 + dt.timedelta(seconds=5)) == 5.0

        def cpu(**filters: Any) -> float | None:
            return store.system(connection, Filters(**filters)).cpu_average

        assert cpu(robot="C3PO", run="1") == 10.0 and cpu(robot="C3PO", run="2") == 50.0
        assert cpu(robot="C3PO") == pytest.approx((10 * 10 + 50 * 5) / 15)

        # Every robot's run N (no robot): read within the run's span (a seek per robot), the same as the
        # robots' own pages put together.
        for run in ("1", "2", "3"):
            assert metres(run=run) == sum(metres(robot=r, run=run) for r in ("C3PO", "R2D2")), run
            explored = store.explore(connection, Filters(name="system", run=run)).records
            each = [
                r
                for robot in ("C3PO", "R2D2")
                for r in store.explore(connection, Filters(name="system", robot=robot, run=run)).records
            ]
            assert sorted(explored, key=lambda r: (r[0], r[1])) == sorted(each, key=lambda r: (r[0], r[1])), run
            found = [i.key for i in store.inspections(connection, Filters(run=run))[0]]
            assert sorted(found) == sorted(
                i.key
                for robot in ("C3PO", "R2D2")
                for i in store.inspections(connection, Filters(robot=robot, run=run))[0]
            ), run
        assert store.explore(connection, Filters(name="system", run="2")).records, "run 2 has system records"
        assert metres(run="9") == 0.0 and not store.explore(connection, Filters(name="system", run="9")).records

        trajectory = store.trajectory(connection, Filters(robot="R2D2"))
        assert trajectory.positions == 20 and [len(s.points) for s in trajectory.series] == [20]
        assert trajectory.map is not None and trajectory.map["key"] == "R2D2/map.png"
        assert store.trajectory(connection, Filters(robot="C3PO")).positions == 15

        inspections, more = store.inspections(connection, Filters(robot="C3PO"))
        assert [i.codes[0]["data"] for i in inspections] == ["PAL-C3PO-2", "PAL-C3PO-1"] and not more
        assert inspections[0].key == "C3PO/inspected/2.jpg"

        assert store.files(connection, Filters()).counts == {
            "all": 4,
            "uploaded": 3,
            "verified": 3,
            "deleted": 2,
            "pending": 1,
        }
        assert store.files(connection, Filters(robot="C3PO")).counts["all"] == 3
        assert store.files(connection, Filters(robot="C3PO", run="2")).counts["all"] == 2
        page = store.files(connection, Filters(robot="C3PO", state="deleted"))
        assert [r["local_path"] for r in page.rows] == ["/d/0.jpg"]


def test_the_queries_use_the_indexes_it_creates(database: PostgresSettings) -> None:
    import psycopg

    assert indexes.create(database, say=lambda text: None) == 0
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        assert indexes.missing(connection, database) == []
        # The table is tiny: forbid the sequential scan to see whether the expressions match the indexes'.
        connection.execute("SET enable_seqscan = off")
        store = Store(database)
        where, params = store._where(Filters(robot="C3PO", run="2"), "system")
        from psycopg import sql

        plan = connection.execute(sql.SQL("EXPLAIN SELECT count(*) FROM dc WHERE {}").format(where), params).fetchall()
    assert "dc_dash_robot_run_name_time" in str(plan), plan


def test_the_runs_without_a_robot_come_from_the_newest_rows_through_the_tag_index(database: PostgresSettings) -> None:
    import psycopg
    from psycopg import sql

    from dc_dashboard.queries import _NEWEST_RUNS

    assert indexes.create(database, say=lambda text: None) == 0
    store = Store(database)
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("SET enable_seqscan = off")  # a tiny table: would a large one be sorted whole?
        assert store.runs(connection, "") == ["2", "1"]
        query = sql.SQL("EXPLAIN " + _NEWEST_RUNS).format(t=store.table, run=indexes.RUN)
        plan = "\n".join(row[0] for row in connection.execute(query).fetchall())
    assert "Index Scan Backward using dc_dash_tag_time" in plan and 'Sort Key: dc."time"' not in plan, plan


def test_the_files_of_a_robots_run_are_found_without_an_index_on_record_id(database: PostgresSettings) -> None:
    import psycopg
    from psycopg import sql

    from dc_dashboard.queries import _filtered

    # A partitioned records table DC makes has no index on record_id alone (its unique btree begins with the robot).
    assert indexes.create(database, say=lambda text: None) == 0
    store, filters = Store(database), Filters(robot="C3PO", run="2")
    with psycopg.connect(**database.connect_kwargs()) as connection:  # one transaction, rolled back
        connection.execute("DROP INDEX dc_record_id")
        connection.execute("SET LOCAL enable_seqscan = off")
        assert store.files(connection, filters).counts["all"] == 2
        conditions, params = _filtered(
            filters,
            robot_column=sql.SQL("robot_name"),
            time_column=sql.SQL("timestamp"),
            run_condition=store.files_run_condition(filters),
        )
        query = sql.SQL("EXPLAIN SELECT 1 FROM files_metrics f WHERE {}").format(sql.SQL(" AND ").join(conditions))
        plan = "\n".join(row[0] for row in connection.execute(query, params).fetchall())
        connection.rollback()
    # The run's rows of the robot, sought in the dashboard's (robot, run, name, time) index: not every row read.
    assert "dc_dash_robot_run_name_time" in plan and "'C3PO'::text" in plan.split("dc_dash_robot_run_name_time")[1]
    assert "Seq Scan on dc" not in plan, plan


def _records_table(database: PostgresSettings, table: str, files_table: str = "files_metrics") -> PostgresSettings:
    """The settings of a new, empty records table ``table`` (DC's columns) in the module's server."""
    import dataclasses

    import psycopg
    from psycopg import sql

    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute(
            sql.SQL("CREATE TABLE {} (tag varchar, time timestamp, data jsonb, record_id text)").format(
                sql.Identifier(table)
            )
        )
    return dataclasses.replace(database, table=table, files_table=files_table)


def test_the_files_of_a_run_without_a_robot_are_those_its_records_brought_found_by_each_robots_span(
    database: PostgresSettings,
) -> None:

    import psycopg
    from psycopg import sql

    from dc_destinations.files_metrics.table import FilesTable

    # Two robots, two runs each, interleaved in time; each run's camera record brought a file (robot named)
    # and so did its system group record (the robot one level down: files_metrics has no robot name).
    runs = [("C3PO", "1", T0), ("R2D2", "1", T0 + dt.timedelta(seconds=5)), ("R2D2", "2", T0 + dt.timedelta(minutes=20)),
            ("C3PO", "2", T0 + dt.timedelta(hours=1))]  # fmt: skip
    settings = _records_table(database, "dc_runs", files_table="files_runs")
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        FilesTable("files_runs").prepare(connection)
        for robot, run, start in runs:
            rows = _run_rows(robot, run, start, 10, cpu=1.0)
            with connection.cursor() as cursor:
                cursor.executemany("INSERT INTO dc_runs VALUES (%s, %s, %s::jsonb, %s)", rows)
            camera, system = rows[-2], rows[1]
            for name, file_robot, (_, when, _, record_id) in (("front_camera", robot, camera), ("system", "", system)):
                connection.execute(
                    "INSERT INTO files_runs (timestamp, robot_name, robot_id, group_name, local_path, remote_path,"
                    " uploaded, on_filesystem, deleted, storage_type, content_type, size, updated_at, record_id,"
                    " bucket) VALUES (%s, %s, '', %s, %s, %s, true, true, false, 'minio', 'image/jpeg', 100, now(),"
                    " %s, 'b')",
                    (when, file_robot, name, f"/d/{record_id}", f"s3://b/{record_id}", record_id),
                )
    assert indexes.create(settings, say=lambda text: None) == 0
    bounded, by_record = Store(settings), Store(settings)
    # Each file's record looked up by record_id, as before: what the page must still show.
    by_record.files_run_condition = lambda filters, connection=None: Store.files_run_condition(  # type: ignore[method-assign]
        by_record, filters
    )
    with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
        for filters in (Filters(run="1"), Filters(run="2"), Filters(run="2", start=T0 + dt.timedelta(minutes=30)),
                        Filters(run="3")):  # fmt: skip
            found, expected = bounded.files(connection, filters), by_record.files(connection, filters)
            assert (found.rows, found.counts) == (expected.rows, expected.counts), filters
        assert [r["local_path"] for r in bounded.files(connection, Filters(run="1")).rows] == [
            "/d/R2D2-1-30", "/d/R2D2-1-1", "/d/C3PO-1-30", "/d/C3PO-1-1"
        ]  # fmt: skip
        condition = bounded.files_run_condition(Filters(run="2"), connection)
        connection.execute("SET enable_seqscan = off")  # a tiny table: would a large one be read whole?
        query = sql.SQL("EXPLAIN SELECT count(*) FROM files_runs f WHERE {}").format(condition)
        plan = "\n".join(row[0] for row in connection.execute(query, {"run": "2"}).fetchall())
    assert "Seq Scan" not in plan, plan  # each robot's span of files_metrics, not every file


def test_a_fleets_plots_are_averaged_by_postgresql_every_robot_drawn_in_wider_buckets_when_many(
    database: PostgresSettings,
) -> None:

    import psycopg

    from dc_dashboard import queries

    # 40 robots x 700 s of a position and a cpu record a second: 40 x 600 buckets would be 24,000 points.
    settings = _records_table(database, "dc_fleet")
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute(
            "INSERT INTO dc_fleet SELECT 'pg', %(t0)s + s * interval '1 s' + r * interval '10 ms',"
            " jsonb_build_object('name', m, 'robot_name', 'r' || lpad(r::text, 2, '0'), 'run_id', '1')"
            "   || CASE m WHEN 'position' THEN jsonb_build_object('x', r + sin(s / 50.0), 'y', cos(s / 7.0), 'yaw', 0)"
            "      ELSE jsonb_build_object('average', (r * 7 + s) %% 100, 'processes', 1) END, m || r || '-' || s"
            " FROM generate_series(1, 40) AS r, generate_series(0, 699) AS s, unnest(ARRAY['position', 'cpu']) AS m",
            {"t0": T0},
        )
        raw = connection.execute(
            "SELECT extract(epoch FROM time)::float8, (data->>'x')::float8, (data->>'y')::float8 FROM dc_fleet"
            " WHERE data->>'robot_name' = 'r07' AND data->>'name' = 'position' ORDER BY time"
        ).fetchall()
        span = connection.execute(
            "SELECT extract(epoch FROM min(time))::float8, extract(epoch FROM max(time))::float8 FROM dc_fleet"
            " WHERE data->>'name' = 'position'"
        ).fetchone()
        cpu = connection.execute(
            "SELECT avg((data->>'average')::float8), max((data->>'average')::float8), count(*) FROM dc_fleet"
            " WHERE data->>'name' = 'cpu'"
        ).fetchone()
    assert span is not None and cpu is not None
    assert indexes.create(settings, say=lambda text: None) == 0
    store = Store(settings)

    def averaged(count: int, low: float, high: float) -> list[tuple[float, float]]:
        """r07's positions averaged in Python over ``count`` buckets of the time from ``low`` to ``high``
        (the filters' rows' first and last), as width_bucket makes them."""
        high += 0.001
        buckets: dict[int, list[tuple[float, float]]] = {}
        for t, x, y in raw:
            buckets.setdefault(int((t - low) / (high - low) * count), []).append((x, y))
        return [(sum(x for x, _ in b) / len(b), sum(y for _, y in b) / len(b)) for _, b in sorted(buckets.items())]

    def same(points: list[tuple[float, float]], expected: list[tuple[float, float]]) -> bool:
        flat = [v for point in points for v in point]
        return flat == pytest.approx([v for point in expected for v in point], abs=1e-9)

    with psycopg.connect(**settings.connect_kwargs(), autocommit=True) as connection:
        alone = store.trajectory(connection, Filters(robot="r07"))
        fleet = store.trajectory(connection, Filters())
        system = store.system(connection, Filters())
    assert [s.label for s in alone.series] == ["r07 run 1"] and alone.positions == 700
    # As before: 600 buckets, a robot alone.
    assert same(alone.series[0].points, averaged(queries.POINTS, raw[0][0], raw[-1][0]))
    # Every robot drawn (the 20,000-row cut left robots 34 to 40 out), each in buckets of twice the time.
    assert [s.label for s in fleet.series] == [f"r{n:02d} run 1" for n in range(1, 41)] and fleet.positions == 28_000
    assert queries.CHART_POINTS // 40 == 300 and sum(len(s.points) for s in fleet.series) == 40 * 300
    assert same(fleet.series[6].points, averaged(300, span[0], span[1]))
    assert system.cpu_average == pytest.approx(cpu[0]) and (system.cpu_max, system.samples) == (cpu[1], cpu[2])
    assert len(system.cpu) == 40


def test_its_indexes_are_built_on_a_partitioned_table_too(database: PostgresSettings) -> None:
    import dataclasses

    import psycopg

    # PgSQL's partition_by: PostgreSQL refuses CREATE INDEX CONCURRENTLY on a partitioned table.
    partitioned = dataclasses.replace(database, table="dc_by_day")
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute(
            "CREATE TABLE dc_by_day (tag text, time timestamptz NOT NULL, data jsonb, record_id text)"
            " PARTITION BY RANGE (time)"
        )
        connection.execute(
            "CREATE TABLE dc_by_day_p20260301 PARTITION OF dc_by_day FOR VALUES FROM ('2026-03-01') TO ('2026-03-02')"
        )
    assert indexes.create(partitioned, say=lambda text: None) == 0
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        assert indexes.missing(connection, partitioned) == []


def test_pages_render_the_numbers_and_say_what_is_wrong(database: PostgresSettings) -> None:
    dead_port = free_port()
    dashboard = Dashboard(
        DashboardSettings(
            database, S3Settings(), metrics=(("destination_server", f"http://127.0.0.1:{dead_port}/api/v1/metrics"),)
        )
    )
    status, html = dashboard.render("/", "robot=C3PO&run=2")
    assert status == 200 and 'id="stat-distance"><span class="value">4.0 m' in html
    assert database.password not in html
    status, html = dashboard.render("/health", "")
    assert status == 200 and f"cannot read http://127.0.0.1:{dead_port}/api/v1/metrics" in html
    status, html = dashboard.render("/files", "state=pending")
    assert status == 200 and html.count("<tr class=file>") == 1

    down = Dashboard(DashboardSettings(PostgresSettings(port=dead_port, password="secret-pw"), S3Settings()))
    status, html = down.render("/system", "")
    assert status == 503 and f"PostgreSQL postgresql://127.0.0.1:{dead_port}/" in html and "Traceback" not in html
    assert "secret-pw" not in html


def test_an_empty_panel_names_what_to_collect_and_blames_filters_only_when_they_are_the_cause(
    database: PostgresSettings,
) -> None:
    import dataclasses

    import psycopg

    # The original's QR demo stores positions but no distance, CPU or memory: the panels said "0.0 m"
    # and "nothing stored for these filters".
    positions_only = dataclasses.replace(database, table="dc_positions_only")
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("CREATE TABLE dc_positions_only (tag varchar, time timestamp, data jsonb, record_id text)")
        with connection.cursor() as cursor:
            cursor.executemany(
                "INSERT INTO dc_positions_only VALUES (%s, %s, %s::jsonb, %s)",
                [row for row in _run_rows("C3PO", "1", T0, 3, cpu=1.0) if '"name": "robot"' in row[2]],
            )
    dashboard = Dashboard(DashboardSettings(positions_only, S3Settings()))
    status, html = dashboard.render("/", "")
    assert status == 200 and 'id="stat-distance"><span class="value">\u2013</span>' in html, html
    assert "distance traveled: not collected" in html
    assert "collect dc_measurements/DistanceTraveled into it" in html and "for these filters" not in html
    status, html = dashboard.render("/system", "")
    assert status == 200
    assert "collect dc_measurements/Cpu into it" in html and "collect dc_measurements/Memory into it" in html

    # Where the table holds them, an empty panel is the filters' doing, and says so.
    everything = Dashboard(DashboardSettings(database, S3Settings()))
    status, html = everything.render("/system", "robot=NOBODY")
    assert status == 200 and "nothing stored for these filters" in html and "collect dc_measurements" not in html
    status, html = everything.render("/", "robot=NOBODY")
    assert "no distance_traveled records for these filters" in html and "not collected" not in html


def test_quick_ranges_follow_the_clock_and_refresh_takes_only_the_offered_periods() -> None:
    now = dt.datetime(2026, 11, 26, 20, 0, 0)
    quick = Filters.parse("robot=C3PO&last=15m&start=2020-01-01T00:00:00&refresh=30", now=now)
    assert (quick.start, quick.end, quick.refresh, quick.problems) == (now - dt.timedelta(minutes=15), None, 30, ())
    # The link keeps the quick range, not the dates of the moment it was drawn: a refreshed page moves on.
    assert quick.query() == "?robot=C3PO&last=15m&refresh=30"
    wrong = Filters.parse("last=3h&refresh=7")
    assert (wrong.last, wrong.start, wrong.refresh) == ("", None, 0)
    assert [p.split(":")[0] for p in wrong.problems] == ["last", "refresh"]


def test_the_explorer_shows_any_record_name_its_numbers_over_time_and_its_records(
    database: PostgresSettings, monkeypatch: pytest.MonkeyPatch
) -> None:
    from dc_dashboard import queries

    dashboard = Dashboard(DashboardSettings(database, S3Settings()))
    status, html = dashboard.render("/explore", "robot=C3PO")
    assert status == 200
    listed = html.partition('<ul id="explore-names">')[2].partition("</ul>")[0]
    for name in ("distance_traveled", "front_camera", "map", "robot", "system"):
        assert f">{name}</a>" in listed, listed

    status, html = dashboard.render("/explore", "name=system&robot=C3PO&run=2")
    assert status == 200
    # Every number of the record, found from its shape: group members' fields by their path.
    for label in ("cpu.average", "cpu.processes", "memory.used"):
        assert f"<h2>{label}</h2>" in html, label
    assert 'id="explore-chart-0"' in html and 'class="chart empty"' not in html
    table = html.partition('<table id="explore-records">')[2].partition("</table>")[0]
    assert table.count("<tr><td class=when>") == 5  # C3PO's run 2: five seconds of system records
    assert "&quot;average&quot;: 50.0" in table and "C3PO" in table

    monkeypatch.setattr(queries, "EXPLORE_PAGE", 10)
    store = Store(database)
    with store.connection() as connection:
        first = store.explore(connection, Filters(name="robot", robot="R2D2"))
        assert len(first.records) == 10 and first.more
        second = store.explore(connection, Filters(name="robot", robot="R2D2", before=first.records[-1][0]))
    assert [r[0] for r in first.records + second.records] == sorted(
        (r[0] for r in first.records + second.records), reverse=True
    )
    assert len({r[0] for r in first.records + second.records}) == 20 and not second.more


def test_the_camera_page_finds_images_by_the_code_read_and_opens_them_full_size(database: PostgresSettings) -> None:
    dashboard = Dashboard(DashboardSettings(database, S3Settings()))
    status, html = dashboard.render("/camera", "code=pal-c3po-2")  # any case, any part of the code
    assert status == 200 and html.count("<figure>") == 1 and "PAL-C3PO-2" in html
    assert '<a class="zoom" href="/image?key=C3PO%2Finspected%2F2.jpg" target="_blank"' in html
    status, html = dashboard.render("/camera", "code=PAL-%25")  # a % is a character, not a pattern
    assert status == 200 and "<figure>" not in html and "no inspected image with a code holding PAL-%" in html
    status, html = dashboard.render("/", "refresh=30&last=24h")
    assert "<meta http-equiv=refresh content=30>" in html and 'id="quick-last-24h" class="active"' in html


def test_the_filters_dates_are_utc_whatever_zone_the_database_is_set_to(database: PostgresSettings) -> None:
    import psycopg

    # A table of DC's new shape (timestamptz) in a database whose zone is not UTC.
    zoned = PostgresSettings(**{**database.__dict__, "table": "dc_zoned"})
    with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
        connection.execute("CREATE TABLE dc_zoned (tag varchar, time timestamptz, data jsonb, record_id text)")
        connection.execute(
            "INSERT INTO dc_zoned SELECT tag, time AT TIME ZONE 'UTC', data, record_id FROM dc"
            " WHERE data->>'name' = 'distance_traveled' AND data->>'robot_name' = 'R2D2'"
        )
        connection.execute(f"ALTER DATABASE {database.database} SET timezone = 'Pacific/Honolulu'")
    try:
        store = Store(zoned)
        with store.connection() as connection:
            metres = store.distance(connection, Filters(start=T0, end=T0 + dt.timedelta(seconds=5))).total_m
        assert metres == 5.0  # the same five seconds as in the UTC table (not 10 hours off: nothing)
    finally:
        with psycopg.connect(**database.connect_kwargs(), autocommit=True) as connection:
            connection.execute(f"ALTER DATABASE {database.database} RESET timezone")


# -- in a browser, over what the demo stored --------------------------------------------------------------


def _browser() -> Any:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.fail("chromium and chromium-driver are not installed (make test-deps)")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for argument in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1366,900",
        "--hide-scrollbars",
    ):
        options.add_argument(argument)
    return webdriver.Chrome(options=options, service=Service(driver))


def _screenshot(browser: Any, folder: Path, name: str) -> None:
    height = browser.execute_script("return document.documentElement.scrollHeight")
    browser.set_window_size(1366, max(700, min(int(height) + 20, 3000)))
    folder.mkdir(parents=True, exist_ok=True)
    browser.save_screenshot(str(folder / f"dashboard-{name}.png"))
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shutil.copy(folder / f"dashboard-{name}.png", ARTIFACTS)
    browser.set_window_size(1366, 900)


def _insert_inspection(dsn: dict[str, Any], s3: Any, robot: str, run: str) -> None:
    """A camera record and its uploaded image, as the demo stores them, for a run too short to inspect a shelf."""
    import cv2
    import numpy as np
    import psycopg

    image = np.full((240, 320, 3), 235, np.uint8)
    cv2.putText(image, "PAL-1000", (60, 130), cv2.FONT_HERSHEY_SIMPLEX, 1.2, (0, 0, 0), 3)
    ok, jpeg = cv2.imencode(".jpg", image)
    assert ok
    key = f"{robot}/inserted/front_camera/inspected/test.jpg"
    s3.client().upload_fileobj(io.BytesIO(jpeg.tobytes()), s3.bucket, key)
    record = {"name": "front_camera", "camera_name": "front_camera", "robot_name": robot, "run_id": run,
              "remote_paths": {"minio": {"inspected": key}},
              "inspected": {"barcode": [{"data": "PAL-1000", "type": "CODE128", "top": 90, "left": 50, "width": 200, "height": 60}]}}  # fmt: skip
    with psycopg.connect(**dsn, autocommit=True) as connection:
        connection.execute(
            "INSERT INTO dc (tag, time, data, record_id) SELECT 'flb_pgsql', max(time), %s::jsonb, 'inserted-by-test' FROM dc",
            (json.dumps(record),),
        )


@pytest.mark.e2e
def test_the_dashboard_in_a_browser_over_the_pgsql_minio_demo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import psycopg
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    for missing in (postgres.missing_reason(), seaweedfs.missing_reason()):
        if missing is not None:
            pytest.fail(missing)
    pg_folder = Path(tempfile.mkdtemp(prefix="dc-pg-dash-e2e-"))
    pg = postgres.PostgresServer(pg_folder, password=secrets.token_urlsafe(12))
    s3 = seaweedfs.SeaweedS3Server(tmp_path / "s3")
    # The demo as docs/demos.md runs it, plus the destination server's metrics for the health page.
    params = yaml.safe_load((REPO / "params" / "demos" / "tb3_pgsql_minio.yaml").read_text())
    metrics_port = free_port()
    params["destination_server"]["ros__parameters"]["flb"].update(http_server=True, http_port=metrics_port)
    params_file = tmp_path / "tb3_pgsql_minio.yaml"
    params_file.write_text(yaml.safe_dump(params))
    sim: subprocess.Popen[bytes] | None = None
    dashboard: subprocess.Popen[bytes] | None = None
    browser = None
    try:
        pg.start()
        s3.start()
        for name, value in environment({"postgres": pg.settings(), "s3": s3.settings()}).items():
            monkeypatch.setenv(name, value)
        dsn = PostgresSettings(port=pg.port, user=pg.user, password=pg.password, database=pg.database).connect_kwargs()

        def count(query: str) -> int:
            try:
                with psycopg.connect(**dsn) as connection:
                    row = connection.execute(query).fetchone()
                    return int(row[0]) if row else 0
            except psycopg.errors.UndefinedTable:
                return 0  # DC creates its tables with its first batch

        with Bringup(params_file, tmp_path / "home", args=["--use-sim-time"]) as run:
            run.wait_ready()
            sim = subprocess.Popen(
                [str(BIN / "dc"), "sim", "--clock", "--rate", "4", "--duration", "120"],
                env=run.env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            run.wait_until(
                lambda: count("select count(distinct data->>'name') from dc where data->>'name' in"
                              " ('robot', 'system', 'distance_traveled', 'map')") == 4
                and count("select count(*) from dc where data->>'name' = 'robot'") >= 20,
                90, "robot, system, distance_traveled and map rows",
            )  # fmt: skip
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not count(
                "select count(*) from files_metrics where deleted and local_path like '%.jpg'"
            ):
                time.sleep(1)
            inspected_by_demo = bool(
                count("select count(*) from files_metrics where deleted and local_path like '%.jpg'")
            )
            if not inspected_by_demo:
                _insert_inspection(dsn, s3, "C3PO", "1")

            port = free_port()
            dashboard = subprocess.Popen(
                [str(BIN / "dc"), "dashboard", "--port", str(port), "--metrics", f"http://127.0.0.1:{metrics_port}/api/v1/metrics"],
                env=dict(os.environ), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            )  # fmt: skip
            base = f"http://127.0.0.1:{port}"
            run.wait_until(lambda: _answers(base), 20, "the dashboard to answer")
            browser = _browser()
            shots = tmp_path / "dashboard"

            browser.get(base + "/")
            lines = browser.find_elements(By.CSS_SELECTOR, "#trajectory polyline.series")
            assert lines and sum(int(line.get_attribute("data-points")) for line in lines) > 0
            assert browser.find_elements(By.CSS_SELECTOR, "#trajectory image#map-image"), (
                "the saved map under the trajectory"
            )
            positions_all = browser.find_element(By.CSS_SELECTOR, "#stat-positions .value").text
            _screenshot(browser, shots, "overview")
            # A narrower time range, set as a user does: the numbers change.
            first, last = _span(dsn)
            browser.execute_script(
                "document.getElementById('filter-start').value = arguments[0];"
                "document.getElementById('filter-end').value = arguments[1];",
                first, last,
            )  # fmt: skip
            browser.find_element(By.ID, "filter-apply").click()
            run.wait_until(lambda: "start=" in browser.current_url, 10, "the filtered page")
            assert browser.find_element(By.CSS_SELECTOR, "#stat-positions .value").text != positions_all

            browser.get(base + "/system?robot=C3PO")
            assert browser.find_elements(By.CSS_SELECTOR, "#cpu-chart polyline.series")
            assert browser.find_elements(By.CSS_SELECTOR, "#memory-chart polyline.series")
            assert browser.find_element(By.CSS_SELECTOR, "#filter-robot option[selected]").text == "C3PO"
            _screenshot(browser, shots, "system")

            browser.get(base + "/camera")
            images = browser.find_elements(By.CSS_SELECTOR, "img.inspected")
            assert images
            run.wait_until(
                lambda: browser.execute_script(
                    "return Array.from(document.querySelectorAll('img.inspected')).some(i => i.complete && i.naturalWidth > 0)"
                ),
                10, "an inspected image shown",
            )  # fmt: skip
            assert browser.find_elements(By.CSS_SELECTOR, "figcaption .code")
            _screenshot(browser, shots, "camera")

            # Searching by a code read, as a user types it: the page keeps only the images with it.
            code = browser.execute_script("return document.querySelector('figcaption .code').lastChild.textContent")
            browser.find_element(By.ID, "code-search").send_keys(code.lower())
            browser.find_element(By.ID, "code-search").submit()
            run.wait_until(lambda: "code=" in browser.current_url, 10, "the code search")
            assert code in browser.find_element(By.CSS_SELECTOR, "figcaption .code").text

            # Any record name, chosen in the explorer's list: its numbers over time and its records.
            browser.get(base + "/explore?robot=C3PO")
            Select(browser.find_element(By.ID, "explore-name")).select_by_visible_text("system")
            run.wait_until(lambda: "name=system" in browser.current_url, 10, "the explorer on system")
            assert browser.find_elements(By.CSS_SELECTOR, "#explore-chart-0 polyline.series")
            assert len(browser.find_elements(By.CSS_SELECTOR, "#explore-records tr")) > 1
            _screenshot(browser, shots, "explorer")

            browser.get(base + "/files")
            assert len(browser.find_elements(By.CSS_SELECTOR, "#files-table tr")) > 1
            assert int(browser.find_element(By.CSS_SELECTOR, "#stat-deleted .value").text.replace(",", "")) > 0
            _screenshot(browser, shots, "files")

            browser.get(base + "/health")
            table = browser.find_element(By.CSS_SELECTOR, "table.destinations").text
            assert "flb_pgsql" in table and "flb_minio" in table
            assert browser.find_element(By.CSS_SELECTOR, "#stat-last-delivery .value").text.endswith("s ago")
            assert browser.find_element(By.CSS_SELECTOR, "#stat-servers .value").text == "1 of 1"
            _screenshot(browser, shots, "health")
        # The demo stopped: its metrics are gone, and the page says so instead of failing.
        browser.get(base + "/health")
        assert "cannot read" in browser.find_element(By.TAG_NAME, "main").text
        # The image proxy passes images only, and never an S3 error page as an image.
        with pytest.raises(urllib.error.HTTPError) as missing_image:
            urllib.request.urlopen(base + "/image?key=nothing/here.png", timeout=5)
        assert missing_image.value.code == 404
    finally:
        if browser is not None:
            browser.quit()
        for process in (dashboard, sim):
            if process is not None:
                process.terminate()
                process.wait(10)
        s3.stop()
        pg.stop()
        shutil.rmtree(pg_folder, ignore_errors=True)
    assert dashboard is not None and dashboard.stderr is not None
    log = dashboard.stderr.read().decode()
    assert pg.password not in log and s3.secret_key not in log
    print(
        f"camera inspection {'from the demo' if inspected_by_demo else 'inserted by the test'}; screenshots in {ARTIFACTS}"
    )


def _answers(base: str) -> bool:
    try:
        with urllib.request.urlopen(base + "/favicon.ico", timeout=2):
            return True
    except OSError:
        return False


def _span(dsn: dict[str, Any]) -> tuple[str, str]:
    """The middle third of the robot's stored time, as datetime-local values."""
    import psycopg

    with psycopg.connect(**dsn) as connection:
        row = connection.execute("select min(time), max(time) from dc where data->>'name' = 'robot'").fetchone()
    assert row is not None
    low, high = row
    third = (high - low) / 3
    return ((low + third).strftime("%Y-%m-%dT%H:%M:%S"), (high - third).strftime("%Y-%m-%dT%H:%M:%S"))


def test_params_gives_the_metrics_url_of_each_server_whose_http_server_it_enables(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """dc dashboard --params: dc_bringup reads the file for the dashboard, which does not import it; the
    destination server's only (the measurement server's endpoint, on by default, has no delivery)."""
    import argparse

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # no server of this session's domain found running

    from dc_bringup.cli import _metrics_urls
    from dc_dashboard.settings import from_sources

    params = yaml.safe_load((REPO / "params" / "demos" / "uptime_stdout.yaml").read_text())
    params["destination_server"]["ros__parameters"]["flb"].update(http_server=True, http_port=2999)
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(params))
    args = argparse.Namespace(params=str(params_file), metrics=["http://10.0.0.1:2020/api/v1/metrics"])
    settings = from_sources(args, environ={}, params_metrics=_metrics_urls)
    assert settings.metrics == (
        ("http://10.0.0.1:2020/api/v1/metrics", "http://10.0.0.1:2020/api/v1/metrics"),
        ("destination_server", "http://127.0.0.1:2999/api/v1/metrics"),
    )
