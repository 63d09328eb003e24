"""docs/data-model.md holds: its team queries and its migration, run as written against a real PostgreSQL
filled by the PgSQL destination (one server for the module)."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.postgres import PostgresServer, missing_reason
from dc_core.destination import OutgoingRecord
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.pgsql import PgSQL, PgSQLParams
from dc_destinations.record_ids import new_record_id
from tests.destination_helpers import running_postgres

if missing_reason() is not None:
    pytest.skip(f"no local PostgreSQL: {missing_reason()}", allow_module_level=True)


PAGE = (Path(__file__).resolve().parent.parent / "docs" / "data-model.md").read_text()
DAY = dt.datetime(2026, 11, 25, tzinfo=dt.UTC)


def queries() -> dict[str, str]:
    return dict(re.findall(r"<!-- query: (\w+) -->\n```sql\n(.*?)```", PAGE, re.S))


def block(tag: str) -> str:
    (sql,) = re.findall(rf"<!-- {tag} -->\n```sql\n(.*?)```", PAGE, re.S)
    return str(sql)


def migration() -> str:
    return block("migration")


# What the latest-record queries must answer: the plain query over the records table.
PLAIN_LATEST = """SELECT DISTINCT ON (robot_name, name) robot_name, name, time, data FROM dc
WHERE robot_name IS NOT NULL AND name IS NOT NULL ORDER BY robot_name, name, time DESC"""


def at(hour: int, minute: int = 0, second: int = 0) -> int:
    return int((DAY + dt.timedelta(hours=hour, minutes=minute, seconds=second)).timestamp() * 1e9)


def record(stamp_ns: int, **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/x", stamp_ns, {**data, "record_id": rid})


def robot(name: str, run: int, measurement: str, **data: Any) -> dict[str, Any]:
    return {"name": measurement, "robot_name": name, "run_id": str(run), "schema_version": 1, **data}


def codes(*texts: str) -> dict[str, Any]:
    return {"barcode": [{"data": t, "type": "QRCODE" if "SHELF" in t else "CODE128"} for t in texts]}


@pytest.fixture(scope="module")
def server() -> Iterator[PostgresServer]:
    with running_postgres("dc-pg-model-", "model-Secret-1") as pg:
        yield pg


def destination(server: PostgresServer, table: str, logger: RecordingLogger, partition_by: str = "day") -> PgSQL:
    settings = {"table": table, "partition_by": partition_by, "value_keys": {"cpu": "average"}, "latest_table": True}
    params = parse_params(PgSQLParams, {**server.settings(), **settings}, "destination_server.pg")
    dest = PgSQL(FakeContext(name="pg", logger=logger), params)
    dest.on_configure()
    return dest


@pytest.fixture(scope="module")
def filled(server: PostgresServer) -> PostgresServer:
    batch = [
        # robot-007's run 11 (the night before), then run 12.
        record(at(1), **robot("robot-007", 11, "position", x=9.0, y=9.0, yaw=0.0)),
        *(record(at(10, s), **robot("robot-007", 12, "position", x=float(s), y=2.0 * s, yaw=0.0)) for s in range(3)),
        # CPU every 20 min over two hours: p95 per hour.
        *(
            record(at(h, m), **robot("robot-007", 12, "cpu", average=float(h * 10 + m)))
            for h in (10, 11)
            for m in (0, 20, 40)
        ),
        record(at(23, 59, 59), **robot("robot-007", 12, "cpu", average=99.0)),
        record(at(24, 0, 1), **robot("robot-007", 12, "cpu", average=1.0)),  # the next UTC day: not counted
        # Codes: shelves read twice and once, a pallet code (not a shelf) ignored.
        record(at(10, 5), **robot("robot-007", 12, "front_camera", inspected=codes("WH1/SHELF-01", "PAL-1"))),
        record(at(10, 6), **robot("robot-007", 12, "front_camera", inspected=codes("WH1/SHELF-01", "WH1/SHELF-02"))),
        # Another robot, one of its records a group's: robot and run at its top level.
        record(at(9), **robot("robot-008", 3, "cpu", average=5.0)),
        record(
            at(9, 1), name="system", robot_name="robot-008", run_id="3", cpu=robot("robot-008", 3, "cpu", average=6.0)
        ),
        record(at(9, 2), name="orphan"),  # no robot: in the table, in none of the robot's answers
    ]
    dest = destination(server, "dc", RecordingLogger())
    try:
        assert dest.send(batch) is None
    finally:
        dest.on_deactivate()
    return server


def run(server: PostgresServer, name: str, zone: str = "UTC") -> list[tuple[Any, ...]]:
    with server.connect() as connection:
        connection.execute(f"SET TIME ZONE '{zone}'")
        return list(connection.execute(queries()[name].encode()).fetchall())


def test_the_page_has_the_team_queries() -> None:
    assert set(queries()) == {"path", "latest", "latest_scan", "cpu_p95", "cpu_p95_json", "codes_per_shelf", "files"}


def test_the_path_of_a_robot_in_a_run(filled: PostgresServer) -> None:
    got = run(filled, "path")
    assert [(x, y) for _, x, y in got] == [(0.0, 0.0), (1.0, 2.0), (2.0, 4.0)], "run 12 only, in time order"
    assert got[0][0] == DAY + dt.timedelta(hours=10)


@pytest.mark.parametrize("query", ["latest", "latest_scan"])
def test_the_latest_record_of_each_measurement_of_each_robot(filled: PostgresServer, query: str) -> None:
    answer = run(filled, query)
    with filled.connect() as connection:
        assert answer == connection.execute(PLAIN_LATEST.encode()).fetchall()
    got = {(r, n): (t, d) for r, n, t, d in answer}
    assert set(got) == {
        ("robot-007", "cpu"),
        ("robot-007", "front_camera"),
        ("robot-007", "position"),
        ("robot-008", "cpu"),
        ("robot-008", "system"),
    }, "a group's record has its robot at the top level; a record without a robot is in no answer"
    assert got[("robot-007", "cpu")][1]["average"] == 1.0
    assert got[("robot-008", "system")][1]["cpu"]["average"] == 6.0


@pytest.mark.parametrize(
    ("query", "zone"), [("cpu_p95", "UTC"), ("cpu_p95", "America/Los_Angeles"), ("cpu_p95_json", "UTC")]
)
def test_cpu_p95_per_utc_hour_whatever_the_sessions_zone(filled: PostgresServer, query: str, zone: str) -> None:
    got = run(filled, query, zone)
    hours = [h.astimezone(dt.UTC).hour for h, _ in got]
    assert hours == [10, 11, 23]
    assert [round(p, 1) for _, p in got] == [138.0, 148.0, 99.0]  # 100, 120, 140: p95 138


def test_codes_read_per_shelf_per_day(filled: PostgresServer) -> None:
    got = [(d.astimezone(dt.UTC).date(), shelf, n) for d, shelf, n in run(filled, "codes_per_shelf")]
    assert got == [(DAY.date(), "WH1/SHELF-01", 2), (DAY.date(), "WH1/SHELF-02", 1)]


def test_files_uploaded_verified_and_deleted_per_storage_and_day(server: PostgresServer) -> None:
    from dc_destinations.files_metrics.table import FilesTable

    # Rows as FilesMetrics leaves them: deleted after verification, uploaded but still on the robot,
    # waiting for its upload; one of another robot, one of the next UTC day.
    rows = [
        ("robot-007", "minio", DAY + dt.timedelta(hours=10), True, True, True),
        ("robot-007", "minio", DAY + dt.timedelta(hours=11), True, True, False),
        ("robot-007", "minio", DAY + dt.timedelta(hours=12), False, False, False),
        ("robot-007", "s3", DAY + dt.timedelta(hours=12), True, True, True),
        ("robot-008", "minio", DAY + dt.timedelta(hours=10), True, True, True),
        ("robot-007", "minio", DAY + dt.timedelta(days=1, minutes=1), True, True, True),
    ]
    with server.connect() as connection:
        FilesTable("files_metrics").prepare(connection)
        for i, (robot_name, storage, when, uploaded, verified, deleted) in enumerate(rows):
            connection.execute(
                "INSERT INTO files_metrics (timestamp, robot_name, robot_id, group_name, local_path, remote_path,"
                " uploaded, on_filesystem, deleted, storage_type, content_type, size, updated_at, record_id,"
                " bucket, verified_at) VALUES (%s, %s, '', 'map', %s, %s, %s, %s, %s, %s, 'image/png', 10, now(),"
                " %s, 'b', %s)",
                (when.replace(tzinfo=None), robot_name, f"/d/{i}.png", f"s3://b/{i}.png", uploaded, not deleted,
                 deleted, storage, f"r{i}", when if verified else None),
            )  # fmt: skip
    got = [(d.date(), storage, *counts) for d, storage, *counts in run(server, "files")]
    assert got == [(DAY.date(), "minio", 3, 2, 2, 1, 1), (DAY.date(), "s3", 1, 1, 1, 1, 0)]


def test_the_documented_migration_makes_a_table_dc_writes_to_without_a_hint(server: PostgresServer) -> None:
    with server.connect() as connection:
        connection.execute("CREATE SCHEMA original")
        connection.execute("CREATE TABLE original.dc (tag varchar, time timestamp, data jsonb, record_id text)")
        connection.execute("CREATE UNIQUE INDEX dc_record_id ON original.dc (record_id)")
        connection.execute(
            "INSERT INTO original.dc VALUES ('pg', '2026-11-25 10:00', %s, 'a'), ('pg', '2026-11-24 23:00', %s, NULL)",
            (
                '{"name": "system", "cpu": {"robot_name": "r1", "run_id": "10"}}',
                '{"name": "cpu", "robot_name": "r1", "run_id": "9"}',
            ),
        )
        connection.execute("SET search_path TO original")
        connection.execute(migration().encode())
        got = connection.execute("SELECT time, name, robot_name, run_id FROM original.dc ORDER BY run_id").fetchall()
        kind = connection.execute("SELECT relkind::text FROM pg_class WHERE oid = 'original.dc'::regclass").fetchone()
    assert kind == ("p",)
    assert got == [
        (dt.datetime(2026, 11, 24, 23, tzinfo=dt.UTC), "cpu", "r1", 9),
        (dt.datetime(2026, 11, 25, 10, tzinfo=dt.UTC), "system", "r1", 10),
    ], "the original's UTC times kept, robot and run of a group's record found in its members"
    logger = RecordingLogger()
    dest = destination(server, "original.dc", logger)
    try:
        assert dest.send([record(at(12), **robot("r1", 11, "cpu", average=1.0))]) is None
    finally:
        dest.on_deactivate()
    assert not [m for m in logger.at("warning") if "original's shape" in m]


def test_the_documented_index_migration_of_a_plain_table_made_before(server: PostgresServer) -> None:
    with server.connect() as connection:
        connection.execute("CREATE SCHEMA before")
        connection.execute("SET search_path TO before")
        connection.execute(
            "CREATE TABLE dc (tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL,"
            " name text, robot_name text, run_id bigint, value double precision)"
        )
        for index in (
            "UNIQUE INDEX dc_record_id ON dc (record_id)",  # the indexes DC makes for a plain table
            "INDEX dc_robot_name_time ON dc (robot_name, name, time) INCLUDE (value)",
            "INDEX dc_robot_run_time ON dc (robot_name, run_id, name, time)",
        ):
            connection.execute(f"CREATE {index}".encode())
        connection.commit()
    batch = [record(at(h), **robot("robot-1", 1, "cpu", average=float(h))) for h in (1, 2, 3)]
    dest = destination(server, "before.dc", RecordingLogger(), partition_by="none")
    try:
        assert dest.send(batch[:2]) is None
        with server.connect() as connection:
            connection.autocommit = True  # CONCURRENTLY: outside a transaction block, a statement at a time
            connection.execute("SET search_path TO before")
            for statement in block("index-migration").split(";"):
                if statement.strip():
                    connection.execute(statement.encode())
        dest.on_deactivate()  # DC's next connection
        assert dest.send(batch) is None, "two sent again, met on the new key, and a new one"
        with server.connect() as connection:
            got = connection.execute("SELECT record_id FROM before.dc ORDER BY time").fetchall()
            indexes = connection.execute(
                "SELECT indexrelid::regclass::text FROM pg_index WHERE indrelid = 'before.dc'::regclass ORDER BY 1"
            ).fetchall()
    finally:
        dest.on_deactivate()
    assert [r for (r,) in got] == [r.record_id for r in batch]
    assert indexes == [("before.dc_robot_name_time",), ("before.dc_robot_run_time",)]


def test_the_documented_fill_of_a_latest_table_added_to_an_existing_table(server: PostgresServer) -> None:
    with server.connect() as connection:
        connection.execute("CREATE SCHEMA added")
        connection.execute("SET search_path TO added")
        connection.execute(
            "CREATE TABLE dc (tag text, time timestamptz NOT NULL, data jsonb, record_id text NOT NULL UNIQUE,"
            " name text, robot_name text, run_id bigint)"
        )
        connection.commit()
    batch = [
        record(at(h), **robot(f"robot-{r}", 1, name, v=h)) for h in (1, 2, 3) for r in (1, 2) for name in ("a", "b")
    ]
    dest = destination(server, "added.dc", RecordingLogger(), partition_by="none")
    try:
        assert dest.send(batch[:6]) is None  # no latest-row table: DC makes none for a table that exists
        with server.connect() as connection:
            connection.execute("SET search_path TO added")
            connection.execute(block("latest-ddl").encode())
            connection.execute(block("latest-table").encode())
            connection.commit()
        assert dest.send(batch[6:]) is None, "the newer records, upserted into the table added"
        with server.connect() as connection:
            connection.execute("SET search_path TO added")
            kept = connection.execute(queries()["latest"].encode()).fetchall()
            assert kept == connection.execute(PLAIN_LATEST.encode()).fetchall()
    finally:
        dest.on_deactivate()
    assert [(r, n, d["v"]) for r, n, _, d in kept] == [(f"robot-{r}", m, 3) for r in (1, 2) for m in ("a", "b")]


def test_dc_makes_the_latest_table_as_the_page_shows(filled: PostgresServer) -> None:
    def definitions(connection: Any, table: str, function: str) -> list[str]:
        found = connection.execute(
            "SELECT (SELECT prosrc || array_to_string(proconfig, ',') FROM pg_proc WHERE oid = %s::regproc),"
            " (SELECT pg_get_triggerdef(oid) FROM pg_trigger WHERE tgrelid = %s::regclass AND NOT tgisinternal),"
            " (SELECT array_agg(format_type(atttypid, -1) ORDER BY attnum)::text FROM pg_attribute"
            "   WHERE attrelid = %s::regclass AND attnum > 0),"
            " (SELECT reloptions::text FROM pg_class WHERE oid = %s::regclass)",
            (function, table, f"{table}_latest", f"{table}_latest"),
        ).fetchone()
        # Spacing, quoting and the schema aside (each made where its search_path pointed).
        return [re.sub(r"[\s\"']|public\.|page\.|search_path=.*", "", str(x)).lower() for x in found]

    with filled.connect() as connection:
        made = definitions(connection, "public.dc", "public.dc_keep_latest")
        connection.execute("CREATE SCHEMA page")
        connection.execute("SET search_path TO page")
        connection.execute("CREATE TABLE dc (LIKE public.dc)")
        connection.execute(block("latest-ddl").encode())
        shown = definitions(connection, "page.dc", "page.dc_keep_latest")
        connection.rollback()
    assert made == shown and all(made), made
