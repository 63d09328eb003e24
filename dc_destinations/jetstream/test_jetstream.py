"""NATS destination against a real nats-server with JetStream started by the tests on loopback.

One server for the module (tests/nats_server.py), with a user and a password and a small
max_payload; each test uses a stream of its own. The outage test stops that server and starts it
again on the same port and store. The records go through DC's real sender and buffer where the
test is about delivery (counted outcomes), straight to ``send`` where it is about one answer.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.nats_server import missing_reason

if missing_reason() is not None:
    pytest.skip(str(missing_reason()), allow_module_level=True)

from dc_bringup.local_servers.nats import NatsCluster
from dc_core.destination import ConfigurationProblem, OutgoingRecord, RetryableError
from dc_core.errors import ConfigError, PluginError
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.jetstream import Nats, NatsParams
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.nats_server import NatsServer, read_stream, stream_leader

USER, PASSWORD = "robot", "n4ts-s3cret"
MAX_PAYLOAD = 4096


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[NatsServer]:
    config = f"max_payload: {MAX_PAYLOAD}\nauthorization {{ user: {USER}, password: {PASSWORD} }}"
    with NatsServer(tmp_path_factory.mktemp("nats"), config=config) as s:
        yield s


def destination(server_urls: list[str], stream: str, logger: RecordingLogger | None = None, **params: Any) -> Nats:
    settings: dict[str, Any] = {
        "servers": server_urls,
        "stream": stream,
        "stream_subjects": [f"{stream.lower()}.>"],
        "subject": stream.lower() + ".{robot_name}.{name}",
        "create_stream": True,
        "username": USER,
        "password": PASSWORD,
        "connect_timeout": 2.0,
        "publish_timeout": 5.0,
        **params,
    }
    context = FakeContext(name="fleet", logger=logger or RecordingLogger())
    plugin = Nats(context, parse_params(NatsParams, settings, "destination_server.fleet"))
    plugin.on_configure()
    return plugin


def record(n: int, **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    fields = {"name": "uptime", "robot_name": "C3PO", "seq": n, **data, "record_id": rid}
    return OutgoingRecord(rid, "/dc/measurement/uptime", 1_700_000_000_000_000_000 + n, fields)


def stored(server: NatsServer, stream: str) -> list[Any]:
    return read_stream([server.url], stream, user=USER, password=PASSWORD)


class Pipeline:
    """DC's real delivery pipeline (SQLite buffer, sender, backoff) around one destination."""

    def __init__(self, tmp_path: Path, dest: Nats, unhealthy_after: float = 0.0) -> None:
        self.dest = dest
        settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=0.3)
        delivery = DestinationDeliveryParams(unhealthy_after=unhealthy_after)
        self.pipeline = DeliveryPipeline(settings, {"fleet": (dest, delivery)}, logging.getLogger("tests.nats"))
        dest.on_activate()
        self.pipeline.start()

    def submit(self, records: list[OutgoingRecord]) -> None:
        for r in records:
            self.pipeline.submit("fleet", r)

    def metrics(self) -> dict[str, Any]:
        return dict(self.pipeline.metrics()["fleet"])

    def wait(self, condition: Any, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while not condition(self.metrics()) and time.monotonic() < deadline:
            time.sleep(0.05)
        metrics = self.metrics()
        assert condition(metrics), metrics
        return metrics

    def stop(self) -> None:
        self.pipeline.stop(1.0)
        self.dest.on_deactivate()


def test_every_record_stored_once_under_its_record_id(server: NatsServer, tmp_path: Path) -> None:
    dest = destination([server.url], "ONCE")
    records = [record(n, name="uptime" if n % 2 else "cpu") for n in range(300)]
    pipeline = Pipeline(tmp_path, dest)
    try:
        pipeline.submit(records)
        metrics = pipeline.wait(lambda m: m["sent"] == 300 and m["buffered"] == 0)
    finally:
        pipeline.stop()
    assert metrics["dead_lettered"] == 0
    messages = stored(server, "ONCE")
    assert [m.msg_id for m in messages] == [r.record_id for r in records], (
        "in order, each once, Nats-Msg-Id = record_id"
    )
    assert [m.data.decode() for m in messages] == [r.to_json() for r in records], "the record's JSON"
    assert {m.subject for m in messages} == {"once.C3PO.uptime", "once.C3PO.cpu"}

    # The same records sent again (a lost ack, a crash before the buffer's delete): stored once.
    again = destination([server.url], "ONCE")
    try:
        assert again.send(records[:50]) is None, "acknowledged as duplicates"
    finally:
        again.on_deactivate()
    assert len(stored(server, "ONCE")) == 300


def test_a_server_outage_loses_nothing_and_stores_nothing_twice(server: NatsServer, tmp_path: Path) -> None:
    dest = destination([server.url], "OUTAGE")
    pipeline = Pipeline(tmp_path, dest)
    sent: list[OutgoingRecord] = []
    stop = threading.Event()

    def produce() -> None:  # a robot's measurements go on through the outage: 200 records/s
        n = 0
        while not stop.is_set() and n < 600:
            batch = [record(n + i) for i in range(10)]
            sent.extend(batch)
            pipeline.submit(batch)
            n += 10
            stop.wait(0.05)

    producer = threading.Thread(target=produce)
    producer.start()
    try:
        pipeline.wait(lambda m: m["sent"] >= 100)
        server.stop()
        pipeline.wait(lambda m: m["retried"] > 0 and m["buffered"] > 0, timeout=15)
        time.sleep(1.0)  # the outage lasts: records pile up in the buffer
        server.start()
        producer.join(30)
        assert not producer.is_alive()
        metrics = pipeline.wait(lambda m: m["sent"] + m["dead_lettered"] == len(sent) and m["buffered"] == 0)
    finally:
        stop.set()
        producer.join()
        if not server.running():
            server.start()
        pipeline.stop()
    assert metrics["dead_lettered"] == 0 and metrics["dropped"] == 0
    assert metrics["sent"] + metrics["dead_lettered"] + metrics["dropped"] == len(sent), "delivered + counted = sent"
    ids = [m.msg_id for m in stored(server, "OUTAGE")]
    assert sorted(ids) == sorted(r.record_id for r in sent), "every record stored, none twice"


def test_wrong_credentials_fail_at_once_with_the_password_masked(server: NatsServer, tmp_path: Path) -> None:
    logger = RecordingLogger()
    dest = destination([server.url], "CREDS", logger, password="wrong-" + PASSWORD, create_stream=True)
    with pytest.raises(ConfigurationProblem) as raised:
        dest.send([record(0)])
    assert "Authorization Violation" in str(raised.value)
    assert "check username and password" in raised.value.fix
    pipeline = Pipeline(tmp_path, destination([server.url], "CREDS", logger, password="wrong-" + PASSWORD))
    try:
        pipeline.submit([record(1), record(2)])
        metrics = pipeline.wait(lambda m: m["health"]["state"] == "failing")
    finally:
        pipeline.stop()
    assert metrics["buffered"] == 2 and metrics["sent"] == 0, "the records wait for the credentials to be fixed"
    everything = json.dumps(metrics) + str(raised.value) + json.dumps(logger.lines)
    assert "wrong-" + PASSWORD not in everything and PASSWORD not in everything


def test_a_record_over_max_payload_and_one_without_the_subject_key_are_dead_lettered_alone(
    server: NatsServer, tmp_path: Path
) -> None:
    records = [record(0), record(1, blob="x" * (MAX_PAYLOAD + 100)), record(2), record(3), record(4)]
    del records[3].data["robot_name"]
    dest = destination([server.url], "BAD")
    outcome = dest.send(records)
    dest.on_deactivate()
    assert outcome is not None and not outcome.retry
    assert set(outcome.reject) == {1, 3}
    assert f"over the server's max_payload of {MAX_PAYLOAD} bytes" in outcome.reject[1]
    assert outcome.reject[3] == "the record has no 'robot_name' for the subject template 'bad.{robot_name}.{name}'"
    assert [m.msg_id for m in stored(server, "BAD")] == [records[i].record_id for i in (0, 2, 4)]

    # Through the buffer: counted as dead letters, the sum holds.
    more = [record(10), record(11, blob="y" * (MAX_PAYLOAD * 2)), record(12)]
    del more[2].data["name"]
    pipeline = Pipeline(tmp_path, destination([server.url], "BAD"))
    try:
        pipeline.submit(more)
        metrics = pipeline.wait(lambda m: m["sent"] + m["dead_lettered"] == 3)
    finally:
        pipeline.stop()
    assert (metrics["sent"], metrics["dead_lettered"]) == (1, 2)


def test_a_missing_stream_is_a_configure_error_naming_it(server: NatsServer) -> None:
    with pytest.raises(PluginError, match=r"stream 'NOPE' does not exist on nats://127\.0\.0\.1:.*create_stream: true"):
        destination([server.url], "NOPE", create_stream=False)
    probed = destination([server.url], "PROBED")
    first = probed.probe()
    assert first.ok and first.reason.endswith("stream PROBED is created at the first batch"), first
    assert probed.send([record(0)]) is None
    probed.on_deactivate()
    again = probed.probe()
    assert again.ok and "stream PROBED: subjects probed.>, 1 replica(s), duplicate window 120 s" in again.reason


def test_a_server_down_at_configure_leaves_the_stream_check_to_the_first_batch(tmp_path: Path) -> None:
    logger = RecordingLogger()
    down = NatsServer(tmp_path / "down")  # configured, never started
    dest = destination([down.url], "LATER", logger, create_stream=False)
    assert any("checked at the first batch" in m for m in logger.at("info"))
    with pytest.raises(RetryableError, match=f"cannot connect to {down.url}"):
        dest.send([record(0)])
    with down, pytest.raises(ConfigurationProblem, match="stream 'LATER' does not exist"):
        dest.send([record(0)])
    dest.on_cleanup()


@pytest.mark.parametrize(
    ("settings", "error"),
    [
        ({"subject": "dc.*.{name}"}, "destination_server.fleet.subject: expected a subject without the wildcards"),
        ({"subject": "dc..{name}"}, "destination_server.fleet.subject: expected a subject of non-empty tokens"),
        ({"subject": "dc.{}"}, "destination_server.fleet.subject: expected placeholders that name a record key"),
        (
            {"servers": ["nats://u:p@h:4222"]},
            "destination_server.fleet.servers: expected no credentials in a server URL",
        ),
        (
            {"servers": ["http://h:4222"]},
            "destination_server.fleet.servers: expected server URLs like nats://host:4222",
        ),
        ({"password": "x"}, "destination_server.fleet.password: set username too"),
        ({"username": "a", "token": "t"}, "destination_server.fleet.token: one way to authenticate"),
    ],
)
def test_settings_refused_at_configure_with_their_yaml_path(settings: dict[str, Any], error: str) -> None:
    with pytest.raises(ConfigError) as raised:
        parse_params(NatsParams, settings, "destination_server.fleet")
    assert str(raised.value).startswith(error)


def test_a_three_node_cluster_keeps_every_record_once_when_the_leader_is_killed(tmp_path: Path) -> None:
    """R3 stream; the node leading it killed with -9 while records flow at ~500/s; then a second node
    killed (no quorum): the records wait, the destination is failing, and all arrive once both are back."""
    cluster = NatsCluster(tmp_path / "cluster")
    cluster.start()
    try:
        dest = destination(cluster.urls, "FLEET", stream_replicas=3, username="", password="", publish_timeout=2.0)
        pipeline = Pipeline(tmp_path / "buffer", dest, unhealthy_after=1.0)
        sent: list[OutgoingRecord] = []
        try:
            killed = ""
            for second in range(40):  # up to 4 s at 500 records/s
                batch = [record(second * 50 + i) for i in range(50)]
                sent.extend(batch)
                pipeline.submit(batch)
                if second == 10:
                    pipeline.wait(lambda m: m["sent"] >= 300)
                    killed = stream_leader(cluster.urls, "FLEET")
                    cluster.node(killed).stop(kill=True)
                time.sleep(0.1)
            pipeline.wait(lambda m: m["sent"] == len(sent) and m["buffered"] == 0, timeout=60)

            next(n for n in cluster.nodes if n.running()).stop(kill=True)  # one node left: no quorum
            late = [record(10_000 + i) for i in range(20)]
            sent.extend(late)
            pipeline.submit(late)
            failing = pipeline.wait(lambda m: m["health"]["state"] == "failing", timeout=30)
            assert failing["buffered"] == 20 and failing["retried"] > 0
            for node in cluster.nodes:
                if not node.running():
                    node.start()
            metrics = pipeline.wait(lambda m: m["sent"] == len(sent) and m["buffered"] == 0, timeout=60)
        finally:
            pipeline.stop()
        assert killed
        ids = [m.msg_id for m in read_stream(cluster.urls, "FLEET")]
        assert metrics["dead_lettered"] == 0
        assert sorted(ids) == sorted(r.record_id for r in sent), "every record stored, none twice"
    finally:
        cluster.stop()


def test_an_nkey_seed_file_and_a_token_authenticate_and_a_wrong_token_is_masked(tmp_path: Path) -> None:
    import nkeys

    seed = nkeys.encode_seed(os.urandom(32), nkeys.PREFIX_BYTE_USER)
    public = nkeys.from_seed(bytearray(seed)).public_key.decode()
    seed_file = tmp_path / "robot.nk"
    seed_file.write_bytes(seed)
    unsigned: dict[str, Any] = {"username": "", "password": ""}
    with NatsServer(tmp_path / "nkey", config=f"authorization {{ users: [ {{ nkey: {public} }} ] }}") as server:
        dest = destination([server.url], "SIGNED", nkey_seed_file=str(seed_file), **unsigned)
        assert dest.send([record(0)]) is None, "the seed signed the server's nonce"
        dest.on_cleanup()
        assert len(read_stream([server.url], "SIGNED", nkeys_seed=str(seed_file))) == 1

    token = "t0ken-s3cret-42"
    with NatsServer(tmp_path / "token", config=f"authorization {{ token: {token} }}") as server:
        dest = destination([server.url], "TOKEN", token=token, **unsigned)
        assert dest.send([record(0)]) is None
        dest.on_cleanup()
        logger = RecordingLogger()
        wrong = destination([server.url], "TOKEN", logger, token="wrong-" + token, **unsigned)
        with pytest.raises(ConfigurationProblem) as raised:
            wrong.send([record(1)])
        wrong.on_cleanup()
    assert "refused the connection" in str(raised.value)
    assert token not in str(raised.value) + json.dumps(logger.lines)


@pytest.mark.parametrize(
    "hub_down",
    [
        False,
        pytest.param(
            True,
            marks=pytest.mark.skipif(
                not os.environ.get("DC_SLOW_TESTS"),
                reason="~40 s: the hub's source retries with a backoff after a restart (DC_SLOW_TESTS=1 runs it)",
            ),
        ),
    ],
)
def test_a_leaf_node_on_the_robot_stores_and_forwards(tmp_path: Path, hub_down: bool) -> None:
    """The edge option of docs/fleet.md: DC publishes into a JetStream leaf node on the robot (its own
    domain); the hub's stream sources the robot's; with ``hub_down``, the hub stopped meanwhile loses nothing."""
    import asyncio

    from nats.js.api import ExternalStream, StreamSource

    from dc_bringup.local_servers.processes import free_port

    leaf_port = free_port()
    hub = NatsServer(
        tmp_path / "hub", name="hub", jetstream="domain: hub", config=f"leafnodes {{ listen: 127.0.0.1:{leaf_port} }}"
    )
    remote = f'leafnodes {{ remotes: [ {{ url: "nats-leaf://127.0.0.1:{leaf_port}" }} ] }}'
    robot = NatsServer(tmp_path / "robot", name="robot1", jetstream="domain: robot1", config=remote)

    async def hub_stream_sourcing_the_robot() -> None:
        import nats

        nc = await nats.connect(hub.url)
        try:
            source = StreamSource(name="ROBOT", external=ExternalStream(api="$JS.robot1.API"))
            await nc.jetstream().add_stream(name="FLEET", sources=[source])
        finally:
            await nc.close()

    with hub, robot:
        dest = destination([robot.url], "ROBOT", stream_subjects=["dc.>"], subject="dc.{robot_name}.{name}")
        sent = [record(n) for n in range(100)]
        assert dest.send(sent[:1]) is None  # the robot's stream made, then the fleet's sourcing it
        asyncio.run(hub_stream_sourcing_the_robot())
        deadline = time.monotonic() + 30
        while len(read_stream([hub.url], "FLEET")) < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(read_stream([hub.url], "FLEET")) == 1, "the fleet's stream sources the robot's"
        if hub_down:
            hub.stop()  # the link, or the data centre, is down
        assert dest.send(sent[1:]) is None, "acknowledged by the robot's own stream"
        dest.on_cleanup()
        if hub_down:
            hub.start()
        deadline = time.monotonic() + 90
        while len(stored := read_stream([hub.url], "FLEET")) < 100 and time.monotonic() < deadline:
            time.sleep(0.1)
    assert sorted(m.msg_id for m in stored) == sorted(r.record_id for r in sent)
