"""Parameters of the system measurements: the original's defaults, errors that name the YAML path."""

from __future__ import annotations

from typing import Any

import pytest

from dc_core.errors import ConfigError
from dc_core.measurement import Measurement
from dc_core.params import parse_params
from dc_measurements.cpu import Cpu
from dc_measurements.memory import Memory
from dc_measurements.network import Network
from dc_measurements.os_info import OperatingSystem
from dc_measurements.permissions import Permissions
from dc_measurements.storage import Storage
from dc_measurements.tcp_health import TcpHealth


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
