"""MQTT destination against a real mosquitto started by the tests: what reaches a subscriber, how failures are classified.

The broker runs on a free loopback port (tests/mqtt_broker.py); a paho subscriber in the test reads
what the destination publishes. The last two tests go through `dc-bringup` with real processes.
"""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dc_core.destination import OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.config import parse_destination_server
from dc_destinations.mqtt import Mqtt, MqttParams, default_client_id
from dc_destinations.record_ids import new_record_id
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import forwarding_params, through_pipeline, tls_refused
from tests.http_receiver import free_port
from tests.mqtt_broker import MOSQUITTO_PASSWD, Broker, Subscriber, missing_reason
from tests.tls_pki import KEY_PASSWORD, Pki, make_pki

if missing_reason() is not None:
    pytest.skip(str(missing_reason()), allow_module_level=True)


def mqtt_destination(name: str = "fleet", logger: RecordingLogger | None = None, **params: Any) -> Mqtt:
    context = FakeContext(name=name, logger=logger or RecordingLogger())
    plugin = Mqtt(context, parse_params(MqttParams, params, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    with Broker(tmp_path / "broker") as b:
        yield b


@pytest.fixture
def destinations() -> Iterator[list[Mqtt]]:
    """Destinations a test made, disconnected at its end (their paho threads stopped)."""
    made: list[Mqtt] = []
    yield made
    for d in made:
        d.on_deactivate()


def record(n: int, **data: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(
        rid, "/dc/measurement/test", 1_700_000_000_000_000_000 + n, {"seq": n, **data, "record_id": rid}
    )


def test_records_arrive_on_their_templated_topics_with_qos_1(broker: Broker, destinations: list[Mqtt]) -> None:
    batch = [record(0, name="uptime", robot="c3po"), record(1, name="memory", robot="r2d2", note="üñí")]
    with Subscriber(broker.port, "dc/#") as subscriber:
        dest = mqtt_destination(port=broker.port, topic="dc/{robot}/{name}")
        destinations.append(dest)
        assert dest.send(batch) is None, "both acknowledged by the broker"
        messages = subscriber.wait_for(2)
    assert [m.topic for m in messages] == ["dc/c3po/uptime", "dc/r2d2/memory"]
    assert [m.payload.decode("utf-8") for m in messages] == [r.to_json() for r in batch], "the record's JSON, UTF-8"
    assert [m.qos for m in messages] == [1, 1]
    assert not any(m.retain for m in messages)


@pytest.mark.parametrize("qos", [0, 2])
def test_qos_0_and_2_deliver(broker: Broker, destinations: list[Mqtt], qos: int) -> None:
    with Subscriber(broker.port, "dc/#", qos=2) as subscriber:
        dest = mqtt_destination(port=broker.port, qos=qos)
        destinations.append(dest)
        batch = [record(i, name="seq") for i in range(50)]
        assert dest.send(batch) is None
        messages = subscriber.wait_for(50)
    assert [json.loads(m.payload)["seq"] for m in messages] == list(range(50))
    assert {m.qos for m in messages} == {qos}
    assert {m.topic for m in messages} == {"dc/seq"}


def test_retain_keeps_the_last_record_for_later_subscribers(broker: Broker, destinations: list[Mqtt]) -> None:
    dest = mqtt_destination(port=broker.port, retain=True, topic="robots/{robot}/state")
    destinations.append(dest)
    assert dest.send([record(0, robot="c3po"), record(1, robot="c3po")]) is None
    with Subscriber(broker.port, "robots/#") as late:  # subscribes after the publication
        (message,) = late.wait_for(1)
    assert message.retain and json.loads(message.payload)["seq"] == 1


def test_a_record_without_a_template_key_is_rejected_alone(broker: Broker, destinations: list[Mqtt]) -> None:
    batch = [
        record(0, name="a", robot="c3po"),
        record(1, name="b"),  # no robot
        record(2, name="c", robot={"id": 7}),  # not text
        record(3, name="d", robot="bb+8"),  # a wildcard in a published topic is a protocol error
        record(4, name="e", robot=8),
    ]
    with Subscriber(broker.port, "dc/#") as subscriber:
        dest = mqtt_destination(port=broker.port, topic="dc/{robot}/{name}")
        destinations.append(dest)
        outcome = dest.send(batch)
        messages = subscriber.wait_for(2)
    assert isinstance(outcome, SendOutcome) and not outcome.retry
    assert sorted(outcome.reject) == [1, 2, 3]
    assert outcome.reject[1] == "the record has no 'robot' for the topic template 'dc/{robot}/{name}'"
    assert "not text or a number" in outcome.reject[2]
    assert "wildcard" in outcome.reject[3]
    assert [m.topic for m in messages] == ["dc/c3po/a", "dc/8/e"]


def test_a_batch_of_only_rejected_records_does_not_connect(destinations: list[Mqtt]) -> None:
    dest = mqtt_destination(port=free_port(), topic="dc/{robot}")  # nothing listens there
    destinations.append(dest)
    outcome = dest.send([record(0)])
    assert outcome is not None and list(outcome.reject) == [0] and not outcome.retry


def test_an_unreachable_broker_is_retryable_with_its_address(destinations: list[Mqtt]) -> None:
    port = free_port()
    dest = mqtt_destination(port=port, connect_timeout=2)
    destinations.append(dest)
    with pytest.raises(RetryableError) as caught:
        dest.send([record(0, name="x")])
    message = str(caught.value)
    assert message.startswith(f"cannot connect to MQTT broker mqtt://127.0.0.1:{port}: ")
    assert "refused" in message.lower()


PASSWORD = "hunter2-Very-Secret"


@pytest.mark.skipif(MOSQUITTO_PASSWD is None, reason="mosquitto_passwd (package mosquitto) is not installed")
def test_wrong_password_is_retryable_names_the_reason_and_never_the_password(
    tmp_path: Path, destinations: list[Mqtt], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    logger = RecordingLogger("test_mqtt.secret")
    texts: list[str] = []
    with Broker(tmp_path / "auth", users={"robot": PASSWORD}) as broker:
        wrong = mqtt_destination(port=broker.port, username="robot", password="not-" + PASSWORD, logger=logger)
        anonymous = mqtt_destination(port=broker.port, logger=logger)
        right = mqtt_destination(port=broker.port, username="robot", password=PASSWORD, logger=logger)
        destinations.extend([wrong, anonymous, right])
        with pytest.raises(RetryableError) as caught:
            wrong.send([record(0, name="x")])
        texts.append(str(caught.value))
        assert str(caught.value) == (
            f"MQTT broker mqtt://127.0.0.1:{broker.port} refused the connection: Not authorized"
            " (check `username` and `password`; sent user 'robot')"
        )
        with pytest.raises(RetryableError, match=r"refused the connection: Not authorized .*sent no user name"):
            anonymous.send([record(0, name="x")])
        assert right.send([record(0, name="x")]) is None, "the right password gets in"
    texts += [r.getMessage() for r in caplog.records] + [m for _, m in logger.lines]
    texts += [repr(right.params), str(right.params), repr(right)]
    assert any("connected to" in t for t in texts)
    for text in texts:
        assert PASSWORD not in text, text
    assert "password" not in repr(right.params), "secret parameters stay out of the repr"


def test_secret_parameters_are_marked_secret() -> None:
    assert {p.name for p in describe_params(MqttParams) if p.secret} == {"password", "tls_key_passwd"}


def test_broker_restart_mid_stream_fails_retryable_then_delivers(tmp_path: Path, destinations: list[Mqtt]) -> None:
    broker = Broker(tmp_path / "broker").start()
    try:
        dest = mqtt_destination(port=broker.port, connect_timeout=2)
        destinations.append(dest)
        assert dest.send([record(0, name="x")]) is None
        broker.stop()
        with pytest.raises(RetryableError) as caught:
            dest.send([record(1, name="x")])
        assert f"mqtt://127.0.0.1:{broker.port}" in str(caught.value)
        broker.start()  # the same port
        with Subscriber(broker.port, "dc/#") as subscriber:
            assert dest.send([record(2, name="x")]) is None
            assert dest.send([record(3, name="x")]) is None
            messages = subscriber.wait_for(2)
        assert [json.loads(m.payload)["seq"] for m in messages] == [2, 3]
    finally:
        broker.stop()


class SilentBroker:
    """Accepts MQTT connections (CONNACK) and never acknowledges a publication."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.server.getsockname()[1])
        self.connections: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                connection, _ = self.server.accept()
            except OSError:
                return
            self.connections.append(connection)
            connection.recv(1024)  # CONNECT
            connection.sendall(b"\x20\x02\x00\x00")  # CONNACK: accepted
            threading.Thread(target=self._drain, args=(connection,), daemon=True).start()

    @staticmethod
    def _drain(connection: socket.socket) -> None:
        while True:
            try:
                if not connection.recv(65536):
                    return
            except OSError:
                return

    def close(self) -> None:
        self.server.close()
        for c in self.connections:
            c.close()


def test_unacknowledged_records_are_retried_after_publish_timeout(destinations: list[Mqtt]) -> None:
    silent = SilentBroker()
    try:
        dest = mqtt_destination(port=silent.port, publish_timeout=0.3)
        destinations.append(dest)
        started = time.monotonic()
        outcome = dest.send([record(0, name="x"), record(1, name="y")])
        assert time.monotonic() - started < 3
    finally:
        silent.close()
    assert outcome is not None and not outcome.reject
    assert outcome.retry == {
        0: f"no acknowledgement from mqtt://127.0.0.1:{silent.port} within 0.3 s",
        1: f"no acknowledgement from mqtt://127.0.0.1:{silent.port} within 0.3 s",
    }


def test_default_client_id_is_stable_short_and_distinct() -> None:
    one = default_client_id("fleet", "broker.example.com", "robot-1")
    assert one == default_client_id("fleet", "broker.example.com", "robot-1"), "the same after a restart"
    assert len(one) == 23 and one.startswith("dc-")
    others = {
        default_client_id("fleet", "broker.example.com", "robot-2"),
        default_client_id("backup", "broker.example.com", "robot-1"),
        default_client_id("fleet", "other.example.com", "robot-1"),
    }
    assert one not in others and len(others) == 3
    assert mqtt_destination(client_id="my-robot").client_id == "my-robot"


def test_a_persistent_session_resumes_with_the_default_client_id(broker: Broker, destinations: list[Mqtt]) -> None:
    logger = RecordingLogger()
    first = mqtt_destination(port=broker.port, clean_session=False, logger=logger)
    first.send([record(0, name="x")])
    first.on_deactivate()
    again = mqtt_destination(port=broker.port, clean_session=False, logger=logger)
    destinations.append(again)
    again.send([record(1, name="x")])
    assert again.client_id == first.client_id
    connected = [m for m in logger.at("info") if m.startswith("connected to")]
    assert connected == [
        f"connected to mqtt://127.0.0.1:{broker.port} as client {first.client_id!r}",
        f"connected to mqtt://127.0.0.1:{broker.port} as client {first.client_id!r} (session resumed)",
    ]


def configure(body: dict[str, Any]) -> Mqtt:
    section = {
        "destination_plugins": ["fleet"],
        "fleet": {"plugin": "dc_destinations/MQTT", "inputs": ["/dc/x"], **body},
    }
    config = parse_destination_server(section)
    (d,) = config.destinations
    plugin: Mqtt = d.plugin_class(FakeContext(name=d.name), d.plugin_params)
    plugin.on_configure()
    return plugin


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"port": 0}, "destination_server.fleet.port: expected a TCP port from 1 to 65535, got 0"),
        ({"qos": 3}, "destination_server.fleet.qos: expected one of 0, 1, 2, got 3"),
        ({"topic": "dc/+/x"}, "destination_server.fleet.topic: expected a topic without the wildcards"),
        ({"topic": "dc/#"}, "destination_server.fleet.topic: expected a topic without the wildcards"),
        ({"topic": "dc/{}"}, "destination_server.fleet.topic: expected placeholders that name a record key"),
        ({"topic": "dc/{name:>5}"}, "destination_server.fleet.topic: expected plain placeholders like {name}"),
        ({"topic": "dc/{a.b}"}, "destination_server.fleet.topic: expected plain placeholders"),
        ({"topic": "dc/{name"}, "destination_server.fleet.topic: expected"),
        ({"topic": ""}, "destination_server.fleet.topic: expected a topic template"),
        ({"password": PASSWORD}, "destination_server.fleet.password: set username too"),
        ({"host": "mqtt://example.com"}, "destination_server.fleet.host: expected a host name or IP address"),
        ({"tls_key_file": "/k.pem"}, "destination_server.fleet.tls_key_file: set tls_crt_file too"),
        ({"keepalive": 1}, "destination_server.fleet.keepalive: expected an integer >= 5"),
        ({"publish_timeout": 0}, "destination_server.fleet.publish_timeout: expected a number >= 0.1"),
        (
            {"tls": True, "tls_ca_file": "/nonexistent/ca.pem"},
            "destination_server.fleet.tls_ca_file: cannot load /nonexistent/ca.pem",
        ),
        (
            {"tls": True, "tls_crt_file": "/nonexistent/crt.pem"},
            "destination_server.fleet.tls_crt_file: cannot load /nonexistent/crt.pem",
        ),
        (
            {"passwd": "x"},
            'destination_server.fleet.passwd: unknown parameter of dc_destinations/MQTT (did you mean "password"?)',
        ),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)
    assert PASSWORD not in str(caught.value)


def test_defaults() -> None:
    p = parse_params(MqttParams, {}, "x")
    assert (p.host, p.port, p.topic, p.qos, p.retain, p.client_id, p.clean_session) == (
        "127.0.0.1", 1883, "dc/{name}", 1, False, "", True,
    )  # fmt: skip
    assert (p.tls, p.tls_verify, p.keepalive) == (False, True, 60)


def test_activation_does_not_connect() -> None:
    dest = mqtt_destination(port=free_port())  # nothing listens: activation must still succeed at once
    assert dest.address.startswith("mqtt://127.0.0.1:")


# -- TLS ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("tls"))


def published(broker: Broker) -> int:
    """PUBLISH packets the broker received (its log says so for each, whatever the client's TLS)."""
    return broker.log_text().count("Received PUBLISH from")


def test_tls_with_the_brokers_ca_file_and_refusal_of_an_unknown_one(
    tmp_path: Path, pki: Pki, destinations: list[Mqtt]
) -> None:
    with Broker(tmp_path / "tls", tls=(pki.server_crt, pki.server_key)) as broker:
        good = mqtt_destination(port=broker.port, tls=True, tls_ca_file=str(pki.ca))
        unknown = mqtt_destination(port=broker.port, tls=True, connect_timeout=3)
        lax = mqtt_destination(port=broker.port, tls=True, tls_verify=False)
        destinations.extend([good, unknown, lax])
        assert good.address.startswith("mqtts://")
        assert good.send([record(0, name="x")]) is None
        with pytest.raises(RetryableError, match=r"(?i)certificate"):
            unknown.send([record(1, name="x")])
        assert lax.send([record(2, name="x")]) is None
        assert published(broker) == 2


def test_tls_client_certificate_with_an_encrypted_key(tmp_path: Path, pki: Pki, destinations: list[Mqtt]) -> None:
    with Broker(tmp_path / "mtls", tls=(pki.server_crt, pki.server_key), client_ca=pki.ca) as broker:
        anonymous = mqtt_destination(port=broker.port, tls=True, tls_ca_file=str(pki.ca), connect_timeout=3)
        destinations.append(anonymous)
        with pytest.raises(RetryableError):
            anonymous.send([record(0, name="x")])
        logger = RecordingLogger()
        robot = mqtt_destination(
            logger=logger,
            port=broker.port,
            **pki.client_params(),
        )
        destinations.append(robot)
        assert robot.send([record(n, name="x") for n in range(3)]) is None
        assert published(broker) == 3
    with pytest.raises(ConfigError) as caught:
        mqtt_destination(
            tls=True, tls_crt_file=str(pki.client_crt), tls_key_file=str(pki.client_key), tls_key_passwd="not-it"
        )
    assert str(caught.value).startswith("destination_server.fleet.tls_key_file: cannot load ")
    texts = [str(caught.value), repr(robot.params), *(m for _, m in logger.lines)]
    assert all(KEY_PASSWORD not in text for text in texts)


def test_a_wrong_ca_fails_the_destination_and_keeps_every_record(tmp_path: Path, pki: Pki) -> None:
    records = [record(n, name="x") for n in range(4)]
    with Broker(tmp_path / "tls", tls=(pki.server_crt, pki.server_key)) as broker:
        params = {"port": broker.port, "tls": True, "tls_ca_file": str(pki.stranger_ca), "connect_timeout": 3}
        dest = Mqtt(FakeContext(name="fleet", logger=RecordingLogger()), parse_params(MqttParams, params, "m"))
        dest.on_configure()
        metrics = through_pipeline(tmp_path / "buffer", dest, records, lambda m: tls_refused(m) and m["buffered"] == 4)
        delivered = published(broker)
    assert delivered + int(metrics["buffered"]) + int(metrics["dead_lettered"]) == len(records)
    assert delivered == 0 and int(metrics["sent"]) == 0


# -- end to end through dc-bringup ------------------------------------------------------------------------


def bringup_params(tmp_path: Path, port: int) -> Path:
    settings = {"plugin": "dc_destinations/MQTT", "port": port, "topic": "robots/{run_id}/{name}"}
    settings.update(connect_timeout=2.0, publish_timeout=5.0)
    return forwarding_params(tmp_path, "fleet", settings, measurement="hello", topic="/hello-world")


def publish(run: Bringup, count: int, rate: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [str(BIN / "dc"), "pub", "/hello-world", '{"hello": "world"}', "--count", str(count), "--rate", str(rate)],
        env=run.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def record_ids(subscriber: Subscriber) -> set[str]:
    return {str(r["record_id"]) for r in subscriber.records()}


@pytest.mark.e2e
def test_e2e_records_published_with_dc_pub_reach_a_subscriber(tmp_path: Path) -> None:
    with (
        Broker(tmp_path / "broker") as broker,
        Subscriber(broker.port, "robots/#") as subscriber,
        Bringup(bringup_params(tmp_path, broker.port), tmp_path / "home") as run,
    ):
        run.wait_ready()
        published = dc("pub", "/hello-world", '{"hello": "world"}', "--count", "3", "--rate", "5", env=run.env)
        assert published.returncode == 0, published.stderr
        messages = subscriber.wait_for(3, timeout=30)
    assert [m.topic for m in messages] == ["robots/1/hello"] * 3
    records = [json.loads(m.payload) for m in messages]
    assert all(r["hello"] == "world" and r["name"] == "hello" for r in records)
    assert len({r["record_id"] for r in records}) == 3, "three records, each once"


OUTAGE_S = 30.0


@pytest.mark.e2e
def test_e2e_a_30_s_broker_outage_loses_no_record(tmp_path: Path) -> None:
    total, rate = 40, 2.0  # 20 s of records: most of them published while the broker is down
    # The broker keeps its sessions across the restart, and the subscriber's session is persistent:
    # what DC re-sends right after the restart waits for the subscriber instead of being missed.
    broker = Broker(tmp_path / "broker", persistent=True).start()
    try:
        with (
            Subscriber(broker.port, "robots/#", qos=1, client_id="outage-test") as subscriber,
            Bringup(bringup_params(tmp_path, broker.port), tmp_path / "home") as run,
        ):
            run.wait_ready()
            publisher = publish(run, total, rate)
            run.wait_until(lambda: len(record_ids(subscriber)) >= 3, 30, "the first records at the subscriber")
            broker.stop()
            down_at = time.monotonic()
            run.wait_stderr(f"cannot connect to MQTT broker mqtt://127.0.0.1:{broker.port}", timeout=OUTAGE_S)
            output, _ = publisher.communicate(timeout=2 * OUTAGE_S)  # 20 s of records, and a loaded machine
            assert publisher.returncode == 0, output
            time.sleep(max(0.0, OUTAGE_S - (time.monotonic() - down_at)))  # the outage lasts 30 s
            broker.start()
            run.wait_until(lambda: len(record_ids(subscriber)) >= total, 30, f"all {total} records after the outage")
    finally:
        broker.stop()
    received = [r["record_id"] for r in subscriber.records()]
    assert len(set(received)) == total, "every record arrived (duplicates allowed, none missing)"
    print(f"\n{len(received)} messages for {total} records across a {OUTAGE_S:g} s outage")
