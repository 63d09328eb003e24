"""The acknowledged hand-off measurement_server → destination_server across kill -9, with real processes.

What a user relies on (docs/delivery.md, "The hand-off"): with default parameters, records published
while destination_server is down reach the destinations once it is back, however long it took and
however many records that was: measurement_server keeps each one until destination_server has
committed it, and sends again what was not acknowledged.
"""

from __future__ import annotations

import contextlib
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

from tests.bringup_util import Bringup, server_env
from tests.test_e2e_delivery_restart import (
    INPUT_DEPTH,
    PUBLISHER,
    ServerProcess,
    hop_metrics,
    numbers_in,
    publish,
    ranges,
    wait_for,
    write_params,
)

pytestmark = pytest.mark.e2e

TOTAL = 6_000
RATE = 1_000.0
KILL_AT = 2_000
HELD_BACK_S = 30.0


def handoff_metrics(lines: list[str]) -> dict[str, Any]:
    """The `handoff` section of measurement_server's metrics (its HTTP server logged its address)."""
    address = [
        m.group(1) for line in lines if "measurement_server" in line and (m := re.search(r"on (http://\S+)", line))
    ]
    with urllib.request.urlopen(address[-1] + "metrics", timeout=5) as response:
        document: dict[str, Any] = json.load(response)
    return dict(document["handoff"]["/dc/measurement/numbers"])


def hop_section(lines: list[str]) -> dict[str, dict[str, int]]:
    """Per input topic, the hop counters of the destination_server that logged last."""
    address = [
        m.group(1)
        for line in lines
        if "destination_server" in line and (m := re.search(r"metrics HTTP server on (http://\S+)", line))
    ]
    with urllib.request.urlopen(address[-1] + "metrics", timeout=5) as response:
        document: dict[str, Any] = json.load(response)
    return dict(document["hop"])


def hop_missing(lines: list[str], counter: str = "missing") -> dict[str, int]:
    """Per input topic, `missing` (or ``counter``) in the hop section of the destination_server that logged last."""
    return {topic: int(counts[counter]) for topic, counts in hop_section(lines).items()}


def active_pid(run: Bringup, server: str) -> int:
    """The pid of the last ``server`` the lifecycle manager reported active."""
    line = [s for s in run.stderr if f"{server} active (pid " in s][-1]
    return int(line.rsplit("pid ", 1)[1].rstrip(")"))


def single_process_pid(run: Bringup) -> int:
    line = [s for s in run.stderr if "DC is up in one process (pid" in s][-1]
    return int(line.split("(pid ", 1)[1].split(")", 1)[0])


def delivered_or_counted(output: Path, lines: list[str], counter: str = "missing") -> int:
    """Records in the File output plus those destination_server counts missing (``counter``: or those
    every run on its buffer counted, ``missing_lifetime``): what a loss must add up to.

    -1 while the destination_server that logged last does not answer: the one killed, until its successor
    says where its metrics are (a fresh-clone run read the dead one's address in between).
    """
    try:
        missing = hop_missing(lines, counter)
    except OSError:  # urllib's URLError included
        return -1
    return len(numbers_in(output)) + sum(missing.values())


def committed_losses(buffer: Path) -> dict[str, int]:
    """Per input topic, the records lost before destination_server as its buffer file holds them."""
    with contextlib.closing(sqlite3.connect(f"file:{buffer}?mode=ro", uri=True, timeout=5)) as db:
        return {str(topic): int(missing) for topic, missing in db.execute("SELECT topic, missing FROM hop_losses")}


def with_metrics(params: Path) -> None:
    """measurement_server's metrics HTTP server on a free port, to read its hand-off counters."""
    text = params.read_text()
    params.write_text(
        text.replace(
            'measurement_plugins: ["numbers"]',
            'measurement_plugins: ["numbers"]\n    http_server: true\n    http_port: 0',
        )
    )


def assert_every_record_once_or_more(output: Path, hop: dict[str, Any]) -> None:
    counts = numbers_in(output)
    absent = [n for n in range(TOTAL) if n not in counts]
    assert not absent, f"{len(absent)} records lost: {ranges(absent)}; hop {hop}"
    assert hop["missing"] == 0, hop


def test_kill_9_of_destination_server_at_1000_records_per_s_loses_none(tmp_path: Path) -> None:
    params, output = write_params(tmp_path)
    with_metrics(params)
    with Bringup(params, tmp_path / "home", args=["--bond-timeout", "5"]) as run:
        run.wait_ready()
        publisher = publish(run.env, 0, TOTAL, RATE)
        run.wait_until(lambda: len(numbers_in(output)) >= KILL_AT, 60, f"{KILL_AT} records in the file")
        os.kill(active_pid(run, "destination_server"), signal.SIGKILL)
        published, _ = publisher.communicate(timeout=TOTAL / RATE + 60)
        assert publisher.returncode == 0, published
        try:
            run.wait_until(lambda: len(numbers_in(output)) >= TOTAL, 60, "every record in the file")
        finally:
            hop = hop_metrics(run.stderr)
            handoff = handoff_metrics(run.stderr)
            counts = numbers_in(output)
            print(
                f"\nkill -9 at {RATE:.0f}/s: {len(counts)} of {TOTAL} delivered, "
                f"{sum(c - 1 for c in counts.values())} twice; hop {hop}; hand-off {handoff}"
            )
        assert_every_record_once_or_more(output, hop)
        wait_for(lambda: handoff_metrics(run.stderr)["unacked"] == 0, 15, "every record acknowledged")
        assert handoff_metrics(run.stderr)["dropped"] == 0
        assert run.stop() == 0
    # Everything was acknowledged before the stop: measurement_server reports nothing held.
    assert not [s for s in run.stderr if "not acknowledged by destination_server" in s]


def test_kill_9_of_destination_server_back_only_30_s_later_loses_none(tmp_path: Path) -> None:
    params, output = write_params(tmp_path)
    env = server_env(tmp_path / "home")
    with_metrics(params)
    # Started without dc-bringup, whose manager would restart destination_server at once.
    measurement = ServerProcess("dc_measurements.server", params, env)
    destination = ServerProcess("dc_destinations.server", params, env)
    second: ServerProcess | None = None
    try:
        destination.wait_line("listening on")
        publisher = publish(env, 0, TOTAL, RATE)
        wait_for(lambda: len(numbers_in(output)) >= KILL_AT, 60, f"{KILL_AT} records in the file")
        destination.process.send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        published, _ = publisher.communicate(timeout=TOTAL / RATE + 60)
        assert publisher.returncode == 0, published
        held = handoff_metrics(measurement.lines)
        assert held["unacked"] > 1_000, f"more than the history waits for destination_server: {held}"
        # The downtime under test: measurement_server must hold the records this long.
        time.sleep(max(0.0, HELD_BACK_S - (time.monotonic() - killed_at)))
        second = ServerProcess("dc_destinations.server", params, env)
        second.wait_line("metrics HTTP server on")
        wait_for(lambda: len(numbers_in(output)) >= TOTAL, 60, "every record in the file")
        hop = hop_metrics(second.lines)
        wait_for(lambda: handoff_metrics(measurement.lines)["unacked"] == 0, 15, "every record acknowledged")
        handoff = handoff_metrics(measurement.lines)
    finally:
        for server in (second, destination, measurement):
            if server is not None:
                server.stop()
    counts = numbers_in(output)
    print(
        f"\nkill -9, back {HELD_BACK_S:.0f} s later: {len(counts)} of {TOTAL} delivered, "
        f"{sum(c - 1 for c in counts.values())} twice; held at the kill {held}; hop {hop}; hand-off {handoff}"
    )
    assert_every_record_once_or_more(output, hop)
    assert handoff["dropped"] == 0 and handoff["resent"] > 0, handoff


SINGLE_TOTAL = 3_000


def publish_tagged(env: dict[str, str], first: int, count: int, rate: float, *flags: str) -> subprocess.Popen[str]:
    """The restart tests' publisher, its records tagged for the File destination (no measurement adds the tag)."""
    script = PUBLISHER.replace('json.dumps({"n": first + i})', 'json.dumps({"n": first + i, "tags": ["file"]})')
    assert script != PUBLISHER
    return subprocess.Popen(
        [sys.executable, "-c", script, str(first), str(count), str(rate), str(INPUT_DEPTH), *flags],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


SINGLE_RATE = 200.0


@pytest.mark.parametrize("path", ["through a StringStamped measurement", "straight to destination_server"])
def test_single_process_kill_9_counts_what_your_node_published_meanwhile(tmp_path: Path, path: str) -> None:
    # Your node publishes on a volatile topic: what it publishes while the servers' process is down
    # is lost, and the restarted process has only the buffer to know where your node was (its
    # publisher continues its numbers).
    params, output = write_params(tmp_path)
    straight = path == "straight to destination_server"
    if straight:
        params.write_text(
            params.read_text().replace('inputs: ["/dc/measurement/numbers"]', 'inputs: ["/robot/numbers"]')
        )
    # The publisher waits after 600 records until the process is killed: on a loaded machine it had
    # published all of them before the file showed 600, and the kill then lost nothing to count.
    gate = tmp_path / "publish-on"
    os.mkfifo(gate)
    with Bringup(params, tmp_path / "home", args=["--single-process", "--bond-timeout", "3"]) as run:
        run.wait_ready()
        publisher = (publish_tagged if straight else publish)(
            run.env, 0, SINGLE_TOTAL, SINGLE_RATE, f"--pause-at=600:{gate}"
        )
        try:
            run.wait_until(lambda: len(numbers_in(output)) >= 600, 60, "600 records in the file")
        except AssertionError:
            publisher.kill()  # it would wait on its gate forever
            raise
        os.kill(single_process_pid(run), signal.SIGKILL)
        with open(gate, "w") as go:  # the publisher, waiting on the other end, goes on
            go.write("go")
        run.wait_until(lambda: sum("DC is up in one process" in s for s in run.stderr) == 2, 60, "the process up again")
        published, _ = publisher.communicate(timeout=SINGLE_TOTAL / SINGLE_RATE + 60)
        assert publisher.returncode == 0, published

        try:
            run.wait_until(
                lambda: delivered_or_counted(output, run.stderr) >= SINGLE_TOTAL,
                90,
                "every record delivered or counted",
            )
        finally:
            counts = numbers_in(output)
            hop = hop_missing(run.stderr)
            lost_lines = [s for s in run.stderr if "never arrived" in s]
            print(
                f"\nsingle process, {path}, kill -9 at {SINGLE_RATE:.0f}/s: {len(counts)} delivered, hop {hop}; {lost_lines}"
            )
    absent = [n for n in range(SINGLE_TOTAL) if n not in counts]
    assert absent, "the kill lost records: what this test is about"
    assert sum(hop.values()) == len(absent), f"lost {ranges(absent)}, counted {hop}"
    assert lost_lines, "the loss is logged"


def test_beyond_the_publishers_limit_the_oldest_are_dropped_and_every_one_is_counted(tmp_path: Path) -> None:
    # A hand-off of 500 records and a history of 100: destination_server down for ~3 s at 1,000/s.
    params, output = write_params(tmp_path, history_depth=100)
    params.write_text(params.read_text().replace("unacked_limit_records: 200000", "unacked_limit_records: 500"))
    with_metrics(params)
    with Bringup(params, tmp_path / "home", args=["--bond-timeout", "5"]) as run:
        run.wait_ready()
        publisher = publish(run.env, 0, TOTAL, RATE)
        run.wait_until(lambda: len(numbers_in(output)) >= KILL_AT, 60, f"{KILL_AT} records in the file")
        os.kill(active_pid(run, "destination_server"), signal.SIGKILL)
        published, _ = publisher.communicate(timeout=TOTAL / RATE + 60)
        assert publisher.returncode == 0, published

        # By every run on the buffer: a destination_server restarted once more (by the bond, on a loaded
        # machine) takes this run's own counters with it, not the buffer's totals.
        try:
            run.wait_until(
                lambda: delivered_or_counted(output, run.stderr, "missing_lifetime") >= TOTAL,
                60,
                "every record delivered or counted",
            )
        finally:
            counts = numbers_in(output)
            missing = hop_missing(run.stderr, "missing_lifetime")
            handoff = handoff_metrics(run.stderr)
            starts = sum("destination_server active (pid " in s for s in run.stderr)
            losses = [s for s in run.stderr if "never arrived" in s or "missing" in s]
            print(
                f"\nlimit 500, kill -9 at {RATE:.0f}/s: {len(counts)} delivered, missing {missing}; hand-off {handoff}; "
                f"destination_server started {starts} times; its loss lines: {losses}"
            )
        dropped_lines = [s for s in run.stderr if "records dropped before destination_server acknowledged them" in s]
        absent = [n for n in range(TOTAL) if n not in counts]
        assert absent and handoff["dropped"] > 0, "the limit was reached: what this test is about"
        assert sum(missing.values()) == len(absent), f"lost {ranges(absent)}, counted {missing}"
        assert dropped_lines, "the publisher logs its drops"

        # The count outlives the process that made it: committed to the buffer, then that server killed too.
        buffer = tmp_path / "buffer" / "delivery.sqlite3"
        wait_for(lambda: committed_losses(buffer) == missing, 15, f"the buffer's totals at {missing}")
        os.kill(active_pid(run, "destination_server"), signal.SIGKILL)
        run.wait_until(
            lambda: sum("destination_server active (pid " in s for s in run.stderr) > starts, 60, "a third start"
        )
        run.wait_until(lambda: delivered_or_counted(output, run.stderr) >= 0, 30, "its metrics")
        after = hop_section(run.stderr)
        assert {t: c["missing_lifetime"] for t, c in after.items()} == missing, after
        assert all(c["missing"] == 0 for c in after.values()), f"counted again by the next run: {after}"
