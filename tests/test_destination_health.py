"""A destination's health (dc_destinations.health): ok, retrying, failing — and said so once, with the fix.

Pure tests of the state and of what is recognised as beyond retrying; the pipeline with an HTTP
destination against a real receiver that goes down and comes back; and end to end, a PgSQL
destination with a wrong password against a real PostgreSQL: failing at once, one ERROR line,
``dc lifecycle is-active`` exiting with its degraded code, the health endpoint and ``dc status``.
"""

from __future__ import annotations

import json
import socket
import ssl
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import yaml

from dc_bringup.cli import EXIT_DEGRADED
from dc_core.destination import ConfigurationProblem, OutgoingRecord, RejectedError, RetryableError
from dc_core.params import parse_params
from dc_core.testing import FakeContext, RecordingLogger
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.health import DestinationHealth, attention_needed, degraded_line
from dc_destinations.http import Http, HttpParams
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.bringup_util import Bringup, dc
from tests.destination_helpers import forwarding_params, running_postgres
from tests.http_receiver import Receiver, free_port
from tests.mqtt_broker import MOSQUITTO_PASSWD, Broker


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


# -- pure ----------------------------------------------------------------------------------------------


def test_retrying_becomes_failing_after_unhealthy_after_said_once_then_ok_again() -> None:
    clock, log = Clock(), RecordingLogger("health")
    health = DestinationHealth("web", 60.0, log, clock=clock, wall=lambda: 1.7e9)
    assert health.snapshot() == {"state": "ok"}
    health.failed("HTTP 503")
    assert health.snapshot()["state"] == "retrying"
    clock.now += 59.0
    health.failed("HTTP 503")
    health.check()
    assert health.snapshot()["state"] == "retrying" and log.at("error") == []
    clock.now += 1.0
    for _ in range(3):  # the sender's next failures and the server's periodic checks
        health.check()
        health.failed("connection refused")
    snapshot = health.snapshot()
    assert snapshot["state"] == "failing" and snapshot["since"] == 1.7e9 and snapshot["for_s"] == 60.0
    assert snapshot["reason"] == "connection refused" and snapshot["fix"] == ""
    assert log.at("error") == [
        "destination web failing for 60 s (unhealthy_after 60 s): HTTP 503 — records wait in the buffer; "
        "check that the destination is reachable"
    ]
    health.succeeded()
    assert health.snapshot() == {"state": "ok"}
    assert log.at("info") == ["destination web ok again: delivered after 60 s failing"]
    health.failed("HTTP 503")  # a new spell: said again when it lasts
    clock.now += 60.0
    health.check()
    assert len(log.at("error")) == 2


def test_a_failure_retrying_cannot_mend_is_failing_at_once_and_a_later_mendable_one_does_not_hide_it() -> None:
    clock, log = Clock(), RecordingLogger("health")
    health = DestinationHealth("pg", 60.0, log, clock=clock)
    problem = attention_needed(ConfigurationProblem("password authentication failed", fix="check the password"))
    health.failed("password authentication failed", problem)
    health.failed("connection refused")  # the server restarting meanwhile
    snapshot = health.snapshot()
    assert snapshot["state"] == "failing" and snapshot["reason"] == "password authentication failed"
    assert log.at("error") == ["destination pg failing at once: password authentication failed — check the password"]
    clock.now += 300
    line = degraded_line({"pg": health.snapshot(), "web": {"state": "retrying"}}, now=snapshot["since"] + 300)
    assert line == "destination pg failing for 5 min: password authentication failed"


def test_unknown_hosts_failed_tls_verification_and_named_fixes_are_beyond_retrying() -> None:
    def raised_from_none(inner: BaseException) -> RetryableError:
        try:
            try:
                raise inner
            except BaseException:
                raise RetryableError("cannot POST to http://nowhere.invalid/") from None
        except RetryableError as exc:
            return exc

    unknown = attention_needed(raised_from_none(socket.gaierror(-2, "Name or service not known")))
    assert unknown is not None and "unknown host" in unknown[0] and "host name" in unknown[1]
    tls = ssl.SSLCertVerificationError(1, "certificate verify failed")
    tls.verify_message = "self-signed certificate"
    verified = attention_needed(raised_from_none(tls))
    assert verified is not None and "self-signed certificate" in verified[0]
    assert attention_needed(RejectedError("HTTP 401", fix="check the token")) == ("HTTP 401", "check the token")
    assert attention_needed(RetryableError("HTTP 503")) is None
    assert attention_needed(raised_from_none(ConnectionRefusedError(111, "refused"))) is None
    assert attention_needed(RejectedError("HTTP 400")) is None


# -- the pipeline, a real HTTP receiver ------------------------------------------------------------------


def _http(port: int) -> Http:
    params = parse_params(HttpParams, {"host": "127.0.0.1", "port": port, "uri": "/in"}, "destination_server.web")
    plugin = Http(FakeContext(name="web"), params)
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def _wait(check: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def test_an_http_destination_down_is_retrying_then_failing_after_unhealthy_after_then_ok_when_back(
    tmp_path: Path,
) -> None:
    port = free_port()
    log = RecordingLogger("health-http")
    settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.1, scheduler_cap=0.3)
    delivery = DestinationDeliveryParams(unhealthy_after=2.0)
    pipeline = DeliveryPipeline(settings, {"web": (_http(port), delivery)}, log)
    pipeline.start()
    try:
        sent = 20
        for n in range(sent):
            rid = new_record_id()
            pipeline.submit("web", OutgoingRecord(rid, "/t", n, {"n": n}))
        state = lambda: pipeline.destination_health()["web"]["state"]  # noqa: E731
        _wait(lambda: state() == "retrying", 10, "retrying")
        started = time.monotonic()
        assert pipeline.health_document()["status"] == "ok", "retrying is not yet a reason to look unhealthy"
        _wait(lambda: state() == "failing", 10, "failing")
        assert time.monotonic() - started >= 1.5, "failing only after unhealthy_after without a success"
        document = pipeline.health_document()
        assert document["status"] == "degraded" and "cannot POST" in document["destinations"]["web"]["reason"]
        pipeline.check_health()
        failing = [line for line in log.at("error") if line.startswith("destination web failing")]
        assert len(failing) == 1 and "unhealthy_after 2 s" in failing[0], log.lines
        with Receiver(port=port) as receiver:
            receiver.wait_until(lambda: len(receiver.records()) >= sent, 15, "the records after the receiver is back")
            _wait(lambda: state() == "ok", 5, "ok again")
        assert pipeline.health_document()["status"] == "ok"
        assert any(line.startswith("destination web ok again") for line in log.at("info"))
        metrics = pipeline.metrics()["web"]
        assert metrics["sent"] == sent and metrics["dropped"] == 0 and metrics["dead_lettered"] == 0
    finally:
        pipeline.stop(grace=0.5)


# -- end to end: a wrong password against a real PostgreSQL ----------------------------------------------


@pytest.mark.e2e
def test_a_wrong_postgresql_password_is_failing_at_once_and_is_active_says_degraded(tmp_path: Path) -> None:
    http_port = free_port()
    with running_postgres("dc-pg-health-") as pg:
        params = forwarding_params(
            tmp_path,
            "pg",
            {
                "plugin": "dc_destinations/PgSQL",
                "host": "127.0.0.1",
                "port": pg.port,
                "user": pg.user,
                "password": "not-" + pg.password,
                "database": pg.database,
                "table": "records",
            },
        )
        document = yaml.safe_load(params.read_text())
        document["destination_server"]["ros__parameters"]["flb"].update(http_server=True, http_port=http_port)
        params.write_text(yaml.safe_dump(document, sort_keys=False))
        with Bringup(params, tmp_path / "home") as run:
            run.wait_ready()
            published = dc("pub", "/robot/events", '{"n": 1}', "--count", "3", "--rate", "20", env=run.env)
            assert published.returncode == 0, published.stderr
            error = run.wait_stderr("destination pg failing at once", 30)
            assert "password authentication failed" in error and "PGPASSWORD" in error, error
            assert pg.password not in "\n".join(run.stderr)
            # Several attempts later (0.2 s doubling to 2 s), still one line.
            run.wait_until(
                lambda: sum("destination pg: delivery failed" in line for line in run.stderr) >= 1, 20, "a retry"
            )

            def is_active() -> subprocess.CompletedProcess[str]:
                return dc("lifecycle", "is-active", "--timeout", "10", env=run.env)

            deadline = time.monotonic() + 20
            answer = is_active()
            while answer.returncode != EXIT_DEGRADED and time.monotonic() < deadline:
                time.sleep(0.5)
                answer = is_active()
            assert answer.returncode == EXIT_DEGRADED, (answer.returncode, answer.stdout, answer.stderr)
            line = answer.stdout.strip()
            assert line.startswith("running, degraded: destination pg failing for ") and "\n" not in line, line
            assert "password authentication failed" in line, line

            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(f"http://127.0.0.1:{http_port}/api/v1/health", timeout=5)
            assert refused.value.code == 503
            health = json.loads(refused.value.read())
            assert health["status"] == "degraded" and health["destinations"]["pg"]["state"] == "failing"

            status = dc("status", "--wide", "--params", str(params), env=run.env)
            assert status.returncode == 0, status.stderr
            assert any(
                text.startswith("destination pg FAILING for ") and "check the user" in text
                for text in status.stdout.splitlines()
            ), status.stdout
            errors = [text for text in run.stderr if "destination pg failing" in text]
            assert len(errors) == 1, errors


# -- what the plugins raise, against real servers ----------------------------------------------------


def _raised(plugin: Any) -> BaseException:
    try:
        plugin.send([OutgoingRecord(new_record_id(), "/t", 1, {"name": "cpu", "v": 1})])
    except Exception as exc:
        return exc
    raise AssertionError("send() did not fail")


def _plugin(cls: Any, params_cls: Any, **params: Any) -> Any:
    plugin = cls(FakeContext(name="dest"), parse_params(params_cls, params, "destination_server.dest"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def test_plugins_say_which_failures_retrying_cannot_mend() -> None:
    from dc_destinations.influxdb import InfluxDB, InfluxDBParams
    from dc_destinations.tcp import Tcp, TcpParams

    answers = {"status": (401, b"unauthorized")}
    with Receiver(lambda request: answers["status"]) as receiver:
        web = _plugin(Http, HttpParams, host="127.0.0.1", port=receiver.port)
        refused = _raised(web)
        assert isinstance(refused, RejectedError) and attention_needed(refused) is not None, refused
        answers["status"] = (503, b"busy")
        assert attention_needed(_raised(web)) is None, "a busy server is for retrying"
        influx = _plugin(InfluxDB, InfluxDBParams, host="127.0.0.1", port=receiver.port, database="ros")
        answers["status"] = (401, b'{"error":"authorization failed"}')
        assert isinstance(_raised(influx), ConfigurationProblem)
        answers["status"] = (404, b'{"error":"database not found: \\"ros\\""}')
        missing = _raised(influx)
        assert isinstance(missing, ConfigurationProblem) and "CREATE DATABASE ros" in missing.fix
    for plugin in (
        _plugin(Http, HttpParams, host="no-such-host.invalid", port=80),
        _plugin(Tcp, TcpParams, host="no-such-host.invalid", port=5170),
    ):
        unknown = attention_needed(_raised(plugin))
        assert unknown is not None and "unknown host" in unknown[0], plugin


@pytest.mark.skipif(MOSQUITTO_PASSWD is None, reason="mosquitto_passwd (package mosquitto) is not installed")
def test_an_mqtt_broker_that_refuses_the_password_is_a_configuration_problem(tmp_path: Path) -> None:
    from dc_destinations.mqtt import Mqtt, MqttParams

    with Broker(tmp_path / "auth", users={"robot": "right-password"}) as broker:
        wrong = _plugin(Mqtt, MqttParams, port=broker.port, username="robot", password="wrong", topic="dc/x")
        try:
            refused = _raised(wrong)
        finally:
            wrong.on_deactivate()
    assert isinstance(refused, ConfigurationProblem) and "username and password" in refused.fix, refused
