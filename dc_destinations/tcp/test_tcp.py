"""TCP destination against real sockets on loopback: framing, reconnection, TLS, errors, end to end.

The receiver is a plain TCP server in threads of the test process (optionally TLS, with the
certificates made here by the ``cryptography`` package). "Stopping" it closes its listening socket
and half-closes its connections (FIN), then reads what was already on its way, as a server that
shuts down cleanly does; the records a peer that dies abruptly never read are TCP's blind spot
(README.md) and are not what these tests measure.
"""

from __future__ import annotations

import contextlib
import json
import socket
import ssl
import struct
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any

import msgpack
import pytest

from dc_bringup.validate import validate_params_file
from dc_core.destination import OutgoingRecord, RetryableError, SendOutcome
from dc_core.errors import ConfigError
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_destinations.config import parse_destination_server
from dc_destinations.record_ids import new_record_id
from dc_destinations.tcp import Tcp, TcpParams
from tests.bringup_util import BIN, Bringup, dc
from tests.destination_helpers import forwarding_params, through_pipeline, tls_refused
from tests.http_receiver import free_port
from tests.tls_pki import KEY_PASSWORD, Pki, make_pki


class TcpReceiver:
    """A TCP (or TLS) server keeping the bytes of each connection, in arrival order."""

    def __init__(self, *, port: int = 0, tls: ssl.SSLContext | None = None) -> None:
        self.tls = tls
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", port))
        self.listener.listen(16)
        self.port = int(self.listener.getsockname()[1])
        self.connections: list[bytearray] = []
        self.peer_certificates: list[dict[str, Any]] = []
        self.handshake_errors: list[str] = []
        self._sockets: list[socket.socket] = []
        self.changed = threading.Condition()
        self._stopped = False
        self._accepting = threading.Thread(target=self._accept, daemon=True)

    def __enter__(self) -> TcpReceiver:
        self._accepting.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                return  # the listener was closed
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        if self.tls is not None:
            try:
                conn = self.tls.wrap_socket(conn, server_side=True)
            except (OSError, ssl.SSLError) as exc:
                with self.changed:
                    self.handshake_errors.append(str(exc))
                    self.changed.notify_all()
                conn.close()
                return
        received = bytearray()
        with self.changed:
            if self._stopped:
                conn.close()
                return
            self.connections.append(received)
            self._sockets.append(conn)
            if isinstance(conn, ssl.SSLSocket):
                self.peer_certificates.append(conn.getpeercert() or {})
            self.changed.notify_all()
        while True:
            try:
                chunk = conn.recv(65536)
            except OSError:
                chunk = b""
            with self.changed:
                if not chunk:
                    self.changed.notify_all()
                    break
                received += chunk
                self.changed.notify_all()
        conn.close()

    def stop(self) -> None:
        """Refuse new connections, and half-close the open ones (the peer sees the end of the stream)."""
        with self.changed:
            self._stopped = True
            sockets = list(self._sockets)
        # shutdown first: a close alone leaves the port listening while accept() blocks in its thread.
        with contextlib.suppress(OSError):
            self.listener.shutdown(socket.SHUT_RDWR)
        self.listener.close()
        for conn in sockets:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_WR)

    def reset(self) -> None:
        """Abort every open connection (RST), as a crashed peer's kernel does; keep listening."""
        with self.changed:
            sockets, self._sockets = list(self._sockets), []
        for conn in sockets:
            with contextlib.suppress(OSError):
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                conn.shutdown(socket.SHUT_RDWR)

    def data(self) -> bytes:
        with self.changed:
            return b"".join(bytes(c) for c in self.connections)

    def lines(self) -> list[dict[str, Any]]:
        """The complete JSON lines of every connection."""
        with self.changed:
            texts = [bytes(c).decode("utf-8") for c in self.connections]
        return [json.loads(line) for text in texts for line in text.split("\n")[:-1]]

    def wait_until(self, check: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        with self.changed:
            while not check():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
                self.changed.wait(min(left, 0.2))

    def wait_lines(self, n: int, timeout: float = 10) -> list[dict[str, Any]]:
        self.wait_until(lambda: len(self.lines()) >= n, timeout, f"{n} lines")
        return self.lines()


def tcp_destination(name: str = "tcp", **params: Any) -> Tcp:
    plugin = Tcp(FakeContext(name=name), parse_params(TcpParams, params, f"destination_server.{name}"))
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def record(n: int, **extra: Any) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(
        rid, "/dc/measurement/test", 1_700_000_000_000_000_000 + n, {"seq": n, "record_id": rid, **extra}
    )


def batch(start: int, count: int) -> list[OutgoingRecord]:
    return [record(n, robot="C3PO", note="üñí 机器人") for n in range(start, start + count)]


@pytest.fixture
def receiver() -> Iterator[TcpReceiver]:
    with TcpReceiver() as r:
        yield r


# -- framing -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["json_lines", "json"])
def test_json_lines_arrive_intact_and_in_order(receiver: TcpReceiver, fmt: str) -> None:
    dest = tcp_destination(port=receiver.port, format=fmt)
    first, second = batch(0, 50), batch(50, 50)
    assert dest.send(first) is None
    assert dest.send(second) is None
    lines = receiver.wait_lines(100)
    assert lines == [r.data for r in first + second]
    assert receiver.data().decode("utf-8").count("üñí 机器人") == 100, "UTF-8 as is"
    assert len(receiver.connections) == 1, "one kept connection, not one per batch"


def test_msgpack_frames_decode_to_the_records(receiver: TcpReceiver) -> None:
    dest = tcp_destination(port=receiver.port, format="msgpack")
    records = [*batch(0, 20), record(20, nested={"a": [1, 2.5, None, True]}, big=2**40)]
    assert dest.send(records) is None

    def decoded() -> list[Any]:
        unpacker = msgpack.Unpacker(raw=False)
        unpacker.feed(receiver.data())
        return list(unpacker)  # a frame not wholly arrived yet is left out

    receiver.wait_until(lambda: len(decoded()) >= len(records), 10, "every msgpack frame")
    got = decoded()
    assert got == [r.data for r in records]


# -- connection lifetime -----------------------------------------------------------------------------------


def test_a_receiver_that_restarts_on_its_port_gets_the_next_batches_and_nothing_confirmed_is_lost() -> None:
    with TcpReceiver() as first:
        port = first.port
        dest = tcp_destination(port=port)
        assert dest.send(batch(0, 10)) is None
        first.wait_lines(10)
        first.stop()
        # The peer is gone and nothing listens: no write into the dead connection, a clear failure.
        with pytest.raises(RetryableError, match=rf"cannot connect to 127\.0\.0\.1:{port}: Connection refused"):
            dest.send(batch(10, 10))
    with TcpReceiver(port=port) as back:
        assert dest.send(batch(10, 10)) is None, "reconnected"
        assert dest.send(batch(20, 10)) is None
        back.wait_lines(20)
    seqs = [line["seq"] for line in first.lines() + back.lines()]
    assert seqs == list(range(30)), "every confirmed record arrived, once, in order"


def test_a_peer_that_closed_the_connection_while_idle_is_reconnected_to_before_writing(
    receiver: TcpReceiver,
) -> None:
    dest = tcp_destination(port=receiver.port)
    dest.send(batch(0, 3))
    receiver.wait_lines(3)
    with receiver.changed:
        sockets = list(receiver._sockets)
    for conn in sockets:
        conn.shutdown(socket.SHUT_WR)  # the server's idle timeout: it says goodbye but the port stays open
    assert dest.send(batch(3, 3)) is None
    receiver.wait_until(lambda: len(receiver.connections) == 2, 5, "the second connection")
    receiver.wait_lines(6)
    assert [len(bytes(c).splitlines()) for c in receiver.connections] == [3, 3], "nothing written to the closed one"


def test_a_reset_connection_is_replaced(receiver: TcpReceiver) -> None:
    dest = tcp_destination(port=receiver.port)
    dest.send(batch(0, 2))
    receiver.wait_lines(2)
    receiver.reset()
    assert dest.send(batch(2, 2)) is None
    assert [line["seq"] for line in receiver.wait_lines(4)] == [0, 1, 2, 3]


def test_connection_refused_is_retryable_with_the_address_and_errno_text() -> None:
    port = free_port()
    with pytest.raises(RetryableError) as caught:
        tcp_destination(port=port, connect_timeout=2).send(batch(0, 1))
    assert str(caught.value) == f"cannot connect to 127.0.0.1:{port}: Connection refused"


def test_a_receiver_that_stops_reading_times_the_write_out_and_only_whole_records_count() -> None:
    """A stuck receiver: the write gives up after write_timeout; records wholly written are confirmed."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    dest = tcp_destination(port=listener.getsockname()[1], write_timeout=0.3)
    records = [record(n, pad="x" * 100_000) for n in range(200)]  # 20 MB: more than the socket buffers hold
    try:
        started = time.monotonic()
        try:
            outcome = dest.send(records)
        except RetryableError as exc:
            outcome = SendOutcome(retry=dict.fromkeys(range(len(records)), str(exc)))
        assert time.monotonic() - started < 10
        assert isinstance(outcome, SendOutcome) and outcome.retry
        retried = sorted(outcome.retry)
        assert retried == list(range(retried[0], len(records))), "the records not wholly written, to the end"
        assert "no progress within 0.3 s" in next(iter(outcome.retry.values()))
    finally:
        listener.close()


def test_activation_does_not_connect() -> None:
    tcp_destination(port=free_port())  # nothing listens: activation must still succeed at once


# -- TLS -----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"), "fleet")


@pytest.fixture(scope="module")
def other_pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("other"), "other")


def tls_params(pki: Pki, **extra: Any) -> dict[str, Any]:
    return {
        "active": True,
        "ca_file": str(pki.ca),
        "crt_file": str(pki.client_crt),
        "key_file": str(pki.client_key),
        "key_passwd": KEY_PASSWORD,
        **extra,
    }


def test_tls_with_the_right_ca_and_a_client_certificate(pki: Pki) -> None:
    with TcpReceiver(tls=pki.server_context(client_ca=pki.ca)) as receiver:
        dest = tcp_destination(port=receiver.port, tls=tls_params(pki))
        assert dest.send(batch(0, 5)) is None
        assert dest.send(batch(5, 5)) is None
        lines = receiver.wait_lines(10)
    assert [line["seq"] for line in lines] == list(range(10))
    (peer,) = receiver.peer_certificates
    assert tuple(peer["subject"]) == ((("commonName", "robot-c3po"),),), "the server saw the client certificate"


def test_tls_refuses_a_server_of_another_ca_with_a_clear_message(pki: Pki, other_pki: Pki) -> None:
    with TcpReceiver(tls=other_pki.server_context()) as receiver:
        context = FakeContext(name="tcp")
        params = parse_params(TcpParams, {"port": receiver.port, "tls": tls_params(pki)}, "destination_server.tcp")
        dest = Tcp(context, params)
        dest.on_configure()
        for _ in range(2):
            with pytest.raises(RetryableError) as caught:
                dest.send(batch(0, 1))
        message = str(caught.value)
        assert message.startswith(f"TLS handshake with 127.0.0.1:{receiver.port} failed: ")
        assert "unable to get local issuer certificate" in message
        assert "destination_server.tcp.tls.ca_file" in message
        errors = context.logger.at("error")
        assert len(errors) == 1 and "records wait in the buffer" in errors[0], "said once at ERROR, not per retry"
        assert receiver.lines() == []


def test_tls_checks_the_host_name(pki: Pki) -> None:
    with TcpReceiver(tls=pki.server_context()) as receiver:
        with pytest.raises(RetryableError, match=r"Hostname mismatch|IP address mismatch"):
            tcp_destination(
                port=receiver.port, tls={"active": True, "ca_file": str(pki.ca), "vhost": "elsewhere"}
            ).send(batch(0, 1))
        assert tcp_destination(port=receiver.port, tls={"active": "on", "ca_file": str(pki.ca), "vhost": "localhost"}).send(
            batch(0, 1)
        ) is None  # fmt: skip


def test_tls_verify_off_accepts_an_unknown_certificate(other_pki: Pki) -> None:
    with TcpReceiver(tls=other_pki.server_context()) as receiver:
        with pytest.raises(RetryableError, match="certificate"):
            tcp_destination(port=receiver.port, tls=True).send(batch(0, 1))
        assert tcp_destination(port=receiver.port, tls={"active": "on", "verify": "off"}).send(batch(0, 1)) is None
        receiver.wait_lines(1)


def test_key_password_stays_out_of_repr_errors_and_logs(pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    params = parse_params(TcpParams, {"tls": tls_params(pki)}, "destination_server.tcp")
    assert KEY_PASSWORD not in repr(params) and KEY_PASSWORD not in str(params)
    assert "tls=True, tls_verify=True" in repr(params)
    with pytest.raises(ConfigError) as caught:
        tcp_destination(tls=tls_params(pki, key_passwd="wrong-" + KEY_PASSWORD))
    message = str(caught.value)
    assert message.startswith("destination_server.tcp.tls.key_file: cannot load "), message
    assert "tls.key_passwd" in message and KEY_PASSWORD not in message
    assert all(KEY_PASSWORD not in r.getMessage() for r in caplog.records)


def test_flat_tls_keys_as_http_and_mqtt_spell_them(pki: Pki) -> None:
    flat = {**pki.client_params(), "tls_vhost": "localhost"}
    with TcpReceiver(tls=pki.server_context(client_ca=pki.ca)) as receiver:
        context = FakeContext(name="tcp")
        dest = Tcp(context, parse_params(TcpParams, {"port": receiver.port, **flat}, "destination_server.tcp"))
        dest.on_configure()
        assert dest.send(batch(0, 3)) is None
        assert [line["seq"] for line in receiver.wait_lines(3)] == [0, 1, 2]
    assert context.logger.at("warning") == [], "the flat spelling is not deprecated"
    with pytest.raises(
        ConfigError, match=r"tls_ca_file: write the TLS settings either as tls_\* keys or as a tls: section"
    ):
        tcp_destination(tls={"active": True}, tls_ca_file=str(pki.ca))


def test_the_tls_section_still_works_and_is_noted_as_deprecated_once(pki: Pki) -> None:
    with TcpReceiver(tls=pki.server_context(client_ca=pki.ca)) as receiver:
        context = FakeContext(name="tcp")
        params = {"port": receiver.port, "tls": tls_params(pki)}
        dest = Tcp(context, parse_params(TcpParams, params, "destination_server.tcp"))
        dest.on_configure()
        assert dest.send(batch(0, 1)) is None
        receiver.wait_lines(1)
    (note,) = context.logger.at("warning")
    assert "destination_server.tcp.tls: the tls: section" in note and "deprecated" in note and "tls_ca_file" in note
    assert KEY_PASSWORD not in note


def test_a_wrong_ca_fails_the_destination_and_keeps_every_record(tmp_path: Path, pki: Pki) -> None:
    records = batch(0, 4)
    with TcpReceiver(tls=pki.server_context()) as receiver:
        params = parse_params(TcpParams, {"port": receiver.port, "tls": True, "tls_ca_file": str(pki.stranger_ca)}, "t")
        dest = Tcp(FakeContext(name="tcp"), params)
        dest.on_configure()
        metrics = through_pipeline(tmp_path, dest, records, lambda m: tls_refused(m) and m["buffered"] == 4)
    assert "unable to get local issuer certificate" in metrics["health"]["reason"]
    assert "tls_ca_file" in metrics["health"]["reason"], "the message names the flat key the file used"
    delivered = len(receiver.lines())
    assert delivered + int(metrics["buffered"]) + int(metrics["dead_lettered"]) == len(records) == 4
    assert delivered == 0 and int(metrics["sent"]) == 0


# -- configuration ---------------------------------------------------------------------------------------------


def configure(body: dict[str, Any]) -> Tcp:
    section = {"destination_plugins": ["tcp"], "tcp": {"plugin": "dc_destinations/TCP", "inputs": ["/dc/x"], **body}}
    (d,) = parse_destination_server(section).destinations
    plugin: Tcp = d.plugin_class(FakeContext(name=d.name), d.plugin_params)
    plugin.on_configure()
    return plugin


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ({"port": 0}, "destination_server.tcp.port: expected a TCP port from 1 to 65535, got 0"),
        ({"format": "gelf"}, "destination_server.tcp.format: expected one of"),
        ({"host": "tcp://robot"}, "destination_server.tcp.host: expected a host name or IP address"),
        ({"tls": "maybe"}, "destination_server.tcp.tls: expected boolean or mapping"),
        ({"tls": {"verfy": False}}, 'destination_server.tcp.tls.verfy: unknown parameter (did you mean "verify"?)'),
        ({"tls": {"active": "sometimes"}}, "destination_server.tcp.tls.active: expected a boolean"),
        ({"tls": {"ca_file": "/etc/ssl/ca.pem"}}, "destination_server.tcp.tls.active: set tls.active: true"),
        ({"tls": {"active": True, "key_file": "k.pem"}}, "destination_server.tcp.tls.key_file: set crt_file too"),
        ({"tls": {"active": True, "ca_file": "/nonexistent/ca.pem"}}, "tls.ca_file: cannot load /nonexistent/ca.pem"),
        ({"tls": {"active": True, "crt_file": "/nonexistent/c.pem"}}, "tls.crt_file: cannot load /nonexistent/c.pem"),
        ({"write_timeout": 0}, "destination_server.tcp.write_timeout: expected a number >= 0.1"),
    ],
)
def test_configuration_errors_name_the_yaml_path(body: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        configure(body)
    assert message in str(caught.value)


def test_a_ca_file_that_is_not_pem_is_a_configuration_error(tmp_path: Path) -> None:
    bad = tmp_path / "ca.pem"
    bad.write_text("not a certificate\n")
    with pytest.raises(ConfigError, match=r"destination_server\.tcp\.tls\.ca_file: cannot load .*ca\.pem"):
        configure({"tls": {"active": True, "ca_file": str(bad)}})


def test_defaults_are_the_originals() -> None:
    p = parse_params(TcpParams, {}, "x")
    assert (p.host, p.port, p.format, p.tls, p.tls_verify) == (
        "127.0.0.1",
        5432,
        "json_lines",
        False,
        True,
    )


def test_the_originals_dotted_keys_and_on_off_words_are_accepted(tmp_path: Path, pki: Pki) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(f"""
destination_server:
  ros__parameters:
    destination_plugins: ["flb_tcp"]
    flb_tcp:
      plugin: "dc_destinations/FlbTCP"
      inputs: ["/dc/measurement/uptime"]
      host: "127.0.0.1"
      port: 5170
      format: "json"
      json_date_key: "date"
      json_date_format: "double"
      workers: 2
      tls.active: "on"
      tls.verify: "on"
      tls.debug: 1
      tls.ca_file: "{pki.ca}"
      tls.crt_file: "{pki.client_crt}"
      tls.key_file: "{pki.client_key}"
      tls.key_passwd: "{KEY_PASSWORD}"
""")
    (d,) = validate_params_file(params).configs["destination_server"].destinations
    tls = d.plugin_params
    assert (tls.tls, tls.tls_verify, tls.tls_key_passwd) == (True, True, KEY_PASSWORD)
    off = configure({"tls": {"active": "off", "verify": "on"}})
    assert off.params.tls is False
    assert configure({"tls": "on"}).params.tls is True


# -- end to end through dc-bringup -----------------------------------------------------------------------------

OUTAGE_S = 30.0


def write_params(tmp_path: Path, port: int) -> Path:
    return forwarding_params(
        tmp_path, "to_tcp", {"plugin": "dc_destinations/TCP", "port": port, "connect_timeout": 2.0}
    )


def dc_pub(run: Bringup, count: int, rate: float) -> subprocess.Popen[str]:
    command = [str(BIN / "dc"), "pub", "/robot/events", '{"event": "dock"}']
    return subprocess.Popen(
        [*command, "--count", str(count), "--rate", str(rate)],
        env=run.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def ids(*receivers: TcpReceiver) -> Counter[str]:
    return Counter(str(line["record_id"]) for r in receivers for line in r.lines())


@pytest.mark.e2e
def test_e2e_records_published_with_dc_pub_reach_the_receiver(tmp_path: Path) -> None:
    with TcpReceiver() as receiver, Bringup(write_params(tmp_path, receiver.port), tmp_path / "home") as run:
        run.wait_ready()
        published = dc("pub", "/robot/events", '{"event": "dock"}', "--count", "5", "--rate", "5", env=run.env)
        assert published.returncode == 0, published.stderr
        lines = receiver.wait_lines(5, timeout=30)
    assert len(lines) == 5 and len(ids(receiver)) == 5
    assert all(line["event"] == "dock" and line["name"] == "events" and "date" in line for line in lines)
    assert "tags" not in lines[0]


@pytest.mark.e2e
def test_e2e_a_30_s_outage_loses_nothing(tmp_path: Path) -> None:
    total = 40
    with TcpReceiver() as first:
        port = first.port
        with Bringup(write_params(tmp_path, port), tmp_path / "home") as run:
            run.wait_ready()
            publisher = dc_pub(run, total, rate=2)  # 20 s of records: most of them during the outage
            first.wait_until(lambda: len(first.lines()) >= 5, 30, "the first records")
            first.stop()
            time.sleep(OUTAGE_S)  # the outage itself, not a synchronisation: nothing listens on the port
            output, _ = publisher.communicate(timeout=30)
            assert publisher.returncode == 0, output
            assert len(ids(first)) < total, "records were published during the outage"
            with TcpReceiver(port=port) as back:
                back.wait_until(lambda: len(ids(first, back)) >= total, 30, f"all {total} records")
    received = ids(first, back)
    assert len(received) == total, "every record_id, none missing"
    print(f"\n{len(first.lines())} records before the outage, {len(back.lines())} after; duplicates: "
          f"{sum(received.values()) - total}")  # fmt: skip
