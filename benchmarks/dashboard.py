"""`dc dashboard` on a table of 1,000,000 rows: time of each page, without and with its indexes.

    .venv/bin/python benchmarks/dashboard.py [--rows 1000000] [--files 50000] [--repeat 5] [--label NAME]

Starts a throw-away PostgreSQL on 127.0.0.1 (dc_bringup.local_servers), creates the PgSQL destination's
table ``dc`` and the FilesMetrics table ``files_metrics`` as DC does, and fills them by ``COPY`` with
synthetic rows shaped as the tb3_pgsql_minio demo stores them: 5 robots, 20 runs each, 30 days; per
robot and run, ``robot`` groups (position, cmd_vel, speed) 50 % of the rows, ``system`` groups (cpu,
memory) 20 %, ``distance_traveled`` 20 %, ``uptime`` 8 %, ``front_camera`` 2 %, a ``map`` every 500th
row. Then it serves the dashboard on a free loopback port and times each page over HTTP, as a
browser fetches it (HTML only: the images come from S3, not part of this), first with only the
table's own indexes (one fetch per page: a statement stops at the dashboard's 15 s
``statement_timeout`` and the page says so), then after ``dc dashboard --create-indexes``, where
each figure is the median of --repeat fetches after one warm-up fetch (which fills the dashboard's
catalog of record names, kept 30 s). JSON in benchmarks/results/dashboard_<date>[_<label>].json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import random
import secrets
import shutil
import statistics
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_dashboard import indexes  # noqa: E402
from dc_dashboard.server import make_server  # noqa: E402
from dc_dashboard.settings import DashboardSettings, PostgresSettings, S3Settings  # noqa: E402

ROBOTS = [f"R2D{i}" for i in range(1, 6)]
RUNS_PER_ROBOT = 20
DAYS = 30
START = dt.datetime(2026, 10, 1)


def record(kind: str, robot: str, run: str, when: dt.datetime, step: int, rng: random.Random) -> dict[str, Any]:
    meta = {"run_id": run, "robot_name": robot}
    date = when.replace(tzinfo=dt.UTC).timestamp()
    if kind == "robot":
        angle = step / 50.0
        return {
            "date": date,
            "name": "robot",
            "position": {"x": 3 * __import__("math").cos(angle), "y": 2 * __import__("math").sin(angle),
                         "yaw": 0.1, "name": "position", **meta},
            "cmd_vel": {"linear": {"x": 0.2, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.1},
                        "computed": 0.2, "name": "cmd_vel", **meta},
            "speed": {"computed": 0.2, "name": "speed", **meta},
        }  # fmt: skip
    if kind == "system":
        return {
            "date": date,
            "name": "system",
            "cpu": {"average": round(rng.uniform(5, 60), 2), "processes": 90, "sorted": [], "name": "cpu", **meta},
            "memory": {"used": round(rng.uniform(20, 50), 2), "name": "memory", **meta},
        }
    if kind == "distance_traveled":
        return {"date": date, "name": kind, "distance_traveled": step * 0.05, **meta}
    if kind == "front_camera":
        key = f"{robot}/{when:%Y/%m/%d/%H}/front_camera/inspected/{when:%Y-%m-%dT%H-%M-%S}.jpg"
        return {
            "date": date, "name": kind, "camera_name": kind, **meta,
            "local_paths": {"inspected": f"var/dc/data/{key}"}, "remote_paths": {"minio": {"inspected": key}},
            "inspected": {"barcode": [{"data": f"PAL-{step}", "type": "CODE128", "top": 1, "left": 2, "width": 90,
                                       "height": 40}]},
        }  # fmt: skip
    if kind == "map":
        key = f"{robot}/{when:%Y/%m/%d/%H}/map/{when:%Y-%m-%dT%H-%M-%S}"
        return {
            "date": date, "name": "map", "resolution": 0.05, "origin": {"x": -5.0, "y": -4.0, "yaw": 0.0},
            "width": 200, "height": 160, **meta,
            "local_paths": {e: f"var/dc/data/{key}.{e}" for e in ("pgm", "png", "yaml")},
            "remote_paths": {"minio": {e: f"{key}.{e}" for e in ("pgm", "png", "yaml")}},
        }  # fmt: skip
    return {"date": date, "name": "uptime", "time": step, **meta}


def fill(dsn: dict[str, Any], rows: int, files: int) -> dict[str, Any]:
    import psycopg
    from psycopg.types.json import Jsonb

    from dc_destinations.files_metrics.table import FilesTable

    rng = random.Random(7)
    kinds = ["robot"] * 50 + ["system"] * 20 + ["distance_traveled"] * 20 + ["uptime"] * 8 + ["front_camera"] * 2
    runs = [(robot, str(run)) for robot in ROBOTS for run in range(1, RUNS_PER_ROBOT + 1)]
    per_run = rows // len(runs)
    run_span = dt.timedelta(days=DAYS) / RUNS_PER_ROBOT
    started = time.monotonic()
    with psycopg.connect(**dsn, autocommit=True) as connection:
        connection.execute("CREATE TABLE dc (tag varchar, time timestamp, data jsonb, record_id text)")
        connection.execute("CREATE UNIQUE INDEX dc_record_id ON dc (record_id)")
        FilesTable("files_metrics").prepare(connection)
        with connection.cursor() as cursor, cursor.copy("COPY dc (tag, time, data, record_id) FROM STDIN") as copy:
            n = 0
            for robot, run in runs:
                begin = START + run_span * (int(run) - 1)
                for step in range(per_run):
                    when = begin + run_span * step / per_run
                    kind = "map" if step % 500 == 0 else kinds[step % len(kinds)]
                    n += 1
                    copy.write_row(("flb_pgsql", when, Jsonb(record(kind, robot, run, when, step, rng)), f"r{n}"))
        with (
            connection.cursor() as cursor,
            cursor.copy(
                "COPY files_metrics (timestamp, robot_name, robot_id, group_name, local_path, remote_path, uploaded,"
                " on_filesystem, deleted, storage_type, content_type, size, updated_at, record_id, bucket, verified_at)"
                " FROM STDIN"
            ) as copy,
        ):
            for i in range(files):
                robot = ROBOTS[i % len(ROBOTS)]
                when = START + dt.timedelta(days=DAYS) * i / files
                key = f"{robot}/{when:%Y/%m/%d/%H}/front_camera/inspected/{i}.jpg"
                done = i % 10 != 0
                copy.write_row((when, robot, "", "front_camera", f"var/dc/data/{key}", f"minio://dc-bucket/{key}",
                                done, not done, done, "minio", "image/jpeg", 27000, when, f"f{i}", "dc-bucket",
                                when if done else None))  # fmt: skip
        connection.execute("ANALYZE dc")
        connection.execute("ANALYZE files_metrics")
        size = connection.execute("SELECT pg_total_relation_size('dc')").fetchone()
    return {"seconds": round(time.monotonic() - started, 1), "table_bytes": int(size[0]) if size else 0}


def pages(robot: str, run: str) -> dict[str, str]:
    day = (START + dt.timedelta(days=3)).strftime("%Y-%m-%dT%H:%M:%S")
    next_day = (START + dt.timedelta(days=4)).strftime("%Y-%m-%dT%H:%M:%S")
    return {
        "overview, all": "/",
        "overview, robot": f"/?robot={robot}",
        "overview, robot+run": f"/?robot={robot}&run={run}",
        "overview, robot+1 day": f"/?robot={robot}&start={day}&end={next_day}",
        "system, robot": f"/system?robot={robot}",
        "system, robot+run": f"/system?robot={robot}&run={run}",
        "camera, all": "/camera",
        "camera, robot+run": f"/camera?robot={robot}&run={run}",
        "files, all": "/files",
        "files, robot+1 day": f"/files?robot={robot}&start={day}&end={next_day}",
        "files, robot+run": f"/files?robot={robot}&run={run}",
        "health": "/health",
    }


def time_pages(base: str, repeat: int, warm_up: bool = True) -> dict[str, dict[str, Any]]:
    results = {}
    for label, path in pages(ROBOTS[1], "7").items():
        times, status = [], 0
        for attempt in range(repeat + 1 if warm_up else repeat):
            started = time.perf_counter()
            try:
                with urllib.request.urlopen(base + path, timeout=120) as response:
                    response.read()
                    status = response.status
            except urllib.error.HTTPError as exc:
                status = exc.code
            if attempt or not warm_up:  # the first fetch warms the catalog and PostgreSQL's cache
                times.append((time.perf_counter() - started) * 1000)
        results[label] = {"path": path, "status": status, "median_ms": round(statistics.median(times), 1),
                          "max_ms": round(max(times), 1)}  # fmt: skip
        print(
            f"  {label:<26} {status}  median {results[label]['median_ms']:>8.1f} ms"
            f"  max {results[label]['max_ms']:>8.1f} ms"
        )
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=1_000_000)
    parser.add_argument("--files", type=int, default=50_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--label", default="")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="dc-pg-dash-"))
    pg = PostgresServer(folder, password=secrets.token_urlsafe(12))
    try:
        pg.start()
        settings = PostgresSettings(host="127.0.0.1", port=pg.port, user=pg.user, password=pg.password,
                                    database=pg.database)  # fmt: skip
        dsn = {k: v for k, v in settings.connect_kwargs().items() if k != "options"}
        print(f"filling {args.rows:,} rows and {args.files:,} files ...")
        filled = fill(dsn, args.rows, args.files)
        print(f"  {filled['seconds']} s, table {filled['table_bytes'] / 2**20:,.0f} MiB")
        server = make_server(DashboardSettings(settings, S3Settings()), "127.0.0.1", 0, quiet=True)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        base = f"http://127.0.0.1:{server.server_address[1]}"
        print("without the dashboard's indexes (one fetch each; a statement stops at the dashboard's 15 s):")
        before = time_pages(base, 1, warm_up=False)
        started = time.monotonic()
        indexes.create(settings, say=lambda text: None)
        built = round(time.monotonic() - started, 1)
        with __import__("psycopg").connect(**dsn, autocommit=True) as connection:
            connection.execute("ANALYZE dc")
            index_bytes = connection.execute(
                "SELECT coalesce(sum(pg_relation_size(indexrelid)), 0) FROM pg_index i JOIN pg_class c"
                " ON c.oid = i.indexrelid WHERE c.relname LIKE '%%dash%%'"
            ).fetchone()
        print(f"--create-indexes: {built} s, {int(index_bytes[0]) / 2**20:,.0f} MiB; with them:")
        time.sleep(31)  # the catalog (and its missing-index list) is read again
        after = time_pages(base, args.repeat)
        server.shutdown()
    finally:
        pg.stop()
        shutil.rmtree(folder, ignore_errors=True)
    result = {
        "date": dt.date.today().isoformat(),
        "machine": {
            "cpus": __import__("os").cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "rows": args.rows,
        "files": args.files,
        "robots": len(ROBOTS),
        "runs_per_robot": RUNS_PER_ROBOT,
        "fill": filled,
        "create_indexes_s": built,
        "index_bytes": int(index_bytes[0]),
        "without_indexes": before,
        "with_indexes": after,
    }
    name = f"dashboard_{result['date']}{'_' + args.label if args.label else ''}.json"
    out = REPO / "benchmarks" / "results" / name
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {out.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
