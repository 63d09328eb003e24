"""The records table of DC's shape at fleet scale: the team queries of docs/data-model.md, and the insert rate.

    .venv/bin/python benchmarks/pgsql_data_model.py [--robots 100] [--hours 24] [--runs 15] [--cold-runs 3]
                                                    [--insert-records 50000] [--insert-runs 7]
                                                    [--index-runs 0] [--ways-runs 0] [--parts-runs 0]
                                                    [--parts TEXT] [--partition-by day] [--label NAME]

Starts a throw-away PostgreSQL on 127.0.0.1 (dc_bringup.local_servers, a folder under /tmp, removed
at the end) and, printing the load averages of each phase (the machine may be shared):

- insert: the PgSQL destination's ``send()`` of --insert-records records (~250 bytes, batches of
  500, handed over as the sender does: read back from the buffer with their JSON text) into a
  fresh table of the original's shape (``tag, time timestamp, data, record_id``: what DC wrote
  until now), of DC's new shape, of DC's new shape partitioned by day, of that without the
  latest-row table (``latest_table: false``) and without it nor the run index (``run_index:
  false``), all with batches of the fleet's records mixed (dc ingest's case: 100 robots in a batch
  of 500); and the original's and the partitioned shape with batches of one robot's records each
  (a robot's own DC). The seven take turns, --insert-runs rounds; rows/s and CPU per row (client
  and server) per round, medians, and the medians of the per-round ratios to the original's shape
  with the same batches.
- index costs (--index-runs N): the server's CPU per row of a binary COPY of the same rows into
  tables that differ only in their indexes, N rounds in turns.
- parts (--parts-runs N, --parts TEXT): the insert's cost part by part (PARTS): each part a table
  and a way of putting the same rows in it; the backend's and the server's CPU, WAL bytes, shared
  buffer accesses (hits and reads, which the machine's load does not change) and client CPU per
  row, N rounds in turns; then the client's CPU per row of the destination's own row building.
- ways (--ways-runs N): the server's CPU and the wall time per row of each way in WAYS of putting
  the same rows into a day-partitioned table with DC's indexes: COPY (into the parent, straight into
  the partition, with the latest-row trigger, batches of one robot, without the run index), the
  staging table's INSERT … ON CONFLICT, executemany; N rounds in turns.
- queries: the PgSQL destination creates table ``dc`` (``partition_by: day``), then the server
  generates --robots robots x --hours hours of records on 2026-11-25 (UTC) into it with one
  ``INSERT … SELECT`` from ``generate_series`` per measurement, in time order (the robots' rows
  side by side, as a fleet inserts them): per robot ``position`` every 2.5 s, ``cpu`` and
  ``memory`` every 5 s and ``front_camera`` (two codes) every 20 s — 0.85 records/s, the rate
  issue 29 measured — in runs of 2 hours (run 12 is the last of the day), with the keys the
  measurement server adds. Then ``VACUUM ANALYZE``, and each query of docs/data-model.md as
  written there (robot-007, run 12): warm, one warm-up then --runs runs, wall time at the client
  (execute and fetch), median and max, and the server's execution time of one more run
  (``EXPLAIN ANALYZE``); cold, the first run after a restart of the server, --cold-runs times.

JSON in benchmarks/results/pgsql_data_model_<date>[_<label>].json; when that file exists, the first free
``…_2.json``, ``…_3.json``: a run never overwrites an earlier result.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.storage import _client_cpu, _tree_cpu  # noqa: E402
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_core.destination import OutgoingRecord, StoredRecord  # noqa: E402
from dc_core.params import parse_params  # noqa: E402
from dc_core.records import dump_record  # noqa: E402
from dc_core.testing import FakeContext, RecordingLogger  # noqa: E402
from dc_destinations.pgsql import PgSQL, PgSQLParams  # noqa: E402
from dc_destinations.record_ids import new_record_id  # noqa: E402

DAY = "2026-11-25"
PAGE = REPO / "docs" / "data-model.md"
BATCH = 500

# (measurement, seconds between records, the record's own fields as SQL over r (robot) and t (time))
MEASUREMENTS = (
    (
        "position",
        2.5,
        "'x', round((r + 10 * cos(extract(epoch FROM t) / 600))::numeric, 3), "
        "'y', round((10 * sin(extract(epoch FROM t) / 600))::numeric, 3), 'yaw', 0.5",
    ),
    ("cpu", 5.0, "'average', round((random() * 100)::numeric, 2), 'processes', 212"),
    ("memory", 5.0, "'used', round((30 + random() * 20)::numeric, 2)"),
    (
        "front_camera",
        20.0,
        "'camera_name', 'front_camera', 'inspected', jsonb_build_object('barcode', jsonb_build_array("
        "jsonb_build_object('data', 'WH1/AISLE-' || (r % 10) || '/SHELF-' || lpad(((extract(epoch FROM t)::bigint"
        " / 20) % 40)::text, 2, '0'), 'type', 'QRCODE', 'top', 198, 'left', 148, 'width', 86, 'height', 86),"
        " jsonb_build_object('data', 'PAL-' || (extract(epoch FROM t)::bigint % 5000), 'type', 'CODE128')))",
    ),
)


def destination(
    server: PostgresServer,
    table: str,
    partition_by: str = "none",
    latest: bool = True,
    value_keys: dict[str, str] | None = None,
    run_index: bool = True,
) -> PgSQL:
    settings = {
        "table": table,
        "partition_by": partition_by,
        "latest_table": latest,
        "value_keys": value_keys or {},
        "run_index": run_index,
    }
    params = parse_params(PgSQLParams, {**server.settings(), **settings}, "destination_server.pg")
    dest = PgSQL(FakeContext(name="pg", logger=RecordingLogger()), params)
    dest.on_configure()
    return dest


def generate(server: PostgresServer, robots: int, hours: int, partition_by: str = "day") -> tuple[int, float]:
    """The fleet's day in table dc (made by the destination); (rows, seconds)."""
    first = int(dt.datetime.fromisoformat(f"{DAY}T00:00:00+00:00").timestamp() * 1e9)
    dest = destination(server, "dc", partition_by, value_keys={"cpu": "average"})
    dest.send([OutgoingRecord(new_record_id(), "/dc/x", first, {"name": "marker"})])  # table and partitions
    dest.on_deactivate()
    started = time.monotonic()
    with server.connect() as connection:
        # Each INSERT … SELECT below is a statement of 0.7-2.9 M rows, whose transition table the
        # latest-row trigger would sort whole: the table is filled after, as the page says for a
        # table that had none.
        connection.execute("ALTER TABLE dc DISABLE TRIGGER USER")
        for name, every, fields in MEASUREMENTS:
            # In time order, the robots' rows side by side at each instant, as a fleet inserts them:
            # one robot's rows of a measurement are then on as many heap pages as they are rows (a
            # robot-by-robot order would put them on a few hundred pages and flatter the queries).
            connection.execute(fill(name, every, fields, DAY, hours * 3600, robots).encode())
        connection.execute(block("latest-table").encode())
        connection.execute("ALTER TABLE dc ENABLE TRIGGER USER")
        connection.execute("VACUUM ANALYZE dc")
        connection.execute("VACUUM ANALYZE dc_latest")
        (rows,) = connection.execute("SELECT count(*) FROM dc").fetchone()
        (size,) = connection.execute("SELECT pg_size_pretty(pg_total_relation_size('dc') + coalesce(sum("
                                     "pg_total_relation_size(c.oid)), 0)) FROM pg_inherits i"
                                     " JOIN pg_class c ON c.oid = i.inhrelid WHERE i.inhparent = 'dc'::regclass"
                                     ).fetchone()  # fmt: skip
    print(f"generated {rows:,} rows in {time.monotonic() - started:.0f} s ({size} with indexes)", flush=True)
    return int(rows), time.monotonic() - started


def fill(
    name: str, every: float, fields: str, day: str, seconds: int, robots: int, run_s: int = 7200, from_s: int = 0
) -> str:
    """The INSERT … SELECT of a measurement's rows into dc: ``robots`` robots from ``day`` 00:00Z plus
    ``from_s`` for ``seconds``, a record every ``every`` s, in time order with the robots side by side
    (10 ms apart), ``fields`` the record's own as SQL over r (robot number), robot and t; runs of
    ``run_s`` counted from ``day`` 00:00Z (the same run numbers whatever ``from_s``)."""
    return f"""INSERT INTO dc (tag, time, data, record_id, name, robot_name, run_id, value)
        SELECT 'pg', t, data || jsonb_build_object('record_id', rid), rid, '{name}', robot, run,
               {"(data->>'average')::float8" if name == "cpu" else "NULL"}
        FROM (SELECT t, rid, robot, run, jsonb_build_object({fields}) || jsonb_build_object(
                  'name', '{name}', 'robot_name', robot, 'run_id', run::text, 'schema_version', 1,
                  'tags', jsonb_build_array('pg')) AS data
              FROM generate_series(timestamptz '{day} 00:00Z' + interval '{from_s} s',
                                   timestamptz '{day} 00:00Z' + interval '{from_s + seconds} s' - interval '1 s',
                                   interval '{every} s') AS t0,
                   LATERAL (SELECT r, t0 + r * interval '10 ms' AS t FROM generate_series(1, {robots}) AS r) AS rt,
                   LATERAL (SELECT gen_random_uuid()::text AS rid, 'robot-' || lpad(r::text, 3, '0') AS robot,
                                   1 + floor(extract(epoch FROM t - timestamptz '{day} 00:00Z') / {run_s})::bigint
                                     AS run) AS k) AS rows"""


def block(tag: str) -> str:
    (sql,) = re.findall(rf"<!-- {tag} -->\n```sql\n(.*?)```", PAGE.read_text(), re.S)
    return str(sql)


def page_queries() -> dict[str, str]:
    return dict(re.findall(r"<!-- query: (\w+) -->\n```sql\n(.*?)```", PAGE.read_text(), re.S))


def time_queries(server: PostgresServer, runs: int) -> dict[str, dict[str, Any]]:
    """Each query of the page on table dc, warm: one warm-up, then ``runs`` runs (wall time at the client,
    execute and fetch; the CPU time of the server's process for the connection and of this one, their
    mean over the runs: what a loaded machine stretches the wall time from) and the server's execution
    time of one more (``EXPLAIN ANALYZE``)."""
    import psutil

    found = {k: v for k, v in page_queries().items() if k != "files"}  # files_metrics: not generated here
    figures: dict[str, dict[str, Any]] = {}
    with server.connect() as connection:
        (backend_pid,) = connection.execute("SELECT pg_backend_pid()").fetchone()
        backend = psutil.Process(backend_pid)

        def backend_cpu() -> float:
            used = backend.cpu_times()
            return float(used.user + used.system)

        for name, query in found.items():
            text = query.encode()
            connection.execute(text).fetchall()  # warm-up: plan, caches
            times = []
            cpu_before, client_before = backend_cpu(), _client_cpu()
            for _ in range(runs):
                started = time.perf_counter()
                got = connection.execute(text).fetchall()
                times.append((time.perf_counter() - started) * 1000)
            server_cpu_ms = (backend_cpu() - cpu_before) / runs * 1000
            client_cpu_ms = (_client_cpu() - client_before) / runs * 1000
            explained = connection.execute(b"EXPLAIN (ANALYZE, FORMAT JSON) " + text).fetchone()[0][0]
            figures[name] = {
                "median_ms": statistics.median(times),
                "max_ms": max(times),
                "runs_ms": [round(t, 1) for t in times],
                "server_cpu_ms_mean": server_cpu_ms,
                "client_cpu_ms_mean": client_cpu_ms,
                "server_ms": explained["Execution Time"],  # the server's own time, without the client's
                "plan": plan_summary(explained["Plan"]),
                "rows": len(got),
                "load_average_1min": os.getloadavg()[0],
            }
            print(f"  plan: {'; '.join(figures[name]['plan'])[:600]}", flush=True)
            print(f"warm {name:16} median {figures[name]['median_ms']:7.1f} ms  max {max(times):7.1f} ms"
                  f"  server {explained['Execution Time']:7.1f} ms  CPU server {server_cpu_ms:5.1f} client"
                  f" {client_cpu_ms:5.1f} ms  ({len(got)} rows)"
                  f"  load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    return figures


def plan_summary(node: dict[str, Any]) -> list[str]:
    """The plan's scans and what they read: node type, relation or index, rows, heap fetches, buffers."""
    found = []
    if "Scan" in node["Node Type"]:
        where = node.get("Index Name") or node.get("Relation Name") or ""
        fetches = f" heap fetches {node['Heap Fetches']}" if "Heap Fetches" in node else ""
        found.append(
            f"{node['Node Type']} {where}: {node.get('Actual Rows')} rows x {node.get('Actual Loops')}{fetches}"
        )
    for child in node.get("Plans", []):
        found.extend(plan_summary(child))
    return found


def time_cold(server: PostgresServer, rounds: int) -> dict[str, dict[str, Any]]:
    """Each query's first run after a restart of the server (its shared buffers empty; the OS's page
    cache may still hold pages: dropping it would slow every other job of a shared machine), ``rounds`` times."""
    found = {k: v for k, v in page_queries().items() if k != "files"}
    times: dict[str, list[float]] = {name: [] for name in found}
    for _ in range(rounds):
        for name, query in found.items():
            server.stop()
            server.start()
            with server.connect() as connection:
                connection.execute("SELECT 1")  # the connection's own start, not the query's
                started = time.perf_counter()
                connection.execute(query.encode()).fetchall()
                times[name].append((time.perf_counter() - started) * 1000)
    figures = {}
    for name, runs in times.items():
        figures[name] = {
            "median_ms": statistics.median(runs),
            "max_ms": max(runs),
            "runs_ms": [round(t, 1) for t in runs],
        }
        print(f"cold {name:16} median {statistics.median(runs):7.1f} ms  max {max(runs):7.1f} ms"
              f"  runs {figures[name]['runs_ms']}  load {os.getloadavg()[0]:.1f}", flush=True)  # fmt: skip
    return figures


def insert_records(n: int, one_robot: bool = False) -> list[StoredRecord]:
    """``n`` records of 100 robots, time and ids in order; mixed in each batch of BATCH (a fleet's, as
    dc ingest gets them), or ``one_robot``: each batch one robot's records (as a robot's DC sends them)."""
    start = time.time_ns()
    out = []
    for i in range(n):
        rid = new_record_id()
        data = {
            "average": (i * 37) % 100 + 0.25,
            "processes": 212,
            "name": "cpu" if i % 2 else "position",
            "robot_name": f"robot-{(i // BATCH if one_robot else i) % 100:03d}",
            "run_id": str(1 + i // 10_000),
            "schema_version": 1,
            "tags": ["pg"],
            "record_id": rid,
        }
        # As the destination server's sender hands them over: read back from the buffer with their JSON
        # text, ``data`` parsed only by a destination that reads it.
        out.append(StoredRecord(rid, "/dc/measurement/cpu", start + i * 1_000_000, json_text=dump_record(data)))
    return out


def time_inserts(server: PostgresServer, n: int, rounds: int) -> dict[str, Any]:
    shapes = (
        "original",
        "typed",
        "typed_before",  # DC's defaults until 2026-11-27 (the run index, the trigger), the table made by hand
        "typed_day",
        "typed_day_no_latest",
        "typed_day_lean",  # run_index and latest_table false
        "typed_day_one_robot",
        "original_one_robot",
    )
    rates: dict[str, list[float]] = {s: [] for s in shapes}
    # CPU per row (this process and the server's, over the same window): what contention on a shared
    # machine inflates far less than the wall time.
    cpu_us: dict[str, list[float]] = {s: [] for s in shapes}
    pid = server_pid(server)
    loads: list[float] = []  # the 1-minute load average at the end of each round
    for k in range(rounds):
        order = shapes[k % len(shapes) :] + shapes[: k % len(shapes)]  # each shape goes first in turn
        for shape in order:
            table = f"insert_{shape}_{k}"
            if shape.startswith("original"):
                with server.connect() as connection:
                    connection.execute(
                        f"CREATE TABLE {table} (tag varchar, time timestamp, data jsonb, record_id text)"
                    )
                    connection.execute(f"CREATE UNIQUE INDEX {table}_record_id ON {table} (record_id)")
            if shape == "typed_before":
                with server.connect() as connection:
                    connection.execute(f"CREATE TABLE {table} ({_TYPED})")
                    for statement in (_RECORD_ID, _TEAM, _RUN, _BRIN):
                        connection.execute(statement.format(t=table))
                    connection.execute(block("latest-ddl").replace("dc", table).encode())
            dest = destination(
                server,
                table,
                "day" if "day" in shape else "none",
                shape not in ("typed_day_no_latest", "typed_day_lean"),
                {"cpu": "average"} if shape.startswith("typed") else None,
                shape != "typed_day_lean",
            )
            records = insert_records(n, shape.endswith("one_robot"))
            dest.send(records[:BATCH])  # connects and prepares: not timed
            started, cpu = time.perf_counter(), _client_cpu() + _tree_cpu(pid)
            for i in range(BATCH, n, BATCH):
                assert dest.send(records[i : i + BATCH]) is None
            rates[shape].append((n - BATCH) / (time.perf_counter() - started))
            cpu_us[shape].append((_client_cpu() + _tree_cpu(pid) - cpu) / (n - BATCH) * 1e6)
            dest.on_deactivate()
        loads.append(os.getloadavg()[0])
    medians = {s: statistics.median(r) for s, r in rates.items()}

    # Each shape against the original's with the same batches (a robot's own, or the fleet's mixed).
    def base(s: str) -> str:
        return "original_one_robot" if s.endswith("one_robot") else "original"

    ratios = [[rates[s][k] / rates[base(s)][k] for k in range(rounds)] for s in shapes[1:]]
    cpu_ratios = [[cpu_us[s][k] / cpu_us[base(s)][k] for k in range(rounds)] for s in shapes[1:]]
    result = {
        "cpu_us_per_row": cpu_us,
        "cpu_ratio_to_original": {s: statistics.median(r) for s, r in zip(shapes[1:], cpu_ratios, strict=True)},
        "rows_per_s": rates,
        "median_rows_per_s": medians,
        "ratio_to_original": {s: statistics.median(r) for s, r in zip(shapes[1:], ratios, strict=True)},
        "per_round_ratios": {s: [round(x, 3) for x in r] for s, r in zip(shapes[1:], ratios, strict=True)},
        "load_average_1min_per_round": loads,
    }
    for s in shapes:
        print(f"insert {s:10} {medians[s]:9,.0f} rows/s  runs {[round(r) for r in rates[s]]}"
              f"  CPU µs/row {[round(c, 1) for c in cpu_us[s]]}", flush=True)  # fmt: skip
    print(f"CPU ratios to the original's shape: {result['cpu_ratio_to_original']}", flush=True)
    print(f"ratios to the original's shape (median of per-round ratios): {result['ratio_to_original']}", flush=True)
    return result


# What each index of the typed table costs the server per row: a binary COPY of the same rows
# (made once, so the client's part is the same in every case) into tables that differ only in
# their indexes. (columns, index statements, COPY types)
_ORIGINAL = "tag varchar, time timestamp, data jsonb, record_id text"
_TYPED = (
    "tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL, name text, robot_name text,"
    " run_id bigint, value double precision"
)
_UNIQUE = "CREATE UNIQUE INDEX ON {t} (robot_name, name, time, record_id) INCLUDE (value) NULLS NOT DISTINCT"
_RUN = "CREATE INDEX ON {t} (robot_name, run_id, name, time)"
_BRIN = "CREATE INDEX ON {t} USING brin (time)"
_RECORD_ID = "CREATE UNIQUE INDEX ON {t} (record_id)"
_TEAM = "CREATE INDEX ON {t} (robot_name, name, time) INCLUDE (value)"
INDEX_SETS = {
    "original's shape: UNIQUE (record_id)": (_ORIGINAL, [_RECORD_ID]),
    "typed, no index": (_TYPED, []),
    "typed: UNIQUE (record_id), (robot_name, name, time)": (_TYPED, [_RECORD_ID, _TEAM]),
    "typed: those + run index + BRIN (DC's plain table)": (_TYPED, [_RECORD_ID, _TEAM, _RUN, _BRIN]),
    "typed: UNIQUE (robot_name, name, time, record_id)": (_TYPED, [_UNIQUE]),
    "typed: that + run index + BRIN (DC's partitioned table)": (_TYPED, [_UNIQUE, _RUN, _BRIN]),
}


def server_pid(server: PostgresServer) -> int:
    return int((server.data_dir / "postmaster.pid").read_text().split("\n", 1)[0])


@contextlib.contextmanager
def copy_connection(server: PostgresServer) -> Iterator[Any]:
    """A connection in autocommit that writes JSON text as jsonb in a binary COPY, as the destination does."""
    from dc_destinations.pgsql import json_text_binary_dumper

    with server.connect() as connection:
        connection.autocommit = True
        connection.adapters.register_dumper(None, json_text_binary_dumper())
        yield connection


def copy_rows(records: list[StoredRecord]) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
    """The rows of a binary COPY of ``records``: into a typed table, and into one of the original's shape."""
    import orjson

    epoch = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    typed, original = [], []
    for r in records:
        assert r.json_text is not None
        data = orjson.loads(r.json_text)
        moment = epoch + dt.timedelta(microseconds=r.stamp_ns // 1000)
        value = data["average"] if data["name"] == "cpu" else None
        typed.append(
            ("pg", moment, r.json_text, r.record_id, data["name"], data["robot_name"], int(data["run_id"]), value)
        )
        original.append(("pg", moment.replace(tzinfo=None), r.json_text, r.record_id))
    return typed, original


def time_index_costs(server: PostgresServer, n: int, rounds: int) -> dict[str, Any]:

    typed, original = copy_rows(insert_records(n))
    pid = server_pid(server)
    names = list(INDEX_SETS)
    cpu: dict[str, list[float]] = {name: [] for name in names}
    with copy_connection(server) as connection:
        for k in range(rounds):
            for j, name in enumerate(names[k % len(names) :] + names[: k % len(names)]):
                columns, indexes = INDEX_SETS[name]
                table = f"index_cost_{k}_{j}"
                connection.execute(f"CREATE TABLE {table} ({columns})")
                for statement in indexes:
                    connection.execute(statement.format(t=table))
                legacy = columns == _ORIGINAL
                rows = original if legacy else typed
                written = "tag, time, data, record_id" + ("" if legacy else ", name, robot_name, run_id, value")
                types = ["varchar", "timestamp", "jsonb", "text"] if legacy else TYPED_COPY_TYPES
                before = _tree_cpu(pid)
                for i in range(0, n, BATCH):
                    with (
                        connection.cursor() as cursor,
                        cursor.copy(f"COPY {table} ({written}) FROM STDIN (FORMAT BINARY)") as copy,
                    ):
                        copy.set_types(types)
                        for row in rows[i : i + BATCH]:
                            copy.write_row(row)
                cpu[name].append((_tree_cpu(pid) - before) / n * 1e6)
                connection.execute(f"DROP TABLE {table}")
    base = cpu[names[0]]
    result = {
        name: {
            "server_cpu_us_per_row": statistics.median(runs),
            "ratio_to_original": statistics.median([a / b for a, b in zip(runs, base, strict=True)]),
            "runs": [round(x, 1) for x in runs],
        }
        for name, runs in cpu.items()
    }
    for name, figures in result.items():
        print(f"server CPU {figures['server_cpu_us_per_row']:5.1f} µs/row  x{figures['ratio_to_original']:.2f}  {name}",
              flush=True)  # fmt: skip
    return result


TYPED_COPY_TYPES = ["text", "timestamptz", "jsonb", "text", "text", "text", "int8", "float8"]
_TYPED_COLUMNS = "tag, time, data, record_id, name, robot_name, run_id, value"
# Each way of putting the same rows into a day-partitioned typed table with DC's indexes (or the
# original's table), in batches of BATCH: what the insert's cost is made of. (way, table DDL)
WAYS = (
    "original's shape, COPY",
    "DC's partitioned table, COPY into the parent (DC)",
    "the same with the latest-row table's trigger (DC)",
    "the same, COPY straight into the day's partition",
    "the same, staging COPY + INSERT … ON CONFLICT DO NOTHING",
    "the same, executemany INSERT … ON CONFLICT DO NOTHING",
    "the same, each batch one robot's rows (COPY)",
    "the same without the run index (COPY)",
    "typed, no index (COPY)",
)


def time_insert_ways(server: PostgresServer, n: int, rounds: int) -> dict[str, Any]:
    """Server CPU and wall time per row of each way in WAYS, ``rounds`` rounds in turns."""

    typed, original = copy_rows(insert_records(n))
    by_robot, _ = copy_rows(insert_records(n, one_robot=True))
    day = typed[0][1].date()
    pid = server_pid(server)
    cpu: dict[str, list[float]] = {way: [] for way in WAYS}
    wall: dict[str, list[float]] = {way: [] for way in WAYS}
    with copy_connection(server) as connection:
        for k in range(rounds):
            for j, way in enumerate(WAYS[k % len(WAYS) :] + WAYS[: k % len(WAYS)]):
                table = f"way_{k}_{j}"
                rows, target, types, columns = typed, table, TYPED_COPY_TYPES, _TYPED_COLUMNS
                if way.startswith("original"):
                    connection.execute(f"CREATE TABLE {table} ({_ORIGINAL})")
                    connection.execute(_RECORD_ID.format(t=table))
                    rows, types, columns = (
                        original,
                        ["varchar", "timestamp", "jsonb", "text"],
                        "tag, time, data, record_id",
                    )
                elif way.startswith("typed, no index"):
                    connection.execute(f"CREATE TABLE {table} ({_TYPED})")
                else:
                    connection.execute(f"CREATE TABLE {table} ({_TYPED}) PARTITION BY RANGE (time)")
                    connection.execute(
                        f"CREATE TABLE {table}_p PARTITION OF {table} FOR VALUES FROM ('{day} 00:00Z')"
                        f" TO ('{day + dt.timedelta(days=1)} 00:00Z')"
                    )
                    connection.execute(_UNIQUE.format(t=table))
                    if "without the run index" not in way:
                        connection.execute(_RUN.format(t=table))
                    connection.execute(_BRIN.format(t=table))
                    if "latest" in way:
                        connection.execute(block("latest-ddl").replace("dc", table).encode())
                    connection.execute(f"CREATE TEMPORARY TABLE staging_{table} ({_TYPED}) ON COMMIT DELETE ROWS")
                    if "straight into" in way:
                        target = f"{table}_p"
                    if "one robot" in way:
                        rows = by_robot
                before, started = _tree_cpu(pid), time.perf_counter()
                for i in range(0, n, BATCH):
                    batch = rows[i : i + BATCH]
                    if "executemany" in way:
                        with connection.transaction(), connection.cursor() as cursor:
                            cursor.executemany(
                                f"INSERT INTO {table} ({columns}) VALUES (%s, %s, %s::jsonb, %s, %s, %s, %s, %s)"
                                " ON CONFLICT DO NOTHING",
                                batch,
                            )
                        continue
                    staged = "staging" in way
                    with (
                        connection.transaction() if staged else contextlib.nullcontext(),
                        connection.cursor() as cursor,
                    ):
                        into = f"staging_{table}" if staged else target
                        with cursor.copy(f"COPY {into} ({columns}) FROM STDIN (FORMAT BINARY)") as copy:
                            copy.set_types(types)
                            for row in batch:
                                copy.write_row(row)
                        if staged:
                            cursor.execute(
                                f"INSERT INTO {table} ({columns}) SELECT {columns} FROM staging_{table}"
                                " ON CONFLICT DO NOTHING"
                            )
                wall[way].append((time.perf_counter() - started) / n * 1e6)
                cpu[way].append((_tree_cpu(pid) - before) / n * 1e6)
                connection.execute(f"DROP TABLE {table}")
                connection.execute(f"DROP TABLE IF EXISTS {table}_latest")
                connection.execute(f"DROP FUNCTION IF EXISTS {table}_keep_latest")
                connection.execute(f"DROP TABLE IF EXISTS staging_{table}")
    result = {}
    for way in WAYS:
        result[way] = {
            "server_cpu_us_per_row": statistics.median(cpu[way]),
            "server_cpu_ratio_to_original": statistics.median(
                [a / b for a, b in zip(cpu[way], cpu[WAYS[0]], strict=True)]
            ),
            "wall_us_per_row": statistics.median(wall[way]),
            "wall_ratio_to_original": statistics.median([a / b for a, b in zip(wall[way], wall[WAYS[0]], strict=True)]),
            "cpu_runs": [round(x, 1) for x in cpu[way]],
            "wall_runs": [round(x, 1) for x in wall[way]],
        }
        f = result[way]
        print(f"server CPU {f['server_cpu_us_per_row']:5.1f} µs/row x{f['server_cpu_ratio_to_original']:.2f}"
              f"  wall {f['wall_us_per_row']:5.1f} µs/row x{f['wall_ratio_to_original']:.2f}  {way}",
              flush=True)  # fmt: skip
    return result


# -- the insert's cost, part by part (--parts-runs) ---------------------------------------------------
# Each part: a table (columns, indexes, partitioned or not) and a way of putting the same rows in it
# (binary COPY in batches of BATCH, the batch sorted by the team key or not, the latest-row table kept
# by the trigger or by one upsert a batch from the client). What a part costs is the difference of
# its server CPU per row from the part it adds to.
_TEAM_BARE = "CREATE INDEX ON {t} (robot_name, name, time)"
_TEAM_NODEDUP = "CREATE INDEX ON {t} (robot_name, name, time) INCLUDE (value) WITH (deduplicate_items = off)"
_RUN_NARROW = "CREATE INDEX ON {t} (robot_name, run_id)"
_RECORD_ID_TIME = "CREATE UNIQUE INDEX ON {t} (record_id, time)"
_GENERATED = (
    "tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL,"
    " name text GENERATED ALWAYS AS (data->>'name') STORED,"
    " robot_name text GENERATED ALWAYS AS (data->>'robot_name') STORED,"
    " run_id bigint GENERATED ALWAYS AS (CASE WHEN data->>'run_id' ~ '^[0-9]{1,18}$'"
    " THEN (data->>'run_id')::bigint END) STORED, value double precision"
)
_LATEST_SMALL = (
    "CREATE TABLE {t}_latest (robot_name text NOT NULL, name text NOT NULL, time timestamptz NOT NULL,"
    " record_id text NOT NULL, PRIMARY KEY (robot_name, name)) WITH (fillfactor = 70)"
)
_UPSERT = (
    "INSERT INTO {t}_latest AS l (robot_name, name, time, data, record_id)"
    " SELECT * FROM unnest(%b::text[], %b::text[], %b::timestamptz[], %b::text[]::jsonb[], %b::text[])"
    " ON CONFLICT (robot_name, name) DO UPDATE SET time = EXCLUDED.time, data = EXCLUDED.data,"
    " record_id = EXCLUDED.record_id WHERE l.time <= EXCLUDED.time"
)
_UPSERT_SMALL = (
    "INSERT INTO {t}_latest AS l (robot_name, name, time, record_id)"
    " SELECT * FROM unnest(%b::text[], %b::text[], %b::timestamptz[], %b::text[])"
    " ON CONFLICT (robot_name, name) DO UPDATE SET time = EXCLUDED.time, record_id = EXCLUDED.record_id"
    " WHERE l.time <= EXCLUDED.time"
)
# (part, columns, indexes, options): options among "partitioned", "into partition", "sorted", "trigger",
# "upsert", "upsert small", "one robot", "generated"
PARTS: tuple[tuple[str, str, list[str], set[str]], ...] = (
    ("original's shape + UNIQUE (record_id)", _ORIGINAL, [_RECORD_ID], set()),
    ("original's shape, no index", _ORIGINAL, [], set()),
    ("typed, no index", _TYPED, [], set()),
    ("original's shape + UNIQUE (record_id), text COPY", _ORIGINAL, [_RECORD_ID], {"text"}),
    ("typed, no index, text COPY", _TYPED, [], {"text"}),
    ("typed, no index, batches of 5,000", _TYPED, [], {"batch 5000"}),
    ("typed, generated name/robot/run, no index", _GENERATED, [], {"generated"}),
    ("typed, partitioned, no index, into the parent", _TYPED, [], {"partitioned"}),
    ("typed, partitioned, no index, into the partition", _TYPED, [], {"partitioned", "into partition"}),
    ("typed + UNIQUE (record_id)", _TYPED, [_RECORD_ID], set()),
    ("typed + UNIQUE (record_id, time)", _TYPED, [_RECORD_ID_TIME], set()),
    ("typed + BRIN (time)", _TYPED, [_BRIN], set()),
    ("typed + (robot_name, name, time)", _TYPED, [_TEAM_BARE], set()),
    ("typed + (robot_name, name, time) INCLUDE (value)", _TYPED, [_TEAM], set()),
    ("typed + the same, deduplicate_items off", _TYPED, [_TEAM_NODEDUP], set()),
    ("typed + the same, batch sorted by robot, name", _TYPED, [_TEAM], {"sorted"}),
    ("typed + UNIQUE (robot_name, name, time, record_id) INCLUDE (value)", _TYPED, [_UNIQUE], set()),
    ("typed + (robot_name, run_id, name, time)", _TYPED, [_RUN], set()),
    ("typed + (robot_name, run_id)", _TYPED, [_RUN_NARROW], set()),
    ("typed + the latest-row trigger", _TYPED, [], {"trigger"}),
    ("typed + the latest row upserted by the client (with data)", _TYPED, [], {"upsert"}),
    ("typed + the latest row upserted by the client (no data)", _TYPED, [], {"upsert small"}),
    ("typed, no index, batches of 10 (one robot's)", _TYPED, [], {"batch 10", "one robot"}),
    ("typed + the latest-row trigger, batches of 10 (one robot's)", _TYPED, [], {"trigger", "batch 10", "one robot"}),
    (
        "typed + the latest row upserted by the client, batches of 10 (one robot's)",
        _TYPED,
        [],
        {"upsert", "batch 10", "one robot"},
    ),
    ("typed + UNIQUE (robot_name, name, time, record_id) + run index + BRIN", _TYPED, [_UNIQUE, _RUN, _BRIN], set()),
    ("DC's plain table now (4 indexes + trigger)", _TYPED, [_RECORD_ID, _TEAM, _RUN, _BRIN], {"trigger"}),
    ("DC's partitioned table now (3 indexes + trigger)", _TYPED, [_UNIQUE, _RUN, _BRIN], {"partitioned", "trigger"}),
    ("the same, batch sorted by robot, name", _TYPED, [_UNIQUE, _RUN, _BRIN], {"partitioned", "trigger", "sorted"}),
    ("UNIQUE (record_id) + team + BRIN", _TYPED, [_RECORD_ID, _TEAM, _BRIN], set()),
    ("the same, batch sorted", _TYPED, [_RECORD_ID, _TEAM, _BRIN], {"sorted"}),
    ("the same, sorted, + (robot_name, run_id)", _TYPED, [_RECORD_ID, _TEAM, _BRIN, _RUN_NARROW], {"sorted"}),
    (
        "the same, sorted, + (robot_name, run_id) + upsert",
        _TYPED,
        [_RECORD_ID, _TEAM, _BRIN, _RUN_NARROW],
        {"sorted", "upsert"},
    ),
    (
        "original's shape + UNIQUE (record_id), batches of 10 (one robot's)",
        _ORIGINAL,
        [_RECORD_ID],
        {"batch 10", "one robot"},
    ),
    (
        "DC's plain table now, batches of 10 (one robot's)",
        _TYPED,
        [_RECORD_ID, _TEAM, _RUN, _BRIN],
        {"trigger", "batch 10", "one robot"},
    ),
    (
        "UNIQUE (record_id) + team + BRIN + (robot_name, run_id) + upsert, batches of 10 (one robot's)",
        _TYPED,
        [_RECORD_ID, _TEAM, _BRIN, _RUN_NARROW],
        {"upsert", "batch 10", "one robot"},
    ),
    ("original's shape + UNIQUE (record_id), one robot a batch", _ORIGINAL, [_RECORD_ID], {"one robot"}),
    ("DC's plain table now, one robot a batch", _TYPED, [_RECORD_ID, _TEAM, _RUN, _BRIN], {"trigger", "one robot"}),
    (
        "UNIQUE (record_id) + team + BRIN + (robot_name, run_id) + upsert, one robot a batch",
        _TYPED,
        [_RECORD_ID, _TEAM, _BRIN, _RUN_NARROW],
        {"upsert", "one robot"},
    ),
)


def shared_buffers_used(connection: Any) -> int:
    """The database's shared buffer accesses so far (hits and reads), this session's flushed first: what the
    machine's load does not change, unlike CPU time (a btree insert's descent is a few of them per row)."""
    connection.execute("SELECT pg_stat_force_next_flush()")
    (used,) = connection.execute(
        "SELECT blks_hit + blks_read FROM pg_stat_database WHERE datname = current_database()"
    ).fetchone()
    return int(used)


def _latest_batch(batch: list[tuple[Any, ...]], small: bool) -> list[list[Any]]:
    """The batch's latest row of each (robot, name), as the arrays of the client's upsert."""
    latest: dict[tuple[str, str], tuple[Any, ...]] = {}
    for row in batch:
        key = (row[5], row[4])
        if key[0] is None or key[1] is None:
            continue
        found = latest.get(key)
        if found is None or found[1] <= row[1]:
            latest[key] = row
    rows = [latest[k] for k in sorted(latest)]
    arrays = [[r[5] for r in rows], [r[4] for r in rows], [r[1] for r in rows]]
    if not small:
        arrays.append([r[2] for r in rows])
    arrays.append([r[3] for r in rows])
    return arrays


def time_parts(server: PostgresServer, n: int, rounds: int, only: list[str]) -> dict[str, Any]:
    """Server CPU (the backend's, and the whole server's), WAL bytes, client CPU and wall time per row of
    each part in PARTS, ``rounds`` rounds in turns."""
    import psutil

    typed, original = copy_rows(insert_records(n))
    by_robot, original_by_robot = copy_rows(insert_records(n, one_robot=True))
    day = typed[0][1].date()
    pid = server_pid(server)
    names = [p[0] for p in PARTS if not only or any(word in p[0] for word in only)]
    figures: dict[str, dict[str, list[float]]] = {
        name: {"backend": [], "server": [], "wal": [], "buffers": [], "client": [], "wall": []} for name in names
    }
    with copy_connection(server) as connection:
        (backend_pid,) = connection.execute("SELECT pg_backend_pid()").fetchone()
        backend = psutil.Process(backend_pid)

        def backend_cpu() -> float:
            used = backend.cpu_times()
            return float(used.user + used.system)

        for k in range(rounds):
            for j, name in enumerate(names[k % len(names) :] + names[: k % len(names)]):
                _, columns, indexes, options = next(p for p in PARTS if p[0] == name)
                table, target = f"part_{k}_{j}", f"part_{k}_{j}"
                legacy = columns == _ORIGINAL
                if "partitioned" in options:
                    connection.execute(f"CREATE TABLE {table} ({columns}) PARTITION BY RANGE (time)")
                    connection.execute(
                        f"CREATE TABLE {table}_p PARTITION OF {table} FOR VALUES FROM ('{day} 00:00Z')"
                        f" TO ('{day + dt.timedelta(days=1)} 00:00Z') WITH (autovacuum_enabled = off)"
                    )
                    if "into partition" in options:
                        target = f"{table}_p"
                else:
                    connection.execute(f"CREATE TABLE {table} ({columns}) WITH (autovacuum_enabled = off)")
                for statement in indexes:
                    connection.execute(statement.format(t=table))
                if "trigger" in options:
                    connection.execute(block("latest-ddl").replace("dc", table).encode())
                if "upsert" in options:  # the page's latest-row table without its trigger
                    connection.execute(
                        block("latest-ddl").split("CREATE OR REPLACE FUNCTION")[0].replace("dc", table).encode()
                    )
                if "upsert small" in options:
                    connection.execute(_LATEST_SMALL.format(t=table))
                one_robot = "one robot" in options
                if legacy:
                    rows = original_by_robot if one_robot else original
                    types, written = ["varchar", "timestamp", "jsonb", "text"], "tag, time, data, record_id"
                elif "generated" in options:
                    rows = [r[:4] for r in (by_robot if one_robot else typed)]
                    types, written = ["text", "timestamptz", "jsonb", "text"], "tag, time, data, record_id"
                else:
                    rows, types, written = by_robot if one_robot else typed, TYPED_COPY_TYPES, _TYPED_COLUMNS
                upsert = _UPSERT_SMALL if "upsert small" in options else _UPSERT if "upsert" in options else ""
                (wal_before,) = connection.execute("SELECT pg_current_wal_insert_lsn()").fetchone()
                buffers_before = shared_buffers_used(connection)
                before, server_before = backend_cpu(), _tree_cpu(pid)
                client_before, started = time.process_time(), time.perf_counter()
                size = 5000 if "batch 5000" in options else 10 if "batch 10" in options else BATCH
                binary = "" if "text" in options else " (FORMAT BINARY)"
                for i in range(0, n, size):
                    batch = rows[i : i + size]
                    if "sorted" in options:
                        batch = sorted(batch, key=lambda r: (r[5] or "", r[4] or "", r[1]))
                    with (
                        connection.cursor() as cursor,
                        cursor.copy(f"COPY {target} ({written}) FROM STDIN{binary}") as copy,
                    ):
                        if binary:
                            copy.set_types(types)
                        for row in batch:
                            copy.write_row(row)
                    if upsert:
                        connection.execute(upsert.format(t=table), _latest_batch(batch, "upsert small" in options))
                wall = (time.perf_counter() - started) / n * 1e6
                client = (time.process_time() - client_before) / n * 1e6
                server_cpu, cpu = (_tree_cpu(pid) - server_before) / n * 1e6, (backend_cpu() - before) / n * 1e6
                (wal,) = connection.execute(
                    "SELECT pg_current_wal_insert_lsn() - %s::pg_lsn", (str(wal_before),)
                ).fetchone()
                buffers = (shared_buffers_used(connection) - buffers_before) / n
                measured = {
                    "backend": cpu,
                    "server": server_cpu,
                    "wal": float(wal) / n,
                    "buffers": buffers,
                    "client": client,
                    "wall": wall,
                }
                for key, value in measured.items():
                    figures[name][key].append(value)
                connection.execute(f"DROP TABLE {table}")
                connection.execute(f"DROP TABLE IF EXISTS {table}_latest")
                connection.execute(f"DROP FUNCTION IF EXISTS {table}_keep_latest")
            print(f"parts: round {k + 1} of {rounds} done, load {os.getloadavg()[0]:.1f}", flush=True)
    base = figures[names[0]]
    result: dict[str, Any] = {}
    for name in names:
        f = figures[name]
        result[name] = {
            "backend_cpu_us_per_row": statistics.median(f["backend"]),
            "backend_cpu_ratio_to_original": statistics.median(
                [a / b for a, b in zip(f["backend"], base["backend"], strict=True)]
            ),
            "server_cpu_us_per_row": statistics.median(f["server"]),
            "wal_bytes_per_row": statistics.median(f["wal"]),
            "shared_buffer_accesses_per_row": statistics.median(f["buffers"]),
            "client_cpu_us_per_row": statistics.median(f["client"]),
            "wall_us_per_row": statistics.median(f["wall"]),
            "runs": {key: [round(x, 2) for x in values] for key, values in f.items()},
        }
        r = result[name]
        print(f"backend {r['backend_cpu_us_per_row']:5.1f} µs/row x{r['backend_cpu_ratio_to_original']:.2f}"
              f"  server {r['server_cpu_us_per_row']:5.1f}  WAL {r['wal_bytes_per_row']:5.0f} B/row"
              f"  buffers {r['shared_buffer_accesses_per_row']:4.1f}/row"
              f"  client {r['client_cpu_us_per_row']:4.1f}  wall {r['wall_us_per_row']:5.1f}  {name}",
              flush=True)  # fmt: skip
    return result


def client_parts(n: int, rounds: int) -> dict[str, float]:
    """The client's CPU per row of the PgSQL destination's own work before the COPY, without a server: the
    JSON text of each record, then the row of each shape (a typed one reads three keys of the JSON)."""
    from dc_destinations.pgsql.table import LEGACY_COLUMNS, TYPED_COLUMNS, TableShape

    params = parse_params(PgSQLParams, {"table": "dc", "value_keys": {"cpu": "average"}}, "destination_server.pg")
    dest = PgSQL(FakeContext(name="pg", logger=RecordingLogger()), params)
    legacy_types = ["character varying", "timestamp without time zone", "jsonb", "text"]
    typed_types = ["text", "timestamp with time zone", "jsonb", "text", "text", "text", "bigint", "double precision"]
    shapes = {
        "original's shape": TableShape(False, dict(zip(LEGACY_COLUMNS, legacy_types, strict=True)), frozenset()),
        "typed": TableShape(
            False, dict(zip((*TYPED_COLUMNS, "value"), typed_types, strict=True)), frozenset({"{record_id}"})
        ),
    }
    times: dict[str, list[float]] = {"JSON text": [], **{f"row, {s}": [] for s in shapes}}
    for _ in range(rounds):
        records = insert_records(n)
        started = time.process_time()
        pending = [(i, r, r.to_json()) for i, r in enumerate(records)]
        times["JSON text"].append((time.process_time() - started) / n * 1e6)
        for name, shape in shapes.items():
            dest._shape = shape
            started = time.process_time()
            dest._rows(pending)
            times[f"row, {name}"].append((time.process_time() - started) / n * 1e6)
    result = {name: statistics.median(runs) for name, runs in times.items()}
    for name, value in result.items():
        print(f"client CPU {value:5.2f} µs/row  {name}", flush=True)
    return result


def load() -> list[float]:
    """The 1, 5 and 15-minute load averages (the machine is shared: every figure is read with them)."""
    return [round(x, 2) for x in os.getloadavg()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=100, help="0: the insert rate only")
    parser.add_argument("--hours", type=int, default=24)
    parser.add_argument("--partition-by", default="day", help="of the queries' table: day, week or none")
    parser.add_argument("--runs", type=int, default=15, help="warm runs of each query")
    parser.add_argument("--cold-runs", type=int, default=3, help="runs of each query right after a server restart")
    parser.add_argument("--insert-records", type=int, default=50_000)
    parser.add_argument("--insert-runs", type=int, default=7)
    parser.add_argument("--index-runs", type=int, default=0, help="rounds of the server's CPU per row per index set")
    parser.add_argument("--ways-runs", type=int, default=0, help="rounds of the insert's ways (COPY, ON CONFLICT, …)")
    parser.add_argument("--parts-runs", type=int, default=0, help="rounds of the insert's cost part by part")
    parser.add_argument("--parts", action="append", default=[], help="only the parts whose name holds this text")
    parser.add_argument("--label", default="")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="dc-bench-model-"))
    server = PostgresServer(folder, password="bench-model-1")
    result: dict[str, Any] = {"date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "robots": args.robots}
    try:
        server.start()
        if args.insert_runs:
            result["load_before_insert"] = load()
            result["insert"] = time_inserts(server, args.insert_records, args.insert_runs)
            result["load_after_insert"] = load()
        if args.index_runs:
            result["load_before_index_costs"] = load()
            result["index_costs"] = time_index_costs(server, args.insert_records, args.index_runs)
            result["load_after_index_costs"] = load()
        if args.ways_runs:
            result["load_before_ways"] = load()
            result["insert_ways"] = time_insert_ways(server, args.insert_records, args.ways_runs)
            result["load_after_ways"] = load()
        if args.parts_runs:
            result["load_before_parts"] = load()
            result["insert_parts"] = time_parts(server, args.insert_records, args.parts_runs, args.parts)
            result["client_parts"] = client_parts(args.insert_records, args.parts_runs)
            result["load_after_parts"] = load()
        if args.robots:
            rows, seconds = generate(server, args.robots, args.hours, args.partition_by)
            result.update(
                hours=args.hours,
                partition_by=args.partition_by,
                rows=rows,
                generate_s=seconds,
                load_before_queries=load(),
            )
            result["queries"] = time_queries(server, args.runs)
            result["load_after_warm_queries"] = load()
            if args.cold_runs:
                result["queries_cold"] = time_cold(server, args.cold_runs)
                result["load_after_cold_queries"] = load()
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)
    print(f"load averages (1, 5, 15 min): {[(k, v) for k, v in result.items() if k.startswith('load')]}")
    out = result_path(REPO / "benchmarks" / "results", dt.date.today(), args.label)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {out}")


def result_path(folder: Path, day: dt.date, label: str) -> Path:
    """pgsql_data_model_<date>[_<label>].json, or with _2, _3, … when taken: a run never overwrites a
    result (committed ones are what docs/performance.md cites)."""
    stem = f"pgsql_data_model_{day}" + (f"_{label}" if label else "")
    out, n = folder / f"{stem}.json", 1
    while out.exists():
        n += 1
        out = folder / f"{stem}_{n}.json"
    return out


if __name__ == "__main__":
    main()
