"""HTTP destination against a real HTTP server in the test: what it sends, how each answer is classified.

Bodies are decoded on the receiver's side (gzip, msgpack) as a server would; TLS runs with a private
CA generated here with the `cryptography` package, with and without a client certificate.
"""

from __future__ import annotations

import base64
import datetime as dt
import gzip
import json
import logging
import re
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import msgpack
import pytest

from dc_core.destination import OutgoingRecord, RejectedError, RetryableError
from dc_core.errors import ConfigError
from dc_core.params import describe_params, parse_params
from dc_core.testing import FakeContext
from dc_destinations.buffer import FILE_NAME, SqliteBuffer
from dc_destinations.config import parse_destination_server
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.http import Http, HttpParams
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams
from tests.destination_helpers import through_pipeline, tls_refused
from tests.http_receiver import Receiver, Request, Responder, free_port
from tests.tls_pki import KEY_PASSWORD, Pki, make_pki


def http_destination(name: str = "web", **params: Any) -> Http:
    plugin = Http(FakeContext(name=name), parse_params(HttpParams, params, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    with Receiver() as r:
        yield r


def record(n: int, **extra: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(
        rid, "/dc/measurement/test", 1_700_000_000_000_000_000 + n, {"seq": n, "record_id": rid, **extra}
    )


BATCH = [record(0, robot="C3PO"), record(1, robot="R2D2", note="üñí")]


def test_json_posts_the_batch_as_one_array(receiver: Receiver) -> None:
    dest = http_destination(port=receiver.port, uri="/ingest/dc?robot=c3po")
    assert dest.send(BATCH) is None
    (request,) = receiver.requests
    assert request.path == "/ingest/dc?robot=c3po"
    assert json.loads(request.body) == [r.data for r in BATCH]
    assert request.header("Content-Type") == "application/json"
    assert request.header("Content-Length") == str(len(request.body))
    assert "üñí" in request.body.decode("utf-8"), "UTF-8, not \\u escapes"
    assert request.header("Authorization") is None


def test_json_lines_is_one_object_per_line(receiver: Receiver) -> None:
    http_destination(port=receiver.port, format="json_lines").send(BATCH)
    (request,) = receiver.requests
    assert request.body.decode().splitlines() == [r.to_json() for r in BATCH]
    assert request.body.endswith(b"\n")
    assert request.header("Content-Type") == "application/x-ndjson"


def test_json_stream_is_objects_back_to_back(receiver: Receiver) -> None:
    http_destination(port=receiver.port, format="json_stream").send(BATCH)
    text = receiver.requests[0].body.decode()
    decoder, objects, at = json.JSONDecoder(), [], 0
    while at < len(text):
        value, at = decoder.raw_decode(text, at)
        objects.append(value)
    assert objects == [r.data for r in BATCH]
    assert "\n" not in text


def test_basic_auth_and_custom_headers(receiver: Receiver) -> None:
    dest = http_destination(
        port=receiver.port,
        http_user="robot",
        http_passwd="s3cr3t-pa55",
        header=["X-Api-Key: abc123", "X-Fleet  warehouse 7", "Content-Type: application/vnd.dc+json"],
        header_tag="X-Tag",
    )
    dest.send(BATCH)
    (request,) = receiver.requests
    scheme, token = (request.header("Authorization") or "").split(" ")
    assert scheme == "Basic" and base64.b64decode(token).decode() == "robot:s3cr3t-pa55"
    assert request.header("X-Api-Key") == "abc123"
    assert request.header("X-Fleet") == "warehouse 7", "Fluent Bit's 'Name value' form"
    assert request.header("X-Tag") == "web", "header_tag carries the destination's name"
    assert request.header_values("Content-Type") == ["application/vnd.dc+json"], (
        "a configured header replaces the default"
    )


def test_duplicated_headers_are_sent_unless_disallowed(receiver: Receiver) -> None:
    headers = ["X-Env: staging", "X-Env: production"]
    http_destination(port=receiver.port, header=headers).send(BATCH)
    http_destination(port=receiver.port, header=headers, allow_duplicated_headers=False).send(BATCH)
    first, second = receiver.requests
    assert first.header_values("X-Env") == ["staging", "production"]
    assert second.header_values("X-Env") == ["production"], "the last one wins"


def test_a_single_header_string_is_accepted(receiver: Receiver) -> None:
    http_destination(port=receiver.port, header="X-Single: yes").send(BATCH)
    assert receiver.requests[0].header("X-Single") == "yes"


@pytest.mark.parametrize("status", [200, 201, 202, 204])
def test_2xx_confirms_the_batch(receiver: Receiver, status: int) -> None:
    receiver.respond = lambda request: (status, b"")
    assert http_destination(port=receiver.port).send(BATCH) is None


@pytest.mark.parametrize("status", [408, 429, 500, 502, 503, 504])
def test_busy_and_server_errors_are_retryable(receiver: Receiver, status: int) -> None:
    receiver.respond = lambda request: (status, b'{"error": "ingest queue full, try later"}')
    with pytest.raises(RetryableError) as caught:
        http_destination(port=receiver.port).send(BATCH)
    message = str(caught.value)
    assert message.startswith(f"HTTP {status} ")
    assert message.endswith(f"(http://127.0.0.1:{receiver.port}/)")
    assert "ingest queue full, try later" in message, "the start of the answer says why"


@pytest.mark.parametrize("status", [400, 401, 403, 404, 413, 422, 301])
def test_other_client_errors_reject_the_batch(receiver: Receiver, status: int) -> None:
    receiver.respond = lambda request: (status, b"schema mismatch: field 'seq' unknown")
    with pytest.raises(RejectedError) as caught:
        http_destination(port=receiver.port).send(BATCH)
    assert f"HTTP {status} " in str(caught.value)
    assert "schema mismatch" in str(caught.value)


def test_answer_excerpt_is_short_and_can_be_left_out(receiver: Receiver) -> None:
    receiver.respond = lambda request: (500, b"<html>\n  " + b"x" * 5000 + b"\n</html>")
    with pytest.raises(RetryableError) as caught:
        http_destination(port=receiver.port).send(BATCH)
    assert len(str(caught.value)) < 300 and "<html> xxx" in str(caught.value)
    with pytest.raises(RetryableError) as caught:
        http_destination(port=receiver.port, log_response_payload=False).send(BATCH)
    assert str(caught.value) == f"HTTP 500 Internal Server Error (http://127.0.0.1:{receiver.port}/)"


def test_a_huge_answer_is_not_read_whole_and_the_next_batch_still_goes(receiver: Receiver) -> None:
    receiver.respond = lambda request: (200, b"y" * 1_000_000)
    dest = http_destination(port=receiver.port)
    assert dest.send(BATCH) is None
    assert dest.send(BATCH) is None
    assert len(receiver.accepted()) == 2


def test_connection_refused_is_retryable() -> None:
    port = free_port()
    with pytest.raises(RetryableError) as caught:
        http_destination(port=port, timeout=2).send(BATCH)
    assert f"cannot POST to http://127.0.0.1:{port}/" in str(caught.value)
    assert "refused" in str(caught.value).lower()


def test_no_answer_within_timeout_is_retryable(receiver: Receiver) -> None:
    def hang(request: Request) -> tuple[int, bytes]:
        receiver.release.wait(10)
        return 200, b""

    receiver.respond = hang
    started = time.monotonic()
    with pytest.raises(RetryableError, match=r"no answer within 0.3 s"):
        http_destination(port=receiver.port, timeout=0.3).send(BATCH)
    assert time.monotonic() - started < 5


def test_one_connection_serves_every_batch(receiver: Receiver) -> None:
    dest = http_destination(port=receiver.port)
    for _ in range(5):
        dest.send(BATCH)
    assert len({r.client for r in receiver.requests}) == 1, "kept alive, not one connection per batch"
    assert receiver.closed_connections == 0


def test_a_connection_the_server_closed_while_idle_is_reopened_without_failing() -> None:
    with Receiver(idle_timeout=0.2) as receiver:
        dest = http_destination(port=receiver.port)
        dest.send(BATCH)
        receiver.wait_until(lambda: receiver.closed_connections == 1, 5, "the server to close the idle connection")
        assert dest.send(BATCH) is None, "a stale kept-alive connection is not a failure of the destination"
    assert len(receiver.accepted()) == 2
    assert receiver.requests[0].client != receiver.requests[1].client


def test_after_a_dropped_connection_the_next_batch_reconnects(receiver: Receiver) -> None:
    receiver.respond = lambda request: None
    dest = http_destination(port=receiver.port)
    with pytest.raises(RetryableError, match="cannot POST"):
        dest.send(BATCH)
    receiver.respond = None
    assert dest.send(BATCH) is None
    assert len(receiver.accepted()) == 1


def test_the_same_destination_delivers_again_once_the_server_is_back() -> None:
    with Receiver() as first:
        port = first.port
        dest = http_destination(port=port)
        dest.send(BATCH)
    with pytest.raises(RetryableError):
        dest.send(BATCH)
    with Receiver(port=port) as back:  # the server restarted on its port
        assert dest.send(BATCH) is None
    assert len(back.accepted()) == 1


PASSWORD = "hunter2-Very-Secret"


def echo_authorization(status: int) -> Responder:
    """A careless server that quotes the request's credentials in its error page."""

    def respond(request: Request) -> tuple[int, bytes]:
        return status, f"bad request, you sent Authorization: {request.header('Authorization')}".encode()

    return respond


def test_password_never_reaches_logs_errors_metrics_or_dead_letters(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    # Any: mypy does not see logging.Logger as a dc_core.logs.Logger (keyword arguments differ), though it is one.
    logger: Any = logging.getLogger("test_http_destination.secret")
    token = base64.b64encode(f"robot:{PASSWORD}".encode()).decode()
    with Receiver(echo_authorization(503)) as receiver:
        params = parse_params(
            HttpParams,
            {"port": receiver.port, "http_user": "robot", "http_passwd": PASSWORD},
            "destination_server.web",
        )
        dest = Http(FakeContext(name="web", logger=logger), params)
        dest.on_configure()
        settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=0.1)
        pipeline = DeliveryPipeline(settings, {"web": (dest, DestinationDeliveryParams(retry_limit=2))}, logger)
        dest.on_activate()
        pipeline.start()
        try:
            pipeline.submit("web", record(1))
            receiver.wait_until(lambda: len(receiver.requests) >= 3, 10, "three attempts")
            receiver.respond = echo_authorization(400)
            pipeline.submit("web", record(2))

            def both_dead() -> bool:
                return int(pipeline.metrics()["web"]["dead_lettered"]) == 2

            deadline = time.monotonic() + 10
            while not both_dead() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert both_dead()
            metrics_text = json.dumps(pipeline.status_document())
        finally:
            pipeline.stop(0.5)
            dest.on_deactivate()
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        letters = buffer.list_dead_letters(None)
    finally:
        buffer.close()
    assert len(letters) == 2 and all("***" in d.error for d in letters), [d.error for d in letters]
    texts = [r.getMessage() for r in caplog.records] + [metrics_text] + [d.error for d in letters]
    texts += [repr(params), str(params)]
    assert any("HTTP 503" in t for t in texts) and any("HTTP 400" in t for t in texts)
    for text in texts:
        assert PASSWORD not in text and token not in text, text
    assert "http_passwd" not in repr(params), "secret parameters stay out of the repr"


def test_secret_parameter_is_marked_secret() -> None:
    secrets = {p.name for p in describe_params(HttpParams) if p.secret}
    assert secrets == {"http_passwd", "bearer_token", "tls_key_passwd"}


def configure(body: dict[str, Any]) -> None:
    section = {"destination_plugins": ["web"], "web": {"plugin": "dc_destinations/HTTP", "inputs": ["/dc/x"], **body}}
    config = parse_destination_server(section)
    (d,) = config.destinations
    d.plugin_class(FakeContext(name=d.name), d.plugin_params).on_configure()


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"port": 0}, "destination_server.web.port: expected a TCP port from 1 to 65535, got 0"),
        ({"port": "eighty"}, "destination_server.web.port: expected an integer"),
        ({"uri": "ingest"}, "destination_server.web.uri: expected a path starting with '/'"),
        ({"uri": "/données"}, "destination_server.web.uri: expected a path starting with '/', ASCII"),
        ({"header": ["X-Robot: 机器人"]}, "destination_server.web.header[0]"),
        ({"format": "gelf"}, "destination_server.web.format: expected one of"),
        ({"compress": "zstd"}, "destination_server.web.compress: expected one of"),
        ({"headers": {"X Bad": "1"}}, "destination_server.web.headers.X Bad: expected a header name"),
        ({"headers": {"X-Multi": "a\nb"}}, "destination_server.web.headers.X-Multi: expected a one-line"),
        ({"headers": {"X-Nested": {"a": 1}}}, "destination_server.web.headers.X-Nested: expected a one-line"),
        ({"bearer_token": "t0ken", "http_user": "u"}, "destination_server.web.bearer_token: choose"),
        ({"tls_key_file": "/k.pem"}, "destination_server.web.tls_key_file: set tls_crt_file too"),
        (
            {"tls": True, "tls_crt_file": "/nonexistent/client.pem"},
            "destination_server.web.tls_crt_file: cannot load /nonexistent/client.pem",
        ),
        ({"header": ["no-value"]}, 'destination_server.web.header[0]: expected "Name: value", got "no-value"'),
        ({"header": ["X-Ok: 1", ": no name"]}, "destination_server.web.header[1]"),
        ({"http_passwd": "x"}, "destination_server.web.http_passwd: set http_user too"),
        ({"http_user": "a:b"}, "destination_server.web.http_user"),
        ({"header_tag": "X Tag"}, "destination_server.web.header_tag"),
        ({"host": "http://example.com"}, "destination_server.web.host: expected a host name or IP address"),
        ({"timeout": 0}, "destination_server.web.timeout: expected a number >= 0.1"),
        (
            {"http_password": "x"},
            'destination_server.web.http_password: unknown parameter of dc_destinations/HTTP (did you mean "http_passwd"?)',
        ),
        (
            {"tls": True, "tls_ca_file": "/nonexistent/ca.pem"},
            "destination_server.web.tls_ca_file: cannot load /nonexistent/ca.pem",
        ),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)


def test_configuration_error_does_not_quote_the_password() -> None:
    with pytest.raises(ConfigError) as caught:
        configure({"http_passwd": PASSWORD})
    assert PASSWORD not in str(caught.value)


def test_fluent_bit_keys_of_the_original_are_accepted() -> None:
    configure(
        {
            "plugin": "dc_destinations/FlbHTTP",
            "host": "127.0.0.1",
            "port": 80,
            "uri": "/",
            "format": "json",
            "json_date_key": "date",
            "json_date_format": "iso8601",
            "log_response_payload": True,
            "allow_duplicated_headers": True,
        }
    )


def test_defaults_are_the_originals() -> None:
    p = parse_params(HttpParams, {}, "x")
    assert (p.host, p.port, p.uri, p.format, p.tls, p.timeout) == ("127.0.0.1", 80, "/", "json", False, 10.0)


def test_activation_does_not_connect() -> None:
    dest = http_destination(port=free_port())  # nothing listens: activation must still succeed at once
    assert dest.url.startswith("http://127.0.0.1:")


# -- formats, compression, headers, bearer token -------------------------------------------------------


def test_msgpack_posts_one_array_of_maps(receiver: Receiver) -> None:
    http_destination(port=receiver.port, format="msgpack").send(BATCH)
    (request,) = receiver.requests
    assert request.header("Content-Type") == "application/msgpack"
    assert msgpack.unpackb(request.body, raw=False) == [r.data for r in BATCH]


@pytest.mark.parametrize("fmt", ["json", "json_lines", "msgpack"])
def test_gzip_compresses_every_format(receiver: Receiver, fmt: str) -> None:
    plain = http_destination(port=receiver.port, format=fmt)
    plain.send(BATCH)
    http_destination(port=receiver.port, format=fmt, compress="gzip").send(BATCH)
    uncompressed, compressed = receiver.requests
    assert compressed.header("Content-Encoding") == "gzip" and uncompressed.header("Content-Encoding") is None
    assert gzip.decompress(compressed.body) == uncompressed.body
    assert compressed.header("Content-Length") == str(len(compressed.body))


def test_gzip_shrinks_a_repetitive_batch(receiver: Receiver) -> None:
    batch = [record(n, robot="C3PO", status="nominal") for n in range(200)]
    http_destination(port=receiver.port, compress="gzip").send(batch)
    body = receiver.requests[0].body
    assert len(body) * 4 < len(gzip.decompress(body))
    assert [r["seq"] for r in json.loads(gzip.decompress(body))] == list(range(200))


def test_headers_mapping_adds_headers(receiver: Receiver) -> None:
    headers = {"X-Robot": "c3po", "X-Schema-Version": 2, "X-Debug": True}
    http_destination(port=receiver.port, headers=headers, header=["X-Fleet: 7"]).send(BATCH)
    request = receiver.requests[0]
    assert request.header("X-Robot") == "c3po"
    assert request.header("X-Schema-Version") == "2" and request.header("X-Debug") == "true"
    assert request.header("X-Fleet") == "7", "with the original's header list"


TOKEN = "eyJhbGciOiJIUzI1NiJ9.c2VjcmV0LXJvYm90.Xq9-token"


def bearer_check(token: str) -> Responder:
    """A server that wants ``token`` and, carelessly, quotes what it got when it refuses."""

    def respond(request: Request) -> tuple[int, bytes]:
        sent = request.header("Authorization") or ""
        if sent == f"Bearer {token}":
            return 200, b"ok"
        return 401, f"invalid token in {sent}".encode()

    return respond


def test_bearer_token_is_sent(receiver: Receiver) -> None:
    receiver.respond = bearer_check(TOKEN)
    assert http_destination(port=receiver.port, bearer_token=TOKEN).send(BATCH) is None
    assert receiver.requests[0].header("Authorization") == f"Bearer {TOKEN}"


def test_a_bad_bearer_token_dead_letters_the_batch_and_is_never_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    logger: Any = logging.getLogger("test_http_destination.bearer")
    bad = "wrong-" + TOKEN
    with Receiver(bearer_check(TOKEN)) as receiver:
        params = parse_params(HttpParams, {"port": receiver.port, "bearer_token": bad}, "destination_server.web")
        dest = Http(FakeContext(name="web", logger=logger), params)
        dest.on_configure()
        settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=0.1)
        pipeline = DeliveryPipeline(settings, {"web": (dest, DestinationDeliveryParams())}, logger)
        dest.on_activate()
        pipeline.start()
        try:
            pipeline.submit("web", record(1))
            deadline = time.monotonic() + 10
            while int(pipeline.metrics()["web"]["dead_lettered"]) < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            metrics = pipeline.metrics()["web"]
            status_text = json.dumps(pipeline.status_document())
        finally:
            pipeline.stop(0.5)
            dest.on_deactivate()
    assert int(metrics["dead_lettered"]) == 1 and int(metrics["retried"]) == 0, "401 is refused for good"
    assert len(receiver.requests) == 1
    buffer = SqliteBuffer(tmp_path / FILE_NAME)
    try:
        (letter,) = buffer.list_dead_letters(None)
    finally:
        buffer.close()
    assert letter.error.startswith("rejected: HTTP 401 Unauthorized: invalid token in Bearer ***")
    texts = [r.getMessage() for r in caplog.records] + [status_text, letter.error, repr(params), str(params)]
    for text in texts:
        assert bad not in text and TOKEN not in text, text


# -- Retry-After -------------------------------------------------------------------------------------------


class RetryAfterServer:
    """Answers ``status`` with a Retry-After header to the first request, then 200; keeps each request's
    arrival time and the records of those it accepted (http_receiver sets no headers)."""

    def __init__(self, retry_after: str, status: int = 429) -> None:
        self.times: list[float] = []
        self.accepted: list[dict[str, Any]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                server.times.append(time.monotonic())
                first = len(server.times) == 1
                self.send_response(status if first else 200)
                if first:
                    self.send_header("Retry-After", retry_after)
                else:
                    server.accepted.extend(json.loads(body))
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, format: str, *args: Any) -> None:
                pass

        self.http = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.http.daemon_threads = True
        self.port = int(self.http.server_address[1])

    def __enter__(self) -> RetryAfterServer:
        threading.Thread(target=self.http.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.shutdown()
        self.http.server_close()


def test_retry_after_goes_to_the_sender_and_send_does_not_wait() -> None:
    with RetryAfterServer("1") as server:
        dest = http_destination(port=server.port)
        with pytest.raises(RetryableError, match=r"HTTP 429 Too Many Requests .*; Retry-After 1 s") as caught:
            dest.send(BATCH)
        assert caught.value.retry_after == 1.0
        assert dest.send(BATCH) is None  # at once: waiting is the sender's backoff's job
    assert server.times[1] - server.times[0] < 0.9


def test_retry_after_as_a_date_is_capped_by_retry_after_max() -> None:
    later = dt.datetime.now(dt.UTC) + dt.timedelta(hours=1)
    with RetryAfterServer(later.strftime("%a, %d %b %Y %H:%M:%S GMT")) as server:
        dest = http_destination(port=server.port, retry_after_max=0.5)
        with pytest.raises(RetryableError, match=r"Retry-After 0.5 s") as caught:
            dest.send(BATCH)
    assert caught.value.retry_after == 0.5
    with RetryAfterServer("30") as server, pytest.raises(RetryableError) as caught:
        http_destination(port=server.port, retry_after_max=0).send(BATCH)
    assert caught.value.retry_after is None, "retry_after_max 0: the backoff alone decides"


@pytest.mark.parametrize(("cap", "earliest", "latest"), [(5.0, 1.95, 5.5), (0.5, 0.0, 1.5)])
def test_the_senders_backoff_honours_retry_after_within_scheduler_cap(
    tmp_path: Path, cap: float, earliest: float, latest: float
) -> None:
    """503 with Retry-After: 2, then 200: the second attempt comes no sooner than 2 s (the backoff
    alone would retry after at most 0.05 s) and no later than scheduler_cap, which bounds it."""
    logger: Any = logging.getLogger("test_http_destination.retry_after")
    records = [record(n) for n in range(5)]
    with RetryAfterServer("2", status=503) as server:
        dest = Http(FakeContext(name="web", logger=logger), parse_params(HttpParams, {"port": server.port}, "web"))
        dest.on_configure()
        settings = DeliveryParams(storage_path=str(tmp_path), flush=0.05, scheduler_base=0.05, scheduler_cap=cap)
        pipeline = DeliveryPipeline(settings, {"web": (dest, DestinationDeliveryParams())}, logger)
        dest.on_activate()
        pipeline.start()
        try:
            for rec in records:
                pipeline.submit("web", rec)
            deadline = time.monotonic() + 15
            while int(pipeline.metrics()["web"]["sent"]) < len(records) and time.monotonic() < deadline:
                time.sleep(0.05)
            metrics = pipeline.metrics()["web"]
        finally:
            pipeline.stop(0.5)
            dest.on_deactivate()
    first, second = server.times[:2]
    assert earliest <= second - first <= latest, server.times
    delivered = {r["record_id"] for r in server.accepted}
    counted = int(metrics["dead_lettered"]) + int(metrics.get("dropped", 0))
    assert len(delivered) + counted == len(records) == int(metrics["sent"]), metrics
    assert int(metrics["retried"]) >= 1


# -- TLS with a private CA -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("tls"))


def tls_receiver(pki: Pki, *, client_ca: Path | None = None) -> Receiver:
    return Receiver(tls=pki.server_context(client_ca=client_ca))


def test_tls_with_the_servers_ca_file(pki: Pki) -> None:
    with tls_receiver(pki) as receiver:
        dest = http_destination(port=receiver.port, tls=True, tls_ca_file=str(pki.ca))
        assert dest.url.startswith("https://")
        assert dest.send(BATCH) is None
        assert dest.send(BATCH) is None
    assert len(receiver.records()) == 4


def test_tls_refuses_an_unknown_certificate_unless_told_not_to_verify(pki: Pki) -> None:
    with tls_receiver(pki) as receiver:
        with pytest.raises(RetryableError, match=re.compile("certificate", re.IGNORECASE)):
            http_destination(port=receiver.port, tls=True).send(BATCH)
        with pytest.raises(RetryableError, match=re.compile("certificate", re.IGNORECASE)):
            http_destination(port=receiver.port, tls=True, tls_ca_file=str(pki.stranger_ca)).send(BATCH)
        assert http_destination(port=receiver.port, tls=True, tls_verify=False).send(BATCH) is None
    assert len(receiver.records()) == 2


def test_tls_client_certificate_with_an_encrypted_key(pki: Pki) -> None:
    with tls_receiver(pki, client_ca=pki.ca) as receiver:
        with pytest.raises(RetryableError):
            http_destination(port=receiver.port, tls=True, tls_ca_file=str(pki.ca)).send(BATCH)
        dest = http_destination(
            port=receiver.port,
            **pki.client_params(),
        )
        assert dest.send(BATCH) is None
    assert len(receiver.records()) == 2


def test_a_wrong_ca_fails_the_destination_and_keeps_every_record(tmp_path: Path, pki: Pki) -> None:
    records = [record(n) for n in range(4)]
    with tls_receiver(pki) as receiver:
        params = parse_params(
            HttpParams, {"port": receiver.port, "tls": True, "tls_ca_file": str(pki.stranger_ca)}, "w"
        )
        dest = Http(FakeContext(name="web"), params)
        dest.on_configure()
        metrics = through_pipeline(tmp_path, dest, records, lambda m: tls_refused(m) and m["buffered"] == 4)
    assert "certificate verify failed" in metrics["health"]["reason"]
    delivered = len(receiver.records())
    assert delivered + int(metrics["buffered"]) + int(metrics["dead_lettered"]) == len(records)
    assert delivered == 0 and int(metrics["sent"]) == 0


def test_a_wrong_key_password_fails_configure_without_quoting_it(pki: Pki) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(
            {
                "tls": True,
                "tls_crt_file": str(pki.client_crt),
                "tls_key_file": str(pki.client_key),
                "tls_key_passwd": "not-the-" + KEY_PASSWORD,
            }
        )
    assert "destination_server.web.tls_key_file: cannot load" in str(caught.value)
    assert KEY_PASSWORD not in str(caught.value)
