"""FilesMetrics against a real PostgreSQL and a real S3 store (SeaweedFS), both started by the tests.

The uploader is played by the tests themselves: they put objects into the buckets with boto3, so
what is checked is FilesMetrics alone — the rows, what `uploaded` and `deleted` mean, when a local
file is deleted, how failures are classified. Each test writes to its own table. The last test
runs the MinIO destination and FilesMetrics together through `dc-bringup`.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from dc_bringup.local_servers.postgres import PostgresServer
from dc_bringup.local_servers.postgres import missing_reason as postgres_missing
from dc_bringup.local_servers.seaweedfs import SeaweedS3Server
from dc_bringup.local_servers.seaweedfs import missing_reason as seaweed_missing
from dc_core.destination import OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.plugins import list_plugins
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.config import parse_destination_server
from dc_destinations.record_ids import new_record_id
from tests.bringup_util import Bringup, dc
from tests.destination_helpers import forwarding_params, running_postgres
from tests.http_receiver import free_port

if postgres_missing() or seaweed_missing():
    pytest.skip(f"no local server: {postgres_missing() or seaweed_missing()}", allow_module_level=True)

import psycopg  # optional dependencies: imported after the skip
from psycopg.rows import dict_row

from dc_destinations.files_metrics import FilesMetrics, FilesMetricsParams
from dc_destinations.files_metrics.table import ADDED_COLUMNS

PASSWORD = "pg-Files-Secret-77"
STAMP_NS = 1_700_000_000_123_456_789
SECOND_BUCKET = "second-bucket"

# The table the original Go plugin created (spec §6.6), verbatim.
ORIGINAL_DDL = """CREATE TABLE {} (id SERIAL PRIMARY KEY, timestamp TIMESTAMP NOT NULL, robot_name TEXT NOT NULL,
    robot_id TEXT NOT NULL, group_name TEXT NOT NULL, duration FLOAT8, local_path TEXT NOT NULL,
    remote_path TEXT NOT NULL, uploaded BOOLEAN NOT NULL, on_filesystem BOOLEAN NOT NULL, deleted BOOLEAN NOT NULL,
    storage_type TEXT NOT NULL, content_type TEXT NOT NULL, size INTEGER NOT NULL, updated_at TIMESTAMP NOT NULL)"""


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresServer]:
    with running_postgres("dc-fm-pg-", PASSWORD) as server:
        yield server


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    server = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    server.start()
    server.client().create_bucket(Bucket=SECOND_BUCKET)
    yield server
    server.stop(timeout=3.0)


@pytest.fixture
def made() -> Iterator[list[FilesMetrics]]:
    plugins: list[FilesMetrics] = []
    yield plugins
    for plugin in plugins:
        plugin.on_deactivate()


def storage(s3: SeaweedS3Server, bucket: str, *fields: str, storage_type: str = "minio") -> dict[str, Any]:
    """A storage section of this store: files at local_paths.<f>, keys at remote_paths.<storage>.<f>."""
    names = fields or ("pgm",)
    return {
        "endpoint": s3.endpoint,
        "access_key_id": s3.access_key,
        "secret_access_key": s3.secret_key,
        "bucket": bucket,
        "src_fields": [f"local_paths.{f}" for f in names],
        "upload_fields": [f"remote_paths.{storage_type}.{f}" for f in names],
    }


def make(
    pg: PostgresServer,
    s3: SeaweedS3Server,
    made: list[FilesMetrics],
    table: str,
    /,
    *,
    logger: RecordingLogger | None = None,
    pgsql: dict[str, Any] | None = None,
    **params: Any,
) -> FilesMetrics:
    settings: dict[str, Any] = {
        "file_storage": ["minio"],
        "minio": storage(s3, s3.bucket),
        "missing_wait": 0.0,
        "allowed_roots": [tempfile.gettempdir()],  # pytest's temporary folders
        "pgsql": {**pg.settings(), "table": table, "connect_timeout": 2, **(pgsql or {})},
        **params,
    }
    context = FakeContext(name="files", logger=logger or RecordingLogger())
    plugin = FilesMetrics(context, parse_params(FilesMetricsParams, settings, "destination_server.files"))
    plugin.on_configure()
    plugin.on_activate()
    made.append(plugin)
    return plugin


MAP = b"P5 2 2 255\n\x00\x01\x02\x03"


def a_file(folder: Path, name: str, content: bytes = MAP) -> Path:
    path = folder / name
    path.write_bytes(content)
    return path


def record(path: Path, key: str, n: int = 0, storages: tuple[str, ...] = ("minio",), **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    body = {
        "name": "map",
        "robot_name": "C3PO",
        "id": "robot-7",
        "local_paths": {"pgm": str(path)},
        "remote_paths": {s: {"pgm": key} for s in storages},
        **data,
        "record_id": rid,
    }
    return OutgoingRecord(rid, "/dc/measurement/map", STAMP_NS + n * 1_000_000_000, body)


def admin(pg: PostgresServer) -> Any:
    return psycopg.connect(
        host="127.0.0.1", port=pg.port, user=pg.user, password=PASSWORD, dbname=pg.database, autocommit=True
    )


def rows(pg: PostgresServer, table: str) -> list[dict[str, Any]]:
    with admin(pg) as connection, connection.cursor(row_factory=dict_row) as cursor:
        return list(cursor.execute(f'SELECT * FROM "{table}" ORDER BY id').fetchall())


def test_a_file_waits_for_its_upload_then_one_row_says_uploaded_and_deleted(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "lifecycle", delete_when_sent=True)
    path = a_file(tmp_path, "2024-05-01T12:00:00.pgm")  # a ':' in the name: the original stored year 1
    batch = [record(path, "C3PO/map/a.pgm")]

    outcome = dest.send(batch)
    assert outcome is not None and not outcome.reject and not outcome.retry, "a wait is no failure"
    assert outcome.waiting[0].startswith("waiting for minio to store C3PO/map/a.pgm: no object")
    (waiting,) = rows(pg, "lifecycle")
    assert (waiting["uploaded"], waiting["on_filesystem"], waiting["deleted"]) == (False, True, False)
    assert waiting["verified_at"] is None and waiting["etag"] is None
    assert path.exists()
    assert dest.send(batch) is not None and len(rows(pg, "lifecycle")) == 1, "a retry adds no row"

    s3.client().upload_file(str(path), s3.bucket, "C3PO/map/a.pgm")
    assert dest.send(batch) is None
    assert not path.exists(), "delete_when_sent: deleted once verified"
    (done,) = rows(pg, "lifecycle")
    assert done["id"] == waiting["id"], "the same row, updated in place"
    assert (done["uploaded"], done["on_filesystem"], done["deleted"], done["ignored"]) == (True, False, True, False)
    assert done["remote_path"] == f"s3://{s3.bucket}/C3PO/map/a.pgm"
    assert (done["storage_type"], done["bucket"], done["local_path"]) == ("minio", s3.bucket, str(path))
    assert (done["robot_name"], done["robot_id"], done["group_name"]) == ("C3PO", "robot-7", "map")
    assert done["size"] == len(MAP)
    assert done["content_type"] == "image/x-portable-graymap"
    assert done["duration"] is None
    assert done["timestamp"].isoformat() == "2023-11-14T22:13:20.123456", "the record's time, UTC"
    assert done["record_id"] == batch[0].record_id
    assert done["etag"] and done["verified_at"] is not None and done["created_at"] <= done["updated_at"]
    assert dest.counters() == {"files_deleted": 1, "files_refused": 0}

    assert dest.send(batch) is None, "retried after the deletion: the object is there, confirmed"
    (again,) = rows(pg, "lifecycle")
    assert (again["id"], again["uploaded"], again["deleted"], again["on_filesystem"]) == (done["id"], True, True, False)
    assert again["size"] == done["size"], "the stored object's size once the local copy is gone"


def test_nothing_is_deleted_until_every_storage_verified_it(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(
        pg,
        s3,
        made,
        "two_storages",
        delete_when_sent=True,
        file_storage=["minio", "s3"],
        s3=storage(s3, SECOND_BUCKET, storage_type="s3"),
    )
    path = a_file(tmp_path, "two.pgm")
    batch = [record(path, "two/map.pgm", storages=("minio", "s3"))]
    s3.client().upload_file(str(path), s3.bucket, "two/map.pgm")

    outcome = dest.send(batch)
    assert outcome is not None and list(outcome.waiting) == [0]
    assert outcome.waiting[0].startswith("waiting for s3 to store two/map.pgm")
    assert path.exists()
    by_storage = {r["storage_type"]: r for r in rows(pg, "two_storages")}
    assert (by_storage["minio"]["uploaded"], by_storage["s3"]["uploaded"]) == (True, False)
    assert by_storage["s3"]["remote_path"] == f"s3://{SECOND_BUCKET}/two/map.pgm"

    s3.client().upload_file(str(path), SECOND_BUCKET, "two/map.pgm")
    assert dest.send(batch) is None
    assert not path.exists()
    got = rows(pg, "two_storages")
    assert len(got) == 2
    assert all(r["uploaded"] and r["deleted"] and not r["on_filesystem"] for r in got)


def test_a_tampered_object_is_not_uploaded(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "tampered", delete_when_sent=True)
    content = b"the real map, 24 bytes.\n"
    path = a_file(tmp_path, "real.pgm", content)
    batch = [record(path, "tampered/real.pgm")]
    client = s3.client()
    for wrong, expected in ((b"short", "holds 5 bytes"), (content.upper(), "differs from")):
        client.put_object(Bucket=s3.bucket, Key="tampered/real.pgm", Body=wrong)
        outcome = dest.send(batch)
        assert outcome is not None and expected in outcome.retry[0], outcome  # a failure, not a wait
        (row,) = rows(pg, "tampered")
        assert not row["uploaded"] and row["on_filesystem"] and path.exists()
    client.put_object(Bucket=s3.bucket, Key="tampered/real.pgm", Body=content)
    assert dest.send(batch) is None
    assert rows(pg, "tampered")[0]["uploaded"] and not path.exists()


def test_the_same_batch_sent_twice_leaves_one_row_per_file(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "twice", delete_when_sent=False)
    batch = []
    for n in range(3):
        path = a_file(tmp_path, f"twice-{n}.pgm", f"map {n}".encode())
        s3.client().upload_file(str(path), s3.bucket, f"twice/{n}.pgm")
        batch.append(record(path, f"twice/{n}.pgm", n))
    assert dest.send(batch) is None
    first = rows(pg, "twice")
    assert dest.send(batch) is None
    second = rows(pg, "twice")
    assert len(second) == 3
    assert [r["id"] for r in second] == [r["id"] for r in first]
    assert all(r["uploaded"] and r["on_filesystem"] and not r["deleted"] for r in second)
    assert all(Path(r["local_path"]).exists() for r in second), "delete_when_sent: false keeps the files"


def test_a_path_with_quotes_and_semicolons_is_stored_literally(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "quoted", delete_when_sent=False)
    name = 'it\'s; DROP TABLE quoted; --"map".pgm'
    path = a_file(tmp_path, name)
    key = "quoted/it's; DROP TABLE quoted;.pgm"
    s3.client().upload_file(str(path), s3.bucket, key)
    assert dest.send([record(path, key, robot_name="O'Brien; --")]) is None
    (row,) = rows(pg, "quoted")
    assert row["local_path"] == str(path)
    assert row["remote_path"] == f"s3://{s3.bucket}/{key}"
    assert row["robot_name"] == "O'Brien; --"
    assert row["uploaded"]


def test_a_missing_file_is_rejected_alone_with_its_path(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "missing", missing_wait=0.3, delete_when_sent=True)
    gone = tmp_path / "never-written.pgm"
    present = a_file(tmp_path, "present.pgm")
    s3.client().upload_file(str(present), s3.bucket, "missing/present.pgm")
    batch = [record(gone, "missing/gone.pgm", 0), record(present, "missing/present.pgm", 1)]
    started = time.monotonic()
    outcome = dest.send(batch)
    assert time.monotonic() - started >= 0.3, "looked for once more after missing_wait"
    assert isinstance(outcome, SendOutcome) and not outcome.retry
    assert list(outcome.reject) == [0]
    assert outcome.reject[0].startswith(f"no file {gone} (local_paths.pgm), and minio does not hold it")
    by_path = {r["local_path"]: r for r in rows(pg, "missing")}
    assert (by_path[str(gone)]["on_filesystem"], by_path[str(gone)]["uploaded"]) == (False, False)
    assert by_path[str(present)]["deleted"] and not present.exists(), "the other record is processed"


def test_a_file_written_during_missing_wait_is_waited_for(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "late", missing_wait=1.0)
    late = tmp_path / "late.pgm"
    writer = threading.Timer(0.3, late.write_bytes, [MAP])
    writer.start()
    try:
        outcome = dest.send([record(late, "late/late.pgm")])
    finally:
        writer.join()
    assert outcome is not None and not outcome.reject
    assert outcome.waiting[0].startswith("waiting for minio to store late/late.pgm")


def test_what_a_record_names_that_is_not_a_file_is_rejected(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "not_files")
    no_key = OutgoingRecord("r1", "/dc/m", STAMP_NS, {"local_paths": {"pgm": str(tmp_path / "x.pgm")}})
    folder = record(tmp_path, "folder.pgm")
    nothing = OutgoingRecord("r3", "/dc/m", STAMP_NS, {"name": "map", "other": 1})
    outcome = dest.send([no_key, folder, nothing])
    assert outcome is not None and not outcome.retry
    assert outcome.reject[0] == f"no object key at remote_paths.minio.pgm for {tmp_path / 'x.pgm'}"
    assert outcome.reject[1] == f"refused: {tmp_path} is not a regular file (local_paths.pgm)"
    assert 2 not in outcome.reject, "a record naming no file has nothing to track: confirmed"


def test_a_file_outside_the_roots_or_linked_from_outside_is_refused_never_deleted(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    root = tmp_path / "data"
    root.mkdir()
    outside = a_file(tmp_path, "id_rsa", b"a private key")
    outside.chmod(0o600)
    os.link(outside, root / "hard.pgm")
    inside = a_file(root, "map.pgm")
    client = s3.client()
    for path, key in ((outside, "loot/id_rsa"), (inside, "roots/map.pgm")):
        client.upload_file(str(path), s3.bucket, key)  # stored intact: only the checks keep it on disk
    dest = make(pg, s3, made, "roots", delete_when_sent=True, allowed_roots=[str(root)])
    batch = [
        record(outside, "loot/id_rsa", 0),
        record(root / "hard.pgm", "loot/id_rsa", 1),
        record(inside, "roots/map.pgm", 2),
    ]
    outcome = dest.send(batch)
    assert outcome is not None and not outcome.retry
    assert outcome.reject == {
        0: f"refused: {outside} is outside allowed_roots ({root}) (local_paths.pgm)",
        1: f"refused: {root / 'hard.pgm'} has 2 hard links: it may be a file from elsewhere (local_paths.pgm)",
    }
    assert outside.read_bytes() == b"a private key" and (root / "hard.pgm").exists()
    assert not inside.exists(), "the file inside the roots: deleted once verified, as before"
    assert [r["local_path"] for r in rows(pg, "roots")] == [str(inside)], "no row for what was refused"
    counters = dest.counters()
    assert counters == {"files_deleted": 1, "files_refused": 2}
    assert (len(batch) - len(outcome.reject)) + counters["files_refused"] == len(batch)


def test_absent_robot_fields_are_empty_and_timestamp_key_sets_the_time(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    dest = make(pg, s3, made, "anonymous", pgsql={"timestamp_key": "date"}, delete_when_sent=False)
    path = a_file(tmp_path, "anon.pgm")
    s3.client().upload_file(str(path), s3.bucket, "anon.pgm")
    bare = OutgoingRecord(
        "r1", "/dc/m", STAMP_NS, {"local_paths": {"pgm": str(path)}, "remote_paths": {"minio": {"pgm": "anon.pgm"}},
                                  "date": 1677668906.5}
    )  # fmt: skip
    assert dest.send([bare]) is None
    (row,) = rows(pg, "anonymous")
    assert (row["robot_name"], row["robot_id"], row["group_name"]) == ("", "", "")
    assert row["timestamp"].isoformat() == "2023-03-01T11:08:26.500000"


def test_two_robots_saving_the_same_path_keep_a_row_each_in_a_bigint_table(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    # The default paths hold no robot name: two robots saving in the same second name the same file.
    dest = make(pg, s3, made, "two_robots")
    path = a_file(tmp_path, "same.pgm")
    s3.client().upload_file(str(path), s3.bucket, "C3PO/same.pgm")
    s3.client().upload_file(str(path), s3.bucket, "R2D2/same.pgm")
    batch = [record(path, "C3PO/same.pgm"), record(path, "R2D2/same.pgm", robot_name="R2D2")]
    assert dest.send(batch) is None and dest.send(batch) is None
    got = rows(pg, "two_robots")
    assert [(r["robot_name"], r["remote_path"]) for r in got] == [
        ("C3PO", f"s3://{s3.bucket}/C3PO/same.pgm"),
        ("R2D2", f"s3://{s3.bucket}/R2D2/same.pgm"),
    ]
    with admin(pg) as connection:
        kinds = dict(
            connection.execute(
                "SELECT attname::text, format_type(atttypid, atttypmod) || ' ' || attidentity::text"
                " FROM pg_attribute WHERE attrelid = 'two_robots'::regclass AND attname = 'id'"
            ).fetchall()
        )
        clocks = dict(
            connection.execute(
                "SELECT attname::text, col_description(attrelid, attnum) FROM pg_attribute"
                " WHERE attrelid = 'two_robots'::regclass AND col_description(attrelid, attnum) IS NOT NULL"
            ).fetchall()
        )
    assert kinds == {"id": "bigint d"}, "a 64-bit identity (generated by default)"
    assert clocks["timestamp"].startswith("record time, UTC")
    assert {clocks[c].split(":")[0] for c in ("created_at", "updated_at", "verified_at")} == {"wall time, UTC"}


def test_a_table_made_by_the_original_is_upgraded_and_used(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    with admin(pg) as connection:
        connection.execute(ORIGINAL_DDL.format("legacy"))
        connection.execute(
            "INSERT INTO legacy (timestamp, robot_name, robot_id, group_name, local_path, remote_path, uploaded,"
            " on_filesystem, deleted, storage_type, content_type, size, updated_at)"
            " VALUES (now(), 'R2D2', 'r2', 'map', '/old/map.pgm', 'minio://b/old', true, false, true, 'minio',"
            " 'image/x-portable-graymap', 10, now())"
        )
    logger = RecordingLogger()
    dest = make(pg, s3, made, "legacy", logger=logger, delete_when_sent=True)
    path = a_file(tmp_path, "legacy.pgm")
    s3.client().upload_file(str(path), s3.bucket, "legacy/new.pgm")
    batch = [record(path, "legacy/new.pgm")]
    assert dest.send(batch) is None and dest.send(batch) is None
    old, new = rows(pg, "legacy")
    assert old["robot_name"] == "R2D2" and old["created_at"] is None and old["ignored"] is False
    assert new["uploaded"] and new["deleted"] and new["record_id"] == batch[0].record_id
    assert set(ADDED_COLUMNS) <= set(new)
    assert any(m.startswith("upgraded table legacy (made by the original plugin): added columns ignored,")
               for m in logger.at("info"))  # fmt: skip


def test_duplicates_left_by_the_original_are_named_with_what_to_clean(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    with admin(pg) as connection:
        connection.execute(ORIGINAL_DDL.format("doubled"))
        for _ in range(2):  # the original inserted a row again at every retry
            connection.execute(
                "INSERT INTO doubled (timestamp, robot_name, robot_id, group_name, local_path, remote_path,"
                " uploaded, on_filesystem, deleted, storage_type, content_type, size, updated_at) VALUES (now(),"
                " 'R2D2', 'r2', 'map', '/old/a.pgm', 'minio://b/a', false, true, false, 'minio', 'x', 1, now())"
            )
    dest = make(pg, s3, made, "doubled")
    path = a_file(tmp_path, "doubled.pgm")
    with pytest.raises(RetryableError) as caught:
        dest.send([record(path, "doubled.pgm")])
    message = str(caught.value)
    assert "table doubled holds several rows for the same (local_path, storage_type)" in message
    assert "DELETE FROM doubled a USING doubled b WHERE a.local_path = b.local_path" in message
    with admin(pg) as connection:
        connection.execute(message.split("e.g. ", 1)[1].split(";", 1)[0])
    s3.client().upload_file(str(path), s3.bucket, "doubled.pgm")
    assert dest.send([record(path, "doubled.pgm")]) is None
    assert len(rows(pg, "doubled")) == 2


def test_a_video_gets_its_duration_from_ffprobe(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    if shutil.which("ffmpeg") is None or shutil.which("ffprobe") is None:
        pytest.skip("ffmpeg is not installed (apt install ffmpeg)")
    video = tmp_path / "clip.mp4"
    subprocess.run(
        ["ffmpeg", "-v", "error", "-f", "lavfi", "-i", "testsrc=duration=1:size=64x48:rate=10",
         "-pix_fmt", "yuv420p", str(video)],
        check=True, timeout=60,
    )  # fmt: skip
    dest = make(pg, s3, made, "videos", delete_when_sent=False)
    s3.client().upload_file(str(video), s3.bucket, "videos/clip.mp4")
    assert dest.send([record(video, "videos/clip.mp4")]) is None
    (row,) = rows(pg, "videos")
    assert row["content_type"] == "video/mp4"
    assert row["duration"] == pytest.approx(1.0, abs=0.05)
    assert row["size"] == video.stat().st_size


def test_without_ffprobe_a_video_has_no_duration_and_one_warning(
    pg: PostgresServer,
    s3: SeaweedS3Server,
    made: list[FilesMetrics],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    logger = RecordingLogger()
    dest = make(pg, s3, made, "no_ffprobe", logger=logger)
    batch = []
    for n in range(2):
        video = a_file(tmp_path, f"v{n}.mp4", b"not really a video")
        s3.client().upload_file(str(video), s3.bucket, f"nf/v{n}.mp4")
        batch.append(record(video, f"nf/v{n}.mp4", n))
    assert dest.send(batch) is None
    assert [r["duration"] for r in rows(pg, "no_ffprobe")] == [None, None]
    assert [m for m in logger.at("warning") if "ffprobe" in m] == [
        "ffprobe not found (apt install ffmpeg): videos are recorded without duration"
    ]


def test_wrong_password_is_retryable_and_no_secret_is_shown(
    pg: PostgresServer,
    s3: SeaweedS3Server,
    made: list[FilesMetrics],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_files_metrics.secret")
    wrong = make(pg, s3, made, "secret", logger=logger, pgsql={"password": "not-" + PASSWORD})
    path = a_file(tmp_path, "secret.pgm")
    s3.client().upload_file(str(path), s3.bucket, "secret.pgm")
    with pytest.raises(RetryableError) as caught:
        wrong.send([record(path, "secret.pgm")])
    message = str(caught.value)
    assert message.startswith(f"cannot connect to PostgreSQL postgresql://dc@127.0.0.1:{pg.port}/dc: ")
    assert message.endswith("(check `user` and `password`)")
    assert path.exists(), "nothing deleted while the table cannot say so"
    right = make(pg, s3, made, "secret", logger=logger)
    assert right.send([record(path, "secret.pgm")]) is None
    texts = [message, repr(wrong), repr(wrong.params), str(right.params), repr(right.params.pgsql)]
    texts += [repr(right.params.minio), repr(right), repr(pg), repr(s3)]
    texts += [r.getMessage() for r in caplog.records] + [m for _, m in logger.lines]
    assert any("connected to" in t for t in texts)
    for text in texts:
        assert PASSWORD not in text, text
        assert s3.secret_key not in text, text
    secrets = {p.name for p in describe_params(FilesMetricsParams) if p.secret}
    assert secrets == {"minio.secret_access_key", "s3.secret_access_key", "pgsql.password"}


def test_an_unreachable_store_retries_the_batch_and_writes_nothing(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    port = free_port()
    section = {**storage(s3, s3.bucket), "endpoint": f"http://127.0.0.1:{port}"}
    dest = make(pg, s3, made, "unreachable", minio=section)
    path = a_file(tmp_path, "unreachable.pgm")
    with pytest.raises(RetryableError, match=rf"cannot reach bucket {s3.bucket} at http://127.0.0.1:{port}"):
        dest.send([record(path, "u.pgm")])
    assert path.exists()
    with admin(pg) as connection:
        assert connection.execute("SELECT to_regclass('unreachable')").fetchone() == (None,)


def test_a_postgresql_restart_between_batches_is_survived(
    pg: PostgresServer, s3: SeaweedS3Server, made: list[FilesMetrics], tmp_path: Path
) -> None:
    logger = RecordingLogger()
    dest = make(pg, s3, made, "restart", logger=logger, delete_when_sent=False)
    batch = []
    for n in range(3):
        path = a_file(tmp_path, f"restart-{n}.pgm", f"{n}".encode())
        s3.client().upload_file(str(path), s3.bucket, f"restart/{n}.pgm")
        batch.append(record(path, f"restart/{n}.pgm", n))
    assert dest.send(batch[:1]) is None
    pg.stop()
    try:
        with pytest.raises(RetryableError, match="cannot connect to PostgreSQL"):
            dest.send(batch[1:2])
    finally:
        pg.start()
    assert dest.send(batch[1:2]) is None
    pg.stop()
    pg.start()
    assert dest.send(batch[2:]) is None, "the kept connection died with the server: a new one, at once"
    assert len(rows(pg, "restart")) == 3
    assert len([m for m in logger.at("info") if m.startswith("connected to")]) == 3


# -- configuration ------------------------------------------------------------------------------------

SEED = """
destination_server:
  ros__parameters:
    destination_plugins: ["flb_files_metrics"]
    flb_files_metrics:
      plugin: "dc_destinations/FlbFilesMetrics"
      inputs: ["/dc/measurement/map"]
      file_storage: ["minio", "s3"]
      db_type: "pgsql"
      debug: true
      delete_when_sent: true
      plugin_path: "/opt/dc/lib/out_files_metrics.so"
      minio:
        endpoint: 127.0.0.1:9000
        access_key_id: "minioadmin"
        secret_access_key: "minio-Secret-1"
        use_ssl: false
        bucket: "mybucket"
        src_fields: ["local_paths.pgm", "local_paths.yaml"]
        upload_fields: ["remote_paths.minio.pgm", "remote_paths.minio.yaml"]
        input_names: ["map", "map"]
      s3:
        endpoint: "s3.eu-west-1.amazonaws.com"
        access_key_id: "AKIAEXAMPLE"
        secret_access_key: "s3-Secret-2"
        bucket: "robot-files"
        src_fields: ["local_paths.pgm"]
        upload_fields: ["remote_paths.s3.pgm"]
      pgsql:
        host: "127.0.0.1"
        port: "5432"
        user: fluentbit
        password: password
        database: "fluentbit"
        table: "files_metrics"
        timestamp_key: "date"
        time_format: "double"
        time_key: "date"
        ssl: false
"""


def seed_section() -> dict[str, Any]:
    section: dict[str, Any] = yaml.safe_load(SEED)["destination_server"]["ros__parameters"]
    return section


def configure(section: dict[str, Any]) -> FilesMetrics:
    (d,) = parse_destination_server(section).destinations
    plugin: FilesMetrics = d.plugin_class(FakeContext(name=d.name), d.plugin_params)
    plugin.on_configure()
    return plugin


def test_the_seed_configuration_is_accepted_as_it_is() -> None:
    plugin = configure(seed_section())
    p = plugin.params
    assert p.file_storage == ["minio", "s3"] and p.delete_when_sent
    assert (p.pgsql.port, p.pgsql.table, p.pgsql.timestamp_key) == ("5432", "files_metrics", "date")
    assert plugin.address == "postgresql://fluentbit@127.0.0.1:5432/fluentbit"
    assert p.minio.input_names == ["map", "map"] and not p.minio.use_ssl
    assert p.s3.use_ssl and p.s3.region == "us-east-1"
    shown = repr(p)
    for secret in ("minio-Secret-1", "s3-Secret-2", "password="):
        assert secret not in shown
    names = {info.name for info in list_plugins("destinations")}
    assert {"dc_destinations/FilesMetrics", "dc_destinations/FlbFilesMetrics"} <= names


def test_defaults() -> None:
    section = {"bucket": "files", "src_fields": ["local_paths.pgm"], "upload_fields": ["remote_paths.s3.pgm"]}
    p = parse_params(FilesMetricsParams, {"file_storage": ["s3"], "s3": section}, "x")
    assert (p.db_type, p.delete_when_sent, p.missing_wait) == ("pgsql", False, 1.0)
    assert (p.allowed_roots, p.key_prefix) == ([], "")
    assert (p.pgsql.host, p.pgsql.port, p.pgsql.table, p.pgsql.user, p.pgsql.database) == (
        "127.0.0.1", 5432, "files_metrics", "", ""
    )  # fmt: skip
    assert p.s3.endpoint == "", "an s3 section without endpoint is AWS"
    assert p.pgsql.server().sslmode == "prefer"


def _without(section: dict[str, Any], key: str) -> dict[str, Any]:
    body = dict(section["flb_files_metrics"])
    body.pop(key)
    return {**section, "flb_files_metrics": body}


def _with(**changes: Any) -> dict[str, Any]:
    section = seed_section()
    body = {**section["flb_files_metrics"], **changes}
    return {**section, "flb_files_metrics": body}


PATH = "destination_server.flb_files_metrics"


@pytest.mark.parametrize(
    ("section", "message"),
    [
        (_with(file_storage=[]), f'{PATH}.file_storage: expected a non-empty list of "minio" and "s3"'),
        (_with(file_storage=["minio", "ftp"]), f'{PATH}.file_storage: expected a non-empty list of "minio" and "s3"'),
        (_with(file_storage=["s3", "s3"]), f"{PATH}.file_storage: expected a non-empty list"),
        (_without(seed_section(), "file_storage"), f"{PATH}.file_storage: required parameter missing"),
        (_without(_with(file_storage=["minio", "s3"]), "s3"), f'{PATH}.s3: section missing: file_storage lists "s3"'),
        (_with(file_storage=["minio"]), f'{PATH}.s3: "s3" is not in file_storage: add it there, or remove the section'),
        (_with(db_type="mysql"), f'{PATH}.db_type: expected one of "pgsql", got "mysql"'),
        (_with(pgsql={"port": "fifty"}), f'{PATH}.pgsql.port: expected a TCP port from 1 to 65535, got "fifty"'),
        (_with(pgsql={"tabel": "x"}), f'{PATH}.pgsql.tabel: unknown parameter (did you mean "table"?)'),
        (
            _with(minio={"src_fields": ["a", "b"], "upload_fields": ["c"]}),
            f"{PATH}.minio.upload_fields: expected one entry",
        ),
        (
            _with(s3={"bucket": "files", "src_fields": [], "upload_fields": []}),
            f"{PATH}.s3.src_fields: expected at least one field",
        ),
        (
            _with(minio={"bucket": "dc_bucket", "src_fields": ["a"], "upload_fields": ["b"]}),
            f"{PATH}.minio.bucket: expected a bucket name",
        ),
    ],
)
def test_configuration_errors_name_the_key(section: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(section)
    assert message in str(caught.value)


# -- end to end through dc-bringup --------------------------------------------------------------------


def uploader_and_metrics_params(tmp_path: Path, pg: PostgresServer, s3: SeaweedS3Server, table: str) -> Path:
    """dc-bringup parameters: records of /map-files to MinIO and FilesMetrics (table ``table``)."""
    if "dc_destinations/MinIO" not in {info.name for info in list_plugins("destinations")}:
        pytest.skip("the MinIO destination is not installed")
    store = storage(s3, s3.bucket)
    roots = {"allowed_roots": [str(tmp_path)]}
    uploader = {"plugin": "dc_destinations/MinIO", **store, **roots, "complete_after": 0.2}
    params = forwarding_params(tmp_path, "flb_minio", uploader, measurement="map", topic="/map-files")
    document = yaml.safe_load(params.read_text())
    destinations = document["destination_server"]["ros__parameters"]
    destinations["destination_plugins"].append("flb_files_metrics")
    destinations["flb_files_metrics"] = {
        "plugin": "dc_destinations/FlbFilesMetrics",
        "inputs": ["/dc/measurement/map"],
        "file_storage": ["minio"],
        "delete_when_sent": True,
        **roots,
        "minio": store,
        "pgsql": {**pg.settings(), "table": table, "connect_timeout": 2},
    }
    document["measurement_server"]["ros__parameters"]["map"]["tags"] = ["flb_minio", "flb_files_metrics"]
    params.write_text(yaml.safe_dump(document, sort_keys=False))
    return params


def map_record(path: Path, key: str) -> str:
    """A record as `dc pub` takes it: a map file at ``path`` going to ``key``."""
    body = f'{{"robot_name": "C3PO", "id": "r1", "local_paths": {{"pgm": "{path}"}},'
    return body + f' "remote_paths": {{"minio": {{"pgm": "{key}"}}}}}}'


@pytest.mark.e2e
def test_e2e_minio_uploads_files_metrics_records_and_deletes(
    tmp_path: Path, pg: PostgresServer, s3: SeaweedS3Server
) -> None:
    params = uploader_and_metrics_params(tmp_path, pg, s3, "e2e")
    path = a_file(tmp_path, "e2e-map.pgm", os.urandom(3000))
    content = path.read_bytes()

    def settled() -> bool:
        try:
            got = rows(pg, "e2e")
        except psycopg.Error:
            return False
        return len(got) == 1 and bool(got[0]["deleted"])

    with Bringup(params, tmp_path / "home") as run:
        run.wait_ready()
        published = dc("pub", "/map-files", map_record(path, "e2e/map.pgm"), "--count", "1", env=run.env)
        assert published.returncode == 0, published.stderr
        run.wait_until(settled, 30, "the file's row uploaded and deleted")
        stderr = "\n".join(run.stderr)
    assert s3.objects("e2e/") == {"e2e/map.pgm": content}
    (row,) = rows(pg, "e2e")
    assert (row["uploaded"], row["deleted"], row["on_filesystem"]) == (True, True, False)
    assert (row["group_name"], row["robot_name"], row["size"]) == ("map", "C3PO", 3000)
    assert not path.exists()
    assert PASSWORD not in stderr and s3.secret_key not in stderr


OUTAGE_S = 30.0


@pytest.mark.e2e
def test_e2e_a_30_s_database_outage_loses_no_row_and_deletes_nothing_unrecorded(
    tmp_path: Path, s3: SeaweedS3Server
) -> None:
    with running_postgres("dc-fm-outage-", PASSWORD) as pg:
        files = [a_file(tmp_path, f"outage-{i:02d}.pgm", os.urandom(2000 + i)) for i in range(10)]

        def recorded() -> list[dict[str, Any]]:
            try:
                return [row for row in rows(pg, "outage") if row["deleted"]]
            except psycopg.Error:
                return []

        def publish(paths: list[Path]) -> None:
            lines = "".join(map_record(path, f"outage/{path.name}") + "\n" for path in paths)
            published = dc("pub", "/map-files", "-", "--rate", "0", env=run.env, stdin=lines)
            assert published.returncode == 0, published.stderr

        with Bringup(uploader_and_metrics_params(tmp_path, pg, s3, "outage"), tmp_path / "home") as run:
            run.wait_ready()
            publish(files[:3])
            run.wait_until(lambda: len(recorded()) == 3, 30, "the first files recorded and deleted")
            pg.stop()
            down_at = time.monotonic()
            publish(files[3:])  # stored by MinIO meanwhile, but neither recorded nor deleted
            run.wait_until(lambda: s3.objects("outage/").keys() >= {f"outage/{p.name}" for p in files}, 30,
                           "every file in the bucket during the outage")  # fmt: skip
            assert all(path.exists() for path in files[3:]), "a file deleted while its row could not be written"
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts 30 s
            pg.start()  # the same data folder, port and password
            run.wait_until(lambda: len(recorded()) == len(files), 60, f"all {len(files)} files after the outage")
        stored = rows(pg, "outage")

    assert sorted(row["local_path"] for row in stored) == sorted(str(p) for p in files), "one row per file"
    assert all(row["uploaded"] and row["deleted"] and not row["on_filesystem"] for row in stored)
    assert not any(path.exists() for path in files)
