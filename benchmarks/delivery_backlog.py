"""RSS and delivery rate of the delivery layer restarting on a large backlog (no ROS).

    .venv/bin/python benchmarks/delivery_backlog.py [--records 1000000]

A child process fills a buffer with --records records for a destination that is down and is
killed; a second, fresh process starts a pipeline on that buffer with a destination that counts
and discards, and reports its RSS before start, its peak RSS while delivering the whole backlog,
the time to open the buffer, and the delivery rate.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence

import psutil

from dc_core.destination import Destination, OutgoingRecord, RetryableError
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

_DATA = {
    "cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]},
    "memory": {"used": 123456789, "percent": 45.6},
    "robot_name": "bench",
    "id": "robot-1",
    "run_id": "3",
    "name": "system",
}


class _Quiet:
    def debug(self, message: str, **kwargs: object) -> None:
        pass

    info = warning = error = debug


class _Context:
    name = "bench"
    logger = _Quiet()
    node = None


class _Down(Destination):
    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        raise RetryableError("down")


class _Count(Destination):
    count = 0

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        self.count += len(batch)


def _params(folder: str) -> DeliveryParams:
    return DeliveryParams(storage_path=folder, scheduler_base=600.0, intake_queue_limit=10_000_000)


def fill(folder: str, count: int) -> None:
    pipeline = DeliveryPipeline(
        _params(folder),
        {"out": (_Down(_Context(), None), DestinationDeliveryParams(storage_total_limit_size="0"))},
        _Quiet(),
    )
    pipeline.start()
    for start in range(0, count, 50_000):
        for n in range(start, min(start + 50_000, count)):
            rid = new_record_id()
            pipeline.submit(
                "out", OutgoingRecord(rid, "/dc/measurement/system", n, {**_DATA, "n": n, "record_id": rid})
            )
        pipeline.flush_intake()


def drain(folder: str, count: int) -> None:
    process = psutil.Process()
    before = process.memory_info().rss
    sink = _Count(_Context(), None)
    pipeline = DeliveryPipeline(_params(folder), {"out": (sink, DestinationDeliveryParams())}, _Quiet())
    peak = before
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.wait(0.05):
            peak = max(peak, process.memory_info().rss)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    started = time.perf_counter()
    pipeline.start()
    opened = time.perf_counter() - started
    while sink.count < count:
        time.sleep(0.01)
    elapsed = time.perf_counter() - started
    done.set()
    sampler.join()
    pipeline.stop(0.0)
    print(
        f"backlog {count:,} records: start {opened * 1000:.0f} ms, delivered at {count / elapsed:,.0f} rec/s; "
        f"RSS {before / 2**20:.0f} MB before start, peak {peak / 2**20:.0f} MB while delivering"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--records", type=int, default=1_000_000)
    parser.add_argument("--role", choices=["main", "fill", "drain"], default="main")
    parser.add_argument("--folder", default="")
    args = parser.parse_args()
    if args.role == "fill":
        fill(args.folder, args.records)
        return
    if args.role == "drain":
        drain(args.folder, args.records)
        return
    with tempfile.TemporaryDirectory() as folder:
        me = [sys.executable, __file__, "--records", str(args.records), "--folder", folder]
        subprocess.run([*me, "--role", "fill"], check=True)
        subprocess.run([*me, "--role", "drain"], check=True)


if __name__ == "__main__":
    main()
