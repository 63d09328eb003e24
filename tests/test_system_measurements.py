"""System measurements (Cpu, Memory, OS, Storage, Network, Permissions, TCPHealth) without ROS.

Every value is compared with a source the plugin does not use (/proc read here, os.statvfs,
os.uname, sockets opened by the test) and every record is validated against the plugin's schema.
The process list and load include other sessions' processes, so no test asserts on global load.
"""

from __future__ import annotations

import grp
import os
import pwd
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jsonschema
import pytest

import dc_measurements.network as network_module
from dc_core.errors import ConfigError, PluginError
from dc_core.measurement import Measurement
from dc_core.params import parse_params
from dc_core.testing import FakeContext
from dc_measurements.cpu import Cpu
from dc_measurements.memory import Memory
from dc_measurements.network import Network
from dc_measurements.os_info import OperatingSystem
from dc_measurements.permissions import Permissions
from dc_measurements.storage import Storage
from dc_measurements.tcp_health import TcpHealth

# TEST-NET-3 (RFC 5737): documentation addresses, routed nowhere. (TEST-NET-1 is this sandbox's gateway,
# and its network answers TCP connections to any outside address, so TCP tests use a local listener.)
UNROUTABLE = "203.0.113.1"
INVALID = "255.255.255.255"  # broadcast: sockets refuse to send there without SO_BROADCAST


def configured(cls: type[Measurement[Any]], measurement_id: str = "m", /, **values: Any) -> Any:
    params: Any = parse_params(cls.Params, values, f"measurement_server.{measurement_id}")
    plugin = cls(FakeContext(measurement_id), params)
    plugin.on_configure()
    plugin.on_activate()
    return plugin


def assert_valid(cls: type[Measurement[Any]], record: dict[str, Any]) -> None:
    schema = cls.load_schema()
    assert schema is not None
    jsonschema.Draft7Validator(schema).validate(record)


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.02)


def meminfo() -> dict[str, int]:
    values = {}
    for line in Path("/proc/meminfo").read_text().splitlines():
        key, rest = line.split(":", 1)
        values[key] = int(rest.split()[0]) * 1024
    return values


# --- registration, schemas, parameters -------------------------------------------------------


def test_defaults_are_the_originals() -> None:
    cpu: Any = parse_params(Cpu.Params, {}, "m")
    assert (cpu.max_processes, cpu.cpu_min) == (5, 5.0)
    net: Any = parse_params(Network.Params, {}, "m")
    assert (net.ping_address, net.ping_timeout) == ("8.8.8.8", 200)
    tcp: Any = parse_params(TcpHealth.Params, {"name": "minio"}, "m")
    assert (tcp.host, tcp.port) == ("127.0.0.1", 80)
    perm: Any = parse_params(Permissions.Params, {"path": "/"}, "m")
    assert perm.format == "int"


BAD_PARAMS = [
    (Cpu, {"max_processes": "five"}, "max_processes"),
    (Cpu, {"max_processes": -2}, "max_processes"),
    (Cpu, {"max_processes": 2.5}, "max_processes"),
    (Cpu, {"cpu_min": "high"}, "cpu_min"),
    (Cpu, {"cpu_min": -5.0}, "cpu_min"),
    (Memory, {"used": 1}, "used"),
    (OperatingSystem, {"cpus": 2}, "cpus"),
    (Storage, {}, "path"),
    (Storage, {"path": True}, "path"),
    (Network, {"ping_timeout": 0}, "ping_timeout"),
    (Network, {"ping_timeout": "fast"}, "ping_timeout"),
    (Network, {"ping_timeout": 60000}, "ping_timeout"),
    (Network, {"ping_method": "raw"}, "ping_method"),
    (Network, {"ping_tcp_port": 70000}, "ping_tcp_port"),
    (Network, {"ping_adress": "1.1.1.1"}, "ping_adress"),
    (Permissions, {}, "path"),
    (Permissions, {"path": "/", "format": "octal"}, "format"),
    (Permissions, {"path": ["/"]}, "path"),
    (TcpHealth, {}, "name"),
    (TcpHealth, {"name": "web", "port": 0}, "port"),
    (TcpHealth, {"name": "web", "port": 65536}, "port"),
    (TcpHealth, {"name": "web", "port": "http"}, "port"),
    (TcpHealth, {"name": "web", "timeout": 0}, "timeout"),
]


@pytest.mark.parametrize(("cls", "values", "key"), BAD_PARAMS)
def test_parameter_errors_name_the_yaml_path(cls: type[Measurement[Any]], values: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_params(cls.Params, values, "measurement_server.x")
    assert info.value.path == f"measurement_server.x.{key}"


# --- Memory, OS ------------------------------------------------------------------------------


def test_memory_used_counts_available_memory_as_free() -> None:
    record = configured(Memory).collect()
    assert_valid(Memory, record)
    info = meminfo()
    expected = (info["MemTotal"] - info["MemAvailable"]) / info["MemTotal"] * 100
    assert record["used"] == pytest.approx(expected, abs=2.0)


def os_release_pretty_name() -> str:
    for candidate in ("/etc/os-release", "/usr/lib/os-release"):
        if os.path.exists(candidate):
            for line in Path(candidate).read_text().splitlines():
                if line.startswith("PRETTY_NAME="):
                    return line.split("=", 1)[1].strip().strip('"')
    pytest.skip("no os-release on this machine")


def test_os_reports_distribution_kernel_cpus_and_memory() -> None:
    record = configured(OperatingSystem).collect()
    assert_valid(OperatingSystem, record)
    assert record["os"] == os_release_pretty_name()
    assert record["kernel"] == os.uname().release
    assert record["cpus"] == os.cpu_count()
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 1024**3
    assert record["memory"] == pytest.approx(physical, abs=0.01)


# --- Storage ---------------------------------------------------------------------------------


def test_storage_matches_statvfs_and_expands_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_STORAGE", str(tmp_path))
    record = configured(Storage, path="$DC_TEST_STORAGE").collect()
    assert_valid(Storage, record)
    fs = os.statvfs(tmp_path)
    capacity = fs.f_blocks * fs.f_frsize
    free = fs.f_bavail * fs.f_frsize  # available to the user, not f_bfree
    assert record["capacity"] == capacity
    # Other sessions write to the same disk: allow some drift between the two reads.
    assert record["free"] == pytest.approx(free, abs=64 * 1024**2)
    assert record["free_percent"] == pytest.approx(free / capacity * 100, abs=0.5)


def test_storage_rejects_unset_variable_and_missing_path(tmp_path: Path) -> None:
    with pytest.raises(PluginError, match="DC_TEST_UNSET_VARIABLE"):
        configured(Storage, path="$DC_TEST_UNSET_VARIABLE/data")
    with pytest.raises(PluginError, match="does not exist"):
        configured(Storage, path=str(tmp_path / "missing"))


def test_storage_publishes_nothing_while_the_path_is_gone(tmp_path: Path) -> None:
    mount = tmp_path / "usb"
    mount.mkdir()
    plugin = configured(Storage, path=str(mount))
    mount.rmdir()
    assert plugin.collect() is None
    mount.mkdir()
    assert plugin.collect() is not None


# --- Permissions -----------------------------------------------------------------------------


@pytest.mark.parametrize(("style", "expected"), [("int", "640"), ("rwx", "rw-r-----")])
def test_permissions_of_a_file(tmp_path: Path, style: str, expected: str) -> None:
    target = tmp_path / "secret"
    target.write_text("x")
    target.chmod(0o640)
    record = configured(Permissions, path=str(target), format=style).collect()
    assert_valid(Permissions, record)
    info = os.stat(target)
    assert record == {
        "exists": True,
        "uid": info.st_uid,
        "gid": info.st_gid,
        "user": pwd.getpwuid(info.st_uid).pw_name,
        "group": record["group"],
        "permissions": expected,
    }
    assert record["group"] == grp.getgrgid(info.st_gid).gr_name


@pytest.mark.parametrize(("style", "expected"), [("int", "1777"), ("rwx", "rwxrwxrwt")])
def test_permissions_show_the_sticky_bit_like_stat_and_ls(tmp_path: Path, style: str, expected: str) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    assert stat.S_IMODE(os.stat(shared).st_mode) == 0o1777
    record = configured(Permissions, path=str(shared), format=style).collect()
    assert_valid(Permissions, record)
    assert record["permissions"] == expected


def test_permissions_of_a_missing_path_says_it_does_not_exist(tmp_path: Path) -> None:
    record = configured(Permissions, path=str(tmp_path / "nothing")).collect()
    assert record == {"exists": False}
    assert_valid(Permissions, record)


def test_permissions_expands_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DC_TEST_PERM", str(tmp_path))
    record = configured(Permissions, path="${DC_TEST_PERM}").collect()
    assert record["exists"] is True
    assert record["permissions"] == f"{stat.S_IMODE(os.stat(tmp_path).st_mode):03o}"


# --- TCPHealth -------------------------------------------------------------------------------


@pytest.fixture
def silent_port() -> Iterator[int]:
    """A local port whose SYNs are dropped: a listener whose accept queue is full."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(0)
    port = server.getsockname()[1]
    fillers = []
    try:
        for _ in range(4):
            filler = socket.socket()
            filler.setblocking(False)
            filler.connect_ex(("127.0.0.1", port))
            fillers.append(filler)
        yield port
    finally:
        for filler in fillers:
            filler.close()
        server.close()


@pytest.fixture
def tcp_server() -> Iterator[socket.socket]:
    server = socket.create_server(("127.0.0.1", 0))
    try:
        yield server
    finally:
        server.close()


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


# --- Network ---------------------------------------------------------------------------------


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


# --- Cpu -------------------------------------------------------------------------------------


def process_ticks(pid: int) -> int:
    # Fields after the command name (which may contain spaces): utime and stime are 14th and 15th.
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def machine_busy_and_total() -> tuple[int, int]:
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    # user nice system idle iowait irq softirq steal (guest time is already inside user/nice)
    total = sum(values[:8])
    return total - values[3] - values[4], total


def proc_process_count() -> int:
    return sum(1 for entry in os.listdir("/proc") if entry.isdigit())


@pytest.fixture
def busy_child() -> Iterator[subprocess.Popen[bytes]]:
    child = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield child
    finally:
        child.kill()
        child.wait()


def test_cpu_reports_a_busy_process_with_its_usage(busy_child: subprocess.Popen[bytes]) -> None:
    ticks_per_second = os.sysconf("SC_CLK_TCK")
    busy_before, total_before = machine_busy_and_total()
    child_before, wall_before = process_ticks(busy_child.pid), time.monotonic()
    plugin = configured(Cpu, max_processes=10000, cpu_min=0.0)  # on_activate starts the window
    wait_until(lambda: process_ticks(busy_child.pid) - child_before >= ticks_per_second // 2)
    record = plugin.collect()
    child_after, wall_after = process_ticks(busy_child.pid), time.monotonic()
    busy_after, total_after = machine_busy_and_total()

    assert_valid(Cpu, record)
    expected_average = (busy_after - busy_before) / (total_after - total_before) * 100
    assert record["average"] > 0
    assert record["average"] == pytest.approx(expected_average, abs=15)
    assert record["processes"] == pytest.approx(proc_process_count(), abs=30)

    mine = [p for p in record["sorted"] if p["pid"] == busy_child.pid]
    assert len(mine) == 1
    child = mine[0]
    expected_cpu = (child_after - child_before) / ticks_per_second / (wall_after - wall_before) * 100
    assert child["cpu"] == pytest.approx(expected_cpu, abs=20)
    assert child["user"] == pwd.getpwuid(os.getuid()).pw_name
    assert "while True" in child["cmd"]
    rss_kib = next(
        int(line.split()[1])
        for line in Path(f"/proc/{busy_child.pid}/status").read_text().splitlines()
        if line.startswith("VmRSS:")
    )
    assert child["ram"] == pytest.approx(rss_kib, abs=2048)
    assert 0 <= child["uptime"] <= wall_after - wall_before + 5

    cpus = [p["cpu"] for p in record["sorted"]]
    assert cpus == sorted(cpus, reverse=True)
    assert max(cpus) <= 100 * (os.cpu_count() or 1) + 5


def test_cpu_first_sample_is_not_a_meaningless_zero(busy_child: subprocess.Popen[bytes]) -> None:
    plugin = configured(Cpu, max_processes=-1)
    start = process_ticks(busy_child.pid)
    wait_until(lambda: process_ticks(busy_child.pid) - start >= 20)
    assert plugin.collect()["average"] > 0


def test_cpu_limits_and_filters_the_process_list() -> None:
    assert "sorted" not in configured(Cpu, max_processes=-1).collect()
    assert len(configured(Cpu, max_processes=3, cpu_min=-1.0).collect()["sorted"]) == 3
    assert len(configured(Cpu, max_processes=2, cpu_min=0.0).collect()["sorted"]) <= 2
    assert configured(Cpu, max_processes=0).collect()["sorted"] == []
    record = configured(Cpu, max_processes=50, cpu_min=30.0).collect()
    assert_valid(Cpu, record)
    assert all(p["cpu"] >= 30.0 for p in record["sorted"])


def test_two_cpu_measurements_do_not_share_their_window(busy_child: subprocess.Popen[bytes]) -> None:
    first = configured(Cpu, "cpu_a", max_processes=-1)
    second = configured(Cpu, "cpu_b", max_processes=-1)
    start = process_ticks(busy_child.pid)
    wait_until(lambda: process_ticks(busy_child.pid) - start >= 20)
    assert first.collect()["average"] > 0
    # A collect of one instance does not reset the other's averaging window.
    assert second.collect()["average"] > 0
