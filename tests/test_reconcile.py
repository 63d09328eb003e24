"""``dc reconcile`` against a real PostgreSQL and SeaweedFS: the orphans between the bucket (objects uploaded
by the MinIO destination, so carrying DC's x-amz-meta-dc-*), the records table and files_metrics, and --repair."""

from __future__ import annotations

import datetime as dt
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from psycopg.types.json import Jsonb

from dc_bringup.cli import main
from dc_bringup.local_servers.postgres import PostgresServer
from dc_bringup.local_servers.postgres import missing_reason as postgres_missing
from dc_bringup.local_servers.run import environment
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_bringup.local_servers.seaweedfs import missing_reason as seaweed_missing
from dc_core.destination import OutgoingRecord
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_dashboard.settings import PostgresSettings
from dc_destinations.files_metrics.table import FileRow, FilesTable
from dc_destinations.minio import MinIO, MinIOParams
from dc_destinations.record_ids import new_record_id
from tests.destination_helpers import running_postgres

pytestmark = pytest.mark.skipif(
    bool(postgres_missing() or seaweed_missing()), reason=str(postgres_missing() or seaweed_missing())
)


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresServer]:
    with running_postgres("dc-reconcile-pg-") as server:
        yield server


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    server = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    server.start()
    yield server
    server.stop(timeout=3.0)


def connect(pg: PostgresServer) -> Any:
    import psycopg

    s = pg.settings()
    where = PostgresSettings(str(s["host"]), int(s["port"]), str(s["user"]), str(s["password"]), str(s["database"]))
    return psycopg.connect(**where.connect_kwargs())


def upload(s3: SeaweedS3Server, tmp_path: Path, robot: str, name: str) -> tuple[str, str]:
    """A file uploaded by the MinIO destination for a record of ``robot``: (record id, key)."""
    path = tmp_path / name
    path.write_bytes(b"P5 " + name.encode())
    settings = {
        "endpoint": s3.endpoint,
        "access_key_id": s3.access_key,
        "secret_access_key": s3.settings()["aws_secret_access_key"],
        "bucket": s3.bucket,
        "region": "us-east-1",
        "src_fields": ["local_paths.pgm"],
        "upload_fields": ["remote_paths.minio.pgm"],
        "allowed_roots": [str(tmp_path)],
        "complete_after": 0.0,
    }
    minio = MinIO(FakeContext(name="minio", logger=RecordingLogger()), parse_params(MinIOParams, settings, "minio"))
    minio.on_configure()
    record_id, key = new_record_id(), f"{robot}/{name}"
    data = {
        "name": "map",
        "robot_name": robot,
        "local_paths": {"pgm": str(path)},
        "remote_paths": {"minio": {"pgm": key}},
    }
    assert minio.send([OutgoingRecord(record_id, "/dc/measurement/map", time.time_ns(), data)]) is None
    return record_id, key


def reconcile(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict[str, Any]]:
    code = main(["reconcile", "--robot", "c3po", "--json", *args])
    return code, json.loads(capsys.readouterr().out)


def test_reconcile_lists_the_three_kinds_of_orphans_of_one_robot_and_repairs_the_uploaded_flag(
    pg: PostgresServer,
    s3: SeaweedS3Server,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    for name, value in environment({"postgres": pg.settings(), "s3": s3.settings()}).items():
        monkeypatch.setenv(name, value)
    now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    kept_id, kept_key = upload(s3, tmp_path, "c3po", "kept.pgm")  # everywhere: no orphan
    lost_id, lost_key = upload(s3, tmp_path, "c3po", "lost.pgm")  # its record dead-lettered by PgSQL
    upload(s3, tmp_path, "r2d2", "other.pgm")  # another robot's: not this reconcile's business
    files = FilesTable("files_metrics")
    with connect(pg) as connection:
        connection.execute(
            "CREATE TABLE dc (tag varchar, time timestamp, data jsonb, record_id text)"
        )  # the original's
        files.prepare(connection)
        for rid, key in ((kept_id, kept_key), (new_record_id(), "c3po/never-uploaded.pgm")):
            data = {"name": "map", "robot_name": "c3po", "remote_paths": {"minio": {"pgm": key}}}
            connection.execute("INSERT INTO dc VALUES ('map', %s, %s, %s)", (now, Jsonb(data), rid))
        for rid, key in ((kept_id, kept_key), (new_record_id(), "c3po/gone.pgm")):
            row = FileRow(
                now,
                "c3po",
                "",
                "map",
                None,
                f"/data/{key}",
                key,
                True,
                False,
                "minio",
                "image/x-portable-graymap",
                4,
                rid,
                s3.bucket,
                None,
            )
            connection.execute(files.upsert, row.values())
    since = (now - dt.timedelta(minutes=5)).isoformat()

    code, report = reconcile(capsys, "--since", since)
    assert code == 1, "orphans found: a cron job sees it in the exit status"
    assert report["checked"] == {"records": 2, "files_metrics_rows": 2, "objects": 3}
    assert report["objects_without_row"] == [{"key": lost_key, "record_id": lost_id}]
    assert [o["key"] for o in report["rows_without_object"]] == ["c3po/never-uploaded.pgm"]
    assert [o["key"] for o in report["uploaded_but_missing"]] == ["c3po/gone.pgm"]
    assert report["repaired"] == 0, "nothing changes without --repair"

    code, report = reconcile(capsys, "--since", since, "--repair")
    assert report["repaired"] == 1
    with connect(pg) as connection:
        uploaded = dict(connection.execute("SELECT remote_path, uploaded FROM files_metrics").fetchall())
    assert uploaded == {kept_key: True, "c3po/gone.pgm": False}
    code, report = reconcile(capsys, "--since", since)
    assert report["uploaded_but_missing"] == [] and len(report["objects_without_row"]) == 1, "the rest only listed"

    code, report = reconcile(capsys, "--since", since, "--files-table", "no_files_metrics_here")
    assert report["checked"]["files_metrics_rows"] == 0 and report["uploaded_but_missing"] == [], "no FilesMetrics"
    assert [o["key"] for o in report["rows_without_object"]] == ["c3po/never-uploaded.pgm"]
    code, report = reconcile(capsys, "--since", (now + dt.timedelta(minutes=5)).isoformat())
    assert code == 0, "nothing in a later range"
    assert report["objects_without_row"] == report["rows_without_object"] == report["uploaded_but_missing"] == []


def test_a_time_that_is_not_iso_8601_is_refused_before_any_store_is_read(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["reconcile", "--robot", "c3po", "--since", "yesterday"])
    assert exited.value.code == 2
    assert "argument --since: invalid ISO 8601 time value: 'yesterday'" in capsys.readouterr().err


def test_a_table_dc_made_is_read_through_its_robot_index_with_the_same_records(pg: PostgresServer) -> None:
    from psycopg import sql

    from dc_bringup.reconcile import _records_query
    from dc_destinations.pgsql.table import create_typed

    now = dt.datetime.now(dt.UTC)
    window = {"robot": "c3po", "since": now - dt.timedelta(minutes=5), "until": now}
    with connect(pg) as connection:
        create_typed(connection, sql.Identifier("typed_dc"), "typed_dc", "none", latest=False)
        rows = [  # (robot, name, seconds before now)
            ("c3po", "map", 60), ("c3po", "cpu", 30), ("c3po", None, 10),  # in the range
            ("c3po", "map", 600), ("c3po", "cpu", 0), ("r2d2", "map", 60),  # before it, at its end, another robot
        ]  # fmt: skip
        for robot, name, ago in rows:
            data = {"name": name, "robot_name": robot}
            connection.execute(
                "INSERT INTO typed_dc (time, data, record_id, name, robot_name) VALUES (%s, %s, %s, %s, %s)",
                (now - dt.timedelta(seconds=ago), Jsonb(data), new_record_id(), name, robot),
            )
        connection.execute("SET enable_seqscan = off")  # a tiny table: see whether the index serves the query
        typed = _records_query(connection, "typed_dc")
        found = sorted(rid for rid, _ in connection.execute(typed, window).fetchall())
        plan = str(connection.execute(sql.SQL("EXPLAIN ") + typed, window).fetchall())
        original_shape = sql.SQL(
            "SELECT record_id FROM typed_dc WHERE time >= %(since)s AND time < %(until)s AND data->>'robot_name' = %(robot)s"
        )
        expected = sorted(rid for (rid,) in connection.execute(original_shape, window).fetchall())
    assert len(found) == 3 and found == expected
    assert "typed_dc_robot_name_time" in plan and "Seq Scan" not in plan, plan
