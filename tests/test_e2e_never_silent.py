"""A thread that dies in destination_server, and a stop that cannot commit, through `dc-bringup` (issue 33, items 2-3).

A fault hook (tests/fault_hooks/sitecustomize.py) makes one method raise once in the servers'
processes: the thread running it dies. What a user relies on: the traceback is in the log, the
server reports itself unhealthy, the lifecycle manager stops it in order and restarts it, and every
record published reaches the receiver (delivered + counted = sent).
"""

from __future__ import annotations

import json
import re
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.bringup_util import Bringup, dc
from tests.fault_helpers import fault_env, fault_gate, fill, tmpfs
from tests.http_receiver import Receiver, Request
from tests.test_e2e_delivery_failures import finish, publish, status, wait_metric, write_params

pytestmark = pytest.mark.e2e

TOTAL = 300


@pytest.mark.parametrize(
    "target",
    ["dc_destinations.commit:GroupCommitter._commit", "dc_destinations.sender:Sender._idle"],
    ids=["writer", "sender"],
)
@pytest.mark.usefixtures("bringup_mode")
def test_a_delivery_thread_that_dies_is_logged_and_its_server_restarted_without_loss(
    tmp_path: Path, target: str
) -> None:
    with (
        Receiver() as receiver,
        fault_gate(tmp_path) as gate,
        Bringup(
            write_params(tmp_path, receiver.port), tmp_path / "home", env=fault_env(tmp_path, target, gate=gate.path)
        ) as run,
    ):
        run.wait_ready()
        # In --single-process the restart is of every server, and records a volatile publisher sends
        # meanwhile are lost (not this test's subject): the thread dies once destination_server has
        # received every record (the thread is held at its fault until then).
        finish(publish(run, TOTAL, rate=1000))
        _wait_until_received(run, TOTAL)
        gate.open()
        run.wait_until(lambda: (tmp_path / "fault-raised").exists(), 30, "the injected failure")
        died = run.wait_stderr("the thread died (thread_failures 1)")
        assert "RuntimeError: injected by the test into " + target in died
        run.wait_stderr("Traceback (most recent call last)")
        run.wait_stderr("reports itself unhealthy")
        _wait_for_every_record(run, receiver)
        after = _web_metrics_of_the_last_start(run)
    delivered = Counter(int(r["seq"]) for r in receiver.records())
    assert sorted(delivered) == list(range(TOTAL)), "delivered + counted = sent, nothing counted"
    assert after["dropped"] == 0 and after["buffered"] == 0
    assert not any("could not be committed" in line for line in run.stderr)


def _wait_until_received(run: Bringup, count: int, timeout: float = 30) -> None:
    """Until destination_server took ``count`` records from the measurement topic (copies sent again not counted)."""
    deadline = time.monotonic() + timeout
    while True:
        hop = status(run)["hop"].get("/dc/measurement/seq", {})
        received = int(hop.get("received", 0)) - int(hop.get("duplicates", 0))
        if received >= count:
            return
        assert time.monotonic() < deadline, f"destination_server received {received} of {count} records: {hop}"
        time.sleep(0.2)


def _wait_for_every_record(run: Bringup, receiver: Receiver) -> None:
    try:
        run.wait_until(lambda: len({int(r["seq"]) for r in receiver.records()}) == TOTAL, 60, "every record")
    except AssertionError as exc:
        missing = sorted(set(range(TOTAL)) - {int(r["seq"]) for r in receiver.records()})
        raise AssertionError(f"missing seqs {missing}\n{exc}") from None


def _web_metrics_of_the_last_start(run: Bringup) -> dict[str, Any]:
    """`dc status --json` of the restarted destination_server (a new port: http_port 0), once its queue is empty."""
    run.wait_stderr("reports itself unhealthy")
    deadline = time.monotonic() + 30
    while True:
        # The restart may still be under way: the last port logged, once it answers.
        line = [line for line in run.stderr if "destination_server]: metrics HTTP server on http://" in line][-1]
        match = re.search(r"http://[^:/]+:(\d+)/", line)
        assert match, line
        result = dc("status", "--json", "--port", match.group(1), env=run.env)
        if result.returncode == 0:
            metrics: dict[str, Any] = json.loads(result.stdout)["destinations"]["web"]
            if metrics["buffered"] == 0:
                return metrics
        assert time.monotonic() < deadline, result.stderr or result.stdout
        time.sleep(0.2)


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    with tmpfs(tmp_path / "disk") as disk:
        yield disk


def test_a_stop_that_cannot_commit_names_the_number_of_records_lost(tmp_path: Path, small_disk: Path) -> None:
    def accept(request: Request) -> tuple[int, bytes]:
        return 200, b"ok"

    with Receiver(accept) as receiver:
        params = write_params(tmp_path, receiver.port)
        params.write_text(params.read_text().replace(str(tmp_path / "buffer"), str(small_disk)))
        with Bringup(params, tmp_path / "home") as run:
            run.wait_ready()
            finish(publish(run, 50, rate=100, padding=200))
            wait_metric(run, lambda m: m["sent"] == 50, 30, "the first 50 delivered")
            fill(small_disk / "filler")
            finish(publish(run, 200, rate=200, padding=201))
            run.wait_stderr("group commit failed", 30)
            wait_metric(run, lambda m: True, 5, "the metrics")
            code = run.stop()
        assert code == 0, "\n".join(run.stderr[-30:])
    lost = [line for line in run.stderr if "could not be committed at the stop" in line]
    assert len(lost) == 1, "\n".join(run.stderr[-40:])
    assert "delivery buffer: 200 records held in memory could not be committed" in lost[0], lost[0]
    delivered = {int(r["seq"]) for r in receiver.records() if len(r["pad"]) == 200}
    assert len(delivered) == 50 and not [r for r in receiver.records() if len(r["pad"]) == 201]
    assert len(delivered) + 200 == 250, "delivered + counted = sent"


def test_the_status_servers_thread_dying_restarts_destination_server_without_loss(tmp_path: Path) -> None:
    target = "dc_core.http_status:_Server.serve_forever"
    with (
        Receiver() as receiver,
        Bringup(write_params(tmp_path, receiver.port), tmp_path / "home", env=fault_env(tmp_path, target)) as run,
    ):
        run.wait_ready()
        died = run.wait_stderr("thread dc-status-http: RuntimeError: injected by the test")
        assert "the thread died (thread_failures 1)" in died
        run.wait_stderr("destination_server reports itself unhealthy")
        finish(publish(run, TOTAL, rate=1000))
        run.wait_until(lambda: len({int(r["seq"]) for r in receiver.records()}) == TOTAL, 60, "every record")
        after = _web_metrics_of_the_last_start(run)
    assert sorted(Counter(int(r["seq"]) for r in receiver.records())) == list(range(TOTAL))
    assert after["dropped"] == 0


NETWORK_PARAMS = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["net"]
    net:
      plugin: "dc_measurements/Network"
      polling_interval: 300
      ping_address: "127.0.0.1"
      ping_method: "tcp"
      ping_tcp_port: 9
      tags: ["out"]
destination_server:
  ros__parameters:
    flb:
      storage_path: "{buffer}"
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/net"]
"""


def test_a_measurement_servers_worker_failing_restarts_it_and_collection_resumes(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(NETWORK_PARAMS.format(buffer=tmp_path / "buffer"))
    target = "dc_core.worker:Worker._hand_over"  # destination_server runs a Worker too (/diagnostics)
    env = fault_env(tmp_path, target, only_in="dc_measurements.server")
    with Bringup(params, tmp_path / "home", env=env) as run:
        run.wait_ready()
        died = run.wait_stderr("thread measurement_server-worker (handing over a finished job): RuntimeError")
        assert "the thread died (thread_failures 1)" in died
        run.wait_stderr("measurement_server reports itself unhealthy")
        before = len(run.records())
        run.wait_records(before + 3, timeout=30)  # the restarted server collects again
