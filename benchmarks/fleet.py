"""The fleet path's rates on this machine: a robot's NATS destination into JetStream, then `dc ingest`
workers into PostgreSQL, against PostgreSQL's own COPY of the same rows.

    .venv/bin/python benchmarks/fleet.py [--records 20000] [--workers 1 2 4] [--cluster]

A throw-away nats-server (or, with --cluster, a 3-node cluster and a stream with 3 replicas) and a
PostgreSQL on loopback. The records (~250 bytes of JSON) are published by the NATS destination in
batches of 500, as a robot's sender would, each acknowledged by the stream. Then, for each worker
count, that many `dc ingest` processes share a new durable consumer and write the whole stream into
a table of their own; the time from their start to the last row is the ingest rate. Last, the same
rows are loaded with COPY into a table with the same unique record_id index. Everything runs on
this one machine: the workers, the server and PostgreSQL share its cores.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from dc_bringup.local_servers.nats import NatsCluster, NatsNode  # noqa: E402
from dc_bringup.local_servers.postgres import PostgresServer  # noqa: E402
from dc_core.destination import OutgoingRecord, RetryableError  # noqa: E402
from dc_core.params import parse_params  # noqa: E402
from dc_core.testing import FakeContext  # noqa: E402
from dc_destinations.jetstream import Nats, NatsParams  # noqa: E402
from dc_destinations.record_ids import new_record_id  # noqa: E402


def records(count: int) -> list[OutgoingRecord]:
    made = []
    for n in range(count):
        rid = new_record_id()
        data = {
            "date": 1_700_000_000 + n / 100,
            "name": "system",
            "robot_name": f"robot-{n % 100:03d}",
            "run_id": "3",
            "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
            "memory": {"used": 123456789, "percent": 45.6},
            "record_id": rid,
        }
        made.append(OutgoingRecord(rid, "/dc/measurement/system", 1_700_000_000_000_000_000 + n, data))
    return made


def connect(pg: PostgresServer) -> Any:
    import psycopg

    s = pg.settings()
    return psycopg.connect(
        host=str(s["host"]), port=int(s["port"]), user=str(s["user"]), password=str(s["password"]), dbname="dc"
    )


def count(pg: PostgresServer, table: str) -> int:
    with connect(pg) as connection:
        try:
            row = connection.execute(f"SELECT count(*) FROM {table}").fetchone()
        except Exception:
            return 0
    return int(row[0]) if row else 0


def ingest(pg: PostgresServer, servers: list[str], workers: int, total: int, folder: Path) -> float:
    """Seconds for ``workers`` dc ingest processes to write the whole stream into a table of their own."""
    table = f"fleet_w{workers}"
    params = folder / f"{table}.yaml"
    s = pg.settings()
    params.write_text(
        "destination_server:\n  ros__parameters:\n    destination_plugins: [warehouse]\n"
        "    flb: {flush: 0.05, http_server: false}\n"
        "    warehouse:\n      plugin: dc_destinations/PgSQL\n      inputs: [/dc/measurement/system]\n"
        f"      host: 127.0.0.1\n      port: {s['port']}\n      user: {s['user']}\n      database: dc\n"
        f"      table: {table}\n      batch_size: 1000\n"
    )
    env = {**os.environ, "PGPASSWORD": str(s["password"]), "PYTHONPATH": str(REPO)}
    started = time.monotonic()
    processes = [
        subprocess.Popen(
            [
                *(sys.executable, "-m", "dc_bringup.cli", "ingest", str(params), "--servers", ",".join(servers)),
                *("--consumer", table, "--batch", "1000", "--storage-path", str(folder / f"{table}-{i}")),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=(folder / f"{table}-{i}.log").open("wb"),
        )
        for i in range(workers)
    ]
    try:
        while count(pg, table) < total:
            if any(p.poll() is not None for p in processes):
                raise RuntimeError(f"a worker exited: see {folder}")
            time.sleep(0.1)
        return time.monotonic() - started
    finally:
        for p in processes:
            p.send_signal(signal.SIGTERM)
        for p in processes:
            p.wait(30)


def copy_rate(pg: PostgresServer, batch: list[OutgoingRecord]) -> float:
    """Seconds for COPY to load the rows into a table like the destination's (record_id unique)."""
    with connect(pg) as connection:
        connection.execute("CREATE TABLE fleet_copy (tag text, time timestamptz, data jsonb, record_id text UNIQUE)")
        connection.commit()
        started = time.monotonic()
        for start in range(0, len(batch), 1000):
            with (
                connection.cursor() as cursor,
                cursor.copy("COPY fleet_copy (tag, time, data, record_id) FROM STDIN") as copy,
            ):
                for r in batch[start : start + 1000]:
                    copy.write_row(("warehouse", "2023-11-14T22:13:20Z", r.to_json(), r.record_id))
            connection.commit()
        return time.monotonic() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=20000)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cluster", action="store_true", help="a 3-node cluster and a stream with 3 replicas")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="dc-fleet-bench-"))
    # Its own temporary folder: as root, PostgreSQL runs as user postgres, who cannot enter `folder`.
    pg_folder = Path(tempfile.mkdtemp(prefix="dc-fleet-bench-pg-"))
    pg = PostgresServer(pg_folder, password="bench-only")
    nats: NatsCluster | NatsNode = NatsCluster(folder / "nats") if args.cluster else NatsNode(folder / "nats")
    servers = nats.urls if isinstance(nats, NatsCluster) else [nats.url]
    batch = records(args.records)
    size = sum(len(r.to_json()) for r in batch) / len(batch)
    try:
        pg.start()
        nats.start()
        settings = {
            "servers": servers,
            "stream": "DC",
            "create_stream": True,
            "stream_replicas": 3 if args.cluster else 1,
            "subject": "dc.{robot_name}.{name}",
        }
        robot = Nats(FakeContext(name="fleet"), parse_params(NatsParams, settings, "destination_server.fleet"))
        robot.on_configure()
        deadline = time.monotonic() + 60
        while True:  # a cluster just started elects its JetStream leader first: retried, as DC's sender would
            try:
                assert robot.send(batch[:1]) is None
                break
            except RetryableError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        started = time.monotonic()
        for start in range(0, len(batch), 500):
            assert robot.send(batch[start : start + 500]) is None
        publish = time.monotonic() - started
        robot.on_cleanup()
        replicas = "3 replicas, 3 nodes" if args.cluster else "1 node"
        print(f"{args.records} records of {size:.0f} bytes of JSON; JetStream file store, {replicas}")
        print(f"robot → stream (NATS destination, batches of 500, each acked): {args.records / publish:,.0f} records/s")
        copy = copy_rate(pg, batch)
        print(f"PostgreSQL COPY of the same rows, 1000 per commit: {args.records / copy:,.0f} rows/s")
        for workers in args.workers:
            seconds = ingest(pg, servers, workers, args.records, folder)
            rate = args.records / seconds
            print(
                f"stream → PostgreSQL, {workers} dc ingest worker(s): {rate:,.0f} records/s "
                f"({rate / (args.records / copy):.2f} of COPY; includes the workers' start, ~1 s)"
            )
    finally:
        nats.stop()
        pg.stop()
        shutil.rmtree(folder, ignore_errors=True)
        shutil.rmtree(pg_folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
