"""`dc ingest`: robots' records in a JetStream stream, delivered to PostgreSQL by two ingest workers
sharing one durable consumer, one of them killed with -9 half way: every record in the table once.

Real parts: nats-server (tests/nats_server.py), PostgreSQL (dc_bringup.local_servers), the workers
as `dc ingest` subprocesses, the records published by the NATS destination as a robot would.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
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


def worker(
    params: Path, url: str, storage: Path, env: dict[str, str] | None = None, options: tuple[str, ...] = ()
) -> subprocess.Popen[bytes]:
    env = {**os.environ, **(env or {})}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    command = [sys.executable, "-m", "dc_bringup.cli", "ingest", str(params), "--servers", url]
    command += ["--consumer", "warehouse", "--ack-wait", "2", "--batch", "100", "--max-in-flight", "300"]
    command += ["--storage-path", str(storage), *options]  # argparse: a repeated option's last value wins
    log = (storage.parent / f"{storage.name}.log").open("ab")
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
            deadline = time.monotonic() + 60
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


# -- routing and bounded redelivery, in-process workers ---------------------------------------------


def ingest_params(postgres: PostgresServer, tmp_path: Path, retry_limit: int = -1) -> dict[str, Any]:
    s = postgres.settings()
    warehouse = {"plugin": "dc_destinations/PgSQL", "inputs": ["/dc/measurement/uptime"], **s, "table": "routed"}
    warehouse["retry_limit"] = retry_limit
    lake = {
        "plugin": "dc_destinations/File",
        "inputs": ["/dc/measurement/uptime", "/dc/measurement/cpu"],
        "path": str(tmp_path),
        "file": "lake.jsonl",
    }
    return {
        "destination_plugins": ["warehouse", "lake"],
        "flb": {"flush": 0.05, "scheduler_base": 0.05, "scheduler_cap": 0.5, "grace": 2, "http_server": False},
        "warehouse": warehouse,
        "lake": lake,
    }


class Worker:
    """An ingest worker in this process, on its own event loop thread, stopped as SIGTERM stops dc ingest."""

    def __init__(self, section: dict[str, Any], url: str, consumer: str, storage: Path, **options: Any) -> None:
        import logging

        from dc_core.logs import SeverityLogger
        from dc_destinations.config import parse_destination_server
        from dc_destinations.ingest import Ingest, IngestOptions, configure_destinations

        config = parse_destination_server(section)
        self.destinations = configure_destinations(config, "test.ingest")
        options = {"batch": 50, "ack_wait": 30, **options}
        settings = IngestOptions(servers=[url], stream="DC", consumer=consumer, **options)
        logger = SeverityLogger(logging.getLogger("test.ingest"))
        self.ingest = Ingest(config, self.destinations, settings, storage, logger)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(self.ingest.run(),))
        self._thread.start()

    def stop(self) -> None:
        self._loop.call_soon_threadsafe(self.ingest.stop_requested.set)
        self._thread.join(30)
        assert not self._thread.is_alive()
        self._loop.close()
        for destination in self.destinations.values():
            destination.on_cleanup()


def consumer_state(url: str, consumer: str) -> tuple[int, int]:
    """(messages not yet delivered, messages delivered and not acknowledged) of the consumer."""

    async def state() -> tuple[int, int]:
        import nats
        import nats.js.errors

        nc = await nats.connect(servers=[url])
        try:
            info = await nc.jetstream().consumer_info("DC", consumer)
            return int(info.num_pending or 0), int(info.num_ack_pending or 0)
        except nats.js.errors.NotFoundError:
            return -1, -1  # the worker has not made it yet
        finally:
            await nc.close()

    return asyncio.run(state())


def wait_for(condition: Any, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.1)


def robot_record(n: int, measurement: str) -> OutgoingRecord:
    rid = new_record_id()
    stamp_ns = 1_700_000_000_000_000_000 + n * 100_000_000
    data = {"date": stamp_ns / 1e9, "name": measurement, "robot_name": "r1", "value": n, "record_id": rid}
    return OutgoingRecord(rid, f"/dc/measurement/{measurement}", stamp_ns, data)


def table_ids(pg: PostgresServer, table: str) -> list[str]:
    with psycopg.connect(**connection_settings(pg)) as connection:
        return [r[0] for r in connection.execute(f"SELECT record_id FROM {table}").fetchall()]


def test_ingest_routes_by_the_destinations_inputs_and_the_records_tags(
    postgres: PostgresServer, tmp_path: Path
) -> None:
    import nats

    uptime = [robot_record(n, "uptime") for n in range(30)]
    cpu = [robot_record(n, "cpu") for n in range(20)]
    memory = [robot_record(n, "memory") for n in range(10)]  # no destination of the ingest takes them
    with NatsServer(tmp_path / "nats") as nats_server:
        publisher = robot(nats_server.url)
        try:
            assert publisher.send(uptime + cpu + memory) is None
        finally:
            publisher.on_cleanup()

        # Not published by DC: the record still has its tags, which name the lake alone.
        tagged = [robot_record(100 + n, "uptime") for n in range(5)]

        async def publish_tagged() -> None:
            nc = await nats.connect(servers=[nats_server.url])
            for r in tagged:
                body = json.dumps({**r.data, "tags": ["lake"]}).encode()
                headers = {"Nats-Msg-Id": r.record_id, "Dc-Topic": r.topic, "Dc-Stamp": str(r.stamp_ns)}
                await nc.jetstream().publish("dc.r1.uptime", body, headers=headers, stream="DC")
            await nc.close()

        asyncio.run(publish_tagged())
        sent = len(uptime) + len(cpu) + len(memory) + len(tagged)
        section = ingest_params(postgres, tmp_path)
        worker = Worker(section, nats_server.url, "routing", tmp_path / "buffer")
        try:
            wait_for(lambda: consumer_state(nats_server.url, "routing") == (0, 0), "every message acknowledged")
        finally:
            worker.stop()
        lake = [json.loads(line) for line in (tmp_path / "lake.jsonl").read_text().splitlines()]
    counters = worker.ingest.counters
    assert sorted(table_ids(postgres, "routed")) == sorted(r.record_id for r in uptime)
    assert sorted(r["record_id"] for r in lake) == sorted(r.record_id for r in uptime + cpu + tagged)
    assert all("tags" not in r for r in lake)
    # The time key is the robot's stamp (Dc-Stamp), not the message's time in the stream.
    stamps = {r.record_id: r.stamp_ns / 1e9 for r in uptime + cpu + tagged}
    assert all(r["date"] == pytest.approx(stamps[r["record_id"]]) for r in lake)
    assert counters.unrouted == {"its tags name no destination listening on this topic": len(memory)}
    delivered = {r["record_id"] for r in lake} | set(table_ids(postgres, "routed"))
    assert len(delivered) + sum(counters.unrouted.values()) == sent
    assert counters.acknowledged == sent
    assert worker.ingest.pipeline.status_document()["ingest"]["unrouted"] == dict(counters.unrouted)


def test_a_message_redelivered_beyond_retry_limit_is_dead_lettered_and_acknowledged(
    postgres: PostgresServer, tmp_path: Path
) -> None:
    from nats.js.api import AckPolicy, ConsumerConfig

    from dc_destinations.buffer import SqliteBuffer

    poison = [robot_record(n, "cpu") for n in range(40)]
    good = [robot_record(100 + n, "cpu") for n in range(60)]
    with NatsServer(tmp_path / "nats") as nats_server:
        publisher = robot(nats_server.url)
        try:
            assert publisher.send(poison) is None

            # Workers that took the first 40 messages and died (here: gave them back) twice.
            async def deliver_twice() -> None:
                import nats

                nc = await nats.connect(servers=[nats_server.url])
                config = ConsumerConfig(durable_name="limits", ack_policy=AckPolicy.EXPLICIT, ack_wait=30)
                sub = await nc.jetstream().pull_subscribe("dc.>", durable="limits", stream="DC", config=config)
                deliveries: dict[int, int] = {}
                while len(deliveries) < len(poison) or min(deliveries.values()) < 2:
                    for msg in await sub.fetch(len(poison), timeout=10):
                        deliveries[msg.metadata.sequence.stream] = msg.metadata.num_delivered
                        await msg.nak()
                await nc.close()

            asyncio.run(deliver_twice())
            assert publisher.send(good) is None
        finally:
            publisher.on_cleanup()
        section = ingest_params(postgres, tmp_path, retry_limit=1)
        section["warehouse"]["inputs"] = ["/dc/measurement/cpu"]
        section["lake"]["retry_limit"] = 5  # twice redelivered is within its limit: the lake takes them all
        worker = Worker(section, nats_server.url, "limits", tmp_path / "buffer")
        try:
            wait_for(lambda: consumer_state(nats_server.url, "limits") == (0, 0), "every message acknowledged")
            metrics = worker.ingest.pipeline.metrics()
        finally:
            worker.stop()
        storage_file = worker.ingest.pipeline.storage_file
        assert storage_file is not None
    stored = table_ids(postgres, "routed")
    assert not set(stored) & {r.record_id for r in poison}
    assert {r.record_id for r in good} <= set(stored)
    assert metrics["warehouse"]["dead_lettered"] == len(poison)
    assert worker.ingest.counters.over_retry_limit == len(poison)
    # delivered + dead-lettered = sent, for each destination
    sent = len(poison) + len(good)
    assert metrics["warehouse"]["sent"] + metrics["warehouse"]["dead_lettered"] == sent
    assert metrics["lake"]["sent"] == sent and metrics["lake"]["dead_lettered"] == 0
    with contextlib.closing(SqliteBuffer(storage_file)) as buffer:
        dead = buffer.list_dead_letters("warehouse")
    assert {d.record_id for d in dead} == {r.record_id for r in poison}
    assert all("beyond retry_limit 1" in d.error for d in dead)


# -- a worker killed between a refusal and its dead letter ------------------------------------------


def buffer_of(storage: Path) -> Any:
    from dc_destinations.buffer import FILE_NAME, SqliteBuffer

    return contextlib.closing(SqliteBuffer(storage / FILE_NAME, repair=False))


def test_a_worker_killed_before_a_dead_letter_is_committed_leaves_the_record_to_the_stream(
    postgres: PostgresServer, tmp_path: Path
) -> None:
    """A record PostgreSQL refuses for good is acknowledged only once its dead letter is on the worker's
    disk. The worker is killed with -9 while that dead letter is being written: a replacement worker
    (the first one's disk gone with it) dead-letters it, and the first one started again on its own
    disk does not do it a second time. Delivered + dead-lettered = sent, each record once."""
    from tests.fault_helpers import fault_env, fault_gate

    params = tmp_path / "ingest.yaml"
    s = postgres.settings()
    params.write_text(
        "destination_server:\n  ros__parameters:\n    destination_plugins: [warehouse]\n"
        "    flb: {flush: 0.05, scheduler_base: 0.05, scheduler_cap: 0.5, grace: 2, http_server: false}\n"
        "    warehouse:\n      plugin: dc_destinations/PgSQL\n      inputs: [/dc/measurement/uptime]\n"
        f"      host: 127.0.0.1\n      port: {s['port']}\n      user: {s['user']}\n      database: {s['database']}\n"
        "      table: refusals\n      batch_size: 100\n"
    )
    good = [robot_record(n, "uptime") for n in range(60)]
    # PostgreSQL refuses a NUL in a string for good (SQLSTATE 22P05): dead letters. Published last,
    # so that every good record is confirmed before the first one is refused.
    refused = [robot_record(100 + n, "uptime") for n in range(5)]
    for r in refused:
        r.data["note"] = "nul \u0000 inside"
    sent = good + refused
    os.environ["PGPASSWORD"] = str(s["password"])  # inherited by the workers: never in a file or command line
    first = replacement = None
    try:
        with NatsServer(tmp_path / "nats") as nats_server, fault_gate(tmp_path) as gate:
            publisher = robot(nats_server.url)
            try:
                assert publisher.send(sent) is None
            finally:
                publisher.on_cleanup()
            # The gate is never opened: the dead letters' commit blocks until the kill.
            hang = fault_env(tmp_path, "dc_destinations.buffer:SqliteBuffer.dead_letter", gate=gate.path)
            first = worker(params, nats_server.url, tmp_path / "w1", env=hang)
            wait_for(lambda: (tmp_path / "fault-raised").exists(), "the refused records reach their dead letters")
            wait_for(
                lambda: consumer_state(nats_server.url, "warehouse") in {(0, len(refused)), (0, 0)},
                "the good records acknowledged",
            )
            first.send_signal(signal.SIGKILL)
            first.wait(10)
            assert consumer_state(nats_server.url, "warehouse") == (0, len(refused)), (
                "the refused records' messages must not be acknowledged before their dead letters are written"
            )

            replacement = worker(params, nats_server.url, tmp_path / "w2")
            wait_for(lambda: "ingesting" in (tmp_path / "w2.log").read_text(), "the replacement worker started")
            wait_for(lambda: consumer_state(nats_server.url, "warehouse") == (0, 0), "every message acknowledged")
            replacement.send_signal(signal.SIGTERM)
            assert replacement.wait(20) == 0

            # The first worker's machine comes back: what its queue held is its messages' business now.
            first = worker(params, nats_server.url, tmp_path / "w1")

            def first_queue_empty() -> bool:
                with buffer_of(tmp_path / "w1") as buffer:
                    return int(buffer.stats("warehouse").rows) == 0

            wait_for(first_queue_empty, "the first worker's queue emptied")
            first.send_signal(signal.SIGTERM)
            assert first.wait(20) == 0
    finally:
        os.environ.pop("PGPASSWORD", None)
        for w in (first, replacement):
            if w is not None and w.poll() is None:
                w.kill()
                w.wait(10)
    stored = table_ids(postgres, "refusals")
    dead = []
    for storage in ("w1", "w2"):
        with buffer_of(tmp_path / storage) as buffer:
            dead += [d.record_id for d in buffer.list_dead_letters("warehouse")]
    assert sorted(stored) == sorted(r.record_id for r in good)
    assert sorted(dead) == sorted(r.record_id for r in refused), "each refused record dead-lettered once"
    assert len(stored) + len(dead) == len(sent)
    # The refused records, and good ones whose rows were not yet deleted when it was killed.
    left = re.findall(r"left by the last run (\d+)", (tmp_path / "w1.log").read_text())
    assert left and int(left[-1]) >= len(refused)


# -- records the worker's buffer drops go back to the stream ----------------------------------------


def test_records_the_buffer_drops_are_handed_back_and_stored_once_the_store_is_back(
    postgres: PostgresServer, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A worker whose PgSQL destination is stuck (its table locked) and whose queue for it holds ~60
    records drops the others (storage_total_limit_size, when_full drop_oldest): their messages are
    handed back to the stream, never acknowledged, and their in-flight slots freed. Once the table is
    released, every record is in PostgreSQL, the File destination (never stuck) has each exactly
    once, every message is acknowledged and nothing is left in flight."""
    import logging

    section = ingest_params(postgres, tmp_path)
    section["warehouse"].update(table="handback", batch_size=20, storage_total_limit_size="16k")
    sent = [robot_record(n, "uptime") for n in range(300)]
    with NatsServer(tmp_path / "nats") as nats_server:
        publisher = robot(nats_server.url)
        table = warehouse_table(postgres, "handback")  # made before it is locked
        lock = psycopg.connect(**connection_settings(postgres))
        worker = None
        try:
            assert publisher.send(sent[:1]) is None  # makes the stream
            worker = Worker(section, nats_server.url, "handback", tmp_path / "buffer", handback_delay=0.3)
            wait_for(lambda: consumer_state(nats_server.url, "handback") == (0, 0), "the first record acknowledged")
            lock.execute("LOCK TABLE handback IN ACCESS EXCLUSIVE MODE")
            with caplog.at_level(logging.WARNING, logger="test.ingest"):
                assert publisher.send(sent[1:]) is None
                ingest = worker.ingest
                # Every record reached the lake; the warehouse's queue is full, and what it dropped went back.
                wait_for(
                    lambda: (
                        ingest.pipeline.metrics()["lake"]["sent"] == len(sent)
                        and sum(ingest.counters.handed_back.values()) >= len(sent) - 100
                    ),
                    "the lake has every record and the warehouse's drops are handed back",
                )
                # Handed back: no longer in flight. Messages handed back come again after the delay and are
                # taken (and handed back) again, so the count moves: waited for, not read once (a fresh
                # clone read 200 in flight at one moment).
                wait_for(lambda: len(ingest.settlements) < len(sent) - 100, "handed back: no longer in flight")
                lock.rollback()
                wait_for(
                    lambda: consumer_state(nats_server.url, "handback") == (0, 0) and len(ingest.settlements) == 0,
                    "every message acknowledged, none in flight",
                )
            metrics = ingest.pipeline.metrics()
        finally:
            lock.close()
            table.on_cleanup()
            publisher.on_cleanup()
            if worker is not None:
                worker.stop()
    counters = worker.ingest.counters
    stored = table_ids(postgres, "handback")
    assert sorted(stored) == sorted(r.record_id for r in sent)
    lake = [json.loads(line)["record_id"] for line in (tmp_path / "lake.jsonl").read_text().splitlines()]
    assert sorted(lake) == sorted(r.record_id for r in sent), "each record once in the lake: not sent to it again"
    assert set(counters.handed_back) == {"size_limit"} and not counters.terminated
    # Each hand-back brought the record to the warehouse once more (a record may go back more than
    # once): what it was given = the records + the hand-backs. Every hand-back was a drop; a drop may
    # be no hand-back (a row confirmed, its message acknowledged, dropped before its delete).
    handed_back = sum(counters.handed_back.values())
    assert metrics["warehouse"]["received"] == len(sent) + handed_back
    assert 0 < handed_back <= metrics["warehouse"]["dropped"]
    assert metrics["lake"]["received"] == metrics["lake"]["sent"] == len(sent)
    assert counters.acknowledged == len(sent) and counters.over_retry_limit == 0
    assert "messages handed back to the stream" in caplog.text and "size_limit" in caplog.text


def warehouse_table(pg: PostgresServer, name: str) -> Any:
    """A PgSQL destination on table ``name``, the table made by a first record (not one of the test's)."""
    from dc_destinations.pgsql import PgSQL, PgSQLParams

    params = parse_params(PgSQLParams, {**pg.settings(), "table": name}, "destination_server.w")
    plugin = PgSQL(FakeContext(name=name), params)
    plugin.on_configure()
    first = robot_record(-1, "uptime")
    assert plugin.send([first]) is None
    with psycopg.connect(**connection_settings(pg)) as connection:
        connection.execute(f"DELETE FROM {name}")
    return plugin


def test_hand_backs_by_any_worker_are_no_redeliveries_and_a_killed_worker_s_are(
    postgres: PostgresServer, tmp_path: Path
) -> None:
    """retry_limit 0, two workers on one consumer. The first one's store hangs (its first PgSQL send
    never returns) and its queue holds ~140 records: it hands the others back, again and again. The
    second one takes them and stores them: none is dead-lettered as redelivered, although each was
    delivered before, to the other worker. The first one is then killed with -9: the messages it
    held come back to the second one counted, and are dead-lettered. Stored + dead-lettered = sent,
    each once."""
    from dc_destinations.buffer import SqliteBuffer
    from tests.fault_helpers import fault_env, fault_gate

    section = ingest_params(postgres, tmp_path, retry_limit=0)
    section["destination_plugins"] = ["warehouse"]
    del section["lake"]
    section["warehouse"].update(table="crossing", batch_size=20)
    hanging = {**section, "warehouse": {**section["warehouse"], "storage_total_limit_size": "16k"}}
    password = str(hanging["warehouse"].pop("password"))  # to the subprocess by its environment, not a file
    params = tmp_path / "ingest.yaml"
    params.write_text(json.dumps({"destination_server": {"ros__parameters": hanging}}))
    warehouse_table(postgres, "crossing").on_cleanup()
    sent = [robot_record(n, "uptime") for n in range(300)]
    # Longer than the first worker lives before its kill: its messages come back by the kill alone.
    ack_wait = 20
    first = second = None
    with NatsServer(tmp_path / "nats") as nats_server, fault_gate(tmp_path) as gate:
        url = nats_server.url
        publisher = robot(url)
        try:
            assert publisher.send(sent) is None
        finally:
            publisher.on_cleanup()
        try:
            hang = fault_env(tmp_path, "dc_destinations.pgsql:PgSQL.send", gate=gate.path)  # never opened
            options = ("--ack-wait", str(ack_wait), "--handback-delay", "0.2")
            first = worker(params, url, tmp_path / "w1", env={**hang, "PGPASSWORD": password}, options=options)
            wait_for(
                lambda: (
                    "messages handed back to the stream" in (tmp_path / "w1.log").read_text()
                    and consumer_state(url, "warehouse")[0] == 0
                ),
                "the first worker took every message and handed some back",
            )
            second = Worker(section, url, "warehouse", tmp_path / "w2", ack_wait=ack_wait, handback_delay=0.2)
            ingest = second.ingest

            def settled_by_the_second() -> int:
                dead = int(ingest.pipeline.metrics()["warehouse"]["dead_lettered"])
                return len(table_ids(postgres, "crossing")) + dead

            # The first worker's queue holds ~140 records: the second one settles 100 of the others.
            wait_for(lambda: settled_by_the_second() >= 100, "the second worker settled 100 handed-back records")
            counted_before_the_kill = ingest.counters.over_retry_limit
            first.send_signal(signal.SIGKILL)
            first.wait(10)
            # Unacknowledged: what it held, and what it handed back that was not delivered again yet.
            held = consumer_state(url, "warehouse")[1]
            wait_for(
                lambda: settled_by_the_second() == len(sent) and consumer_state(url, "warehouse") == (0, 0),
                "the killed worker's messages settled by the second one",
            )
            metrics = ingest.pipeline.metrics()["warehouse"]
        finally:
            if second is not None:
                second.stop()
            if first is not None and first.poll() is None:
                first.kill()
                first.wait(10)
    counters = second.ingest.counters
    assert counted_before_the_kill == 0, "the first worker's hand-backs counted as redeliveries by the second"
    assert counters.came_back > 0 and not counters.handed_back, "it took messages the other one had handed back"
    stored = table_ids(postgres, "crossing")
    storage_file = second.ingest.pipeline.storage_file
    assert storage_file is not None
    with contextlib.closing(SqliteBuffer(storage_file)) as buffer:
        dead = buffer.list_dead_letters("warehouse", limit=len(sent))
    assert sorted(stored + [d.record_id for d in dead]) == sorted(r.record_id for r in sent), "each once"
    # What the killed worker held counts (killed between a hand-back's record and its nak, one may not).
    assert 0 < len(dead) <= held and counters.over_retry_limit == len(dead) == metrics["dead_lettered"]
    assert all(re.search(r"redelivered [1-9]\d* times, beyond retry_limit 0", d.error) for d in dead)
    assert counters.handback_record_failures == 0


def test_the_shared_record_of_hand_backs_is_read_only_for_messages_delivered_before(tmp_path: Path) -> None:
    """dc_destinations.handbacks against a real server: no lookup for a message delivered once (the
    normal path), a recorded count read back by whoever takes the message next, no count for a
    message never handed back, and none from an entry left for another message of that sequence
    (a stream deleted and made again)."""
    import nats

    from dc_destinations.handbacks import HandbackRecord, bucket_name

    async def scenario(url: str) -> None:
        nc = await nats.connect(servers=[url])
        try:
            js = nc.jetstream()
            await js.add_stream(name="DC", subjects=["dc.>"], num_replicas=1)
            for n in range(3):
                await js.publish("dc.r1.uptime", json.dumps({"n": n}).encode())
            record = await HandbackRecord.open(js, "DC", "ingest")
            sub = await js.pull_subscribe("dc.>", durable="ingest", stream="DC")
            first = await sub.fetch(3, timeout=10)
            assert await record.counts(first) == {}, "nothing looked up for messages delivered once"
            handed, stale, never = first
            await record.record(handed, 2)  # handed back twice already (by any worker)
            kv = await js.key_value(bucket_name("DC", "ingest"))
            await kv.put(str(stale.metadata.sequence.stream), b"5 2001-01-01T00:00:00+00:00")
            for msg in first:
                await msg.nak()
            again: list[Any] = []
            while len(again) < 3:  # a fetch returns what has come back so far (a fresh clone got 1 of 3)
                again += await sub.fetch(3 - len(again), timeout=10)
            counts = await record.counts(again)
            assert counts == {
                handed.metadata.sequence.stream: 2,
                stale.metadata.sequence.stream: 0,
                never.metadata.sequence.stream: 0,
            }
            opened = await HandbackRecord.open(js, "DC", "ingest")  # the next worker finds the bucket
            assert await opened.counts(again) == counts
        finally:
            await nc.close()

    with NatsServer(tmp_path / "nats") as nats_server:
        asyncio.run(scenario(nats_server.url))


def test_settlements_answer_each_message_by_what_its_destinations_did() -> None:
    from dc_destinations.ingest import ACK, NAK, TERM, Settlements, Taken

    verdicts: list[tuple[Any, str, str, str, int]] = []
    s = Settlements(lambda *verdict: verdicts.append(verdict), remember=2)
    assert s.add("a", "m1", ["pg", "lake"]) == Taken(["lake", "pg"], 0)
    s.settled("lake", ["a"])
    s.dropped("pg", ["a"], "size_limit")
    assert verdicts.pop() == ("m1", NAK, "size_limit", "pg", 1) and len(s) == 0
    # Back again: only to the destination that had not settled it, its hand-back known.
    assert s.add("a", "m1 again", ["pg", "lake"]) == Taken(["pg"], 1)
    s.dropped("lake", ["a"], "size_limit")  # a late report of a destination that settled it: no effect
    s.settled("pg", ["a"])
    assert verdicts.pop() == ("m1 again", ACK, "", "", 1)
    s.add("b", "m2", ["pg", "lake"])
    s.dropped("pg", ["b"], "not_storable")
    s.settled("lake", ["b"])
    assert verdicts.pop() == ("m2", TERM, "not_storable", "pg", 0)
    # A drop for want of room wins over one for good: the other destination may take it later.
    s.add("c", "m3", ["pg", "lake"])
    s.dropped("pg", ["c"], "not_storable")
    s.dropped("lake", ["c"], "disk_budget")
    assert verdicts.pop() == ("m3", NAK, "disk_budget", "lake", 1)
    # Handed back by other workers too (the shared record says 3): the larger count is the message's.
    assert s.add("c", "m3 again", ["pg", "lake"], handbacks=3) == Taken(["lake"], 3)
    s.dropped("lake", ["c"], "size_limit")
    assert verdicts.pop() == ("m3 again", NAK, "size_limit", "lake", 4)
    assert s.add("c", "m3 once more", ["pg", "lake"], handbacks=2) == Taken(["lake"], 4)
    s.settled("lake", ["c"])
    assert verdicts.pop() == ("m3 once more", TERM, "not_storable", "pg", 4)
    # At most `remember` hand-backs are remembered, the oldest forgotten first.
    for rid in ("x", "y", "z"):
        s.add(rid, rid, ["pg"])
        s.dropped("pg", [rid], "intake")
    assert s.add("x", "x", ["pg"]) == Taken(["pg"], 0) and s.add("z", "z", ["pg"]) == Taken(["pg"], 1)
    s.settled("pg", ["unknown"])  # a replayed dead letter: not in flight here
    assert len(s) == 2 and [v[1] for v in verdicts] == [NAK, NAK, NAK]
    # Handed back only by another worker: this one learns its count from the shared record alone.
    assert s.add("w", "w", ["pg"], handbacks=2) == Taken(["pg"], 2)
