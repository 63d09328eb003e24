"""The dashboard's rollup (``dc dashboard --create-rollups``): the fleet's hour pages with and without it, and
what its trigger costs a COPY into the records table.

    .venv/bin/python benchmarks/dashboard_rollup.py --folder DIR [--hours 2] [--runs 7] [--rounds 4] [--label NAME]
        [--only pages|copy] [--filters hour,run,robot,robot+run,robot+hour,robot+run+hour|all]

The PostgreSQL in --folder is dashboard_fleet_day.py's (made and filled there at the first call with
``--hours`` hours of 100 robots, ``--layout main``: 2 h are 2.1 M rows, ~1 min; a folder made by
``dashboard_fleet_day.py --layout main`` is used as it is, give --hours as it was made, 24 for its
default day). Any rollup there is dropped first. Then:

1. the rollup built (``rollup_setup.create``: the series the charts draw, the trigger, filled from the rows),
   its time, rows and size;
2. the overview, the system page and the explorer of cpu for each of --filters (``hour``, the
   default: 10:00-11:00 of every robot, no robot filter; ``run``: every robot's run 6, hours 10-12;
   and robot-007 alone, with that run, that hour, or both), whole pages as ``Dashboard.render``
   serves them: one warm-up each, then --runs pairs, each page once from the rows (a Store that does
   not see the rollup) and once from the rollup, alternately; median and max of each, the load, and
   whether the two pages' HTML is the same (it must be where both read the rows: with a robot);
3. COPY into ``dc`` (all its indexes, as generated) with the trigger and without it (``ALTER TABLE …
   DISABLE TRIGGER``), alternately, --rounds of each: the fleet's 10 minutes 10:00-10:10 (175,098
   rows, those of the table a day later with new record ids, robot after robot as each robot's
   destination sends its own) in one COPY, and the same rows in COPYs of 100 rows (a robot's 34 s: a
   statement each, so the trigger's cost per statement shows);
   each round in a transaction rolled back (the table unchanged; a ``VACUUM`` after, not timed).
   Rows per second, median of the rounds, and their ratio.

JSON in benchmarks/results/dashboard_rollup_<date>[_<label>].json (never overwritten: ``_2``, ``_3``…).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.dashboard_fleet_day import (  # noqa: E402
    LAST_DAY,
    PASSWORD,
    ROBOT,
    RUN,
    generate,
    pg_settings,
    set_layout,
    sizes,
    write_result,
)
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_dashboard import rollup_setup, rollups  # noqa: E402
from dc_dashboard.queries import Catalog, Store  # noqa: E402
from dc_dashboard.server import Dashboard  # noqa: E402
from dc_dashboard.settings import DashboardSettings, S3Settings  # noqa: E402

BATCH = 100  # rows per COPY of the batched rounds
HOUR = f"start={LAST_DAY}T10:00:00&end={LAST_DAY}T11:00:00"


class RawStore(Store):
    """The dashboard's Store as it was before the rollup: it does not see one."""

    def catalog(self, connection: Any) -> Catalog:
        return dataclasses.replace(super().catalog(connection), rollup_series={})


def drop(server: PostgresServer) -> None:
    names = rollups.names("dc")
    with server.connect() as connection:
        connection.execute("DROP TRIGGER IF EXISTS dc_roll_up ON dc")
        connection.execute(f"DROP FUNCTION IF EXISTS {names['_roll_up']}()")
        connection.execute(f"DROP TABLE IF EXISTS {names['_rollup']}, {names['_rollup_series']}")


def build(server: PostgresServer) -> dict[str, Any]:
    settings = pg_settings(server)
    began = time.monotonic()
    assert rollup_setup.create(settings, say=lambda text: None) == 0
    built_s = time.monotonic() - began
    with server.connect() as connection:
        connection.execute("ANALYZE dc_rollup")
        (rows,) = connection.execute("SELECT count(*) FROM dc_rollup").fetchone()
        (size,) = connection.execute("SELECT pg_total_relation_size('dc_rollup')").fetchone()
    return {"create_s": built_s, "rollup_rows": int(rows), "rollup_mb": round(int(size) / 1e6, 1)}


# The filters the pages are timed with (label: query): every robot's hour (the rollup's case), every
# robot's run 6 (hours 10-12: 60 s buckets, the rollup too), and a robot's (the rows, rollup or not).
FILTERS = {
    "hour": HOUR,
    "run": f"run={RUN}",
    "robot": f"robot={ROBOT}",
    "robot+run": f"robot={ROBOT}&run={RUN}",
    "robot+hour": f"robot={ROBOT}&{HOUR}",
    "robot+run+hour": f"robot={ROBOT}&run={RUN}&{HOUR}",
}


def pages(server: PostgresServer, runs: int, chosen: list[str]) -> dict[str, Any]:
    settings = pg_settings(server)
    rolled = Dashboard(DashboardSettings(settings, S3Settings()))
    raw = Dashboard(DashboardSettings(settings, S3Settings()))
    raw.store = RawStore(settings)
    figures: dict[str, Any] = {}
    for label in chosen:
        for page in ("/", "/system", "/explore"):
            query = FILTERS[label] + ("&name=cpu" if page == "/explore" else "")
            times: dict[str, list[float]] = {"rows": [], "rollup": []}
            html = {}
            for name, dashboard in (("rows", raw), ("rollup", rolled)):
                status, html[name] = dashboard.render(page, query)  # warm-up: plans, caches, the catalog
                assert status == 200, (page, query, status)
            for _ in range(runs):
                for name, dashboard in (("rows", raw), ("rollup", rolled)):
                    started = time.perf_counter()
                    dashboard.render(page, query)
                    times[name].append(time.perf_counter() - started)
            key = f"{page} {label}"
            figures[key] = {
                name: {"median_s": statistics.median(t), "max_s": max(t), "all_s": t} for name, t in times.items()
            }
            # With a robot both read the rows, so the two pages should be the same to the byte: checked, not assumed.
            figures[key]["same_html"] = html["rows"] == html["rollup"]
            figures[key]["load_average_1min"] = os.getloadavg()[0]
            print(f"{key:26} {json.dumps({k: round(figures[key][k]['median_s'], 3) for k in times})}"
                  f" same_html={figures[key]['same_html']}  load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    return figures


def copies(server: PostgresServer, rounds: int) -> dict[str, Any]:
    """Rows/s of COPY into dc with and without the rollup's trigger, alternately."""
    import psycopg

    columns = "tag, time, data, record_id, name, robot_name, run_id, value"
    source = (
        "COPY (SELECT tag, time + interval '1 day', data, gen_random_uuid()::text, name, robot_name, run_id, value"
        f" FROM dc WHERE time >= '{LAST_DAY} 10:00Z' AND time < '{LAST_DAY} 10:10Z' ORDER BY robot_name, time)"
        " TO STDOUT"
    )
    block = bytearray()
    with server.connect() as connection, connection.cursor() as cursor, cursor.copy(source) as copy:
        for data in copy:
            block += data
    lines = bytes(block).splitlines(keepends=True)
    batches = [b"".join(lines[i : i + BATCH]) for i in range(0, len(lines), BATCH)]
    figures: dict[str, Any] = {"rows": len(lines), "batch_rows": BATCH}
    settings = pg_settings(server)
    for shape, parts in (("one_copy", [bytes(block)]), ("copies_of_100", batches)):
        rates: dict[str, list[float]] = {"without": [], "with": []}
        for n in range(2 * rounds + 2):  # the first pair: a warm-up, not counted
            trigger = "with" if n % 2 else "without"
            with server.connect() as connection:
                connection.execute(f"ALTER TABLE dc {'ENABLE' if trigger == 'with' else 'DISABLE'} TRIGGER dc_roll_up")
            with psycopg.connect(**settings.connect_kwargs()) as connection:
                started = time.perf_counter()
                with connection.cursor() as cursor:
                    for part in parts:
                        with cursor.copy(f"COPY dc ({columns}) FROM STDIN") as copy:
                            copy.write(part)
                took = time.perf_counter() - started
                connection.rollback()
            with server.connect() as connection:
                connection.execute("VACUUM dc")
            if n >= 2:
                rates[trigger].append(len(lines) / took)
                print(f"{shape:14} {trigger:8} {len(lines) / took:,.0f} rows/s  load {os.getloadavg()[0]:.1f}",
                      flush=True)  # fmt: skip
        medians = {k: statistics.median(v) for k, v in rates.items()}
        figures[shape] = {
            "rows_per_s": rates,
            "median_rows_per_s": medians,
            "with_over_without": medians["with"] / medians["without"],
        }
    with server.connect() as connection:
        connection.execute("ALTER TABLE dc ENABLE TRIGGER dc_roll_up")
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, required=True, help="dashboard_fleet_day.py's PostgreSQL folder")
    parser.add_argument("--hours", type=int, default=2, help="generated when the folder is new (from 10:00)")
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--label", default="")
    parser.add_argument("--only", choices=("pages", "copy"), help="that part alone (the rollup built all the same)")
    parser.add_argument(
        "--filters", default="hour", help=f"comma-separated, of {', '.join(FILTERS)} (all: all of them)"
    )
    args = parser.parse_args()
    chosen = list(FILTERS) if args.filters == "all" else args.filters.split(",")
    if unknown := set(chosen) - set(FILTERS):
        parser.error(f"--filters: no {', '.join(sorted(unknown))}")
    server = PostgresServer(args.folder, password=PASSWORD)
    result: dict[str, Any] = {"date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "hours": args.hours}
    try:
        fresh = not (args.folder / "data" / "PG_VERSION").is_file()
        server.start(timeout=120)
        if fresh:
            result["generated"] = generate(server, 100, 1, 1.0, "none", args.hours)
        result.update(sizes(server))
        result["layout_s"] = set_layout(server, "main")
        drop(server)
        load = os.getloadavg()[0]
        result["rollup"] = build(server)
        print(json.dumps(result["rollup"]), flush=True)
        if args.only != "copy":
            result["pages"] = pages(server, args.runs, chosen)
        if args.only != "pages":
            result["copy"] = copies(server, args.rounds)
        result["load_average_1min"] = [load, os.getloadavg()[0]]
    finally:
        server.stop(timeout=60)
    write_result("dashboard_rollup", args.label, result)


if __name__ == "__main__":
    main()
