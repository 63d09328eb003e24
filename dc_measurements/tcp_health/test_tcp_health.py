"""TCPHealth measurement against sockets the test opens on loopback."""

from __future__ import annotations

import socket
import time

import pytest

from dc_measurements.tcp_health import TcpHealth
from tests.measurement_helpers import assert_valid, configured


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost"])
def test_tcp_health_is_active_while_the_server_listens(tcp_server: socket.socket, host: str) -> None:
    port = tcp_server.getsockname()[1]
    plugin = configured(TcpHealth, name="local_api", host=host, port=port)
    try:
        record = plugin.collect()
        assert_valid(TcpHealth, record)
        assert record == {"host": host, "port": port, "server_name": "local_api", "active": True}
        tcp_server.close()
        assert plugin.collect()["active"] is False
    finally:
        plugin.on_cleanup()


def test_tcp_health_gives_up_within_its_timeout(silent_port: int) -> None:
    plugin = configured(TcpHealth, name="stuck", port=silent_port, timeout=200)
    start = time.monotonic()
    record = plugin.collect()
    assert record["active"] is False
    assert time.monotonic() - start < 1.0
