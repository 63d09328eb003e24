"""Every dashboard page filtered by robot, run or hour on a fleet's day of the robot job, and `dc reconcile`'s queries.

    .venv/bin/python benchmarks/dashboard_fleet_day.py --folder DIR [--robots 100] [--days 1] [--hours 24]
        [--fraction 1] [--partition-by none|day] [--layout dm4|main] [--runs 5] [--only PAGES] [--label NAME] [--drop]

Keeps a PostgreSQL in --folder (made and filled at the first call, reused by the next ones: a
25-million-row table takes most of an hour to generate on a shared 2-core machine; --drop removes it
at the end). The table ``dc`` is made by the PgSQL destination with its defaults (``partition_by``
as given: DC's plain table, or day partitions) and filled by the server, one ``INSERT … SELECT``
from ``generate_series`` per measurement, in time order with the robots' rows side by side (as a
fleet inserts them), its indexes dropped meanwhile and built again after (the same definitions):
--robots robots x --days days of the robot job's timed measurements at their intervals
(params/benchmarks/robot_footprint.yaml: position and speed every 1 s, cpu, memory and
distance_traveled every 5 s, uptime and network every 10 s, storage every 30 s) plus a camera
inspection with an image every 12 s (issue 29's file rate; the robot job's own files are its map's,
saved only when the map changes) and a map every 10 min, in runs of 2 hours; 2.92 records/s per
robot, 25.2 million rows for 100 robots x 1 day. --hours N (fewer than 24, one day) generates only
the N hours from 10:00 of the day (the measured hour first, run 6 whole with 2 or more): the fleet's
rows of those hours are the day's, the table and its indexes smaller (2.1 million rows for 2 hours: an
index one level shallower, the whole table cached); the pages of a robot's day then read 2 hours,
not 24. --fraction thins every measurement (0.1: a record
where ten were). files_metrics gets a row per inspection (its record id, robot, name and time; 1 in
20 not uploaded), every robot a ``destination_health`` record an hour (a robot in ten failing),
then the dashboard's indexes (``dc dashboard --create-indexes``' statements) and ``VACUUM ANALYZE``.

--layout sets the records table's index on record_id before the measures: ``dm4`` none (the
one-btree layout of branch dm4, whose default made the table of the 2026-11-27 results: unique
(robot_name, name, time, record_id), no index on record_id) or ``main`` a unique index on
record_id (a plain table's default; made with CREATE INDEX, dropped again by ``dm4``). Then,
warm (one warm-up, then --runs runs, wall time at the client): each dashboard page
as ``Dashboard.render`` serves it (its queries and its HTML) for robot-007 alone, with run 6
(hours 10-12 of each day), with the hour 10:00-11:00 of the last day, with both, and the hour alone
(every robot); the Files page filtered by run alone; the Fleet page (``fleet.overview`` and its HTML,
"now" the last second generated: every row of the last day is today's); ``dc reconcile``'s queries for
robot-007 and that hour (its records and files_metrics reads, against a bucket listing nothing).
Median and max per item, the load average, and the plans of the files-by-run queries. --only
/files,reconcile (say): those alone.

JSON in benchmarks/results/dashboard_fleet_day_<date>[_<label>].json (never overwritten: ``_2``, ``_3``…).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.dashboard_fleet import timed  # noqa: E402
from benchmarks.pgsql_data_model import destination, fill  # noqa: E402
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_dashboard import fleet, indexes  # noqa: E402
from dc_dashboard.filters import Filters  # noqa: E402
from dc_dashboard.server import Dashboard  # noqa: E402
from dc_dashboard.settings import DashboardSettings, PostgresSettings, S3Settings  # noqa: E402

LAST_DAY = dt.date(2026, 11, 25)
RUN_HOURS = 2
ROBOT = "robot-007"
RUN = 6  # hours 10-12 of a day
FIRST_HOUR = 10  # --hours below 24 generates from here: the measured hour 10:00-11:00 and run 6
PASSWORD = "bench-fleet-day-1"
SLOW_S = 5.0  # a page slower than this once is not run again (a statement stops at the timeout below)
# The camera's image key, as DC's default paths name it (robot first).
_KEY = "robot || '/inspected/' || to_char(t AT TIME ZONE 'UTC', 'YYYY/MM/DD/HH24MISS') || '.jpg'"

# (name, seconds between records, the record's own fields as SQL over r (robot number), robot, t (time))
MEASUREMENTS = (
    (
        "position",
        1.0,
        "'x', round((r + 10 * cos(extract(epoch FROM t) / 600))::numeric, 3),"
        " 'y', round((10 * sin(extract(epoch FROM t) / 600))::numeric, 3), 'yaw', 0.5",
    ),
    ("speed", 1.0, "'computed', round((random() * 0.5)::numeric, 3)"),
    ("cpu", 5.0, "'average', round((random() * 100)::numeric, 2), 'processes', 212"),
    ("memory", 5.0, "'used', round((30 + random() * 20)::numeric, 2)"),
    ("distance_traveled", 5.0, "'distance_traveled', round((extract(epoch FROM t) % 86400 / 20)::numeric, 2)"),
    ("uptime", 10.0, "'time', (extract(epoch FROM t) % 86400)::bigint"),
    ("network", 10.0, "'online', true, 'ping_ms', round((random() * 5)::numeric, 2)"),
    ("storage", 30.0, "'free_percent', 61.5, 'used_bytes', 120000000000"),
    (
        "front_camera",
        12.0,
        "'camera_name', 'front_camera', 'remote_paths', jsonb_build_object('minio', jsonb_build_object("
        f"'inspected', {_KEY})), 'inspected', jsonb_build_object('barcode', jsonb_build_array(jsonb_build_object("
        "'data', 'WH1/AISLE-' || (r % 10) || '/SHELF-' || lpad(((extract(epoch FROM t)::bigint / 12) % 40)::text,"
        " 2, '0'), 'type', 'QRCODE', 'top', 198, 'left', 148, 'width', 86, 'height', 86)))",
    ),
    (
        "map",
        600.0,
        "'resolution', 0.05, 'origin', jsonb_build_object('x', -10, 'y', -10, 'yaw', 0), 'width', 400,"
        " 'height', 400, 'remote_paths', jsonb_build_object('minio', jsonb_build_object('png',"
        " robot || '/map/' || to_char(t AT TIME ZONE 'UTC', 'YYYY/MM/DD/HH24MISS') || '.png'))",
    ),
)


def first_day(days: int) -> dt.date:
    return LAST_DAY - dt.timedelta(days=days - 1)


def generate(
    server: PostgresServer, robots: int, days: int, fraction: float, partition_by: str, hours: int = 24
) -> dict[str, Any]:
    """The fleet's days (or ``hours`` of its one day from FIRST_HOUR) in table dc (made by the destination,
    with its defaults), files_metrics, health records."""
    start = first_day(days)
    from_s, seconds = (0, days * 86_400) if hours >= 24 else (FIRST_HOUR * 3600, hours * 3600)
    start_ns = int(dt.datetime(start.year, start.month, start.day, tzinfo=dt.UTC).timestamp() * 1e9)
    from dc_core.destination import OutgoingRecord
    from dc_destinations.files_metrics.table import FilesTable
    from dc_destinations.record_ids import new_record_id

    dest = destination(server, "dc", partition_by, latest=False)  # latest_table's default on this branch
    if partition_by != "none":
        # Partitions for every day generated: the destination makes those of the days it writes.
        for day in range(days):
            when = start_ns + day * 86_400 * 10**9
            dest.send([OutgoingRecord(new_record_id(), "/dc/x", when, {"name": "marker"})])
    else:
        dest.send([OutgoingRecord(new_record_id(), "/dc/x", start_ns, {"name": "marker"})])
    dest.on_deactivate()
    began = time.monotonic()
    with server.connect() as connection:
        connection.execute("DELETE FROM dc")
        kept = [
            (name, sql)
            for name, sql in connection.execute(
                "SELECT indexname, indexdef FROM pg_indexes WHERE tablename = 'dc' ORDER BY indexname"
            ).fetchall()
        ]
        for name, _ in kept:
            connection.execute(f"DROP INDEX {name}")  # built again after the rows: sorted once, not row by row
        FilesTable("files_metrics").prepare(connection)
        # The camera's rows first: files_metrics is filled from them before the others come.
        order = sorted(MEASUREMENTS, key=lambda m: m[0] != "front_camera")
        for name, every, fields in order:
            connection.execute(
                fill(name, every / fraction, fields, str(start), seconds, robots, RUN_HOURS * 3600, from_s)
            )
            print(f"  {name}: {time.monotonic() - began:.0f} s  load {os.getloadavg()[0]:.1f}", flush=True)
            if name == "front_camera":
                connection.execute(
                    """INSERT INTO files_metrics (timestamp, robot_name, robot_id, group_name, local_path, remote_path,
                        uploaded, on_filesystem, deleted, storage_type, content_type, size, updated_at, created_at,
                        record_id, bucket, verified_at)
                    SELECT time AT TIME ZONE 'UTC', robot_name, robot_name, name, '/var/dc/data/' || key,
                           's3://fleet/' || key, n % 20 <> 0, n % 20 = 0, n % 20 <> 0, 'minio', 'image/jpeg', 48000,
                           time AT TIME ZONE 'UTC', time AT TIME ZONE 'UTC', record_id, 'fleet',
                           CASE WHEN n % 20 <> 0 THEN time AT TIME ZONE 'UTC' + interval '5 s' END
                    FROM (SELECT time, robot_name, name, record_id, data #>> '{remote_paths,minio,inspected}' AS key,
                                 row_number() OVER () AS n FROM dc) AS camera"""
                )
        connection.execute(
            f"""INSERT INTO dc (tag, time, data, record_id, name, robot_name, run_id)
            SELECT 'pg', t, jsonb_build_object(
                       'pg', jsonb_build_object('state', CASE WHEN r % 10 = 0 THEN 'failing' ELSE 'ok' END,
                                                'reason', 'password authentication failed'),
                       'fleet', jsonb_build_object('state', 'ok'), 'name', 'destination_health',
                       'robot_name', robot, 'run_id', run::text, 'record_id', rid),
                   rid, 'destination_health', robot, run
            FROM generate_series(1, {robots}) AS r,
                 generate_series(timestamptz '{start} 00:30Z' + interval '{from_s} s',
                                 timestamptz '{start} 00:30Z' + interval '{from_s + seconds - 3600} s',
                                 interval '1 hour') AS t,
                 LATERAL (SELECT gen_random_uuid()::text AS rid, 'robot-' || lpad(r::text, 3, '0') AS robot,
                                 1 + floor(extract(epoch FROM t - timestamptz '{start} 00:00Z')
                                           / {RUN_HOURS * 3600})::bigint AS run) AS k"""
        )
        generated_s = time.monotonic() - began
        print(f"rows in {generated_s:.0f} s; indexes ...", flush=True)
        began = time.monotonic()
        connection.execute("SET maintenance_work_mem = '1GB'")
        for name, statement in kept:
            connection.execute(statement.replace(" ON ONLY ", " ON "))  # a partitioned table's, with its partitions'
            print(f"  {name}: {time.monotonic() - began:.0f} s  load {os.getloadavg()[0]:.1f}", flush=True)
        settings = pg_settings(server)
        partitioned = frozenset({settings.table}) if partition_by != "none" else frozenset()
        # Without CONCURRENTLY (nothing writes meanwhile): one scan of the table per index, not two.
        for statement in indexes.statements(settings, partitioned | {settings.files_table}):
            connection.execute(statement)
            print(f"  {statement.as_string(connection)[:70]}: {time.monotonic() - began:.0f} s", flush=True)
        index_s = time.monotonic() - began
        connection.execute("VACUUM ANALYZE dc")
        connection.execute("VACUUM ANALYZE files_metrics")
    return {"generate_s": generated_s, "indexes_s": index_s, **sizes(server)}


def sizes(server: PostgresServer) -> dict[str, Any]:
    with server.connect() as connection:
        (rows,) = connection.execute("SELECT count(*) FROM dc").fetchone()
        (files,) = connection.execute("SELECT count(*) FROM files_metrics").fetchone()
        (records_bytes,) = connection.execute(
            "SELECT pg_total_relation_size('dc') + coalesce(sum(pg_total_relation_size(c.oid)), 0) FROM pg_inherits i"
            " JOIN pg_class c ON c.oid = i.inhrelid WHERE i.inhparent = 'dc'::regclass"
        ).fetchone()
        (files_bytes,) = connection.execute("SELECT pg_total_relation_size('files_metrics')").fetchone()
        (partitions,) = connection.execute(
            "SELECT count(*) FROM pg_inherits WHERE inhparent = 'dc'::regclass"
        ).fetchone()
    return {
        "rows": int(rows),
        "files_metrics_rows": int(files),
        "records_gb": round(int(records_bytes) / 1e9, 2),
        "files_metrics_gb": round(int(files_bytes) / 1e9, 3),
        "partitions": int(partitions),
    }


def pg_settings(server: PostgresServer) -> PostgresSettings:
    s = server.settings()
    settings = PostgresSettings(
        port=int(s["port"]), user=str(s["user"]), password=str(s["password"]), database=str(s["database"])
    )
    return dataclasses.replace(
        settings, statement_timeout_ms=60_000
    )  # the dashboard's is 15 s: a slower query measured


def set_layout(server: PostgresServer, layout: str) -> float:
    """``main``: a unique index on record_id; ``dm4``: none."""
    began = time.monotonic()
    with server.connect() as connection:
        if layout == "main":
            connection.execute("SET maintenance_work_mem = '1GB'")
            connection.execute("CREATE UNIQUE INDEX IF NOT EXISTS dc_record_id ON dc (record_id)")
        else:
            connection.execute("DROP INDEX IF EXISTS dc_record_id")
        connection.execute("ANALYZE dc")
    return time.monotonic() - began


class EmptyBucket:
    """An S3 client whose bucket lists nothing: reconcile's database side alone is timed."""

    def get_paginator(self, name: str) -> Any:
        class Pages:
            def paginate(self, **kwargs: Any) -> list[dict[str, Any]]:
                return [{"Contents": []}]

        return Pages()


def measure(server: PostgresServer, days: int, runs: int, only: list[str]) -> dict[str, Any]:
    """``only``: these pages (and "fleet", "reconcile") alone; all when empty."""
    import psycopg

    from dc_bringup.reconcile import reconcile

    settings = pg_settings(server)
    dashboard = Dashboard(DashboardSettings(settings, S3Settings()))
    hour = f"start={LAST_DAY}T10:00:00&end={LAST_DAY}T11:00:00"
    run = f"run={RUN + (days - 1) * 24 // RUN_HOURS}"  # the last day's hours 10-12
    filters = {
        "robot": f"robot={ROBOT}",
        "robot+run": f"robot={ROBOT}&{run}",
        "robot+hour": f"robot={ROBOT}&{hour}",
        "robot+run+hour": f"robot={ROBOT}&{run}&{hour}",
        "hour": hour,
    }
    pages = ("/", "/system", "/camera", "/files", "/explore", "/incidents")
    queries = [(page, label, query + ("&name=cpu" if page == "/explore" else "")) for page in pages
               for label, query in filters.items()]  # fmt: skip
    queries += [("/files", "run", run), ("/files", "run+hour", f"{run}&{hour}")]
    queries = [q for q in queries if not only or q[0] in only]
    figures: dict[str, Any] = {}
    for page, label, query in queries:
        figures[f"{page} {label}"] = page_time(dashboard, page, query, runs)
        print(f"{page:10} {label:15} {figures[f'{page} {label}']}  load {os.getloadavg()[0]:.1f}", flush=True)
    now = dt.datetime(LAST_DAY.year, LAST_DAY.month, LAST_DAY.day, 23, 59, 59)
    store = dashboard.store
    with store.connection() as connection:
        if only and "fleet" not in only:
            return figures | {"files_by_run_plans": files_plans(store, connection, run[4:])}

        def fleet_page() -> str:
            rows, estimated = fleet.overview(store, connection, Filters(), now)
            return fleet.page(rows, now, estimated)

        figures["/fleet"] = timed(runs, fleet_page)
        rows, estimated = fleet.overview(store, connection, Filters(), now)
        figures["/fleet"].update(robots=len(rows), failing=sum(1 for r in rows if r.failing), estimated=estimated)
        print(f"/fleet {figures['/fleet']}", flush=True)
        figures["files_by_run_plans"] = files_plans(store, connection, run[4:])
    if only and "reconcile" not in only:
        return figures
    since = dt.datetime(LAST_DAY.year, LAST_DAY.month, LAST_DAY.day, 10, tzinfo=dt.UTC)
    with psycopg.connect(**settings.connect_kwargs()) as connection:

        def reconciled() -> Any:
            return reconcile(connection, EmptyBucket(), "fleet", ROBOT, since, since + dt.timedelta(hours=1))

        figures["reconcile robot+hour"] = timed(runs, reconciled)
        figures["reconcile robot+hour"]["checked"] = reconciled().checked
        print(f"reconcile {figures['reconcile robot+hour']}", flush=True)
    return figures


def page_time(dashboard: Dashboard, page: str, query: str, runs: int) -> dict[str, Any]:
    """The first time, then ``runs`` more as timed() does; a page failing or slower than SLOW_S: its first alone."""
    started = time.perf_counter()
    status, html = dashboard.render(page, query)
    first = time.perf_counter() - started
    if status != 200:
        return {"status": status, "first_s": first, "error": html[html.find('class="error') :][:300]}
    if first > SLOW_S:
        return {"first_s": first}
    return {"first_s": first, **timed(runs, lambda: dashboard.render(page, query))}


def files_plans(store: Any, connection: Any, run: str) -> dict[str, list[str]]:
    chosen = {"robot+run": Filters(robot=ROBOT, run=run), "run": Filters(run=run)}
    return {label: files_plan(store, connection, filters) for label, filters in chosen.items()}


def files_plan(store: Any, connection: Any, filters: Filters) -> list[str]:
    """The plan of the Files page's count query for ``filters``, its scans and joins only."""
    from psycopg import sql

    from dc_dashboard import queries

    conditions, params = queries._filtered(
        filters,
        robot_column=sql.SQL("robot_name"),
        time_column=sql.SQL("timestamp"),
        run_condition=store.files_run_condition(filters, connection),
    )
    scope = sql.SQL(" AND ").join([sql.SQL("true"), *conditions])
    query = sql.SQL("EXPLAIN (COSTS OFF) SELECT count(*) FROM {f} f WHERE {s}").format(f=store.files_table, s=scope)
    return [row[0] for row in connection.execute(query, params).fetchall()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, required=True, help="the PostgreSQL's folder, kept between calls")
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--days", type=int, default=1)
    parser.add_argument("--hours", type=int, default=24, help="fewer than 24: those hours of one day from 10:00")
    parser.add_argument("--fraction", type=float, default=1.0, help="records kept of each measurement's rate")
    parser.add_argument("--partition-by", choices=("none", "day"), default="none")
    parser.add_argument("--layout", choices=("dm4", "main"), default="dm4")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--label", default="")
    parser.add_argument("--only", default="", help="comma-separated pages (/files…), fleet, reconcile: those alone")
    parser.add_argument("--no-measure", action="store_true", help="generate (if needed) and stop")
    parser.add_argument("--drop", action="store_true", help="remove the folder at the end")
    args = parser.parse_args()
    if args.hours < 24 and (args.days != 1 or not 1 <= args.hours <= 24 - FIRST_HOUR):
        parser.error(f"--hours below 24: one day (--days 1) and 1 to {24 - FIRST_HOUR} hours")
    server = PostgresServer(args.folder, password=PASSWORD)
    result: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "robots": args.robots,
        "days": args.days,
        "hours": args.hours,
        "fraction": args.fraction,
        "partition_by": args.partition_by,
        "layout": args.layout,
    }
    try:
        fresh = not (args.folder / "data" / "PG_VERSION").is_file()
        server.start(timeout=120)
        if fresh:
            result["generated"] = generate(server, args.robots, args.days, args.fraction, args.partition_by, args.hours)
            print(json.dumps(result["generated"]), flush=True)
        result.update(sizes(server))
        result["layout_s"] = set_layout(server, args.layout)
        if not args.no_measure:
            load = os.getloadavg()
            result["figures"] = measure(server, args.days, args.runs, [o for o in args.only.split(",") if o])
            result["load_average_1min"] = [load[0], os.getloadavg()[0]]
    finally:
        server.stop(timeout=60)
        if args.drop:
            shutil.rmtree(args.folder, ignore_errors=True)
    print(json.dumps({k: v for k, v in result.items() if k != "figures"}, indent=2))
    write_result("dashboard_fleet_day", args.label, result)


def write_result(name: str, label: str, result: dict[str, Any]) -> None:
    """benchmarks/results/<name>_<date>[_<label>].json, never overwritten (``_2``, ``_3``…)."""
    stem = f"{name}_{dt.date.today()}" + (f"_{label}" if label else "")
    out = REPO / "benchmarks" / "results" / f"{stem}.json"
    n = 2
    while out.exists():
        out, n = out.with_name(f"{stem}_{n}.json"), n + 1
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"written {out}")


if __name__ == "__main__":
    main()
