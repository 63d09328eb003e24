"""The dashboard's Fleet page at fleet scale: the time of its queries on a generated fleet's day.

    .venv/bin/python benchmarks/dashboard_fleet.py [--robots 100] [--hours 2] [--runs 5]

Starts a throw-away PostgreSQL on 127.0.0.1, fills table ``dc`` (DC's typed shape, day partitions)
with --robots robots x --hours hours of the fleet day of benchmarks/pgsql_data_model.py (position,
cpu, memory, front_camera: 0.85 records/s per robot) plus one ``destination_health`` record per
robot and hour (a robot in ten with a failing destination), creates the dashboard's indexes
(``dc dashboard --create-indexes``), ``VACUUM ANALYZE``, then times ``dc_dashboard.fleet.overview``
with "now" at the end of the generated hours, so every row is "today" (the worst case for the
records today): one warm-up then --runs runs, wall time at the client, as the page does it (above
``fleet.EXACT_UP_TO`` rows today, the records today estimated with seeks), and up to
--exact-up-to-rows rows also with the records today counted (every row of the day read through the
(robot, name, time) index and the heap); the estimates' largest error per robot against the count.

JSON in benchmarks/results/dashboard_fleet_<date>.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.pgsql_data_model import DAY, generate  # noqa: E402
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_dashboard import fleet, indexes  # noqa: E402
from dc_dashboard.filters import Filters  # noqa: E402
from dc_dashboard.queries import Store  # noqa: E402
from dc_dashboard.settings import PostgresSettings  # noqa: E402


def add_health(server: PostgresServer, robots: int, hours: int) -> None:
    with server.connect() as connection:
        connection.execute(
            f"""INSERT INTO dc (tag, time, data, record_id, name, robot_name, run_id)
            SELECT 'pg', t, jsonb_build_object(
                       'pg', jsonb_build_object('state', CASE WHEN r % 10 = 0 THEN 'failing' ELSE 'ok' END,
                                                'reason', 'password authentication failed'),
                       'fleet', jsonb_build_object('state', 'ok'),
                       'name', 'destination_health', 'robot_name', robot, 'run_id', '1', 'record_id', rid),
                   rid, 'destination_health', robot, '1'
            FROM generate_series(1, {robots}) AS r,
                 generate_series(timestamptz '{DAY} 00:30Z', timestamptz '{DAY} 00:00Z' + interval '{hours} hours',
                                 interval '1 hour') AS t,
                 LATERAL (SELECT gen_random_uuid()::text AS rid, 'robot-' || lpad(r::text, 3, '0') AS robot) AS k
            WHERE t < timestamptz '{DAY} 00:00Z' + interval '{hours} hours'"""
        )


def timed(runs: int, work: Any) -> dict[str, float]:
    work()  # warm-up: plans, caches
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        work()
        times.append(time.perf_counter() - started)
    return {"median_s": statistics.median(times), "max_s": max(times)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--hours", type=int, default=2)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument(
        "--exact-up-to-rows", type=int, default=3_000_000, help="time the counted records today up to this many rows"
    )
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="dc-bench-fleet-page-"))
    server = PostgresServer(folder, password="bench-fleet-1")
    try:
        server.start()
        rows, seconds = generate(server, args.robots, args.hours)
        add_health(server, args.robots, args.hours)
        s = server.settings()
        settings = PostgresSettings(
            port=int(s["port"]), user=str(s["user"]), password=str(s["password"]), database=str(s["database"])
        )
        settings = dataclasses.replace(settings, statement_timeout_ms=600_000)
        with server.connect() as connection:
            connection.execute(
                "CREATE TABLE IF NOT EXISTS files_metrics (timestamp timestamptz, robot_name text)"
            )  # the files indexes need the table
        started = time.monotonic()
        indexes.create(settings, say=lambda text: None)
        index_s = time.monotonic() - started
        with server.connect() as connection:
            connection.execute("VACUUM ANALYZE dc")
        # The last second generated: with --hours 24 the end itself would be the next day's midnight.
        now = dt.datetime.fromisoformat(f"{DAY}T00:00:00") + dt.timedelta(hours=args.hours, seconds=-1)
        store = Store(settings)
        load = os.getloadavg()[0]
        figures: dict[str, Any] = {}
        with store.connection() as connection:
            result_rows, estimated = fleet.overview(store, connection, Filters(), now)
            exact, _ = fleet.overview(store, connection, Filters(), now, exact_up_to=1 << 62)
            figures["fleet_page"] = timed(args.runs, lambda: fleet.overview(store, connection, Filters(), now))
            if rows <= args.exact_up_to_rows:
                figures["fleet_page_counted"] = timed(
                    args.runs, lambda: fleet.overview(store, connection, Filters(), now, exact_up_to=1 << 62)
                )
        counted = {r.robot: r.records_today for r in exact}
        errors = [abs(r.records_today - counted[r.robot]) / max(counted[r.robot], 1) for r in result_rows]
        load = max(load, os.getloadavg()[0])
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)
    result = {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "robots": args.robots,
        "hours": args.hours,
        "rows": rows + args.robots * args.hours,
        "generate_s": seconds,
        "dashboard_indexes_s": index_s,
        "robots_listed": len(result_rows),
        "failing_robots": sum(1 for r in result_rows if r.failing),
        "records_today_estimated": estimated,
        "records_today": sum(r.records_today for r in result_rows),
        "records_today_counted": sum(counted.values()),
        "estimate_error_per_robot_max": max(errors, default=0.0),
        **figures,
        "load_average_1min": load,
    }
    print(json.dumps(result, indent=2))
    out = REPO / "benchmarks" / "results" / f"dashboard_fleet_{dt.date.today()}.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {out}")


if __name__ == "__main__":
    main()
