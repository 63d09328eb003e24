"""One DC per ROS domain and namespace: the nodes of another DC found in the graph, and whose they are.

Two DCs in one domain and namespace have servers of the same names, and a request to a lifecycle
service reaches every server of that name: one manager would configure, activate or stop the other's
servers. So a manager looks before each server's first transition (the first look once discovery
had DISCOVERY_S), and again before each transition: a node with one of DC's names in its namespace
that no process of its own runs means another DC is there.

Whose a node is: the graph gives names only, but with Fast DDS (ROS 2's default middleware) the GUID
of each of a node's endpoints starts with the vendor id, a host id and the low 16 bits of the process
id. On this host that is enough to find the process in /proc — and to tell a node of a process that
is gone (DDS keeps a killed process in the graph for about 20 s, until its lease ends) from a live
one. With another middleware, or for a node on another machine, the pid is not known.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from dc_bringup.validate import SERVER_MODULES

# How long a new manager gives graph discovery to show another DC's nodes, from its process' start:
# measured here, a node of another process is in the graph within ~0.1 s mostly, but 2.5 s and more
# under load (a missed announcement waits for the next, Fast DDS announcing every 3 s). In a process
# per server, most of it passes while the first server starts.
DISCOVERY_S = 3.5
# Once a node of another DC is seen, how long to wait for its other processes' nodes, to name them all.
MORE_NODES_S = 2.0
# ... and, while its lifecycle manager (the process to stop) is not among them, up to this long: on a
# loaded machine the other processes' participants are discovered seconds apart.
MANAGER_WAIT_S = 6.0
# Every node has a /rosout publisher: its GUID tells the node's process.
_ROSOUT = "/rosout"
_FASTDDS_VENDOR = b"\x01\x0f"
_PID_BITS = 0xFFFF


@dataclass(frozen=True)
class SeenNode:
    """A node with one of DC's names, as the graph shows it."""

    name: str
    # ours: a process of this DC; gone: its process is dead (a left-over in the graph); other: a
    # live process of this host that is not ours, or a node of another host; unknown: cannot be told.
    owner: str
    pid: int | None = None

    def describe(self) -> str:
        if self.pid is not None:
            return f"{self.name} (pid {self.pid})"
        if self.owner == "other":
            return f"{self.name} (on another machine)"
        return f"{self.name} (pid unknown)"


def dc_node_names(manager_name: str) -> frozenset[str]:
    return frozenset(SERVER_MODULES) | {manager_name, f"{manager_name}_services"}


def seen_nodes(node: Any, namespace: str, names: frozenset[str], own_pids: Iterable[int]) -> list[SeenNode]:
    """The nodes named one of ``names`` in ``namespace`` (as ROS writes it: "/" or "/robot1"), each with its owner."""
    namespace = namespace or "/"
    entries = Counter(n for n, ns in node.get_node_names_and_namespaces() if ns == namespace and n in names)
    if not entries:
        return []
    own_low = {pid & _PID_BITS for pid in own_pids}
    gids: dict[str, list[bytes]] = {}
    own_host: bytes | None = None
    for info in node.get_publishers_info_by_topic(_ROSOUT):
        gid = bytes(info.endpoint_gid)
        if info.node_namespace == namespace and info.node_name in names:
            gids.setdefault(info.node_name, []).append(gid)
        participant = _participant(gid)
        if participant is not None and participant[1] == os.getpid() & _PID_BITS and info.node_name == node.get_name():
            own_host = participant[0]
    seen = []
    for name, count in entries.items():
        found = [_owner(gid, own_host, own_low) for gid in gids.get(name, [])]
        found += [("unknown", None)] * max(count - len(found), 0)
        seen += [SeenNode(name, owner, pid) for owner, pid in found]
    return seen


def others(seen: Iterable[SeenNode], own_names: Mapping[str, int] | None = None) -> list[SeenNode]:
    """The nodes of another DC among ``seen``.

    A node whose process cannot be told (another middleware than Fast DDS) counts as another DC's
    only when ``own_names`` is given and its name is in the graph more often than this DC runs it.
    """
    seen = list(seen)
    found = [n for n in seen if n.owner == "other"]
    if own_names is not None:
        counts = Counter(n.name for n in seen if n.owner in ("ours", "unknown"))
        for name, count in counts.items():
            extra = count - own_names.get(name, 0)
            found += [SeenNode(name, "unknown")] * max(extra, 0)
    return sorted(found, key=lambda n: n.name)


def refusal(found: Iterable[SeenNode], domain_id: int, namespace: str) -> str:
    """The one line a second DC stops with."""
    nodes = ", ".join(n.describe() for n in found)
    where = namespace or "/"
    return (
        f"another DC runs in ROS domain {domain_id}, namespace {where}: {nodes}; this one stops without touching it. "
        "Start this one with --namespace NAME or another ROS_DOMAIN_ID, or stop the running one"
    )


def _participant(gid: bytes) -> tuple[bytes, int] | None:
    """(host id, low 16 bits of the pid) of a Fast DDS GUID; None for another middleware."""
    if len(gid) < 12 or gid[:2] != _FASTDDS_VENDOR:
        return None
    return gid[2:4], gid[4] | gid[5] << 8


def _owner(gid: bytes, own_host: bytes | None, own_low: set[int]) -> tuple[str, int | None]:
    participant = _participant(gid)
    if participant is None or own_host is None:
        return "unknown", None
    host, low = participant
    if host != own_host:
        return "other", None
    if low in own_low:
        return "ours", None
    alive = [pid for pid in _pids() if pid & _PID_BITS == low]
    if not alive:
        return "gone", None
    if len(alive) > 1:  # pid_max above 65536: the one that runs DC, if it is one
        alive = [pid for pid in alive if _runs_dc(pid)] or alive
    return "other", alive[0] if len(alive) == 1 else None


def _pids() -> list[int]:
    try:
        return [int(entry) for entry in os.listdir("/proc") if entry.isdigit()]
    except OSError:
        return []


def _runs_dc(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as cmdline:
            text = cmdline.read()
    except OSError:
        return False
    return b"dc_" in text or b"dc-bringup" in text
