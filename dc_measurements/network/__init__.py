"""Network measurement: round trip to a host, online status and network interfaces.

Needs no root. The round trip is measured, in order of preference, with an ICMP echo on an
unprivileged datagram socket (allowed when the process's group is in net.ipv4.ping_group_range),
an ICMP echo on a raw socket (when the process has CAP_NET_RAW), the system `ping` command, or as
a last resort the time a TCP connection attempt to `ping_tcp_port` takes to be answered (accepted
or refused: either way the host is reachable).
"""

from __future__ import annotations

import ipaddress
import random
import re
import shutil
import socket
import struct
import subprocess
import time
from dataclasses import dataclass
from typing import Any

from dc_core.errors import PluginError
from dc_core.measurement import Measurement, MeasurementContext
from dc_core.params import param

_ECHO_REQUEST = 8
_ECHO_REPLY = 0
_PING_TIME = re.compile(r"time[=<]\s*([0-9.]+)\s*ms")


@dataclass(frozen=True, kw_only=True)
class NetworkParams:
    ping_address: str = param("8.8.8.8", doc="IPv4 address to ping")
    ping_timeout: int = param(200, minimum=1, maximum=10000, doc="Milliseconds to wait for the reply")
    ping_method: str = param(
        "auto",
        choices=("auto", "icmp", "command", "tcp"),
        doc="How to measure the round trip; auto takes the first of icmp, command, tcp that is usable",
    )
    ping_tcp_port: int = param(53, minimum=1, maximum=65535, doc="Port probed by the tcp method")


def internet_checksum(data: bytes) -> int:
    if len(data) % 2:
        data += b"\0"
    total = sum(int(word) for word in struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def echo_request(ident: int, sequence: int, payload: bytes) -> bytes:
    header = struct.pack("!BBHHH", _ECHO_REQUEST, 0, 0, ident, sequence)
    checksum = internet_checksum(header + payload)
    return struct.pack("!BBHHH", _ECHO_REQUEST, 0, checksum, ident, sequence) + payload


def open_icmp_socket() -> socket.socket | None:
    """An ICMP socket this process may use: datagram (unprivileged) first, then raw."""
    for kind in (socket.SOCK_DGRAM, socket.SOCK_RAW):
        try:
            return socket.socket(socket.AF_INET, kind, socket.IPPROTO_ICMP)
        except OSError:
            continue
    return None


def icmp_echo(address: str, timeout: float, ident: int, sequence: int) -> float | None:
    """Round trip in ms of one ICMP echo, or None without a reply within ``timeout`` seconds."""
    sock = open_icmp_socket()
    if sock is None:
        return None
    with sock:
        raw = sock.type == socket.SOCK_RAW
        start = time.monotonic()
        deadline = start + timeout
        try:
            sock.sendto(echo_request(ident, sequence, struct.pack("!d", start)), (address, 0))
        except OSError:
            return None  # e.g. network unreachable: no route at all
        while (remaining := deadline - time.monotonic()) > 0:
            sock.settimeout(remaining)
            try:
                packet, (source, _) = sock.recvfrom(1024)
            except OSError:  # timeout included
                return None
            if raw:
                # Raw sockets see every ICMP packet with its IP header, our own requests included.
                packet = packet[(packet[0] & 0x0F) * 4 :]
            if len(packet) < 8 or source != address:
                continue
            kind, _, _, reply_ident, reply_sequence = struct.unpack("!BBHHH", packet[:8])
            # The kernel rewrites the identifier of datagram sockets and filters replies itself.
            if kind == _ECHO_REPLY and reply_sequence == sequence and (not raw or reply_ident == ident):
                return (time.monotonic() - start) * 1000.0
    return None


def ping_command(executable: str, address: str, timeout: float) -> float | None:
    """Round trip in ms reported by one `ping`, or None (killed at ``timeout`` seconds)."""
    # -W takes whole seconds; the subprocess timeout enforces the shorter limit.
    wait = str(max(1, int(timeout + 0.999)))
    start = time.monotonic()
    try:
        done = subprocess.run(
            [executable, "-n", "-c", "1", "-W", wait, address],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except (subprocess.TimeoutExpired, OSError):
        return None
    if done.returncode != 0:
        return None
    match = _PING_TIME.search(done.stdout)
    return float(match.group(1)) if match else (time.monotonic() - start) * 1000.0


def tcp_probe(address: str, port: int, timeout: float) -> float | None:
    """Time in ms until the host accepts or refuses a TCP connection, or None."""
    start = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        try:
            sock.connect((address, port))
        except ConnectionRefusedError:
            pass  # a refusal is an answer from the host
        except OSError:
            return None
    return (time.monotonic() - start) * 1000.0


def interface_names() -> list[str]:
    return [name for _, name in socket.if_nameindex()]


class Network(Measurement[NetworkParams]):
    """Round trip to a host (ms, -1 when unanswered), online status and network interface names."""

    # A probe waits up to ping_timeout (10 s at most) for its answer.
    collect_in_worker = True

    def __init__(self, context: MeasurementContext, params: NetworkParams) -> None:
        super().__init__(context, params)
        self.method = ""
        self._ping_executable = ""
        self._ident = random.getrandbits(16)
        self._sequence = 0

    def on_configure(self) -> None:
        p = self.params
        try:
            address = ipaddress.ip_address(p.ping_address)
        except ValueError:
            address = None
        if not isinstance(address, ipaddress.IPv4Address):
            raise PluginError(f"{self.context.name}: ping_address {p.ping_address!r} is not an IPv4 address")
        self.method = self._choose_method(p.ping_method)
        self.context.logger.info(f"{self.context.name}: pinging {p.ping_address} by {self.method}")

    def _choose_method(self, wanted: str) -> str:
        if wanted in ("auto", "icmp"):
            sock = open_icmp_socket()
            if sock is not None:
                sock.close()
                return "icmp"
            if wanted == "icmp":
                raise PluginError(
                    f"{self.context.name}: ICMP sockets are not allowed: add the process's group to "
                    "net.ipv4.ping_group_range (sysctl) or choose ping_method command or tcp"
                )
        if wanted in ("auto", "command"):
            executable = shutil.which("ping")
            if executable is not None:
                self._ping_executable = executable
                return "command"
            if wanted == "command":
                raise PluginError(f"{self.context.name}: ping_method is command but no `ping` is on PATH")
        return "tcp"

    def collect(self) -> dict[str, Any]:
        round_trip = self._round_trip()
        return {
            "ping": -1 if round_trip is None else round(round_trip, 3),
            "online": round_trip is not None,
            "interfaces": interface_names(),
        }

    def _round_trip(self) -> float | None:
        p = self.params
        timeout = p.ping_timeout / 1000.0
        if self.method == "command":
            return ping_command(self._ping_executable, p.ping_address, timeout)
        if self.method == "tcp":
            return tcp_probe(p.ping_address, p.ping_tcp_port, timeout)
        self._sequence = (self._sequence + 1) & 0xFFFF
        return icmp_echo(p.ping_address, timeout, self._ident, self._sequence)
