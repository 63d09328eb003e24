"""Whose is a node in the graph (dc_bringup.instances): ours, another live DC's, or a dead process' left-over."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass

import pytest

from dc_bringup.instances import SeenNode, others, refusal, seen_nodes

HOST = b"\x12\x34"


def gid(pid: int, host: bytes = HOST) -> bytes:
    """A Fast DDS endpoint GUID as rmw_fastrtps gives it: vendor, host id, low 16 bits of the pid, ..."""
    return b"\x01\x0f" + host + (pid & 0xFFFF).to_bytes(2, "little") + b"\xab\xcd" + bytes(4) + bytes([0, 0, 0x13, 3])


@dataclass
class Info:
    node_name: str
    node_namespace: str
    endpoint_gid: bytes


class Graph:
    """What seen_nodes asks of a node: the graph's names and each node's /rosout publisher."""

    def __init__(self, nodes: list[tuple[str, str, bytes | None]]) -> None:
        self.nodes = nodes

    def get_name(self) -> str:
        return "lifecycle_manager_dc"

    def get_node_names_and_namespaces(self) -> list[tuple[str, str]]:
        return [(name, ns) for name, ns, _ in self.nodes]

    def get_publishers_info_by_topic(self, topic: str) -> list[Info]:
        assert topic == "/rosout"
        return [Info(name, ns, g) for name, ns, g in self.nodes if g is not None]


NAMES = frozenset({"destination_server", "measurement_server", "lifecycle_manager_dc", "lifecycle_manager_dc_services"})


def test_nodes_are_told_apart_by_their_process() -> None:
    me = os.getpid()
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        graph = Graph(
            [
                ("lifecycle_manager_dc", "/", gid(me)),  # this manager: gives this host's id
                ("destination_server", "/", gid(me)),
                ("destination_server", "/", gid(other.pid)),  # another DC's, alive
                ("measurement_server", "/", gid(dead.pid)),  # a killed DC's, left in the graph
                ("measurement_server", "/robot1", gid(other.pid)),  # another namespace
                ("destination_server", "/", gid(4242, host=b"\x99\x99")),  # another machine
                ("talker", "/", gid(other.pid)),  # not one of DC's names
            ]
        )
        seen = seen_nodes(graph, "/", NAMES, {me})
        owners = sorted((n.name, n.owner, n.pid or 0) for n in seen)
        assert owners == [
            ("destination_server", "other", 0),
            ("destination_server", "other", other.pid),
            ("destination_server", "ours", 0),
            ("lifecycle_manager_dc", "ours", 0),
            ("measurement_server", "gone", 0),
        ]
        found = others(seen)
        assert sorted(n.describe() for n in found) == [
            "destination_server (on another machine)",
            f"destination_server (pid {other.pid})",
        ]
        line = refusal(found, 5, "/")
        assert line.startswith("another DC runs in ROS domain 5, namespace /: destination_server (")
        assert f"destination_server (pid {other.pid})" in line
        assert "--namespace" in line and "ROS_DOMAIN_ID" in line and "\n" not in line
    finally:
        other.kill()
        other.wait()


def test_with_another_middleware_a_name_seen_more_often_than_this_dc_runs_it_is_another_dcs() -> None:
    graph = Graph(
        [("lifecycle_manager_dc", "/", None), ("destination_server", "/", None), ("destination_server", "/", None)]
    )
    seen = seen_nodes(graph, "/", NAMES, {os.getpid()})
    assert {n.owner for n in seen} == {"unknown"}
    assert others(seen) == [], "without counts, a node that cannot be told is not refused (a transition's check)"
    found = others(seen, {"lifecycle_manager_dc": 1, "destination_server": 1})
    assert (
        found == [SeenNode("destination_server", "unknown")]
        and found[0].describe() == "destination_server (pid unknown)"
    )


def test_another_dc_seen_only_after_the_discovery_window_still_stops_the_bring_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On a loaded machine discovery can take longer than DISCOVERY_S: another DC's nodes seen only
    once this one's first server is up stop the bring-up before the next server's first transition,
    with the one-line refusal. The graph is a stand-in (a late discovery cannot be ordered), and so
    are the servers (ready at once, their transitions recorded)."""
    import rclpy

    from dc_bringup import instances
    from dc_bringup.manager import LifecycleManager
    from dc_bringup.single_process import InProcessServer

    monkeypatch.setattr(instances, "MORE_NODES_S", 0.0)
    rclpy.init()
    try:
        servers = [InProcessServer("measurement_server"), InProcessServer("destination_server")]
        manager = LifecycleManager(servers, bond_timeout=5.0, discovery_from=time.monotonic() - instances.DISCOVERY_S)
        try:
            sent: list[tuple[str, str]] = []

            def transition(server: str, label: str, target: str, attempts: int = 3) -> None:
                sent.append((server, label))

            late = [SeenNode("destination_server", "other", 4242), SeenNode("lifecycle_manager_dc", "other", 4230)]
            monkeypatch.setattr(manager, "_not_ready", lambda proc, started: None)
            monkeypatch.setattr(manager, "transition", transition)
            monkeypatch.setattr(manager, "_seen_nodes", lambda: late if sent else [])
            assert not manager.start_all()
            assert sent == [("measurement_server", "configure"), ("measurement_server", "activate")]
            assert manager.conflict is not None and manager.conflict.startswith("another DC runs in ROS domain")
            assert "lifecycle_manager_dc (pid 4230)" in manager.conflict
        finally:
            manager.destroy_node()
    finally:
        rclpy.shutdown()
