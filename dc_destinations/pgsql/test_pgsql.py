"""PgSQL destination against a real PostgreSQL started by the tests: the rows, exactly once, and how failures are classified.

One server (dc_bringup.local_servers.postgres) serves the whole module, in a folder under /tmp that
the postgres system user can enter when the tests run as root; each test writes to its own table.
The last two tests go through `dc-bringup` with real processes, the last one across a 30 s outage.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.postgres import PostgresServer, missing_reason
from dc_core.destination import ConfigurationProblem, OutgoingRecord, RetryableError, SendOutcome, StoredRecord
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.records import dump_record
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.config import parse_destination_server
from dc_destinations.pgsql import PgSQL, PgSQLParams
from dc_destinations.record_ids import new_record_id
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import forwarding_params, running_postgres
from tests.http_receiver import free_port

if missing_reason() is not None:
    pytest.skip(f"no local PostgreSQL: {missing_reason()}", allow_module_level=True)

import psycopg  # an optional dependency: imported after the skip

PASSWORD = "pg-Very-Secret-42"
STAMP_NS = 1_700_000_000_123_456_789


@pytest.fixture(scope="module")
def server() -> Iterator[PostgresServer]:
    with running_postgres("dc-pg-", PASSWORD) as pg:
        yield pg


@pytest.fixture
def destinations() -> Iterator[list[PgSQL]]:
    made: list[PgSQL] = []
    yield made
    for d in made:
        d.on_deactivate()


def make(
    server: PostgresServer, destinations: list[PgSQL], logger: RecordingLogger | None = None, **params: Any
) -> PgSQL:
    settings = {**server.settings(), **params}
    name = str(settings.pop("name", "warehouse"))
    context = FakeContext(name=name, logger=logger or RecordingLogger())
    plugin = PgSQL(context, parse_params(PgSQLParams, settings, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    destinations.append(plugin)
    return plugin


def record(n: int, **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(
        rid, "/dc/measurement/test", STAMP_NS + n * 1_000_000_000, {"seq": n, **data, "record_id": rid}
    )


def rows(server: PostgresServer, table: str) -> list[tuple[Any, ...]]:
    s = server.settings()
    with psycopg.connect(
        host=str(s["host"]), port=int(s["port"]), user=str(s["user"]), password=str(s["password"]), dbname="dc"
    ) as connection:
        query = f'SELECT tag, time, data, record_id FROM "{table}" ORDER BY time'
        return [(r[0], utc(r[1]), *r[2:]) for r in connection.execute(query).fetchall()]


def utc(moment: dt.datetime) -> dt.datetime:
    """A time as a naive UTC datetime, whichever of timestamptz (DC's tables) or timestamp (the original's) it came from."""
    return moment.astimezone(dt.UTC).replace(tzinfo=None) if moment.tzinfo else moment


@pytest.mark.parametrize("plugin", ["PgSQL", "FilesMetrics"])
def test_without_psycopg_configure_says_what_to_install(plugin: str, monkeypatch: pytest.MonkeyPatch) -> None:
    from dc_destinations.files_metrics import FilesMetrics
    from tests.destination_helpers import make as make_destination

    destination = (
        make_destination(PgSQL, name="db")
        if plugin == "PgSQL"
        else make_destination(
            FilesMetrics,
            name="db",
            file_storage=["minio"],
            minio={"bucket": "dc-bucket", "src_fields": ["local_path"], "upload_fields": ["remote_path"]},
        )
    )
    monkeypatch.setitem(sys.modules, "psycopg", None)  # what an install without the pgsql extra gives
    with pytest.raises(ConfigError) as error:
        destination.on_configure()
    assert str(error.value) == (
        f'destination_server.db.plugin: the {plugin} destination needs psycopg (pip install "ros2-dc[pgsql]")'
    )


def test_rows_arrive_with_tag_time_data_and_record_id(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="arrive")
    batch = [record(0, name="uptime", note="üñí"), record(1, name="memory", used=41.27)]
    assert dest.send(batch) is None
    got = rows(server, "arrive")
    assert [r[0] for r in got] == ["warehouse", "warehouse"], "tag: the destination's name"
    assert got[0][1] == dt.datetime(2023, 11, 14, 22, 13, 20, 123456), "time: the record's stamp, UTC"
    assert got[1][1] - got[0][1] == dt.timedelta(seconds=1)
    assert [r[2] for r in got] == [r.data for r in batch], "data: the record's JSON"
    assert [r[3] for r in got] == [r.record_id for r in batch]


def test_timestamp_key_and_the_originals_spelling(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="stamped", timestamp_Key="date")
    assert dest.params.timestamp_key == "date"
    batch = [record(0, date=1677668906.5), record(1, date="2024-05-01T12:00:00Z"), record(2, date="soon")]
    assert dest.send(batch) is None
    times = sorted(r[1] for r in rows(server, "stamped"))
    assert times == [
        dt.datetime(2023, 3, 1, 11, 8, 26, 500000),
        dt.datetime(2023, 11, 14, 22, 13, 22, 123456),  # unreadable: the stamp
        dt.datetime(2024, 5, 1, 12, 0),
    ]


def test_a_batch_sent_twice_is_inserted_once(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="twice")
    batch = [record(i, name="seq") for i in range(1000)]
    assert dest.send(batch) is None
    assert dest.send(batch) is None, "a retried batch is confirmed too"
    assert dest.send([*batch[500:], record(1000, name="seq")]) is None
    got = rows(server, "twice")
    assert len(got) == 1001
    assert len({r[3] for r in got}) == 1001


def test_a_refused_record_goes_alone_to_the_dead_letters(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="refused")
    batch = [record(0, text="fine"), record(1, text="nul \u0000 inside"), record(2, text="fine too")]
    outcome = dest.send(batch)
    assert isinstance(outcome, SendOutcome) and not outcome.retry
    assert list(outcome.reject) == [1]
    assert outcome.reject[1].startswith("PostgreSQL refused the record: unsupported Unicode escape sequence")
    assert "SQLSTATE 22P05" in outcome.reject[1]
    assert [r[2]["seq"] for r in rows(server, "refused")] == [0, 2], "the others are delivered"


def test_a_constraint_refuses_only_the_rows_that_break_it(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="checked")
    assert dest.send([record(0, level=1)]) is None  # creates the table
    s = server.settings()
    with psycopg.connect(
        host="127.0.0.1", port=int(s["port"]), user="dc", password=PASSWORD, dbname="dc", autocommit=True
    ) as admin:
        admin.execute("ALTER TABLE checked ADD CONSTRAINT level_small CHECK ((data->>'level')::int < 10)")
    outcome = dest.send([record(1, level=5), record(2, level=50), record(3, level=99), record(4, level=7)])
    assert outcome is not None and sorted(outcome.reject) == [1, 2]
    assert 'violates check constraint "level_small"' in outcome.reject[1]
    assert sorted(r[2]["level"] for r in rows(server, "checked")) == [1, 5, 7]


def admin(server: PostgresServer) -> Any:
    s = server.settings()
    return psycopg.connect(
        host="127.0.0.1", port=int(s["port"]), user="dc", password=PASSWORD, dbname="dc", autocommit=True
    )


def test_a_batch_sent_again_goes_through_the_staging_table(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="staged")
    batch = [record(i, name="seq") for i in range(500)]
    assert dest.send(batch) is None and dest.send(batch) is None
    assert dest._staging, "COPY into the session's staging table, not INSERT … VALUES"
    with admin(server) as connection:
        got = connection.execute("SELECT data, record_id FROM staged ORDER BY (data->>'seq')::int").fetchall()
    assert [(r[0], r[1]) for r in got] == [(r.data, r.record_id) for r in batch]


def test_a_refused_row_in_a_large_batch_holds_up_no_other(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="refused_large")
    batch = [record(i, text="fine") for i in range(500)]
    batch[250] = record(250, text="nul \u0000 inside")
    outcome = dest.send(batch)
    assert outcome is not None and list(outcome.reject) == [250] and not outcome.retry
    assert "SQLSTATE 22P05" in outcome.reject[250]
    assert sorted(r[2]["seq"] for r in rows(server, "refused_large")) == [i for i in range(500) if i != 250]
    assert dest.send([record(500)]) is None, "the staging table is empty again and usable after the rollback"
    assert len(rows(server, "refused_large")) == 500


class CopySpy:
    """The COPY statements a destination's connection ran, as text, and how each ended."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.statements: list[tuple[str, str]] = []
        copy = psycopg.Cursor.copy
        spy = self

        @contextlib.contextmanager
        def spied(cursor: Any, statement: Any, *args: Any, **kwargs: Any) -> Iterator[Any]:
            text = statement.as_string(cursor.connection) if hasattr(statement, "as_string") else str(statement)
            try:
                with copy(cursor, statement, *args, **kwargs) as running:
                    yield running
            except psycopg.Error as exc:
                spy.statements.append((text, type(exc).__name__))
                raise
            spy.statements.append((text, "ok"))

        monkeypatch.setattr(psycopg.Cursor, "copy", spied)

    def into(self, table: str) -> list[str]:
        """How each COPY straight into ``table`` ended: "ok" or the error's class."""
        return [outcome for text, outcome in self.statements if text.startswith(f'COPY "{table}"')]

    def staged(self) -> int:
        return sum(1 for text, _ in self.statements if "dc_staging" in text)


def test_a_batch_is_one_binary_copy_into_the_table(
    server: PostgresServer, destinations: list[PgSQL], monkeypatch: pytest.MonkeyPatch
) -> None:
    spy = CopySpy(monkeypatch)
    dest = make(server, destinations, table="direct")
    batch = [record(i, name="seq", note="üñí \\ \t") for i in range(300)]
    assert dest.send(batch) is None
    assert spy.into("direct") == ["ok"] and spy.staged() == 0, spy.statements
    assert "FORMAT BINARY" in spy.statements[0][0], "the table DC made takes binary"
    got = rows(server, "direct")
    assert [(r[0], r[2], r[3]) for r in got] == [("warehouse", r.data, r.record_id) for r in batch]
    assert got[0][1] == dt.datetime(2023, 11, 14, 22, 13, 20, 123456)


def test_a_batch_with_a_row_already_there_takes_the_staging_table(
    server: PostgresServer, destinations: list[PgSQL], monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = make(server, destinations, table="partly_there")
    first = [record(i) for i in range(10)]
    assert dest.send(first) is None
    spy = CopySpy(monkeypatch)
    assert dest.send([*first[5:], record(10), record(11)]) is None
    assert spy.into("partly_there") == ["UniqueViolation"] and spy.staged() == 1, spy.statements
    assert sorted(r[2]["seq"] for r in rows(server, "partly_there")) == list(range(12))
    assert dest.send([record(12)]) is None
    assert spy.into("partly_there") == ["UniqueViolation", "ok"], "the next batch is copied straight again"


def test_a_refused_row_and_a_row_already_there_in_one_batch(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="refused_and_there")
    there = record(0)
    assert dest.send([there]) is None
    outcome = dest.send([record(1), there, record(2, text="nul \u0000 inside"), record(3)])
    assert outcome is not None and list(outcome.reject) == [2] and not outcome.retry
    assert "SQLSTATE 22P05" in outcome.reject[2]
    assert sorted(r[2]["seq"] for r in rows(server, "refused_and_there")) == [0, 1, 3]


def test_a_table_made_by_hand_with_other_types_gets_text(
    server: PostgresServer, destinations: list[PgSQL], monkeypatch: pytest.MonkeyPatch
) -> None:
    with admin(server) as connection:
        connection.execute(
            "CREATE TABLE handmade (tag varchar(20), time timestamptz, data json, record_id text UNIQUE)"
        )
    spy = CopySpy(monkeypatch)
    dest = make(server, destinations, table="handmade")
    batch = [record(0, name="uptime"), record(1, name="memory")]
    assert dest.send(batch) is None and dest.send(batch) is None
    assert spy.into("handmade") == ["ok", "UniqueViolation"]
    assert "BINARY" not in spy.statements[0][0]
    assert [(r[2], r[3]) for r in rows(server, "handmade")] == [(r.data, r.record_id) for r in batch]
    refused = make(server, destinations, table="handmade", name="a_tag_longer_than_twenty_characters")
    outcome = refused.send([record(2)])
    assert outcome is not None and "value too long" in outcome.reject[0]


def test_a_table_with_row_level_security_takes_the_staging_table(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="guarded")
    assert dest.send([record(0)]) is None  # creates the table
    with admin(server) as connection:
        connection.execute("ALTER TABLE guarded ENABLE ROW LEVEL SECURITY")
        connection.execute("ALTER TABLE guarded FORCE ROW LEVEL SECURITY")
        connection.execute("CREATE POLICY everything ON guarded USING (true) WITH CHECK (true)")
    dest.on_deactivate()  # a new connection, as after a restart
    assert dest.send([record(1), record(2)]) is None
    assert dest.send([record(3)]) is None
    assert not dest._direct
    assert [r[2]["seq"] for r in rows(server, "guarded")] == [0, 1, 2, 3]
    assert len([m for m in logger.at("warning") if "takes no COPY" in m]) == 1


def test_a_record_twice_in_one_batch_is_one_row(server: PostgresServer, destinations: list[PgSQL]) -> None:
    # A dead letter replayed while its first copy still waits in the queue: both can meet in a batch.
    dest = make(server, destinations, table="twice_in_batch")
    first, second = record(0), record(1)
    assert dest.send([first, second, first]) is None
    assert dest.send([second, first]) is None
    assert sorted(r[3] for r in rows(server, "twice_in_batch")) == sorted([first.record_id, second.record_id])


def test_a_connection_lost_during_copy_is_retried_without_duplicates(
    server: PostgresServer, destinations: list[PgSQL], monkeypatch: pytest.MonkeyPatch
) -> None:
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="lost_in_copy", connect_timeout=2)
    assert dest.send([record(0)]) is None
    assert dest._database is not None and dest._database._connection is not None
    backend = dest._database._connection.info.backend_pid
    write_row = psycopg.Copy.write_row
    written = 0

    def write_then_lose(copy: Any, row: Any) -> None:
        nonlocal written
        written += 1
        if written == 100:  # mid-COPY: the server ends the session that is sending it rows
            with admin(server) as connection:
                connection.execute("SELECT pg_terminate_backend(%s)", (backend,))
        write_row(copy, row)

    monkeypatch.setattr(psycopg.Copy, "write_row", write_then_lose)
    batch = [record(i) for i in range(1, 301)]
    assert dest.send(batch) is None, "the kept connection died: the batch again at once, on a new one"
    assert written > 300, "the batch was copied a second time"
    assert dest.send(batch) is None, "sent again after an unknown outcome"
    got = rows(server, "lost_in_copy")
    assert sorted(r[2]["seq"] for r in got) == list(range(301))
    assert len([m for m in logger.at("info") if m.startswith("connected to")]) == 2


def test_a_table_named_like_the_staging_table(server: PostgresServer, destinations: list[PgSQL]) -> None:
    dest = make(server, destinations, table="dc_staging")
    assert dest.send([record(0), record(1)]) is None and dest.send([record(2)]) is None
    assert [r[2]["seq"] for r in rows(server, "dc_staging")] == [0, 1, 2]


def test_without_the_right_to_temporary_tables_rows_still_arrive(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    logger = RecordingLogger()
    with admin(server) as connection:
        connection.execute("REVOKE TEMPORARY ON DATABASE dc FROM PUBLIC, dc")
    try:
        dest = make(server, destinations, logger=logger, table="no_temp")
        batch = [record(0), record(1, text="nul \u0000 inside"), record(2)]
        outcome = dest.send(batch)
        assert not dest._staging
        assert outcome is not None and list(outcome.reject) == [1]
        assert dest.send(batch[::2]) is None
    finally:
        with admin(server) as connection:
            connection.execute("GRANT TEMPORARY ON DATABASE dc TO PUBLIC, dc")
    assert [r[2]["seq"] for r in rows(server, "no_temp")] == [0, 2]
    assert any("no temporary table allowed" in m for m in logger.at("warning"))


def test_a_table_made_by_the_original_gets_record_id(server: PostgresServer, destinations: list[PgSQL]) -> None:
    with admin(server) as connection:
        connection.execute("CREATE TABLE legacy (tag varchar, time timestamp, data jsonb)")
        connection.execute("INSERT INTO legacy VALUES ('flb_pgsql', now(), '{\"old\": true}')")
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="legacy")
    batch = [record(0, name="cpu", robot_name="r1", run_id="7")]
    assert dest.send(batch) is None and dest.send(batch) is None
    dest.on_deactivate()  # a new connection: the hint is not said again
    assert dest.send([record(1)]) is None
    got = rows(server, "legacy")
    assert [r[3] for r in got].count(batch[0].record_id) == 1 and len(got) == 3
    with admin(server) as connection:
        columns = connection.execute(
            "SELECT attname::text, format_type(atttypid, atttypmod) FROM pg_attribute"
            " WHERE attrelid = 'legacy'::regclass AND attnum > 0 ORDER BY attnum"
        ).fetchall()
    assert columns == [
        ("tag", "character varying"),
        ("time", "timestamp without time zone"),
        ("data", "jsonb"),
        ("record_id", "text"),
    ], "used as it is: no column changed or added besides record_id"
    hints = [m for m in logger.at("warning") if "has the original's shape" in m]
    assert len(hints) == 1 and "docs/data-model.md#migrating-a-table-of-the-originals-shape" in hints[0]


def table_facts(server: PostgresServer, table: str) -> tuple[list[tuple[str, str]], list[str], list[str]]:
    """(columns and types, index definitions, partition names) of ``table``."""
    with admin(server) as connection:
        columns = connection.execute(
            "SELECT attname::text, format_type(atttypid, atttypmod) FROM pg_attribute"
            " WHERE attrelid = to_regclass(%s) AND attnum > 0 AND NOT attisdropped ORDER BY attnum",
            (table,),
        ).fetchall()
        indexes = [
            r[0]
            for r in connection.execute(
                "SELECT pg_get_indexdef(indexrelid) FROM pg_index WHERE indrelid = to_regclass(%s) ORDER BY 1",
                (table,),
            )
        ]
        partitions = [
            r[0]
            for r in connection.execute(
                "SELECT c.relname::text FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid"
                " WHERE i.inhparent = to_regclass(%s) ORDER BY 1",
                (table,),
            )
        ]
    return columns, indexes, partitions


def test_a_new_table_has_typed_columns_and_the_team_indexes(server: PostgresServer, destinations: list[PgSQL]) -> None:
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="typed", value_keys={"cpu": "average", "robot": "v"})
    group = {
        "name": "robot",
        "robot_name": "r1",
        "run_id": "10",
        "cpu": {"robot_name": "r1", "run_id": "10"},
        "v": True,
    }
    batch = [
        record(0, name="cpu", robot_name="r1", run_id="2", average=12),
        record(1, **group),
        record(2, run_id="run-x", average=3.5),
    ]
    assert dest.send(batch) is None and dest.send(batch) is None
    columns, indexes, partitions = table_facts(server, "typed")
    assert columns == [
        ("tag", "text"),
        ("time", "timestamp with time zone"),
        ("data", "jsonb"),
        ("record_id", "text"),
        ("name", "text"),
        ("robot_name", "text"),
        ("run_id", "bigint"),
        ("value", "double precision"),
    ]
    assert any('(robot_name, name, "time") INCLUDE (value)' in i for i in indexes), indexes
    assert any('(robot_name, run_id, name, "time")' in i for i in indexes), indexes
    assert any('USING brin ("time")' in i for i in indexes), indexes
    assert any("UNIQUE" in i and "(record_id)" in i for i in indexes), indexes
    assert partitions == []
    with admin(server) as connection:
        found = connection.execute(
            "SELECT to_regclass('typed_latest'), (SELECT count(*) FROM pg_trigger WHERE tgrelid = 'typed'::regclass)"
        ).fetchone()
    assert found == (None, 0), "no latest-row table by default: its trigger would cost every insert"
    with admin(server) as connection:
        connection.execute("SET TIME ZONE 'America/Los_Angeles'")  # a session in another zone sees the same rows
        got = connection.execute(
            "SELECT name, robot_name, run_id, value FROM typed WHERE time >= '2023-11-14 22:13:20Z' ORDER BY run_id"
        ).fetchall()
    assert got == [("cpu", "r1", 2, 12.0), ("robot", "r1", 10, None), (None, None, None, None)], (
        "run_id sorts as a number; value: the number under the measurement's value_keys key (a bool is none)"
    )
    told = [m for m in logger.at("warning") if "is not a counter" in m]
    assert len(told) == 1, logger.lines


def test_records_read_back_from_the_buffer_fill_the_typed_columns(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    # As the sender hands them over: the JSON text, parsed only by a destination that reads it.
    def stored(n: int, **data: Any) -> StoredRecord:
        rid = new_record_id()
        text = dump_record({"seq": n, **data, "record_id": rid})
        return StoredRecord(rid, "/dc/measurement/test", STAMP_NS + n * 1_000_000_000, json_text=text)

    batch = [
        stored(0, name="cpu", robot_name="r1", run_id="2", cpu={"name": "inner", "robot_name": "r9"}),
        stored(1, name=7, robot_name=None, run_id=str(2**63)),
    ]
    assert make(server, destinations, table="typed_stored").send(batch) is None
    with admin(server) as connection:
        got = connection.execute("SELECT name, robot_name, run_id FROM typed_stored ORDER BY time").fetchall()
    assert got == [("cpu", "r1", 2), (None, None, None)], "the top-level keys, strings and 64-bit counters only"
    legacy = [stored(2, name="cpu")]
    with admin(server) as connection:
        connection.execute("CREATE TABLE legacy_stored (tag varchar, time timestamp, data jsonb, record_id text)")
    assert make(server, destinations, table="legacy_stored").send(legacy) is None
    assert "data" not in legacy[0].__dict__, "the original's columns need no parse of the record's text"


def test_partition_by_day_makes_partitions_ahead_and_drops_the_expired(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    today = dt.datetime.now(dt.UTC).date()
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="daily", partition_by="day", retention_days=30)
    old = today - dt.timedelta(days=40)
    old_ns = int(dt.datetime.combine(old, dt.time(12), dt.UTC).timestamp() * 1e9)
    now_ns = time.time_ns()
    batch = [
        OutgoingRecord(new_record_id(), "/dc/measurement/t", now_ns, {"name": "cpu"}),
        OutgoingRecord(new_record_id(), "/dc/measurement/t", old_ns, {"name": "cpu"}),
    ]
    assert dest.send(batch) is None and dest.send(batch) is None, "a retried batch meets its unique key"
    _, indexes, partitions = table_facts(server, "daily")
    expected = {f"daily_p{today + dt.timedelta(days=n):%Y%m%d}" for n in range(3)} | {f"daily_p{old:%Y%m%d}"}
    assert set(partitions) == expected, "today, two days ahead, and the day of the late record"
    # Partitioned, the team's index is the unique key too (PostgreSQL 15+): one btree where two were.
    unique = 'UNIQUE INDEX daily_robot_name_time ON ONLY public.daily USING btree (robot_name, name, "time", record_id)'
    assert any(i.startswith("CREATE " + unique) and "NULLS NOT DISTINCT" in i for i in indexes), indexes
    assert any('(robot_name, run_id, name, "time")' in i for i in indexes), indexes
    assert len(indexes) == 3, indexes
    assert len(rows(server, "daily")) == 2
    with admin(server) as connection:
        connection.execute(
            "CREATE TABLE daily_by_hand PARTITION OF daily FOR VALUES FROM ('2001-01-01Z') TO ('2001-01-02Z')"
        )
    dest.on_deactivate()  # the next connection expires what is older than 30 days
    assert dest.send([record(5)]) is None  # 2023: made again for this record, dropped at the next pass
    _, _, partitions = table_facts(server, "daily")
    assert f"daily_p{old:%Y%m%d}" not in partitions and "daily_by_hand" in partitions, "only DC's own are dropped"
    assert any("dropped partitions" in m and f"daily_p{old:%Y%m%d}" in m for m in logger.at("info"))


def latest_rows(server: PostgresServer, table: str) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
    """(the latest-row table's rows, what DISTINCT ON finds in the records table), both by pair."""
    with admin(server) as connection:
        kept = connection.execute(
            f"SELECT robot_name, name, time, data, record_id FROM {table}_latest ORDER BY 1, 2"
        ).fetchall()
        found = connection.execute(
            f"SELECT DISTINCT ON (robot_name, name) robot_name, name, time, data, record_id FROM {table}"
            " WHERE robot_name IS NOT NULL AND name IS NOT NULL ORDER BY robot_name, name, time DESC"
        ).fetchall()
    return kept, found


def test_the_latest_table_holds_each_pairs_latest_record_whatever_the_order(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    today_ns = int(dt.datetime.combine(dt.datetime.now(dt.UTC).date(), dt.time(1), dt.UTC).timestamp() * 1e9)

    def at(seconds: int, robot: str | None, name: str | None, **data: Any) -> OutgoingRecord:
        rid = new_record_id()
        keys = {"robot_name": robot, "name": name} if robot else {"name": name}
        return OutgoingRecord(rid, "/dc/measurement/t", today_ns + seconds * 10**9, {**keys, **data, "record_id": rid})

    dest = make(server, destinations, table="latest", partition_by="day", retention_days=30, latest_table=True)
    first = [
        at(5, "r1", "cpu", v=5),
        at(3, "r1", "cpu", v=3),
        at(1, "r2", "cpu", v=1),
        at(-40 * 86_400, "r3", "cpu", v=0),  # in a partition past retention_days: dropped at the next pass
        at(9, None, "cpu", v=9),  # no robot: no pair to file it under
    ]
    assert dest.send(first) is None
    # A robot's backlog after newer records: an older record of r1 replaces nothing.
    backlog = [at(2, "r1", "cpu", v=2), at(7, "r2", "cpu", v=7)]
    assert dest.send(backlog) is None and dest.send(backlog) is None, "the second time, through the staging table"
    refused = dest.send([at(4, "r2", "memory", v=4), at(8, "r2", "memory", text="\u0000")])
    assert refused is not None and list(refused.reject) == [1]
    kept, found = latest_rows(server, "latest")
    assert kept == found
    assert [(r, n, d["v"]) for r, n, _, d, _ in kept] == [
        ("r1", "cpu", 5),
        ("r2", "cpu", 7),
        ("r2", "memory", 4),
        ("r3", "cpu", 0),  # until its partition expires
    ]
    dest.on_deactivate()  # the next connection drops the partition past retention, and r3's row with it
    assert dest.send([at(6, "r1", "memory", v=6)]) is None
    kept, found = latest_rows(server, "latest")
    assert kept == found, "the latest-row table answers what DISTINCT ON over the records table does"
    assert [(r, n) for r, n, *_ in kept] == [("r1", "cpu"), ("r1", "memory"), ("r2", "cpu"), ("r2", "memory")]


def test_an_existing_table_gets_no_latest_table_nor_a_new_one_with_latest_table_and_run_index_false(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    with admin(server) as connection:
        connection.execute(
            "CREATE TABLE mine (tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL UNIQUE,"
            " name text, robot_name text, run_id bigint)"
        )
    assert make(server, destinations, table="mine").send([record(0, name="cpu", robot_name="r1")]) is None
    off = make(server, destinations, table="not_kept", latest_table=False, run_index=False)
    assert off.send([record(0, name="cpu", robot_name="r1")]) is None
    with admin(server) as connection:
        found = connection.execute(
            "SELECT to_regclass('mine_latest'), to_regclass('not_kept_latest'),"
            " (SELECT count(*) FROM pg_trigger WHERE tgrelid IN ('mine'::regclass, 'not_kept'::regclass))"
        ).fetchone()
    assert found == (None, None, 0), "an existing table is never changed; latest_table: false makes none"
    _, indexes, _ = table_facts(server, "not_kept")
    assert not [i for i in indexes if "run_id" in i] and len(indexes) == 3, indexes


def test_a_week_partition_is_an_iso_week_of_utc_days() -> None:
    from dc_destinations.pgsql.table import Partitions, period_start

    thursday_late = dt.datetime(2026, 11, 26, 23, 30, tzinfo=dt.timezone(dt.timedelta(hours=-8)))  # Friday, UTC
    assert period_start(thursday_late, "week") == dt.date(2026, 11, 23), "the Monday of the UTC day"
    assert period_start(thursday_late, "day") == dt.date(2026, 11, 27)
    ahead = Partitions("telemetry.records", "week", 0).ahead(dt.date(2026, 11, 29))
    assert ahead == {dt.date(2026, 11, 23), dt.date(2026, 11, 30), dt.date(2026, 12, 7)}


def test_partition_by_on_a_table_that_is_not_partitioned_names_the_migration(
    server: PostgresServer, destinations: list[PgSQL]
) -> None:
    make(server, destinations, table="flat").send([record(0)])
    dest = make(server, destinations, table="flat", partition_by="week")
    with pytest.raises(ConfigurationProblem) as caught:
        dest.send([record(1)])
    assert "table flat of postgresql://dc@127.0.0.1" in str(caught.value)
    assert "is not partitioned" in str(caught.value)
    assert "docs/data-model.md#migrating-a-table-of-the-originals-shape" in caught.value.fix
    assert len(rows(server, "flat")) == 1


def test_wrong_password_is_retryable_clear_and_never_shown(
    server: PostgresServer, destinations: list[PgSQL], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_pgsql.secret")
    wrong = make(server, destinations, logger=logger, password="not-" + PASSWORD, table="secret")
    with pytest.raises(RetryableError) as caught:
        wrong.send([record(0)])
    message = str(caught.value)
    assert message.startswith(f"cannot connect to PostgreSQL postgresql://dc@127.0.0.1:{server.port}/dc: ")
    assert 'password authentication failed for user "dc"' in message
    assert message.endswith("(check `user` and `password`)")
    right = make(server, destinations, logger=logger, table="secret")
    assert right.send([record(1)]) is None
    texts = [message, repr(wrong.params), str(right.params), repr(right), repr(server)]
    texts += [r.getMessage() for r in caplog.records] + [m for _, m in logger.lines]
    assert any("connected to" in t for t in texts)
    for text in texts:
        assert PASSWORD not in text, text
    assert {p.name for p in describe_params(PgSQLParams) if p.secret} == {"password"}


def test_an_unreachable_server_is_retryable(destinations: list[PgSQL], server: PostgresServer) -> None:
    port = free_port()
    dest = make(server, destinations, port=port, connect_timeout=2)
    with pytest.raises(RetryableError, match=rf"cannot connect to PostgreSQL postgresql://dc@127.0.0.1:{port}/dc: .*"):
        dest.send([record(0)])


def test_a_server_restart_between_batches_is_survived(server: PostgresServer, destinations: list[PgSQL]) -> None:
    logger = RecordingLogger()
    dest = make(server, destinations, logger=logger, table="restart", connect_timeout=2)
    assert dest.send([record(0)]) is None
    server.stop()
    with pytest.raises(RetryableError, match="cannot connect to PostgreSQL"):
        dest.send([record(1)])
    server.start()
    assert dest.send([record(2)]) is None
    server.stop()
    server.start()
    assert dest.send([record(3)]) is None, "the kept connection died with the server: a new one, at once"
    assert [r[2]["seq"] for r in rows(server, "restart")] == [0, 2, 3]
    assert len([m for m in logger.at("info") if m.startswith("connected to")]) == 3


def configure(body: dict[str, Any]) -> PgSQL:
    section = {"destination_plugins": ["pg"], "pg": {"plugin": "dc_destinations/FlbPgSQL", "inputs": ["/dc/x"], **body}}
    (d,) = parse_destination_server(section).destinations
    plugin: PgSQL = d.plugin_class(FakeContext(name=d.name), d.plugin_params)
    plugin.on_configure()
    return plugin


def test_the_originals_keys_are_accepted() -> None:
    plugin = configure(
        {"user": "fluentbit", "password": "password", "database": "fluentbit", "table": "dc", "timestamp_key": "date",
         "async": False, "min_pool_size": "1", "max_pool_size": 4, "cockroachdb": False}
    )  # fmt: skip
    assert plugin.address == "postgresql://fluentbit@127.0.0.1:5432/fluentbit"
    assert "password" not in repr(plugin.params)


def test_the_port_as_the_originals_files_write_it_is_a_number() -> None:
    """PgSQL and FilesMetrics share their server parameters: FilesMetrics took "5432", PgSQL does too."""
    p = parse_params(PgSQLParams, {"port": "5433"}, "x")
    assert p.server().port == 5433
    with pytest.raises(ConfigError, match=r"x\.port: expected a TCP port from 1 to 65535"):
        parse_params(PgSQLParams, {"port": "54x"}, "x")


def test_defaults() -> None:
    p = parse_params(PgSQLParams, {}, "x")
    assert (p.host, p.port, p.user, p.database, p.table, p.timestamp_key) == ("127.0.0.1", 5432, "", "", "dc", "")
    assert (p.ssl, p.effective_sslmode, p.connect_timeout) == (False, "prefer", 10)
    assert parse_params(PgSQLParams, {"ssl": True}, "x").effective_sslmode == "verify-full"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"port": 0}, "destination_server.pg.port: expected a TCP port from 1 to 65535, got 0"),
        ({"table": ""}, 'destination_server.pg.table: expected a table name or "schema.table"'),
        ({"table": "a.b.c"}, 'destination_server.pg.table: expected a table name or "schema.table"'),
        ({"sslmode": "strict"}, "destination_server.pg.sslmode: expected one of"),
        ({"ssl": True, "sslmode": "disable"}, 'destination_server.pg.sslmode: "disable" contradicts ssl: true'),
        ({"sslrootcert": "/ca.pem"}, "destination_server.pg.sslrootcert: set sslmode to verify-full"),
        ({"host": "postgres://db"}, "destination_server.pg.host: expected a host name or IP address"),
        ({"connect_timeout": 1}, "destination_server.pg.connect_timeout: expected an integer >= 2"),
        ({"partition_by": "month"}, "destination_server.pg.partition_by: expected one of"),
        ({"retention_days": 7}, "destination_server.pg.retention_days: retention drops whole partitions"),
        ({"passwd": "x"}, 'unknown parameter of dc_destinations/FlbPgSQL (did you mean "password"?)'),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)


# -- end to end through dc-bringup ------------------------------------------------------------------------


def bringup_params(tmp_path: Path, server: PostgresServer, table: str) -> Path:
    settings = {"plugin": "dc_destinations/PgSQL", **server.settings(), "table": table, "connect_timeout": 2}
    return forwarding_params(tmp_path, "warehouse", settings, measurement="hello", topic="/hello-world")


def count(server: PostgresServer, table: str) -> tuple[int, int]:
    """(rows, distinct record ids) of ``table``; (0, 0) while it does not exist or the server is down."""
    try:
        got = rows(server, table)
    except psycopg.Error:
        return 0, 0
    return len(got), len({r[3] for r in got})


@pytest.mark.e2e
def test_e2e_records_published_with_dc_pub_become_rows(tmp_path: Path, server: PostgresServer) -> None:
    with Bringup(bringup_params(tmp_path, server, "e2e"), tmp_path / "home") as run:
        run.wait_ready()
        published = dc("pub", "/hello-world", '{"hello": "world"}', "--count", "3", "--rate", "5", env=run.env)
        assert published.returncode == 0, published.stderr
        run.wait_until(lambda: count(server, "e2e")[0] >= 3, 30, "three rows")
    got = rows(server, "e2e")
    assert len(got) == 3 and {r[0] for r in got} == {"warehouse"}
    assert all(r[2]["hello"] == "world" and r[2]["name"] == "hello" for r in got)
    assert [r[2]["record_id"] for r in got] == [r[3] for r in got]
    assert password_absent(tmp_path)


def password_absent(tmp_path: Path) -> bool:
    return all(PASSWORD not in p.read_text(errors="replace") for p in tmp_path.rglob("*.log") if p.is_file())


OUTAGE_S = 30.0


@pytest.mark.e2e
def test_e2e_a_30_s_database_outage_loses_and_duplicates_no_record(tmp_path: Path, server: PostgresServer) -> None:
    total, rate = 40, 2.0  # 20 s of records: most of them published while the database is down
    with Bringup(bringup_params(tmp_path, server, "outage"), tmp_path / "home") as run:
        run.wait_ready()
        publisher = subprocess.Popen(
            [str(BIN / "dc"), "pub", "/hello-world", '{"hello": "world"}', "--count", str(total), "--rate", str(rate)],
            env=run.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            run.wait_until(lambda: count(server, "outage")[0] >= 3, 30, "the first rows")
            server.stop()
            down_at = time.monotonic()
            run.wait_stderr(
                f"cannot connect to PostgreSQL postgresql://dc@127.0.0.1:{server.port}/dc", timeout=OUTAGE_S
            )
            output, _ = publisher.communicate(timeout=2 * OUTAGE_S)  # 20 s of records, and a loaded machine
            assert publisher.returncode == 0, output
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts 30 s
        finally:
            server.start()  # the module's other tests need it back, whatever happened
        run.wait_until(lambda: count(server, "outage")[1] >= total, 30, f"all {total} rows after the outage")
        stderr = "\n".join(run.stderr)
    assert count(server, "outage") == (total, total), "every record exactly once"
    assert PASSWORD not in stderr
    print(f"\n{total} rows, each once, across a {OUTAGE_S:g} s outage")
