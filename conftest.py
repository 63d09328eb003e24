"""Test-session environment (tests/ and the plugin folders' tests): ROS traffic stays on this
machine, in a domain of its own; and the fixtures tests of several plugin folders share."""

from __future__ import annotations

import atexit
import os
import random
import shutil
import socket
import tempfile
from collections.abc import Iterator
from typing import Any

import pytest

from tests.domains import session_domain_id

# Set before any test module imports rclpy, so every context of this session uses them.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
if "PYTEST_XDIST_WORKER" in os.environ or "ROS_DOMAIN_ID" not in os.environ:
    # A worker inherits the controller's environment: it needs a domain of its own.
    os.environ["ROS_DOMAIN_ID"] = str(session_domain_id())


def _session_dir(prefix: str) -> str:
    """A folder for this test process that goes when it exits (a developer's /tmp gained two
    folders per process and run before)."""
    path = tempfile.mkdtemp(prefix=prefix)
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path


if "ROS_LOG_DIR" not in os.environ:
    os.environ["ROS_LOG_DIR"] = _session_dir("dc-test-roslog-")
os.environ.setdefault("RCUTILS_COLORIZED_OUTPUT", "0")
# Servers run in the test process keep state under $XDG_DATA_HOME (the default buffer folder, the
# hand-off marks of dc_core.handoff_marks): this session's, never the account's.
os.environ["XDG_DATA_HOME"] = _session_dir("dc-test-data-")


# -- dc-bringup's two modes ---------------------------------------------------------------------


@pytest.fixture(params=["processes", "single-process"])
def bringup_mode(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test (``@pytest.mark.usefixtures("bringup_mode")``) with a process per server, then with
    every server in one process (``dc-bringup --single-process``)."""
    from tests.bringup_util import Bringup

    if request.param == "single-process":
        monkeypatch.setattr(Bringup, "mode_args", ["--single-process"])
    return str(request.param)


# -- sockets for the tests of measurements that probe the network (Network, TCPHealth) --------


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


# -- a ROS node for tests that give plugins a node (FakeContext(node=...)) ---------------------------


@pytest.fixture(scope="module")
def ros_node() -> Iterator[Any]:
    """A node in the default context, shared by the tests of one module."""
    import rclpy  # here, not at the top: the environment above is set before anything imports rclpy

    rclpy.init()
    node = rclpy.create_node(f"dc_test_{os.getpid()}_{random.randint(0, 1 << 30)}")
    try:
        yield node
    finally:
        node.destroy_node()
        rclpy.shutdown()


# -- the files' order: the longest first, for xdist's loadfile distribution (tests/file_order.py) ------


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    from tests.file_order import file_seconds, longest_first

    def file_of(item: pytest.Item) -> str:
        return item.nodeid.split("::", 1)[0]

    rank = {path: i for i, path in enumerate(longest_first([file_of(item) for item in items], file_seconds()))}
    items.sort(key=lambda item: rank[file_of(item)])  # stable: a file's tests keep their order
