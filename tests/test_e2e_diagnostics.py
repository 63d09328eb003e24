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
from tests.test_e2e_delivery_failures import SCHEDULER_BASE, SCHEDULER_CAP, finish, publish

pytestmark = pytest.mark.e2e

DEADLINE_S = 45.0


def _params(tmp_path: Path, port: int) -> Path:
    params = tmp_path / "params.yaml"
    params.write_text(f"""
measurement_server:
  ros__parameters:
    diagnostics_period: 0.2
    measurement_plugins: ["seq"]
    seq:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/seq"
      timer_based: false
      qos_depth: 1000
      enable_validator: false
      tags: ["web"]
destination_server:
  ros__parameters:
    diagnostics_period: 0.2
    unhealthy_after: 4.0
    flb:
      storage_path: "{tmp_path / "buffer"}"
      flush: 0.2
      scheduler_base: {SCHEDULER_BASE}
      scheduler_cap: {SCHEDULER_CAP}
    destination_plugins: ["web"]
    web:
      plugin: "dc_destinations/HTTP"
      inputs: ["/dc/measurement/seq"]
      port: {port}
      uri: "/ingest"
      timeout: 2.0
""")
    return params


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
    with Receiver() as receiver, Bringup(_params(tmp_path, receiver.port), tmp_path / "home") as run:
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
        finally:
            monitor.close()
    assert web.message == "delivering"
    assert values(web)["pending"] == "0" and values(web)["state"] == "ok"
    assert values(server)["state"] == "active" and values(server)["thread_failures"] == "0"
    assert values(measurement)["namespace"] == "/"
    assert web.hardware_id  # the host


def test_a_destination_that_cannot_be_reached_is_warn_then_error_with_the_reason(tmp_path: Path) -> None:
    with Bringup(_params(tmp_path, free_port()), tmp_path / "home") as run:
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
        Bringup(_params(tmp_path, receiver.port), tmp_path / "home", env=fault_env(tmp_path, target)) as run,
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
