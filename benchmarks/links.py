"""What only_when and the caps cost per record, and how close a cap keeps to its rate (no ROS).

    .venv/bin/python benchmarks/links.py [--records 100000] [--rounds 3]

Cost: a backlog of --records records is delivered by the real sender to a destination that counts
and discards, once plain and once with every rule that reads the machine (default route through
/proc/net/route, an interface's flags in /sys/class/net, a condition, a daily window of 24 h) and
a cap and a link cap too high to ever wait: the sender's CPU time (the process's, the writer idle)
per record, alternated round by round; median of the rounds and the ratio (target: <= 1.05).

Accuracy: 2 MB of records through a 200 kB/s cap with a 0.5 s burst: bytes per second delivered
against the cap, and the most any 1 s window carried against cap + burst.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from dc_core.destination import Destination, OutgoingRecord
from dc_destinations.delivery import DeliveryPipeline
from dc_destinations.links import OnlyWhenParams
from dc_destinations.record_ids import new_record_id
from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

# The repository's root: benchmarks/ is a namespace package there, which mypy resolves as well.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.delivery_backlog import _Context, _Quiet  # a sibling script's quiet plugin context

_DATA = {"cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]}, "memory": {"used": 123456789}, "name": "system"}


class _Count(Destination):  # type: ignore[type-arg]
    def __init__(self) -> None:
        super().__init__(_Context(), None)
        self.count = 0
        self.log: list[tuple[float, int]] = []
        self.done = threading.Event()
        self.expect = 0

    def send(self, batch: Sequence[OutgoingRecord]) -> None:
        self.count += len(batch)
        self.log.append((time.monotonic(), sum(len(r.to_json()) for r in batch)))
        if self.count >= self.expect:
            self.done.set()


def _records(n: int) -> list[OutgoingRecord]:
    return [OutgoingRecord.serialised(new_record_id(), "/dc/measurement/system", i, dict(_DATA)) for i in range(n)]


def _deliver(records: list[OutgoingRecord], params: DestinationDeliveryParams, flb: dict[str, object]) -> float:
    """CPU seconds of the process while the sender delivers a committed backlog."""
    with tempfile.TemporaryDirectory() as folder:
        sink = _Count()
        sink.expect = len(records)
        settings = DeliveryParams(storage_path=folder, flush=0.05, **flb)  # type: ignore[arg-type]
        # The backlog committed while held (a condition never heard), then delivered by a new pipeline.
        held = DestinationDeliveryParams(only_when=OnlyWhenParams(conditions=["never"]))
        pipeline = DeliveryPipeline(settings, {"bench": (sink, held)}, _Quiet())
        pipeline.start()
        for i, record in enumerate(records):
            pipeline.submit("bench", record)
            if i % 5000 == 4999:  # within intake_queue_limit
                pipeline.flush_intake(60)
        pipeline.flush_intake(60)
        pipeline.stop(0.0)
        sink = _Count()
        sink.expect = len(records)
        pipeline = DeliveryPipeline(settings, {"bench": (sink, params)}, _Quiet())
        pipeline.start()
        start = time.process_time()
        sink.done.wait(120)
        used = time.process_time() - start
        pipeline.stop(0.0)
        assert sink.count == len(records), sink.count
        return used


def cost(n: int, rounds: int) -> None:
    records = _records(n)
    plain = DestinationDeliveryParams(batch_size=500)
    ruled = DestinationDeliveryParams(
        batch_size=500,
        only_when=OnlyWhenParams(
            default_route_not_via=["wwan-none"], interfaces_up=["lo"], window="00:00-24:00", window_utc=True
        ),
        max_bytes_per_s="10G",
        link="lan",
        priority=1,
    )
    flb = {"links": {"lan": "10G"}}
    times: dict[str, list[float]] = {"plain": [], "rules+caps": []}
    for i in range(rounds):  # in turns, each first every other round
        order = [("plain", plain), ("rules+caps", ruled)]
        for name, params in order if i % 2 == 0 else reversed(order):
            times[name].append(_deliver(records, params, flb))
    medians = {name: statistics.median(values) for name, values in times.items()}
    for name, value in medians.items():
        rounds_s = ", ".join(f"{v:.3f}" for v in times[name])
        print(f"{name:12s} {value / n * 1e6:7.2f} µs CPU per record (rounds: {rounds_s} s)")
    print(f"ratio rules+caps / plain: {medians['rules+caps'] / medians['plain']:.3f} (target <= 1.05)")


def accuracy() -> None:
    rate, burst_s = 200_000, 0.5
    records = _records(20_000)  # ~100 bytes each: ~2 MB
    with tempfile.TemporaryDirectory() as folder:
        sink = _Count()
        sink.expect = len(records)
        settings = DeliveryParams(storage_path=folder, flush=0.05, burst_s=burst_s)
        params = DestinationDeliveryParams(batch_size=100, max_bytes_per_s=str(rate))
        pipeline = DeliveryPipeline(settings, {"bench": (sink, params)}, _Quiet())
        pipeline.start()
        for i, record in enumerate(records):
            pipeline.submit("bench", record)
            if i % 5000 == 4999:
                pipeline.flush_intake(60)
        sink.done.wait(120)
        pipeline.stop(0.0)
    start, end = sink.log[0][0], sink.log[-1][0]
    total = sum(n for _, n in sink.log)
    worst = max(sum(n for t, n in sink.log if s <= t < s + 1.0) for s, _ in sink.log)
    after_burst = (total - rate * burst_s) / (end - start)
    print(
        f"cap {rate} B/s, burst {rate * burst_s:.0f} B: {total} B in {end - start:.2f} s = "
        f"{after_burst:.0f} B/s after the burst ({after_burst / rate:.3f} of the cap); "
        f"worst 1 s window {worst} B (cap + burst: {rate * (1 + burst_s):.0f})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=100_000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    cost(args.records, args.rounds)
    accuracy()


if __name__ == "__main__":
    main()
