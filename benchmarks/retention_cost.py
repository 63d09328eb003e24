"""What retention priorities per measurement cost per record: commit, send and delete (no ROS).

    .venv/bin/python benchmarks/retention_cost.py [--records 50000] [--rounds 6] [NAME=PATH ...]

One run: a process submits --records records of two measurements, alternating (~170 bytes of
JSON each), to a pipeline under a disk budget too large to evict anything, delivered as they come
to a destination that counts and discards; its CPU time from the first submit to the stop that
deletes the last confirmed rows, per record. Each run in a process of its own, the configurations
and code trees in turns round by round (order reversed every other round); medians and ratios:

- ``plain``: the budget, no ``retention_priorities`` (what a destination without them runs);
- ``per-measurement``: the budget and ``retention_priorities`` giving the two measurements
  different priorities: the queue indexed by topic and, as once the budget first needed them, its
  bytes kept per topic on every commit and delete.

``NAME=PATH`` adds a checkout (``git worktree add /tmp/before <commit>``) whose ``plain`` is run
in the same turns, its own packages imported (PYTHONPATH): the cost of this code against it when
no priority per measurement is configured (target: within 1.05).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

_DATA = {"cpu": {"percent": 12.5, "load": [0.5, 0.4, 0.3]}, "memory": {"used": 123456789}, "robot_name": "bench"}
_TOPICS = ("/dc/measurement/health", "/dc/measurement/camera")
HERE = Path(__file__).resolve().parent.parent


def child(config: str, count: int) -> float:
    """In the measured process: CPU seconds of commit + send + delete of ``count`` records."""
    from dc_core.destination import Destination, OutgoingRecord
    from dc_destinations.delivery import DeliveryPipeline
    from dc_destinations.record_ids import new_record_id
    from dc_destinations.settings import DeliveryParams, DestinationDeliveryParams

    # A sibling script's quiet plugin context (its folder, not the checkout's root, is on the path:
    # the checkout measured is the one PYTHONPATH names).
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from delivery_backlog import _Context, _Quiet

    class Count(Destination):  # type: ignore[type-arg]
        def __init__(self) -> None:
            super().__init__(_Context(), None)
            self.count = 0
            self.done = threading.Event()

        def send(self, batch: Sequence[OutgoingRecord]) -> None:
            self.count += len(batch)
            if self.count >= count:
                self.done.set()

    records = [OutgoingRecord.serialised(new_record_id(), _TOPICS[i % 2], i, {**_DATA, "n": i}) for i in range(count)]
    options: dict[str, Any] = {"batch_size": 500}
    if config == "per-measurement":
        options["retention_priorities"] = {"health": 10, "camera": 0}
    with tempfile.TemporaryDirectory() as folder:
        sink = Count()
        settings = DeliveryParams(storage_path=folder, flush=0.05, disk_budget="1G")
        pipeline = DeliveryPipeline(settings, {"bench": (sink, DestinationDeliveryParams(**options))}, _Quiet())
        pipeline.start()
        if config == "per-measurement":
            # What the first time over the budget does: from then on the queue is counted per topic.
            buffer = pipeline._buffer
            assert buffer is not None
            buffer.queued_topics("bench")
        start = time.process_time()
        for i, record in enumerate(records):
            pipeline.submit("bench", record)
            if i % 5000 == 4999:  # within intake_queue_limit
                pipeline.flush_intake(60)
        pipeline.flush_intake(60)
        if not sink.done.wait(300):
            raise RuntimeError(f"{sink.count} of {count} delivered")
        pipeline.stop(1.0)
        used = time.process_time() - start
    return used


def run(tree: Path, config: str, count: int) -> float:
    script = Path(__file__).resolve()
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run(
        [sys.executable, str(script), "--child", config, "--records", str(count)],
        cwd=tree,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return float(json.loads(out.strip().splitlines()[-1])["cpu_s"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trees", nargs="*", help="NAME=PATH of another checkout whose plain run is measured too")
    parser.add_argument("--records", type=int, default=50_000)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--child", choices=("plain", "per-measurement"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps({"cpu_s": child(args.child, args.records)}))
        return
    runs: list[tuple[str, Path, str]] = [("this", HERE, "plain"), ("this", HERE, "per-measurement")]
    for spec in args.trees:
        name, _, path = spec.partition("=")
        runs.append((name, Path(path).resolve(), "plain"))
    cpu: dict[str, list[float]] = {f"{name} {config}": [] for name, _, config in runs}
    for round_ in range(args.rounds):
        for name, tree, config in runs if round_ % 2 == 0 else list(reversed(runs)):
            cpu[f"{name} {config}"].append(run(tree, config, args.records))
        print(f"round {round_ + 1}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in cpu.items()), flush=True)
    medians = {key: statistics.median(values) for key, values in cpu.items()}
    for key, value in medians.items():
        print(f"{key:28s} {value / args.records * 1e6:6.2f} µs CPU per record (median of {args.rounds})")
    plain = medians["this plain"]
    print(f"ratio this per-measurement / this plain: {medians['this per-measurement'] / plain:.3f}")
    for spec in args.trees:
        name = spec.partition("=")[0]
        print(f"ratio this plain / {name} plain: {plain / medians[f'{name} plain']:.3f} (target <= 1.05)")


if __name__ == "__main__":
    main()
