"""Network measurement: ICMP, TCP and `ping` probes against loopback and addresses routed nowhere."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import pytest

import dc_measurements.network as network_module
from dc_core.errors import PluginError
from dc_measurements.network import Network
from tests.measurement_helpers import assert_valid, configured

# TEST-NET-3 (RFC 5737): documentation addresses, routed nowhere. (TEST-NET-1 is this sandbox's gateway,
# and its network answers TCP connections to any outside address, so TCP tests use a local listener.)
UNROUTABLE = "203.0.113.1"


INVALID = "255.255.255.255"  # broadcast: sockets refuse to send there without SO_BROADCAST


def interfaces_from_sysfs() -> set[str]:
    return set(os.listdir("/sys/class/net"))


def test_network_pings_localhost_and_lists_interfaces() -> None:
    plugin = configured(Network, ping_address="127.0.0.1", ping_timeout=1000)
    record = plugin.collect()
    assert_valid(Network, record)
    assert record["online"] is True, f"method {plugin.method}"
    assert 0 <= record["ping"] < 1000
    assert set(record["interfaces"]) == interfaces_from_sysfs()


needs_icmp = pytest.mark.skipif(
    network_module.open_icmp_socket() is None,
    reason="ICMP sockets not allowed here (net.ipv4.ping_group_range, no CAP_NET_RAW)",
)


@needs_icmp
def test_network_is_offline_when_the_host_does_not_answer() -> None:
    plugin = configured(Network, ping_address=UNROUTABLE, ping_timeout=200, ping_method="icmp")
    start = time.monotonic()
    record = plugin.collect()
    assert time.monotonic() - start < 1.0
    assert_valid(Network, record)
    assert (record["online"], record["ping"]) == (False, -1)


@pytest.mark.parametrize("method", [pytest.param("icmp", marks=needs_icmp), "tcp"])
def test_network_is_offline_for_an_address_it_cannot_reach(method: str) -> None:
    record = configured(Network, ping_address=INVALID, ping_timeout=200, ping_method=method).collect()
    assert_valid(Network, record)
    assert (record["online"], record["ping"]) == (False, -1)


def test_network_tcp_method_is_offline_when_syns_go_unanswered(silent_port: int) -> None:
    plugin = configured(
        Network, ping_address="127.0.0.1", ping_timeout=200, ping_method="tcp", ping_tcp_port=silent_port
    )
    start = time.monotonic()
    record = plugin.collect()
    assert time.monotonic() - start < 1.0
    assert (record["online"], record["ping"]) == (False, -1)


def test_network_tcp_method_counts_a_refused_connection_as_an_answer() -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        closed_port = probe.getsockname()[1]  # nothing listens once the socket is closed
    plugin = configured(Network, ping_address="127.0.0.1", ping_method="tcp", ping_tcp_port=closed_port)
    record = plugin.collect()
    assert record["online"] is True
    assert record["ping"] >= 0


def fake_ping(directory: Path, body: str) -> None:
    script = directory / "ping"
    script.write_text(f"#!/bin/sh\n{body}\n")
    script.chmod(0o755)


def test_network_command_method_reads_the_round_trip_of_ping(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_ping(tmp_path, 'echo "64 bytes from 10.1.2.3: icmp_seq=1 ttl=64 time=0.042 ms"')
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    record = configured(Network, ping_address="10.1.2.3", ping_method="command").collect()
    assert record["ping"] == pytest.approx(0.042)
    assert record["online"] is True


def test_network_command_method_is_bounded_by_ping_timeout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_ping(tmp_path, "exec sleep 10")
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    plugin = configured(Network, ping_address="10.1.2.3", ping_method="command", ping_timeout=200)
    start = time.monotonic()
    record = plugin.collect()
    assert time.monotonic() - start < 1.0
    assert (record["online"], record["ping"]) == (False, -1)


def test_network_without_icmp_falls_back_and_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(network_module, "open_icmp_socket", lambda: None)
    monkeypatch.setenv("PATH", str(tmp_path))  # no ping command either
    with pytest.raises(PluginError, match="ping_group_range"):
        configured(Network, ping_method="icmp")
    with pytest.raises(PluginError, match="no `ping`"):
        configured(Network, ping_method="command")
    assert configured(Network, ping_address="127.0.0.1").method == "tcp"


@pytest.mark.parametrize("address", ["example.com", "8.8.8.8.8", "::1", ""])
def test_network_needs_an_ipv4_address(address: str) -> None:
    with pytest.raises(PluginError, match="IPv4"):
        configured(Network, ping_address=address)
