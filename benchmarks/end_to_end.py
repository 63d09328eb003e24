"""End-to-end benchmark of destination_server against the raw rclpy transport, in one run.

    .venv/bin/python benchmarks/end_to_end.py [--transports single,intake] [--runs 1] [--json PATH]

Every figure comes from separate processes on this machine (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
a ROS domain of its own), so the ratios compare like with like:

1. transport: a publisher process floods (or paces at 1,000/s) StringStamped records of ~200 bytes
   to a bare rclpy subscriber process (the transport's limit), one per --transports kind:
   ``single``, rclpy's SingleThreadedExecutor in a ``spin_once`` loop (what destination_server used
   before its intake, and what a plain rclpy node does); ``intake``, the same loop as
   destination_server's (dc_core.lifecycle.ServerLoop: the subscription taken by dc_core.intake,
   the executor for the rest) (the ``events`` kind, rclpy's experimental EventsExecutor, went with
   dc_core/executors.py: DC's servers cannot use it, docs/performance.md);
2. intake: the same publisher to a real destination_server process (`python -m
   dc_destinations.server PARAMS --autostart`) whose File destination is down (its folder is
   missing), so the committed rows stay in the SQLite buffer: records/s from the first publish to
   the commit of 95 % of the records committed (to the arrival of 95 % in (1): a few records resent
   late by the reliable protocol must not set the rate), for storage_sync normal and full, and the
   ratio to each (1) (target >= 80 %);
3. drain: a buffer of --backlog records → File destination, records/s;
4. cost: CPU seconds per 1,000 records of destination_server at a paced 1,000/s (File destination
   up) against each bare subscriber's in the same run (target within 1.3x), from /proc/<pid>/stat
   utime+stime over the same window: from the first publish to 2 s after the last;
5. memory: VmRSS/VmHWM of destination_server started on the --backlog buffer with its destination
   down, then its peak while delivering the backlog.

destination_server always runs as shipped (`python -m dc_destinations.server PARAMS --autostart`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import random
import shutil
import signal
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

REPO = Path(__file__).resolve().parent.parent
TOPIC = "/bench/records"
FORWARDED = "/bench/forwarded"  # where the bare forwarder publishes again what it takes
DESTINATION = "bench"
SETTLE_S = 2.0  # CPU window ends this long after the last publish, for the bare subscriber and the server
START_DEADLINE_S = 30.0
CLK_TCK = os.sysconf("SC_CLK_TCK")
INTAKE_TARGET = 0.8
BULK = 0.95  # rates are those of the first 95 % of the records delivered
CPU_TARGET = 1.3
SERVER = "dc"  # the executor column of destination_server's rows: run_server's own loop

# ~200 bytes of JSON once tagged, like design.md §7's figures.
_DATA = {
    "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
    "memory": {"used": 123456789, "percent": 45.6},
    "robot_name": "bench",
    "id": "robot-1",
    "run_id": "3",
    "name": "system",
    "tags": [DESTINATION],
}

# ---------------------------------------------------------------------------------------------
# child roles
# ---------------------------------------------------------------------------------------------


def _payloads(count: int) -> list[str]:
    return [json.dumps({**_DATA, "n": n}, separators=(",", ":")) for n in range(count)]


def role_publisher(count: int, rate: float) -> None:
    """Wait for a subscriber, print ready, wait for 'go', publish, print what was sent, wait for EOF."""
    import rclpy

    from dc_core.qos import RECORD_QOS
    from dc_interfaces.msg import StringStamped

    rclpy.init()
    node = rclpy.create_node(f"bench_publisher_{os.getpid()}")
    publisher = node.create_publisher(StringStamped, TOPIC, RECORD_QOS)
    messages = []
    for text in _payloads(count):
        msg = StringStamped()
        msg.data = text
        messages.append(msg)
    deadline = time.monotonic() + START_DEADLINE_S
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    if publisher.get_subscription_count() < 1:
        print("nomatch", flush=True)
        return
    time.sleep(0.5)  # let discovery finish on the subscriber's side too
    print("ready", flush=True)
    sys.stdin.readline()
    clock = node.get_clock()
    first = time.time()
    start = time.perf_counter()
    for i, msg in enumerate(messages):
        if rate > 0:
            delay = start + i / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        msg.header.stamp = clock.now().to_msg()
        publisher.publish(msg)
    last = time.time()
    print(json.dumps({"sent": count, "t_first": first, "t_last": last}), flush=True)
    sys.stdin.read()  # keep the writer (and its reliable history) alive until the parent is done
    node.destroy_node()
    rclpy.shutdown()


def role_subscriber(kind: str, topic: str = TOPIC) -> None:
    """A bare subscriber: counts records; ``intake`` with run_server's loop, else an executor's spin_once loop.

    ``forward``: the cheapest forwarder, on the intake loop too: each record taken as its bytes and
    published again as they are on ``FORWARDED`` (with DC's record QoS, as measurement_server does).
    """
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from dc_core.intake import Intake
    from dc_core.lifecycle import ServerLoop
    from dc_core.qos import RECORD_QOS, VOLATILE_RECORD_QOS
    from dc_interfaces.msg import StringStamped

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.set())
    node = rclpy.create_node(f"bench_subscriber_{os.getpid()}")
    state = {"count": 0, "last": 0.0}

    def on_message(msg: Any) -> None:
        state["count"] += 1
        state["last"] = time.time()

    on_intake = kind in ("intake", "forward")
    if kind not in ("single", "intake", "forward"):
        raise SystemExit(f"unknown subscriber kind {kind!r}: single, intake or forward")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    intake = Intake(node)
    if kind == "forward":
        forwarded = node.create_publisher(StringStamped, FORWARDED, RECORD_QOS)

        def forward(serialised: Any, info: Any) -> None:
            forwarded.publish(serialised)
            on_message(serialised)

        intake.subscribe(StringStamped, topic, forward, VOLATILE_RECORD_QOS).raw = True
    elif kind == "intake":
        intake.subscribe(StringStamped, topic, lambda msg, info: on_message(msg), VOLATILE_RECORD_QOS)
    else:
        node.create_subscription(StringStamped, topic, on_message, VOLATILE_RECORD_QOS)
    reported = [-1]

    def report() -> None:  # a line every 0.2 s at most: negligible beside the records
        if state["count"] != reported[0]:
            reported[0] = int(state["count"])
            print(f"{state['count']} {state['last']:.6f}", flush=True)

    node.create_timer(0.2, report)
    print("ready", flush=True)
    if on_intake:
        ServerLoop(executor, intake).run(stop, _StderrLog())
    else:
        while not stop.is_set():  # what a plain rclpy node does; SIGTERM is seen within 0.1 s
            executor.spin_once(timeout_sec=0.1)
    report()
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()


def checkouts(parser: argparse.ArgumentParser, specs: list[str]) -> dict[str, Path]:
    """``NAME=PATH`` arguments as DC checkouts by name (for benchmarks that compare code trees in turns)."""
    trees = {}
    for spec in specs:
        name, _, path = spec.partition("=")
        if not path or not (Path(path) / "dc_core").is_dir():
            parser.error(f"{spec!r}: expected NAME=PATH of a DC checkout")
        trees[name] = Path(path).resolve()
    return trees


class _StderrLog:
    def error(self, message: str) -> None:
        print(f"error {message}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# process plumbing
# ---------------------------------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14 and 15)


def memory_mb(pid: int) -> dict[str, float]:
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0]) / 1024
    return values


class Child:
    """A child process; its stdout lines are collected by a thread so that it never blocks."""

    def __init__(self, argv: list[str], env: dict[str, str], log: Path, *, stdin: bool = False) -> None:
        self.log = log.open("w")
        self.process = subprocess.Popen(
            argv,
            env=env,
            cwd=REPO,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
        )
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int:
        return self.process.pid

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with self._changed:
                self.lines.append(line.rstrip("\n"))
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def wait_line(self, predicate: Callable[[str], bool], timeout: float) -> str | None:
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.lines:
                    if predicate(line):
                        return line
                left = deadline - time.monotonic()
                if left <= 0 or (self.process.poll() is not None and not self._reader.is_alive()):
                    return None
                self._changed.wait(min(left, 0.2))

    def log_text(self) -> str:
        """What the child wrote to stderr so far (ROS logs go there)."""
        return Path(self.log.name).read_text(errors="replace")

    def send(self, text: str) -> None:
        stdin: IO[str] | None = self.process.stdin
        assert stdin is not None
        stdin.write(text)
        stdin.flush()

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL after 10 s; the exit code (None when it had to be killed)."""
        code: int | None = None
        if self.process.poll() is None:
            if self.process.stdin is not None:
                with contextlib.suppress(OSError):
                    self.process.stdin.close()
            self.process.send_signal(signal.SIGTERM)
            try:
                code = self.process.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        else:
            code = self.process.returncode
        self._reader.join(timeout=5.0)
        self.log.close()
        return code


@contextlib.contextmanager
def running(child: Child) -> Iterator[Child]:
    try:
        yield child
    finally:
        child.stop()


class Bench:
    def __init__(self, workdir: Path, domain: int) -> None:
        self.workdir = workdir
        self.env = dict(os.environ)
        self.env.update(
            ROS_DOMAIN_ID=str(domain),
            ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
            ROS_LOG_DIR=str(workdir / "roslog"),
            XDG_DATA_HOME=str(workdir / "xdg"),
            PYTHONUNBUFFERED="1",
        )
        self._seq = 0

    def _log(self, name: str) -> Path:
        self._seq += 1
        return self.workdir / f"{self._seq:02d}-{name}.log"

    def me(self, *args: str) -> list[str]:
        return [sys.executable, str(Path(__file__).resolve()), *args]

    def publisher(self, count: int, rate: float) -> Child:
        return Child(
            self.me("--role", "publisher", "--count", str(count), "--rate", str(rate)),
            self.env,
            self._log("publisher"),
            stdin=True,
        )

    def subscriber(self, kind: str, topic: str = TOPIC) -> Child:
        return Child(
            self.me("--role", "subscriber", "--executor", kind, "--topic", topic),
            self.env,
            self._log(f"subscriber-{kind}"),
        )

    def server(self, params: Path) -> Child:
        argv = [sys.executable, "-m", "dc_destinations.server", str(params), "--autostart"]
        return Child(argv, self.env, self._log("server"))

    def params(self, name: str, sync: str, destination_up: bool) -> tuple[Path, Path, Path]:
        """A destination_server parameter file; returns it, the buffer folder and the output folder."""
        self._seq += 1
        folder = self.workdir / f"{self._seq:02d}-{name}"
        folder.mkdir(parents=True)
        buffer, out = folder / "buffer", folder / "out"
        if destination_up:
            out.mkdir(exist_ok=True)
        params = folder / "params.yaml"
        params.write_text(
            f"""destination_server:
  ros__parameters:
    flb:
      storage_path: "{buffer}"
      storage_sync: "{sync}"
      scheduler_base: 0.2
      scheduler_cap: 1.0
    destination_plugins: ["{DESTINATION}"]
    {DESTINATION}:
      plugin: "dc_destinations/File"
      inputs: ["{TOPIC}"]
      path: "{out}"
      file: "records.jsonl"
      mkdir: false
"""
        )
        return params, buffer, out


# ---------------------------------------------------------------------------------------------
# buffer readings (a read-only connection of our own; WAL lets it read while the server writes)
# ---------------------------------------------------------------------------------------------


class BufferReader:
    def __init__(self, folder: Path) -> None:
        self.path = folder / "delivery.sqlite3"
        self._conn: sqlite3.Connection | None = None

    def _connection(self) -> sqlite3.Connection | None:
        if self._conn is None and self.path.exists():
            try:
                self._conn = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, timeout=5.0)
            except sqlite3.Error:
                return None
        return self._conn

    def counters(self) -> tuple[int, int]:
        """(received, sent) of the destination's queue: records committed and delivered since created."""
        conn = self._connection()
        if conn is None:
            return 0, 0
        try:
            row = conn.execute("SELECT received, sent FROM queues WHERE name=?", (DESTINATION,)).fetchone()
        except sqlite3.Error:
            return 0, 0
        return (int(row[0]), int(row[1])) if row else (0, 0)

    def commit_wall(self, position: int) -> float | None:
        """Wall time of the commit of the ``position``-th row (from 1) of a queue nothing drained."""
        conn = self._connection()
        if conn is None or position < 1:
            return None
        row = conn.execute("SELECT qid FROM queues WHERE name=?", (DESTINATION,)).fetchone()
        if row is None:
            return None
        # The writer stamps rows with the wall time of the group commit that appends them.
        stamp = conn.execute(
            f"SELECT enqueued_ns FROM q_{int(row[0])} ORDER BY id LIMIT 1 OFFSET ?", (position - 1,)
        ).fetchone()
        return None if stamp is None else int(stamp[0]) / 1e9

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()


def wait_until(condition: Callable[[], bool], timeout: float, period: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(period)
    return condition()


def wait_stable(read: Callable[[], int], target: int, timeout: float, quiet: float = 1.5) -> int:
    """Poll ``read`` until it reaches ``target`` or stops changing for ``quiet`` s (bounded)."""
    deadline = time.monotonic() + timeout
    value, changed = read(), time.monotonic()
    while time.monotonic() < deadline and value < target and time.monotonic() - changed < quiet:
        time.sleep(0.05)
        new = read()
        if new != value:
            value, changed = new, time.monotonic()
    return value


# ---------------------------------------------------------------------------------------------
# scenarios
# ---------------------------------------------------------------------------------------------


@dataclass
class Flow:
    """One publisher → receiver measurement."""

    scenario: str
    executor: str
    storage_sync: str
    sent: int
    delivered: int
    bulk: int  # the first BULK share of the delivered records ...
    seconds: float  # ... arrived this long after the first publish
    cpu_s: float
    rate: float = field(init=False)
    lost: int = field(init=False)
    cpu_ms_per_1000: float = field(init=False)

    def __post_init__(self) -> None:
        self.rate = self.bulk / self.seconds if self.seconds > 0 else 0.0
        self.lost = self.sent - self.delivered
        self.cpu_ms_per_1000 = self.cpu_s / max(self.delivered, 1) * 1e6


def _publish(publisher: Child, receiver_pid: int, count: int, rate: float) -> tuple[dict[str, float], float, float]:
    """Run the publisher once it is ready; returns its report and the receiver's CPU at start and window end."""
    if publisher.wait_line(lambda line: line in ("ready", "nomatch"), START_DEADLINE_S) != "ready":
        raise RuntimeError(f"publisher found no subscriber; see {publisher.log.name}")
    cpu_start = cpu_seconds(receiver_pid)
    publisher.send("go\n")
    expected = count / rate if rate > 0 else 0.0
    report = publisher.wait_line(lambda line: line.startswith("{"), expected + 120.0)
    if report is None:
        raise RuntimeError(f"publisher did not finish; see {publisher.log.name}")
    sent = json.loads(report)
    time.sleep(max(sent["t_last"] + SETTLE_S - time.time(), 0.0))
    return sent, cpu_start, cpu_seconds(receiver_pid)


def transport(bench: Bench, kind: str, count: int, rate: float) -> Flow:
    with running(bench.subscriber(kind)) as sub, running(bench.publisher(count, rate)) as pub:
        if sub.wait_line(lambda line: line == "ready", START_DEADLINE_S) is None:
            raise RuntimeError(f"subscriber did not start; see {sub.log.name}")
        sent, cpu0, cpu1 = _publish(pub, sub.pid, count, rate)

        def reports() -> list[tuple[int, float]]:
            return [(int(n), float(t)) for n, t in (line.split() for line in sub.lines if line[:1].isdigit())]

        wait_stable(lambda: reports()[-1][0] if reports() else 0, count, 60.0)
        progress = reports() or [(0, 0.0)]
    delivered = progress[-1][0]
    # The rate of the bulk: a few records resent late by the reliable protocol must not set it.
    bulk, t_bulk = next((n, t) for n, t in progress if n >= BULK * delivered)
    name = "transport flood" if rate <= 0 else f"transport paced {rate:,.0f}/s"
    return Flow(name, kind, "-", count, delivered, bulk, max(t_bulk - sent["t_first"], 1e-9), cpu1 - cpu0)


def intake(bench: Bench, sync: str, count: int, rate: float, destination_up: bool) -> Flow:
    name = f"server-{sync}-{'up' if destination_up else 'down'}-{rate:g}"
    params, buffer, _out = bench.params(name, sync, destination_up)
    reader = BufferReader(buffer)
    with running(bench.server(params)) as server, running(bench.publisher(count, rate)) as pub:
        sent, cpu0, cpu1 = _publish(pub, server.pid, count, rate)
        if destination_up:
            wait_stable(lambda: reader.counters()[1], count, 60.0)
        committed = wait_stable(lambda: reader.counters()[0], count, 60.0)
        bulk = max(math.ceil(BULK * committed), 1)
        t_bulk = None if destination_up else reader.commit_wall(bulk)
        reader.close()
        if server.process.poll() is not None:
            raise RuntimeError(f"destination_server exited; see {server.log.name}")
    scenario = ("server flood" if rate <= 0 else f"server paced {rate:,.0f}/s") + (
        " → file" if destination_up else " → buffer"
    )
    if t_bulk is None:  # delivered rows are gone from the queue: paced, the rate is the publisher's
        bulk, t_bulk = committed, sent["t_last"]
    return Flow(scenario, SERVER, sync, count, committed, bulk, max(t_bulk - sent["t_first"], 1e-9), cpu1 - cpu0)


def fill_backlog(folder: Path, count: int) -> float:
    """A buffer of ``count`` records for the destination, written with the buffer API; returns seconds."""
    from dc_destinations.buffer import PendingRecord, SqliteBuffer
    from dc_destinations.record_ids import new_record_id

    started = time.perf_counter()
    buffer = SqliteBuffer(folder / "delivery.sqlite3", synchronous="normal")
    try:
        buffer.ensure_queues([DESTINATION])
        now = time.time_ns()
        for start in range(0, count, 20_000):
            batch = []
            for n in range(start, min(start + 20_000, count)):
                rid = new_record_id()
                data = {"date": now / 1e9, **{k: v for k, v in _DATA.items() if k != "tags"}, "n": n, "record_id": rid}
                batch.append(PendingRecord(rid, TOPIC, now, json.dumps(data, separators=(",", ":"))))
            buffer.append({DESTINATION: batch})
    finally:
        buffer.close()
    return time.perf_counter() - started


@dataclass
class Backlog:
    storage_sync: str
    executor: str
    records: int
    start_s: float
    rss_idle_mb: float
    hwm_idle_mb: float
    hwm_delivering_mb: float
    delivered: int
    drain_rate: float


def backlog(bench: Bench, sync: str, prepared: Path, count: int) -> Backlog:
    params, buffer, out = bench.params(f"backlog-{sync}", sync, destination_up=False)
    shutil.copytree(prepared, buffer)
    reader = BufferReader(buffer)
    started = time.monotonic()
    with running(bench.server(params)) as server:
        if not wait_until(lambda: "listening on" in server.log_text(), START_DEADLINE_S):
            raise RuntimeError(f"destination_server did not start; see {server.log.name}")
        start_s = time.monotonic() - started
        time.sleep(2.0)  # a few failed delivery rounds against the missing folder
        idle = memory_mb(server.pid)
        out.mkdir()  # the destination comes up at its next retry
        first: float | None = None
        deadline = time.monotonic() + max(120.0, count / 5_000)
        sent = 0
        while time.monotonic() < deadline and sent < count:
            time.sleep(0.05)
            sent = reader.counters()[1]
            if sent and first is None:
                first = time.monotonic()
        done = time.monotonic()
        peak = memory_mb(server.pid)
        reader.close()
    with (out / "records.jsonl").open("rb") as lines:
        delivered = sum(chunk.count(b"\n") for chunk in iter(lambda: lines.read(1 << 20), b""))
    rate = sent / (done - first) if first is not None and done > first else 0.0
    return Backlog(sync, SERVER, count, start_s, idle["VmRSS"], idle["VmHWM"], peak["VmHWM"], delivered, rate)


# ---------------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------------


def _median_flow(flows: list[Flow]) -> Flow:
    ordered = sorted(flows, key=lambda f: f.rate)
    return ordered[len(ordered) // 2] if len(flows) % 2 else ordered[len(ordered) // 2 - 1]


def summarise(flows: list[Flow], kinds: list[str]) -> dict[str, Any]:
    by_key: dict[tuple[str, str, str], list[Flow]] = {}
    for f in flows:
        by_key.setdefault((f.scenario, f.executor, f.storage_sync), []).append(f)
    med = {
        key: {
            "rate": statistics.median(f.rate for f in fs),
            "cpu": statistics.median(f.cpu_ms_per_1000 for f in fs),
            "lost": statistics.median(f.lost for f in fs),
        }
        for key, fs in by_key.items()
    }
    ratios: dict[str, Any] = {}
    for kind in kinds:
        raw_flood = med.get(("transport flood", kind, "-"))
        raw_paced = med.get(("transport paced 1,000/s", kind, "-"))
        for sync in ("normal", "full"):
            server_flood = med.get(("server flood → buffer", SERVER, sync))
            server_paced = med.get(("server paced 1,000/s → file", SERVER, sync))
            if raw_flood and server_flood:
                ratios[f"intake/transport {kind} {sync}"] = server_flood["rate"] / raw_flood["rate"]
            if raw_paced and server_paced:
                ratios[f"cpu server/bare {kind} {sync}"] = server_paced["cpu"] / raw_paced["cpu"]
    return {"medians": {" | ".join(k): v for k, v in med.items()}, "ratios": ratios}


def print_table(flows: list[Flow], backlogs: list[Backlog], summary: dict[str, Any], runs: int) -> None:
    print(
        f"\n{'scenario':<30} {'executor':<8} {'sync':<6} {'sent':>7} {'delivered':>9} {'lost':>6} "
        f"{'rec/s':>8} {'CPU ms/1000':>11}   (medians of {runs} run(s))"
    )
    for key, m in summary["medians"].items():
        scenario, kind, sync = key.split(" | ")
        sample = next(f for f in flows if (f.scenario, f.executor, f.storage_sync) == (scenario, kind, sync))
        print(
            f"{scenario:<30} {kind:<8} {sync:<6} {sample.sent:>7} {sample.sent - m['lost']:>9.0f} {m['lost']:>6.0f} "
            f"{m['rate']:>8,.0f} {m['cpu']:>11.0f}"
        )
    print()
    for name, value in summary["ratios"].items():
        if name.startswith("intake"):
            verdict = "met" if value >= INTAKE_TARGET else "MISSED"
            print(f"{name:<34} {value:6.0%}   target >= {INTAKE_TARGET:.0%}: {verdict}")
        else:
            verdict = "met" if value <= CPU_TARGET else "MISSED"
            print(f"{name:<34} {value:6.2f}x  target <= {CPU_TARGET}x: {verdict}")
    for b in backlogs:
        print(
            f"backlog {b.records:,} ({b.storage_sync}, {b.executor}): started in {b.start_s:.1f} s; "
            f"RSS {b.rss_idle_mb:.0f} MB (peak {b.hwm_idle_mb:.0f}) with the destination down; "
            f"peak {b.hwm_delivering_mb:.0f} MB while delivering; buffer → file {b.drain_rate:,.0f} rec/s "
            f"({b.delivered:,} lines written)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--role", choices=["main", "publisher", "subscriber"], default="main")
    parser.add_argument("--executor", default="single", help=argparse.SUPPRESS)
    parser.add_argument("--count", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--rate", type=float, default=0.0, help=argparse.SUPPRESS)
    parser.add_argument("--topic", default=TOPIC, help=argparse.SUPPRESS)
    parser.add_argument(
        "--transports", default="single,intake", help="bare subscribers, comma-separated: single, intake"
    )
    parser.add_argument("--flood", type=int, default=20_000, help="records published as fast as possible")
    parser.add_argument("--paced-seconds", type=float, default=10.0, help="length of the 1,000/s runs")
    parser.add_argument("--backlog", type=int, default=1_000_000, help="records of the backlog (0: skip)")
    parser.add_argument("--runs", type=int, default=1, help="repeat the flows; medians are reported")
    parser.add_argument("--domain", type=int, default=random.randint(150, 230), help="ROS_DOMAIN_ID")
    parser.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "end_to_end.json"))
    args = parser.parse_args()
    if args.role == "publisher":
        role_publisher(args.count, args.rate)
        return
    if args.role == "subscriber":
        role_subscriber(args.executor, args.topic)
        return

    kinds = [k for k in args.transports.split(",") if k]
    paced = int(args.paced_seconds * 1000)
    flows: list[Flow] = []
    backlogs: list[Backlog] = []
    started = datetime.now(UTC)
    with tempfile.TemporaryDirectory(prefix="dc-bench-") as tmp:
        bench = Bench(Path(tmp), args.domain)
        for run in range(args.runs):
            steps: list[tuple[str, str, int, float, bool]] = []
            for kind in kinds:
                steps += [(kind, "-", args.flood, 0.0, False), (kind, "-", paced, 1000.0, True)]
            for sync in ("normal", "full"):
                steps += [(SERVER, sync, args.flood, 0.0, False), (SERVER, sync, paced, 1000.0, True)]
            for kind, sync, count, rate, destination_up in steps:
                if sync == "-":
                    flow = transport(bench, kind, count, rate)
                else:
                    flow = intake(bench, sync, count, rate, destination_up)
                flows.append(flow)
                print(
                    f"run {run + 1}: {flow.scenario:<30} {flow.executor:<7} {flow.storage_sync:<6} "
                    f"{flow.delivered:>6}/{flow.sent:<6} {flow.rate:>8,.0f} rec/s "
                    f"{flow.cpu_ms_per_1000:>5.0f} ms CPU/1000",
                    flush=True,
                )
        if args.backlog > 0:
            prepared = Path(tmp) / "backlog"
            seconds = fill_backlog(prepared, args.backlog)
            print(f"backlog of {args.backlog:,} records written in {seconds:.1f} s", flush=True)
            for sync in ("normal", "full"):
                backlogs.append(backlog(bench, sync, prepared, args.backlog))
    summary = summarise(flows, kinds)
    print_table(flows, backlogs, summary, args.runs)
    document = {
        "date": started.isoformat(timespec="seconds"),
        "machine": {
            "cpus": os.cpu_count(),
            "processor": _processor(),
            "python": platform.python_version(),
            "kernel": platform.release(),
        },
        "settings": {k: v for k, v in vars(args).items() if k not in ("role", "executor", "count", "rate", "topic")},
        "flows": [asdict(f) for f in flows],
        "backlog": [asdict(b) for b in backlogs],
        **summary,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {args.json}")


def _processor() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor()


if __name__ == "__main__":
    main()
