"""The status HTTP server on its own: paths, status codes, loopback binding."""

from __future__ import annotations

import json
import socket
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from typing import Any

import pytest

from dc_core.http_status import StatusServer
from dc_core.logs import BurstLog
from dc_core.testing import RecordingLogger
from dc_destinations.metrics import DestinationMetrics, prometheus_text


class State:
    healthy = True
    broken = False

    def metrics(self) -> dict[str, Any]:
        if self.broken:
            raise RuntimeError("metrics unavailable")
        return {"destinations": {"sink": {"sent": 3}}}


@pytest.fixture
def served() -> Iterator[tuple[State, str]]:
    state = State()
    server = StatusServer(
        "127.0.0.1", 0, health=lambda: state.healthy, metrics=state.metrics, prometheus=lambda: "dc_x 1\n"
    )
    try:
        yield state, f"http://127.0.0.1:{server.address[1]}"
    finally:
        server.stop()


def get(url: str) -> tuple[int, str, str]:
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return reply.status, reply.headers["Content-Type"], reply.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers["Content-Type"], exc.read().decode()


def test_health_follows_the_pipeline(served: tuple[State, str]) -> None:
    state, base = served
    assert get(f"{base}/api/v1/health")[0] == 200
    state.healthy = False
    status, _type, body = get(f"{base}/api/v1/health")
    assert status == 503 and json.loads(body) == {"status": "error"}


def test_metrics_json_and_prometheus(served: tuple[State, str]) -> None:
    _state, base = served
    status, content_type, body = get(f"{base}/api/v1/metrics")
    assert status == 200 and content_type == "application/json"
    assert json.loads(body)["destinations"]["sink"]["sent"] == 3
    status, content_type, body = get(f"{base}/api/v1/metrics/prometheus/")
    assert status == 200 and content_type.startswith("text/plain; version=0.0.4")
    assert body.startswith("dc_x 1\n")  # the server's own text first, then the HTTP server's counter


def test_unknown_path_and_failing_metrics(served: tuple[State, str]) -> None:
    state, base = served
    assert get(f"{base}/api/v1/nothing")[0] == 404
    state.broken = True
    status, _type, body = get(f"{base}/api/v1/metrics")
    assert status == 500 and "metrics unavailable" in body
    state.broken = False
    assert get(f"{base}/api/v1/metrics")[0] == 200  # the server survived


def test_a_taken_port_raises_oserror() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(OSError):
            StatusServer("127.0.0.1", port, health=lambda: True, metrics=dict, prometheus=str)


def test_an_idle_connection_does_not_block_health(served: tuple[State, str]) -> None:
    """A client that connects and says nothing (a stuck scraper, a port scan) used to hold the only thread."""
    _state, base = served
    port = int(base.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port)):
        started = time.monotonic()
        assert get(f"{base}/api/v1/health")[0] == 200
        assert time.monotonic() - started < 2.0


def test_connections_beyond_the_cap_are_refused_counted_and_the_server_recovers() -> None:
    logger = RecordingLogger()
    server = StatusServer(
        "127.0.0.1", 0, health=lambda: True, metrics=dict, prometheus=str, logger=logger, max_connections=2, timeout=1.0
    )
    base = f"http://127.0.0.1:{server.address[1]}"
    try:
        idle = [socket.create_connection(server.address) for _ in range(2)]
        # Each idle connection holds a handler thread once accepted: wait for both to be taken.
        deadline = time.monotonic() + 5.0
        while server.refused == 0 and time.monotonic() < deadline:
            status, _type, body = get(f"{base}/api/v1/health")
            if status == 503:
                assert "busy" in body
        assert server.refused >= 1
        assert any("metrics HTTP server: connection refused" in line for line in logger.at("warning"))
        # The socket timeout frees the threads of the idle connections: served again, without closing them.
        deadline = time.monotonic() + 5.0
        while get(f"{base}/api/v1/health")[0] != 200:
            assert time.monotonic() < deadline, "the idle connections were never timed out"
        for sock in idle:
            sock.close()
        status, _type, body = get(f"{base}/api/v1/metrics")
        assert status == 200 and json.loads(body)["metrics_http"]["refused_connections"] == server.refused
        _status, _type, text = get(f"{base}/api/v1/metrics/prometheus")
        assert f"dc_http_refused_connections_total {server.refused}" in text
    finally:
        server.stop()


def test_prometheus_text_format() -> None:
    row = {
        "received": 5,
        "sent": 4,
        "retried": 1,
        "failed": 1,
        "dropped": 0,
        "malformed": 3,
        "dead_lettered": 0,
        "dead_letters_dropped": 2,
        "buffered": 1,
        "buffered_bytes": 120,
        "dead_letters": 0,
        "oldest_pending_age_s": 2.5,
        "last_error": "x",
    }
    delivered = {**row, "last_delivery": 1795326396.643, "last_error_time": None}
    text = prometheus_text(
        {'we"ird': row, "b": delivered}, {"quarantined": 1, "intake_pending": 0, "commit_failing_s": 12.5}
    )
    assert "# TYPE dc_delivery_sent_total counter" in text
    assert 'dc_delivery_sent_total{destination="b"} 4' in text
    assert 'dc_delivery_received_total{destination="we\\"ird"} 5' in text
    assert 'dc_delivery_oldest_pending_age_seconds{destination="b"} 2.5' in text
    assert 'dc_delivery_dead_letters_dropped_total{destination="b"} 2' in text
    assert "dc_delivery_buffer_quarantined_total 1" in text
    assert 'dc_delivery_malformed_total{destination="b"} 3' in text
    assert "dc_delivery_commit_failing_seconds 12.5" in text
    # Whole seconds, not 1.79533e+09; no sample for a destination that has none yet.
    assert 'dc_delivery_last_success_timestamp_seconds{destination="b"} 1795326396\n' in text
    assert "# TYPE dc_delivery_last_error_timestamp_seconds gauge" in text
    assert 'timestamp_seconds{destination="we' not in text
    assert text.endswith("\n")


def test_destination_metrics_stamp_the_last_delivery_and_the_last_error() -> None:
    now = [1795326396.5]
    metrics = DestinationMetrics(clock=lambda: now[0])
    metrics.add("received", 3)
    metrics.add("sent", 0)  # nothing confirmed: no delivery
    assert metrics.snapshot()["last_delivery"] is None and metrics.snapshot()["last_error_time"] is None
    metrics.add("sent", 2)
    now[0] += 10.0
    metrics.set_error("HTTP 503")
    metrics.add("failed")
    snapshot = metrics.snapshot()
    assert snapshot["last_delivery"] == 1795326396.5 and snapshot["last_error_time"] == 1795326406.5
    assert snapshot["sent"] == 2 and snapshot["last_error"] == "HTTP 503"
    now[0] += 5.0
    metrics.add("sent")
    assert metrics.snapshot()["last_delivery"] == 1795326411.5


def test_burst_log_is_one_line_then_a_summary() -> None:
    now = [0.0]
    lines: list[str] = []
    log = BurstLog(lines.append, "sink: records dropped", quiet=5.0, interval=60.0, clock=lambda: now[0])
    for _ in range(1000):
        log.event(1, "limit reached")
        now[0] += 0.001
    assert lines == ["sink: records dropped: 1 (limit reached)"]
    now[0] += 5.0
    log.tick()
    assert len(lines) == 2 and "999 more" in lines[1]
    log.tick()
    assert len(lines) == 2
    log.event(2, "again")  # a new burst starts with a line of its own
    assert lines[2] == "sink: records dropped: 2 (again)"


def test_burst_log_gives_the_first_events_of_a_burst_a_line_each() -> None:
    now = [0.0]
    lines: list[str] = []
    log = BurstLog(lines.append, "malformed", quiet=5.0, clock=lambda: now[0], each=3)
    own_lines = [log.event(1, f"record {i}") for i in range(10)]
    assert own_lines == [True] * 3 + [False] * 7
    assert lines == [f"malformed: 1 (record {i})" for i in range(3)]
    now[0] += 5.0
    log.tick()
    assert lines[3] == "malformed: 7 more in the last 5 s (latest: record 9)"
    assert log.event(1, "next burst")  # a new burst has its own lines again


def test_burst_log_reports_a_burst_that_never_ends() -> None:
    now = [0.0]
    lines: list[str] = []
    log = BurstLog(lines.append, "drops", quiet=5.0, interval=60.0, clock=lambda: now[0])
    for _ in range(130):
        log.event(1, "x")
        now[0] += 1.0
    assert len(lines) == 3  # the first event, then a summary each minute
