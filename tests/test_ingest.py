"""`dc ingest`: robots' records in a JetStream stream, delivered to PostgreSQL by two ingest workers
sharing one durable consumer, one of them killed with -9 half way: every record in the table once.

Real parts: nats-server (tests/nats_server.py), PostgreSQL (dc_bringup.local_servers), the workers
as `dc ingest` subprocesses, the records published by the NATS destination as a robot would.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.postgres import PostgresServer
from dc_bringup.local_servers.postgres import missing_reason as postgres_missing
from tests.nats_server import missing_reason as nats_missing

if nats_missing() or postgres_missing():
    pytest.skip(str(nats_missing() or postgres_missing()), allow_module_level=True)

import psycopg

from dc_core.destination import OutgoingRecord
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_destinations.jetstream import Nats, NatsParams
from dc_destinations.record_ids import new_record_id
from tests.destination_helpers import running_postgres
from tests.nats_server import NatsServer

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def postgres() -> Iterator[PostgresServer]:
    with running_postgres("dc-ingest-") as pg:
        yield pg


def robot(url: str) -> Nats:
    params = {"servers": [url], "stream": "DC", "create_stream": True, "stream_subjects": ["dc.>"]}
    plugin = Nats(FakeContext(name="fleet"), parse_params(NatsParams, params, "destination_server.fleet"))
    plugin.on_configure()
    return plugin


def record(n: int) -> OutgoingRecord:
    rid = new_record_id()
    data = {"date": 1_700_000_000 + n / 10, "name": "uptime", "robot_name": f"r{n % 3}", "time": n, "record_id": rid}
    return OutgoingRecord(rid, "/dc/measurement/uptime", 1_700_000_000_000_000_000 + n, data)


def worker(params: Path, url: str, storage: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    command = [sys.executable, "-m", "dc_bringup.cli", "ingest", str(params), "--servers", url]
    command += ["--consumer", "warehouse", "--ack-wait", "2", "--batch", "100", "--max-in-flight", "300"]
    command += ["--storage-path", str(storage)]
    log = (storage.parent / f"{storage.name}.log").open("wb")
    return subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)


def connection_settings(pg: PostgresServer) -> dict[str, Any]:
    s = pg.settings()
    return {"host": s["host"], "port": s["port"], "user": s["user"], "password": s["password"], "dbname": "dc"}


def warehouse(pg: PostgresServer) -> Any:
    from dc_destinations.pgsql import PgSQL, PgSQLParams

    plugin = PgSQL(FakeContext(name="warehouse"), parse_params(PgSQLParams, pg.settings(), "destination_server.w"))
    plugin.on_configure()
    return plugin


def ack_pending(url: str) -> int:
    async def pending() -> int:
        import nats

        nc = await nats.connect(servers=[url])
        try:
            info = await nc.jetstream().consumer_info("DC", "warehouse")
            return int(info.num_ack_pending or 0)
        except Exception:
            return 0
        finally:
            await nc.close()

    return asyncio.run(pending())


def rows(pg: PostgresServer) -> list[Any]:
    with psycopg.connect(**connection_settings(pg)) as connection:
        return connection.execute("SELECT record_id FROM dc").fetchall()


def test_two_workers_share_a_consumer_and_one_killed_loses_nothing(postgres: PostgresServer, tmp_path: Path) -> None:
    params = tmp_path / "ingest.yaml"
    s = postgres.settings()
    params.write_text(
        "destination_server:\n  ros__parameters:\n    destination_plugins: [warehouse]\n"
        "    flb: {flush: 0.05, scheduler_base: 0.05, scheduler_cap: 0.5, grace: 2}\n"
        "    warehouse:\n      plugin: dc_destinations/PgSQL\n      inputs: [/dc/measurement/uptime]\n"
        f"      host: 127.0.0.1\n      port: {s['port']}\n      user: {s['user']}\n      database: {s['database']}\n"
        "      batch_size: 100\n"
    )
    os.environ["PGPASSWORD"] = str(s["password"])  # inherited by the workers: never in a file or command line
    with NatsServer(tmp_path / "nats") as nats_server:
        publisher = robot(nats_server.url)
        sent = [record(n) for n in range(1500)]
        assert publisher.send(sent[:1000]) is None
        # The table held locked: the workers take messages and cannot confirm them yet.
        table = warehouse(postgres)
        assert table.send(sent[:1]) is None
        table.on_cleanup()
        lock = psycopg.connect(**connection_settings(postgres))
        lock.execute("LOCK TABLE dc IN ACCESS EXCLUSIVE MODE")
        first = worker(params, nats_server.url, tmp_path / "w1")
        second = worker(params, nats_server.url, tmp_path / "w2")
        try:
            deadline = time.monotonic() + 30
            while ack_pending(nats_server.url) < 600 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert ack_pending(nats_server.url) == 600, "each worker holds 300 messages it has not acknowledged"
            first.send_signal(signal.SIGKILL)
            first.wait(10)
            lock.rollback()
            lock.close()
            assert publisher.send(sent[1000:]) is None
            wanted = {r.record_id for r in sent}
            deadline = time.monotonic() + 40
            while {r[0] for r in rows(postgres)} != wanted and time.monotonic() < deadline:
                time.sleep(0.1)
            stored = [r[0] for r in rows(postgres)]
        finally:
            publisher.on_cleanup()
            for w in (first, second):
                if w.poll() is None:
                    w.send_signal(signal.SIGTERM)
            second.wait(20)
            first.wait(10)
            os.environ.pop("PGPASSWORD", None)
        assert set(stored) == wanted, f"{len(wanted - set(stored))} records missing"
        assert len(stored) == len(wanted), "the unique record_id index kept each once"
        assert second.returncode == 0
        log = (tmp_path / "w2.log").read_text()
        assert "ingest stopped after" in log and "dead_lettered 0" in log, log[-2000:]
