"""Benchmark of the delivery layer alone (no ROS): intake → committed buffer, buffer → destination.

    .venv/bin/python benchmarks/delivery_pipeline.py [--records 50000] [--runs 3]

Prints, for storage_sync normal and full (medians of --runs):
- intake: records/s from submit() to committed (flush_intake returned), with a destination that is
  down so nothing is drained meanwhile; CPU ms per 1,000 records of the whole process;
- drain: records/s from the buffer to a destination that writes JSON lines to a file;
- paced: CPU ms per 1,000 records at a paced 1,000 records/s, submit to file (what the pipeline
  adds to destination_server's cost at robot rates);
- restart: RSS and time to deliver a backlog of --backlog records after a restart.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dc_core.destination import Destination, OutgoingRecord, RetryableError
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

# ~200 bytes of JSON, like the measured figures of design.md §7.
_DATA = {
    "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
    "memory": {"used": 123456789, "percent": 45.6},
    "robot_name": "bench",
    "id": "robot-1",
    "run_id": "3",
    "name": "system",
}


class _Quiet:
    def debug(self, message: str, **kwargs: Any) -> None:
        pass

    info = warning = error = debug


class _NoContext:
    name = "bench"
    logger = _Quiet()
    node = None


class _Down(Destination):
    def __init__(self) -> None:
        super().__init__(_NoContext(), None)

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("down")


class _JsonLines(Destination):
    def __init__(self, path: Path) -> None:
        super().__init__(_NoContext(), None)
        self.path = path
        self.count = 0

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        with self.path.open("a", encoding="utf-8") as out:
            out.writelines(r.to_json() + "\n" for r in batch)
        self.count += len(batch)


def _record(n: int) -> OutgoingRecord:
    rid = new_record_id()
    return OutgoingRecord(rid, "/dc/measurement/system", n, {**_DATA, "n": n, "record_id": rid})


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _settings(path: str, sync: str) -> DeliveryParams:
    # A tight submit() loop outruns any disk: let the hand-off queue hold the whole flood, so the
    # figures are commit throughput rather than intake_queue_limit drops.
    return DeliveryParams(storage_path=path, storage_sync=sync, scheduler_base=60.0, intake_queue_limit=10_000_000)


def intake(sync: str, count: int) -> tuple[float, float]:
    records = [_record(i) for i in range(count)]
    with tempfile.TemporaryDirectory() as folder:
        pipeline = DeliveryPipeline(_settings(folder, sync), {"down": (_Down(), DestinationDeliveryParams())}, _Quiet())
        pipeline.start()
        cpu, start = _cpu(), time.perf_counter()
        for r in records:
            pipeline.submit("down", r)
        pipeline.flush_intake()
        elapsed, used = time.perf_counter() - start, _cpu() - cpu
        pipeline.stop(0.0)
    return count / elapsed, used / count * 1e6


def drain(sync: str, count: int) -> float:
    with tempfile.TemporaryDirectory() as folder:
        first = DeliveryPipeline(_settings(folder, sync), {"out": (_Down(), DestinationDeliveryParams())}, _Quiet())
        first.start()
        for i in range(count):
            first.submit("out", _record(i))
        first.flush_intake()
        first.stop(0.0)
        sink = _JsonLines(Path(folder) / "out.jsonl")
        second = DeliveryPipeline(_settings(folder, sync), {"out": (sink, DestinationDeliveryParams())}, _Quiet())
        start = time.perf_counter()
        second.start()
        while sink.count < count:
            time.sleep(0.002)
        elapsed = time.perf_counter() - start
        second.stop(0.0)
    return count / elapsed


def pacing_only(seconds: float, rate: float = 1000.0) -> float:
    """CPU µs per record of the pacing loop itself, subtracted from :func:`paced`."""
    total = int(seconds * rate)
    cpu, start = _cpu(), time.perf_counter()
    for i in range(total):
        delay = start + i / rate - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    return (_cpu() - cpu) / total * 1e6


def paced(sync: str, seconds: float, rate: float = 1000.0) -> float:
    with tempfile.TemporaryDirectory() as folder:
        sink = _JsonLines(Path(folder) / "out.jsonl")
        pipeline = DeliveryPipeline(_settings(folder, sync), {"out": (sink, DestinationDeliveryParams())}, _Quiet())
        pipeline.start()
        total = int(seconds * rate)
        records = [_record(i) for i in range(total)]
        cpu, start = _cpu(), time.perf_counter()
        for i, r in enumerate(records):
            delay = start + i / rate - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            pipeline.submit("out", r)
        while sink.count < total:
            time.sleep(0.005)
        used = _cpu() - cpu
        pipeline.stop(0.0)
    return used / total * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--records", type=int, default=50_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--paced-seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(
        f"{os.cpu_count()} CPUs, {args.records} records of ~{len(_record(0).to_json())} bytes, "
        f"medians of {args.runs} runs"
    )
    baseline = statistics.median(pacing_only(args.paced_seconds) for _ in range(args.runs))
    print(f"pacing loop alone: {baseline:.0f} ms CPU/1000 (subtracted from the paced figures)")
    for sync in ("normal", "full"):
        rates, costs = zip(*(intake(sync, args.records) for _ in range(args.runs)), strict=True)
        drains = [drain(sync, args.records) for _ in range(args.runs)]
        pace = [paced(sync, args.paced_seconds) for _ in range(args.runs)]
        print(
            f"storage_sync={sync:<6}  intake→committed {statistics.median(rates):>9,.0f} rec/s "
            f"({statistics.median(costs):.0f} ms CPU/1000)   buffer→file {statistics.median(drains):>9,.0f} rec/s   "
            f"paced 1000/s submit→file {statistics.median(pace):.0f} ms CPU/1000"
        )


if __name__ == "__main__":
    main()
