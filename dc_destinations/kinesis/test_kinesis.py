"""Kinesis Streams destination against moto_server, a mock of the AWS APIs on a loopback port.

AWS itself cannot be reached from here: moto_server (the `moto[server]` test dependency) answers the
Kinesis and STS APIs as AWS documents them, keeps the streams in memory and accepts any credentials.
Each test module starts its own moto_server on a free port and resets it between tests. What moto
does not do — refuse some records of a PutRecords request — is simulated with botocore's Stubber.
The end-to-end tests run dc-bringup with records published by `dc pub`, and stop moto_server for
30 s in the middle of the stream.
"""

from __future__ import annotations

import json
import logging
import signal
import socket
import subprocess
import time
import urllib.request
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import boto3
import pytest
from botocore.stub import ANY, Stubber

from dc_core.destination import OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.config import parse_destination_server
from dc_destinations.kinesis import MAX_RECORD_BYTES, KinesisParams, KinesisStreams
from dc_destinations.record_ids import new_record_id
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import forwarding_params
from tests.http_receiver import free_port

REGION = "eu-west-1"
KEY_ID = "AKIAIOSFODNN7EXAMPLE"
SECRET = "wJalrXUtnFEMI/K7MDENG/bPxRfiCYEXAMPLEKEY"


class Moto:
    """A moto_server process on 127.0.0.1: started, stopped and started again on the same port."""

    def __init__(self, port: int | None = None) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> Moto:
        self.process = subprocess.Popen(
            [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(self.port)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        # Ready when it accepts connections: about 0.5 s, over 20 s at load 15 (moto imports a lot).
        deadline = time.monotonic() + 90
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    exited = self.process.poll()
                    raise RuntimeError(
                        f"moto_server did not start on port {self.port}"
                        + (f" (exited with {exited})" if exited is not None else " within 90 s")
                    ) from None
                time.sleep(0.05)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None

    def reset(self) -> None:
        urllib.request.urlopen(urllib.request.Request(f"{self.url}/moto-api/reset", method="POST"), timeout=5).close()

    def client(self, service: str = "kinesis") -> Any:
        return boto3.client(
            service, endpoint_url=self.url, region_name=REGION, aws_access_key_id="test", aws_secret_access_key="test"
        )

    def create_stream(self, name: str = "robots", shards: int = 1) -> None:
        client = self.client()
        client.create_stream(StreamName=name, ShardCount=shards)
        client.get_waiter("stream_exists").wait(StreamName=name, WaiterConfig={"Delay": 0.1, "MaxAttempts": 50})

    def read(self, name: str = "robots") -> list[dict[str, Any]]:
        """Every record of the stream, in order within each shard (shard after shard)."""
        client = self.client()
        out = []
        for shard in client.list_shards(StreamName=name)["Shards"]:
            iterator = client.get_shard_iterator(
                StreamName=name, ShardId=shard["ShardId"], ShardIteratorType="TRIM_HORIZON"
            )["ShardIterator"]
            while iterator:
                page = client.get_records(ShardIterator=iterator, Limit=10000)
                out.extend(page["Records"])
                if not page["Records"]:
                    break
                iterator = page.get("NextShardIterator")
        return out


@pytest.fixture(scope="module")
def moto_server() -> Iterator[Moto]:
    server = Moto().start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def moto(moto_server: Moto) -> Moto:
    moto_server.reset()
    moto_server.create_stream("robots", shards=2)
    return moto_server


def kinesis(moto: Moto, name: str = "stream", logger: Any = None, **params: Any) -> KinesisStreams:
    values = {
        "stream": "robots",
        "region": REGION,
        "endpoint": moto.url,
        "aws_access_key_id": KEY_ID,
        "aws_secret_access_key": SECRET,
        "timeout": 2.0,
        **params,
    }
    context = FakeContext(name=name) if logger is None else FakeContext(name=name, logger=logger)
    plugin = KinesisStreams(context, parse_params(KinesisParams, values, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def record(n: int, name: str = "uptime", **extra: Any) -> OutgoingRecord:
    rid = new_record_id()
    data = {"date": 1_700_000_000.0 + n, "seq": n, "name": name, "record_id": rid, **extra}
    return OutgoingRecord(rid, f"/dc/measurement/{name}", 1_700_000_000_000_000_000 + n * 1_000_000, data)


def payloads(moto: Moto, name: str = "robots") -> list[dict[str, Any]]:
    return [json.loads(r["Data"]) for r in moto.read(name)]


def count_put_records(dest: KinesisStreams) -> list[int]:
    """Records per PutRecords request the destination makes from now on."""
    sizes: list[int] = []

    def seen(params: dict[str, Any], **kwargs: Any) -> None:
        sizes.append(len(params["Records"]))

    dest._client.meta.events.register("provide-client-params.kinesis.PutRecords", seen)
    return sizes


# -- delivery ------------------------------------------------------------------------------------------


def test_records_arrive_in_order_per_partition_key(moto: Moto) -> None:
    dest = kinesis(moto)
    names = ["uptime", "memory", "cpu", "battery"]
    batch = [record(n, names[n % 4]) for n in range(40)]
    assert dest.send(batch[:25]) is None
    assert dest.send(batch[25:]) is None
    stored = moto.read()
    assert len(stored) == 40
    by_key: dict[str, list[int]] = defaultdict(list)
    for item in stored:
        body = json.loads(item["Data"])
        assert item["PartitionKey"] == body["name"], "default partition key: the measurement's name"
        by_key[item["PartitionKey"]].append(body["seq"])
    assert set(by_key) == set(names)
    for name, seqs in by_key.items():
        assert seqs == sorted(seqs), f"{name}: records of one key keep their order in their shard"
    first = next(r for r in stored if json.loads(r["Data"])["seq"] == 0)
    assert first["Data"] == (batch[0].to_json() + "\n").encode(), "the record's JSON text, one line"


def test_partition_key_template_and_record_id_fallback(moto: Moto) -> None:
    dest = kinesis(moto, partition_key="{robot}/{name}")
    with_robot, without = record(1, robot="c3po"), record(2)
    assert dest.send([with_robot, without]) is None
    keys = {json.loads(r["Data"])["seq"]: r["PartitionKey"] for r in moto.read()}
    assert keys == {1: "c3po/uptime", 2: without.record_id}, "a missing key spreads by record_id"
    kinesis(moto, partition_key="{record_id}").send([with_robot])
    assert with_robot.record_id in {r["PartitionKey"] for r in moto.read()}


def test_a_batch_of_1200_records_goes_in_three_put_records_requests(moto: Moto) -> None:
    dest = kinesis(moto)
    sizes = count_put_records(dest)
    batch = [record(n, "bulk") for n in range(1200)]
    assert dest.send(batch) is None
    assert sizes == [500, 500, 200]
    assert [p["seq"] for p in payloads(moto)] == list(range(1200))


def test_requests_stay_under_five_megabytes(moto: Moto) -> None:
    dest = kinesis(moto)
    sizes = count_put_records(dest)
    batch = [record(n, "blob", pad="x" * 600_000) for n in range(12)]
    assert dest.send(batch) is None
    assert sizes == [8, 4], "8 of 600 kB fit in 5 MiB, 9 do not"
    assert len(moto.read()) == 12


def test_a_record_over_one_megabyte_is_rejected_alone(moto: Moto) -> None:
    dest = kinesis(moto)
    big = record(1, "camera", image="x" * MAX_RECORD_BYTES)
    outcome = dest.send([record(0), big, record(2)])
    assert isinstance(outcome, SendOutcome) and not outcome.retry
    assert list(outcome.reject) == [1]
    assert "above Kinesis' 1048576" in outcome.reject[1] and "stream robots" in outcome.reject[1]
    assert sorted(p["seq"] for p in payloads(moto)) == [0, 2]


def test_the_one_megabyte_limit_counts_the_partition_key(moto: Moto) -> None:
    dest = kinesis(moto)
    probe = record(0, "edge", pad="")
    overhead = len(probe.to_json()) + 1 + len("edge")  # JSON, newline, partition key
    exact = record(0, "edge", pad="x" * (MAX_RECORD_BYTES - overhead))
    over = record(1, "edge", pad="x" * (MAX_RECORD_BYTES - overhead + 1))
    assert len(exact.to_json()) == len(over.to_json()) - 1
    outcome = dest.send([exact, over])
    assert isinstance(outcome, SendOutcome) and list(outcome.reject) == [1] and not outcome.retry
    assert len(moto.read()) == 1


def test_log_key_sends_only_that_value_and_rejects_records_without_it(moto: Moto) -> None:
    dest = kinesis(moto, log_key="message")
    batch = [record(0, message="dock reached"), record(1), record(2, message={"code": 7})]
    outcome = dest.send(batch)
    assert isinstance(outcome, SendOutcome) and list(outcome.reject) == [1]
    assert "no key 'message' (log_key)" in outcome.reject[1]
    assert [r["Data"] for r in moto.read()] == [b"dock reached\n", b'{"code":7}\n']


def test_time_key_format_rewrites_the_time_key(moto: Moto) -> None:
    dest = kinesis(moto, time_key_format="%Y-%m-%dT%H:%M:%S.%3N")
    one = record(0)
    stamped = OutgoingRecord(one.record_id, one.topic, 1_700_000_000_123_456_789, one.data)
    dest.send([stamped])
    (body,) = payloads(moto)
    assert body["date"] == "2023-11-14T22:13:20.123"
    assert one.data["date"] == 1_700_000_000.0, "the record itself is left unchanged"


# -- failures ------------------------------------------------------------------------------------------


def test_only_the_records_the_service_failed_are_retried(moto: Moto) -> None:
    # moto accepts every record; a partial failure is simulated with botocore's Stubber.
    dest = kinesis(moto)
    batch = [record(n) for n in range(4)]
    with Stubber(dest._client) as stub:
        stub.add_response(
            "put_records",
            {
                "FailedRecordCount": 2,
                "Records": [
                    {"SequenceNumber": "1", "ShardId": "shardId-000000000000"},
                    {"ErrorCode": "ProvisionedThroughputExceededException", "ErrorMessage": "Rate exceeded for shard"},
                    {"SequenceNumber": "2", "ShardId": "shardId-000000000000"},
                    {"ErrorCode": "InternalFailure", "ErrorMessage": "Internal service failure."},
                ],
            },
            {"StreamName": "robots", "Records": ANY},
        )
        outcome = dest.send(batch)
    assert isinstance(outcome, SendOutcome) and not outcome.reject
    assert sorted(outcome.retry) == [1, 3]
    assert outcome.retry[1].startswith("ProvisionedThroughputExceededException: Rate exceeded for shard")
    assert outcome.retry[3].startswith("InternalFailure")
    # The sender sends the retried records again: now moto takes them.
    assert dest.send([batch[1], batch[3]]) is None
    assert sorted(p["seq"] for p in payloads(moto)) == [1, 3]


def test_a_failed_request_retries_its_records_and_the_later_ones_only(moto: Moto) -> None:
    dest = kinesis(moto)
    batch = [record(n) for n in range(1100)]
    accepted = {"Records": [{"SequenceNumber": "1", "ShardId": "shardId-0"}] * 500}
    with Stubber(dest._client) as stub:
        stub.add_response("put_records", accepted, {"StreamName": "robots", "Records": ANY})
        stub.add_client_error("put_records", "LimitExceededException", "Rate exceeded", 400)
        outcome = dest.send(batch)
    assert isinstance(outcome, SendOutcome) and not outcome.reject
    assert sorted(outcome.retry) == list(range(500, 1100)), "the first 500 were confirmed"
    assert "LimitExceededException: Rate exceeded (stream robots in eu-west-1" in outcome.retry[500]


def test_a_stream_that_does_not_exist_is_retried_with_a_clear_message(moto: Moto) -> None:
    logger = RecordingLogger("test_kinesis.missing")
    dest = kinesis(moto, stream="robts", logger=logger)
    for _ in range(3):
        with pytest.raises(RetryableError) as caught:
            dest.send([record(0)])
    message = str(caught.value)
    assert message.startswith(f"no stream robts in {REGION} at {moto.url}: create it or correct `stream` / `region`")
    assert logger.at("error") == [message], "logged once when it starts, not on every retry"
    moto.create_stream("robts")
    assert dest.send([record(1)]) is None, "fixed by an operator: the records go"
    assert logger.at("info")[-1].endswith("records accepted again")


def test_the_region_is_used(moto: Moto) -> None:
    # The original never passed `region` on; a stream of another region is another stream.
    with pytest.raises(RetryableError, match="no stream robots in us-west-2"):
        kinesis(moto, region="us-west-2").send([record(0)])


def test_unreachable_endpoint_is_retryable() -> None:
    port = free_port()
    dest = kinesis(Moto(port), timeout=1.0)
    started = time.monotonic()
    with pytest.raises(RetryableError, match=f"cannot reach Kinesis for stream robots in {REGION}"):
        dest.send([record(0)])
    assert time.monotonic() - started < 10


def test_refused_credentials_are_retryable_and_named(moto: Moto) -> None:
    dest = kinesis(moto)
    with Stubber(dest._client) as stub:
        stub.add_client_error("put_records", "UnrecognizedClientException", "The security token is invalid.", 400)
        with pytest.raises(RetryableError) as caught:
            dest.send([record(0)])
    assert str(caught.value).startswith("AWS refused the credentials for stream robots in eu-west-1")


def test_the_secret_key_is_never_in_logs_errors_or_repr(moto: Moto, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_kinesis.secret")
    texts: list[str] = []
    for dest in (kinesis(moto, stream="nope", logger=logger), kinesis(Moto(free_port()), logger=logger)):
        with pytest.raises(RetryableError) as caught:
            dest.send([record(0)])
        texts += [str(caught.value), repr(dest.params), str(dest.params), repr(dest)]
    with Stubber(dest._client) as stub:
        stub.add_client_error("put_records", "AccessDeniedException", f"denied for {SECRET}", 400)
        with pytest.raises(RetryableError) as caught:
            dest.send([record(0)])
    texts.append(str(caught.value))
    with pytest.raises(ConfigError) as config_error:
        parse_params(KinesisParams, {"stream": "s", "aws_secret_access_key": SECRET}, "d")
    texts.append(str(config_error.value))
    texts += [message for _, message in logger.lines] + [r.getMessage() for r in caplog.records]
    assert any("no stream nope" in t for t in texts) and any("***" in t for t in texts)
    for text in texts:
        assert SECRET not in text, text
    assert {p.name for p in describe_params(KinesisParams) if p.secret} == {"aws_secret_access_key"}


def test_role_arn_is_assumed_through_sts(moto: Moto) -> None:
    dest = kinesis(
        moto,
        role_arn="arn:aws:iam::123456789012:role/dc-writer",
        external_id="fleet-7",
        sts_endpoint=moto.url,
    )
    assert dest.send([record(0)]) is None
    used = dest._client._request_signer._credentials.get_frozen_credentials()
    assert used.access_key != KEY_ID and used.token, "the role's temporary credentials sign the puts"
    assert len(moto.read()) == 1


def test_default_credentials_chain(moto: Moto, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "from-the-environment")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "env-secret")
    dest = kinesis(moto, aws_access_key_id="", aws_secret_access_key="")
    assert dest.send([record(0)]) is None
    assert dest._client._request_signer._credentials.access_key == "from-the-environment"


def test_auto_retry_requests_sets_one_immediate_retry(moto: Moto) -> None:
    assert kinesis(moto)._client.meta.config.retries["total_max_attempts"] == 2
    assert kinesis(moto, auto_retry_requests="false")._client.meta.config.retries["total_max_attempts"] == 1


# -- configuration -------------------------------------------------------------------------------------


def configure(body: dict[str, Any]) -> None:
    section = {
        "destination_plugins": ["k"],
        "k": {"plugin": "dc_destinations/KinesisStreams", "inputs": ["/x"], **body},
    }
    (d,) = parse_destination_server(section).destinations
    d.plugin_class(FakeContext(name=d.name), d.plugin_params).on_configure()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({}, "destination_server.k.stream: required parameter missing"),
        ({"stream": "my stream"}, "destination_server.k.stream: expected a stream name"),
        ({"stream": "s", "region": "Europe"}, "destination_server.k.region: expected an AWS region"),
        ({"stream": "s", "partition_key": "{a.b}"}, "destination_server.k.partition_key: expected a template"),
        ({"stream": "s", "partition_key": ""}, "destination_server.k.partition_key: expected a non-empty template"),
        ({"stream": "s", "aws_access_key_id": "A"}, "destination_server.k.aws_secret_access_key: set"),
        ({"stream": "s", "external_id": "abc"}, "destination_server.k.external_id: set role_arn too"),
        ({"stream": "s", "role_arn": "dc-writer"}, "destination_server.k.role_arn: expected an IAM role ARN"),
        ({"stream": "s", "timeout": 0}, "destination_server.k.timeout: expected a number >= 0.1"),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)


def test_the_originals_keys_are_accepted() -> None:
    configure(
        {
            "plugin": "dc_destinations/FlbKinesisStreams",
            "region": "eu-west-1",
            "stream": "dc",
            "role_arn": "arn:aws:iam::123456789012:role/dc",
            "time_key": "date",
            "time_key_format": "%Y-%m-%dT%H:%M:%S",
            "log_key": "",
            "endpoint": "kinesis.eu-west-1.amazonaws.com",
            "auto_retry_requests": "true",  # a string in the original
        }
    )


def test_stream_arn_is_accepted() -> None:
    configure({"stream": "arn:aws:kinesis:eu-west-1:123456789012:stream/robots"})


# -- end to end through dc-bringup -----------------------------------------------------------------


def bringup_params(tmp_path: Path, moto: Moto) -> Path:
    settings = {"plugin": "dc_destinations/KinesisStreams", "region": REGION, "stream": "robots", "endpoint": moto.url}
    return forwarding_params(tmp_path, "kinesis", {**settings, "timeout": 2.0})


def aws_env() -> dict[str, str]:
    """Credentials for boto3's default chain in dc-bringup: the environment, as on a robot."""
    return {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing-secret"}


def publish(run: Bringup, record: dict[str, Any], count: int, rate: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [str(BIN / "dc"), "pub", "/robot/events", json.dumps(record), "--count", str(count), "--rate", str(rate)],
        env=run.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def record_ids(moto: Moto, phase: int) -> set[str]:
    return {p["record_id"] for p in payloads(moto) if p.get("phase") == phase}


def wait_for(check: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.3)


@pytest.fixture
def own_moto() -> Iterator[Moto]:
    server = Moto().start()
    try:
        yield server
    finally:
        server.stop()


@pytest.mark.e2e
def test_e2e_published_records_reach_the_stream(tmp_path: Path, own_moto: Moto) -> None:
    own_moto.create_stream("robots")
    with Bringup(bringup_params(tmp_path, own_moto), tmp_path / "home", env=aws_env()) as run:
        run.wait_ready()
        published = dc(
            "pub", "/robot/events", '{"phase": 1, "event": "dock"}', "--count", "5", "--rate", "10", env=run.env
        )
        assert published.returncode == 0, published.stderr
        wait_for(lambda: len(record_ids(own_moto, 1)) == 5, 30, "5 records in the stream")
    stored = own_moto.read()
    assert {r["PartitionKey"] for r in stored} == {"events"}
    body = json.loads(stored[0]["Data"])
    assert body["event"] == "dock" and body["name"] == "events" and "date" in body
    assert "testing-secret" not in "\n".join(run.stderr)


@pytest.mark.e2e
def test_e2e_every_record_arrives_after_a_30_s_outage(tmp_path: Path, own_moto: Moto) -> None:
    own_moto.create_stream("robots")
    with Bringup(bringup_params(tmp_path, own_moto), tmp_path / "home", env=aws_env()) as run:
        run.wait_ready()
        # Before the outage: delivered and read back while moto still holds them (it forgets on stop).
        before = dc("pub", "/robot/events", '{"phase": 1}', "--count", "10", "--rate", "20", env=run.env)
        assert before.returncode == 0, before.stderr
        wait_for(lambda: len(record_ids(own_moto, 1)) == 10, 30, "the first 10 records in the stream")

        own_moto.stop()
        down_at = time.monotonic()
        # 70 records over 35 s: 60 published while the service is down, 10 after it is back.
        publisher = publish(run, {"phase": 2}, count=70, rate=2)
        time.sleep(max(0.0, down_at + 30 - time.monotonic()))
        own_moto.start()
        own_moto.create_stream("robots")  # moto's state was lost with the process
        output, _ = publisher.communicate(timeout=30)
        assert publisher.returncode == 0, output
        wait_for(lambda: len(record_ids(own_moto, 2)) == 70, 30, "all 70 records after the outage")
        stderr = "\n".join(run.stderr)
    assert f"cannot reach Kinesis for stream robots in {REGION}" in stderr
    assert "testing-secret" not in stderr
    assert all(json.loads(r["Data"])["name"] == "events" for r in own_moto.read())
