"""Who may announce ended hand-off publishers to destination_server, with real processes.

An announcement on ``dc/handoff_ended`` makes destination_server count records as missing and commit
that the publisher is settled. What a user relies on (docs/security.md): a node that is not one of
DC's servers cannot do that — its announcement changes no count and settles nothing, so a later real
loss of that publisher (kill -9 of measurement_server) is still counted; the refusal is counted and
logged with the node's name.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn

import dc_destinations.server as destination_module
from dc_core.handoff import ENDED_SUFFIX
from dc_core.handoff_marks import ENDED_TOPIC, HEADER, Ended, ended_document, ended_qos
from dc_core.lifecycle import ServerLoop
from dc_destinations.server import DestinationServer
from dc_interfaces.msg import StringStamped
from tests.bringup_util import server_env
from tests.test_e2e_delivery_restart import ServerProcess, file_destination, wait_for

TOPIC = "/dc/measurement/tick"

# Publishes the first line of its stdin on ENDED_TOPIC as a node named "intruder"; leaves when stdin closes.
FORGER = """
import os, sys
import rclpy
from dc_core.handoff_marks import ENDED_TOPIC, ended_qos
from dc_interfaces.msg import StringStamped
rclpy.init()
node = rclpy.create_node("intruder")
publisher = node.create_publisher(StringStamped, ENDED_TOPIC, ended_qos())
msg = StringStamped()
msg.data = sys.stdin.readline()
publisher.publish(msg)
sys.stdin.read()
node.destroy_node()  # leaves the graph
rclpy.shutdown()
os._exit(0)
"""


def write_params(tmp_path: Path) -> tuple[Path, Path]:
    output = tmp_path / "out" / "ticks.jsonl"
    params = tmp_path / "params.yaml"
    params.write_text(f"""
measurement_server:
  ros__parameters:
    measurement_plugins: ["tick"]
    tick:
      plugin: "dc_measurements/Dummy"
      polling_interval: 100
      record: '{{"m": "tick"}}'
      tags: ["file"]
{file_destination(tmp_path, output, [TOPIC])}""")
    return params, output


def metrics(server: ServerProcess, path: str = "") -> Any:
    (address,) = [m.group(1) for line in server.lines if (m := re.search(r"metrics HTTP server on (http://\S+)", line))]
    with urllib.request.urlopen(address + "metrics" + path, timeout=5) as response:
        return json.load(response) if not path else response.read().decode()


def the_mark(home: Path) -> Path:
    (mark,) = (home / ".local" / "share" / "dc" / "handoff").glob("domain-*/default/measurement_server/*.mark")
    return mark


def mark_high(mark: Path) -> int:
    return int(HEADER.unpack_from(mark.read_bytes())[1])


def ended_keys(buffer: Path) -> int:
    """Keys in destination_server's buffer that say a publisher's end was counted."""
    database = buffer / "delivery.sqlite3"
    with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as conn:
        return int(conn.execute("SELECT count(*) FROM hop_seen WHERE topic = ?", (TOPIC + ENDED_SUFFIX,)).fetchone()[0])


def delivered_before(output: Path, moment: float) -> int:
    """Distinct records in the file stamped before ``moment`` (one delivered again counts once)."""
    ids = set()
    for line in output.read_text().splitlines() if output.exists() else []:
        if line.endswith("}") and float((record := json.loads(line))["date"]) < moment:
            ids.add(record["record_id"])
    return len(ids)


def test_a_forged_end_of_a_live_publisher_is_refused_and_its_real_end_still_counted(tmp_path: Path) -> None:
    params, output = write_params(tmp_path)
    home = tmp_path / "home"
    env = server_env(home)
    destination = ServerProcess("dc_destinations.server", params, env)
    measurement = ServerProcess("dc_measurements.server", params, env)
    successor: ServerProcess | None = None
    # Started with the servers: its announcement names the publisher they are about to create.
    forger = subprocess.Popen(
        [sys.executable, "-c", FORGER], env=env, stdin=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    try:
        wait_for(lambda: delivered_before(output, time.time()) >= 3, 30, "records of measurement_server in the file")
        mark = the_mark(home)
        writer = mark.name.removesuffix(".mark")
        # The live publisher "ended" far beyond what it published: believed, this counts about a
        # million records missing and settles the publisher, so that its real end is not counted.
        forged = json.dumps({"server": "measurement_server", "ended": [[TOPIC, writer, 1_000_000, 0]]})
        assert forger.stdin is not None
        forger.stdin.write(forged + "\n")
        forger.stdin.flush()
        wait_for(
            lambda: (
                metrics(destination)["intake"].get("handoff_announcements_refused") == 1
                or metrics(destination)["hop"].get(TOPIC, {}).get("writers_ended")
            ),
            15,
            "the forged announcement taken or refused",
        )
        hop = metrics(destination)["hop"][TOPIC]
        assert (hop["missing"], hop["writers_ended"]) == (0, 0), hop
        assert ended_keys(tmp_path / "buffer") == 0, "nothing settled for the forged end"
        (warning,) = [line for line in destination.lines if "announcement of ended publishers refused" in line]
        assert "WARN" in warning and "/intruder" in warning
        assert "dc_hop_handoff_announcements_refused_total 1" in metrics(destination, "/prometheus").splitlines()
        forger.communicate(timeout=10)
        assert forger.returncode == 0

        # The real end of that publisher: destination_server stops (nothing acknowledged from then on),
        # measurement_server is killed -9 holding what it published meanwhile; both start again and the
        # successor announces where the killed one got to.
        assert destination.stop() == 0
        stopped_at = mark_high(mark)
        wait_for(lambda: mark_high(mark) >= stopped_at + 3, 10, "records held by measurement_server")
        os.kill(measurement.process.pid, signal.SIGSTOP)  # its mark is final: written before each record
        killed_at = time.time()
        produced = mark_high(mark)
        os.kill(measurement.process.pid, signal.SIGKILL)
        measurement.process.wait()
        destination = ServerProcess("dc_destinations.server", params, env)
        successor = ServerProcess("dc_measurements.server", params, env)
        destination.wait_line("listening on")
        wait_for(
            lambda: metrics(destination)["hop"].get(TOPIC, {}).get("writers_ended") == 1, 30, "the real end counted"
        )
        hop = metrics(destination)["hop"][TOPIC]
        assert hop["missing"] >= 3, hop
        wait_for(
            lambda: delivered_before(output, killed_at) + hop["missing"] >= produced, 10, "the records before delivered"
        )
        assert delivered_before(output, killed_at) + hop["missing"] == produced
        # Committed with the next group commit, then acknowledged: the successor deletes the mark.
        wait_for(lambda: ended_keys(tmp_path / "buffer") == 1, 10, "that the end was counted, committed")
        prometheus = metrics(destination, "/prometheus").splitlines()
        assert f'dc_hop_missing_total{{topic="{TOPIC}"}} {hop["missing"]}' in prometheus
        assert f'dc_hop_gaps_total{{topic="{TOPIC}"}} 1' in prometheus
        assert f'dc_hop_writers_ended_total{{topic="{TOPIC}"}} 1' in prometheus
        assert "dc_hop_handoff_announcements_refused_total 0" in prometheus
    finally:
        if forger.poll() is None:
            forger.kill()
        for server in (successor, measurement, destination):
            if server is not None:
                if server.process.poll() is None:
                    os.kill(server.process.pid, signal.SIGCONT)
                server.stop()


def test_an_announcement_refused_while_a_foreign_node_publishes_there_is_taken_once_it_left(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A foreign publisher on the topic cannot keep DC's own announcement from being counted: refused
    while it is there, taken from DC's publisher (transient local) once it left. In one process: the
    server under its own executor, the other nodes in a second context (their own DDS participant)."""
    monkeypatch.setattr(destination_module, "FOREIGN_MEMORY_S", 0.5)
    params, _ = write_params(tmp_path)
    rclpy.init()
    others = Context()
    rclpy.init(context=others)
    server = DestinationServer(str(params))
    executor = SingleThreadedExecutor()
    executor.add_node(server)
    loop = ServerLoop(executor, server.intake)
    nodes = []

    def announce(node_name: str, ended: Ended) -> None:
        node = rclpy.create_node(node_name, context=others)
        nodes.append(node)
        msg = StringStamped()
        msg.data = ended_document("measurement_server", [ended])
        node.create_publisher(StringStamped, ENDED_TOPIC, ended_qos()).publish(msg)

    def spin_until(done: Any) -> bool:
        deadline = time.monotonic() + 15
        while not done() and time.monotonic() < deadline:
            loop.spin_once(timeout_sec=0.02)
        return bool(done())

    try:
        assert server.trigger_configure() == TransitionCallbackReturn.SUCCESS
        assert server.trigger_activate() == TransitionCallbackReturn.SUCCESS
        announce("intruder", Ended(TOPIC, 5, 1_000, 0))
        assert spin_until(lambda: server.stats.handoff_announcements_refused == 1)
        # DC's server (a node of its name) announces while the intruder is still there: refused too.
        announce("measurement_server", Ended(TOPIC, 7, 10, 4))
        assert spin_until(lambda: server.stats.handoff_announcements_refused == 2)
        assert server.hop_metrics().get(TOPIC, {}).get("writers_ended", 0) == 0
        nodes.pop(0).destroy_node()  # the intruder leaves; its announcement goes with it
        assert spin_until(lambda: server.hop_metrics().get(TOPIC, {}).get("writers_ended") == 1)
        hop = server.hop_metrics()[TOPIC]
        assert (hop["missing"], hop["gaps"]) == (6, 1), hop  # 5..10 of publisher 7; nothing of the forged one
        assert server.stats.handoff_announcements_refused == 2
    finally:
        if server.lifecycle_state in ("active", "inactive"):
            server.trigger_shutdown()
        executor.shutdown()
        server.destroy_node()
        for node in nodes:
            node.destroy_node()
        rclpy.shutdown(context=others)
        rclpy.shutdown()
