"""Logging at several severities through one helper line, on rclpy's real loggers (issue 33, item 1).

rclpy raises ``ValueError: Logger severity cannot be changed between calls`` when one line logs at
two severities on one logger. Burst logs at warning and at error level on destination_server's
logger did so from ``BurstLog``'s lines: the writer or a sender thread died, records stayed in
memory, a false ``failed`` was counted. These tests run the paths that did, on real loggers and,
end to end, through `dc-bringup` with a real HTTP receiver and a real full file system.
"""

from __future__ import annotations

import subprocess
import sys
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy.logging

from dc_core.logs import BurstLog, SeverityLogger
from tests.bringup_util import Bringup
from tests.fault_helpers import fill, tmpfs
from tests.http_receiver import Receiver, Request
from tests.test_e2e_delivery_failures import finish, publish, wait_metric, write_params

CLASH = "Logger severity cannot be changed"


def _real_logger() -> Any:
    return rclpy.logging.get_logger(f"dc_test_clash_{uuid.uuid4().hex[:8]}")


def test_burst_logs_at_two_severities_share_a_real_rclpy_logger() -> None:
    logger = _real_logger()
    warned = BurstLog(logger.warning, "retrying", quiet=0.0)
    failed = BurstLog(logger.error, "dead-lettered", quiet=0.0)
    for _ in range(3):
        warned.event(1, "HTTP 503")
        failed.event(1, "HTTP 400")
        warned.tick()
        failed.tick()


def test_a_helper_logging_at_a_severity_its_caller_chose_is_safe_on_a_severity_logger() -> None:
    logger = SeverityLogger(_real_logger())

    def helper(log: Callable[[str], Any], message: str) -> None:
        log(message)  # one line, any severity

    for method in (logger.debug, logger.info, logger.warning, logger.error, logger.fatal):
        helper(method, "said")
    for severity in ("warning", "error", "info"):
        logger.log_at(severity, "said")
    child = logger.get_child("plugin")
    assert isinstance(child, SeverityLogger)
    helper(child.error, "said")
    helper(child.warning, "said")
    with pytest.raises(TypeError):
        logger.warning("filters would be shared by every caller", once=True)  # type: ignore[call-arg]


# -- end to end: the paths that killed a thread -----------------------------------------------------


def _sequence_then(answers: list[int], then: int) -> Callable[[Request], tuple[int, bytes]]:
    calls: list[int] = []

    def respond(request: Request) -> tuple[int, bytes]:
        calls.append(1)
        status = answers[len(calls) - 1] if len(calls) <= len(answers) else then
        return status, b"ok" if status == 200 else f"status {status} set by the test".encode()

    return respond


def _no_clash(run: Bringup) -> None:
    bad = [line for line in run.stderr if CLASH in line or "Traceback" in line]
    assert not bad, "\n".join(bad)


def test_http_receiver_answering_400_503_503_400_503_then_200_gets_or_counts_every_record(tmp_path: Path) -> None:
    with (
        Receiver(_sequence_then([400, 503, 503, 400, 503], then=200)) as receiver,
        Bringup(write_params(tmp_path, receiver.port), tmp_path / "home") as run,
    ):
        run.wait_ready()
        finish(publish(run, 600, rate=100))
        wait_metric(run, lambda m: m["buffered"] == 0 and m["sent"] > 0, 30, "the first 600 sent or dead-lettered")
        # The second wave: with the writer or the sender dead, these waited in memory forever.
        finish(publish(run, 300, rate=100, padding=1))  # told apart by their padding
        after = wait_metric(
            run, lambda m: m["sent"] + m["dead_lettered"] == 900, 30, "900 records sent or dead-lettered"
        )
        _no_clash(run)
        assert any("records dead-lettered" in line for line in run.stderr)
        assert any("delivery failed, will retry" in line for line in run.stderr)
    delivered = Counter((int(r["seq"]), len(r["pad"])) for r in receiver.records())
    assert set(delivered.values()) == {1}, "nothing delivered twice"
    assert len(delivered) == after["sent"]
    assert after["dead_lettered"] > 0 and after["dropped"] == 0 and after["buffered"] == 0
    assert len(delivered) + after["dead_lettered"] == 900, "delivered + counted = sent"


def test_http_receiver_answering_503_then_401_dead_letters_and_says_so_without_a_false_failure(
    tmp_path: Path,
) -> None:
    total = 20
    with (
        Receiver(_sequence_then([503], then=401)) as receiver,
        Bringup(write_params(tmp_path, receiver.port), tmp_path / "home") as run,
    ):
        run.wait_ready()
        finish(publish(run, total, rate=50))
        after = wait_metric(run, lambda m: m["dead_lettered"] == total, 30, f"{total} records dead-lettered")
        run.wait_stderr("records dead-lettered")
        _no_clash(run)
    assert after["last_error"].startswith("rejected: HTTP 401"), after["last_error"]
    # One failure per answer that was not a success: the 503 and each 401, nothing counted for a log line.
    refused = [r for r in receiver.requests if r.status != 200]
    assert after["failed"] == len(refused), (after, [r.status for r in receiver.requests])
    assert after["buffered"] == 0 and after["sent"] == 0


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real file system of 4 MB (tmpfs): the buffer meets a real ENOSPC."""
    with tmpfs(tmp_path / "disk") as disk:
        yield disk


def test_a_full_disk_under_the_buffer_and_back_delivers_everything(tmp_path: Path, small_disk: Path) -> None:
    receiver_down = [True]

    def respond(request: Request) -> tuple[int, bytes]:
        return (503, b"down") if receiver_down[0] else (200, b"ok")

    with Receiver(respond) as receiver:
        params = write_params(tmp_path, receiver.port)
        params.write_text(params.read_text().replace(str(tmp_path / "buffer"), str(small_disk)))
        with Bringup(params, tmp_path / "home") as run:
            run.wait_ready()
            finish(publish(run, 100, rate=100, padding=200))  # retried: a failure logged at warning level
            wait_metric(run, lambda m: m["buffered"] == 100 and m["retried"] > 0, 30, "100 records waiting")
            filler = small_disk / "filler"
            fill(filler)
            finish(publish(run, 400, rate=200, padding=201))
            run.wait_stderr("group commit failed", 30)  # logged at error level from the same helper
            receiver_down[0] = False
            filler.unlink()
            after = wait_metric(run, lambda m: m["sent"] == 500, 60, "all 500 records sent once space returned")
            _no_clash(run)
    delivered = Counter((int(r["seq"]), len(r["pad"])) for r in receiver.records())
    assert sorted(delivered) == sorted([(n, 200) for n in range(100)] + [(n, 201) for n in range(400)])
    assert set(delivered.values()) == {1}
    assert after["dropped"] == 0 and after["dead_lettered"] == 0


STRING_STAMPED_PARAMS = """
measurement_server:
  ros__parameters:
    measurement_plugins: ["seq"]
    seq:
      plugin: "dc_measurements/StringStamped"
      topic: "/robot/seq"
      timer_based: true
      polling_interval: 60000
      enable_validator: false
      tags: ["out"]
destination_server:
  ros__parameters:
    flb:
      storage_path: "{buffer}"
    destination_plugins: ["out"]
    out:
      plugin: "dc_destinations/Stdout"
      inputs: ["/dc/measurement/seq"]
"""

# A malformed record (its burst log is at error level), then two records before a poll (the second
# replaces the first: warning level), on one plugin logger.
MIXED_PUBLISHER = """
import sys, time
import rclpy
from rclpy.duration import Duration
from rclpy.qos import QoSProfile, ReliabilityPolicy
from dc_interfaces.msg import StringStamped
rclpy.init()
node = rclpy.create_node("mixed_records")
pub = node.create_publisher(StringStamped, "/robot/seq", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
deadline = time.monotonic() + 30
while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
for text in ["{not json", '{"n": 1}', '{"n": 2}', "[also not an object]", '{"n": 3}']:
    msg = StringStamped()
    msg.data = text
    pub.publish(msg)
    time.sleep(0.05)
sys.exit(0 if pub.wait_for_all_acked(Duration(seconds=30)) else 4)
"""


def test_string_stamped_logs_malformed_and_replaced_records_from_one_callback(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(STRING_STAMPED_PARAMS.format(buffer=tmp_path / "buffer"))
    with Bringup(params, tmp_path / "home") as run:
        run.wait_ready()
        publisher = subprocess.run(
            [sys.executable, "-c", MIXED_PUBLISHER], env=run.env, capture_output=True, text=True, timeout=60
        )
        assert publisher.returncode == 0, publisher.stdout + publisher.stderr
        run.wait_stderr("malformed records on /robot/seq not published")
        run.wait_stderr("replaced by a newer one before a poll")
        _no_clash(run)
        assert not [line for line in run.stderr if "callback failed" in line]
