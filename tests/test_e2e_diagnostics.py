"""DC's health on /diagnostics (docs/diagnostics.md), read as rqt_robot_monitor or an aggregator reads it.

A real `dc-bringup` delivers numbered records to a real HTTP receiver (or to a port where nothing
listens); the test's own node in the run's domain subscribes to /diagnostics.
"""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Any

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from dc_core.diagnostics import scrub
from tests.bringup_util import Bringup
from tests.fault_helpers import fault_env
from tests.http_receiver import Receiver, free_port
from tests.test_e2e_delivery_failures import finish, publish, write_params

pytestmark = pytest.mark.e2e

DEADLINE_S = 45.0


def _bringup(tmp_path: Path, port: int, env: dict[str, str] | None = None) -> Bringup:
    """A run delivering /robot/seq to http://127.0.0.1:``port``; statuses five times a second (every server's
    parameter, given as a user would on the command line) and ``failing`` after 4 s."""
    ros_args = ["--ros-args", "-p", "diagnostics_period:=0.2", "-p", "destination_server:unhealthy_after:=4.0"]
    return Bringup(write_params(tmp_path, port), tmp_path / "home", args=ros_args, env=env)


class Monitor:
    """What a robot monitor shows: the latest status of each name, and every level each name had."""

    def __init__(self, run: Bringup) -> None:
        self.run = run
        self.context = Context()
        rclpy.init(context=self.context, domain_id=run.domain_id)
        self.node = rclpy.create_node(f"monitor_{uuid.uuid4().hex[:8]}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.latest: dict[str, DiagnosticStatus] = {}
        self.seen: dict[str, list[DiagnosticStatus]] = {}
        # Deep: the test may not spin for a while (waiting for its publisher), every status counts.
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_array, 1000)

    def _on_array(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.latest[status.name] = status
            self.seen.setdefault(status.name, []).append(status)

    def wait(self, name: str, check: Any, what: str) -> DiagnosticStatus:
        """The first status of ``name`` (latest or seen before) for which ``check(status)`` holds."""
        deadline = time.monotonic() + DEADLINE_S
        while True:
            for status in self.seen.get(name, []):
                if check(status):
                    return status
            if time.monotonic() > deadline:
                shown = {n: (s.level, s.message) for n, s in self.latest.items()}
                raise AssertionError(
                    f"no status {name!r} with {what} in {DEADLINE_S} s; latest: {shown}\n"
                    + "\n".join(self.run.stderr[-40:])
                )
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def level(wanted: bytes) -> Any:
    return lambda status: status.level == wanted


@pytest.mark.usefixtures("bringup_mode")
def test_a_healthy_run_shows_ok_for_each_server_and_destination(tmp_path: Path) -> None:
    with Receiver() as receiver, _bringup(tmp_path, receiver.port) as run:
        run.wait_ready()
        finish(publish(run, 20, rate=200))
        run.wait_until(lambda: len(receiver.records()) == 20, 30, "every record")
        monitor = Monitor(run)
        try:
            web = monitor.wait(
                "destination_server: web",
                lambda s: s.level == DiagnosticStatus.OK and values(s)["sent"] == "20",
                "OK and 20 sent",
            )
            server = monitor.wait("destination_server: server", level(DiagnosticStatus.OK), "OK")
            measurement = monitor.wait("measurement_server: server", level(DiagnosticStatus.OK), "OK")
            seq = monitor.wait(
                "measurement_server: seq",
                lambda s: s.level == DiagnosticStatus.OK and values(s)["published"] == "20",
                "OK and 20 published",
            )
            # diagnostics_period 0.2 from --ros-args: about five a second (one a second by default).
            before = len(monitor.seen["measurement_server: server"])
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:
                monitor.executor.spin_once(timeout_sec=0.05)
            assert len(monitor.seen["measurement_server: server"]) - before >= 3
        finally:
            monitor.close()
    assert web.message == "delivering"
    assert values(web)["pending"] == "0" and values(web)["state"] == "ok"
    assert values(server)["state"] == "active" and values(server)["thread_failures"] == "0"
    assert values(measurement)["namespace"] == "/"
    assert values(seq)["malformed"] == values(seq)["lost"] == values(seq)["errors"] == "0"
    assert web.hardware_id  # the host


def test_a_destination_that_cannot_be_reached_is_warn_then_error_with_the_reason(tmp_path: Path) -> None:
    with _bringup(tmp_path, free_port()) as run:
        run.wait_ready()
        monitor = Monitor(run)
        try:
            finish(publish(run, 5, rate=100))
            retrying = monitor.wait("destination_server: web", level(DiagnosticStatus.WARN), "WARN")
            failing = monitor.wait("destination_server: web", level(DiagnosticStatus.ERROR), "ERROR")
        finally:
            monitor.close()
    assert retrying.message.startswith("retrying: ") and values(retrying)["state"] == "retrying"
    assert failing.message.startswith("failing: ") and values(failing)["state"] == "failing"
    assert "refused" in failing.message.lower(), failing.message
    shown = values(failing)
    assert shown["pending"] == "5", shown  # delivered + counted = sent: all 5 wait in the buffer
    assert float(shown["oldest_pending_s"]) > 0 and "refused" in shown["last_error"].lower()


def test_a_killed_writer_thread_is_error_on_the_server_status(tmp_path: Path) -> None:
    target = "dc_destinations.commit:GroupCommitter._commit"
    with (
        Receiver() as receiver,
        _bringup(tmp_path, receiver.port, fault_env(tmp_path, target)) as run,
    ):
        run.wait_ready()
        monitor = Monitor(run)
        try:
            finish(publish(run, 10, rate=100))
            error = monitor.wait("destination_server: server", level(DiagnosticStatus.ERROR), "ERROR")
            # The restarted server (the fault is raised once) delivers everything and says OK again.
            run.wait_until(lambda: len({r["seq"] for r in receiver.records()}) == 10, 60, "every record")
            monitor.seen.clear()
            monitor.wait("destination_server: server", level(DiagnosticStatus.OK), "OK after the restart")
        finally:
            monitor.close()
    assert "injected by the test" in error.message and "thread" in error.message, error.message
    assert values(error)["thread_failures"] == "1"


def test_texts_published_are_scrubbed_of_credentials() -> None:
    text = "connect to postgresql://dc:hunter2@db:5432/x failed; password=hunter2 token: abc123\nnext line"
    shown = scrub(text, ["s3cr3t"]) + scrub("key s3cr3t rejected", ["s3cr3t"])
    assert "hunter2" not in shown and "abc123" not in shown and "s3cr3t" not in shown
    assert "postgresql://***@db:5432/x" in shown and "\n" not in shown
