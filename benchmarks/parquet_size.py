"""Bytes per record of the S3 destination's objects: JSON lines, JSON lines + gzip, Parquet (zstd).

No S3 server: the objects' bytes are what the destination would upload (its own encoders:
``S3._json_objects`` with ``compression: gzip`` as ``_upload`` compresses, and
``dc_destinations.s3.parquet.encode`` per measurement). The records are shaped as the robot job's
(Cpu with its five busiest processes, Memory, Uptime, Position), with DC's keys (date, name,
robot_name, run_id, schema_version, record_id). Also the CPU time to encode, per record.

    .venv/bin/python benchmarks/parquet_size.py [--batches 100 500 5000]
"""

from __future__ import annotations

import argparse
import gzip
import random
import time
from typing import Any

from dc_core.destination import OutgoingRecord
from dc_destinations.record_ids import new_record_id
from dc_destinations.s3 import parquet

COMMANDS = ["/usr/bin/python3 -m dc_bringup", "nav2_controller", "[kworker/0:1]", "/usr/lib/xorg/Xorg", "rviz2"]


def robot_records(count: int, seed: int = 1) -> list[OutgoingRecord]:
    rng = random.Random(seed)
    stamp_ns = 1_764_000_000_000_000_000
    out = []
    for n in range(count):
        stamp_ns += 250_000_000
        kind = n % 4
        data: dict[str, Any]
        if kind == 0:
            processes = [
                {
                    "pid": 1000 + rng.randrange(5000),
                    "user": "robot",
                    "cmd": rng.choice(COMMANDS),
                    "cpu": round(rng.uniform(0, 80), 1),
                    "ram": rng.randrange(10_000, 900_000),
                    "uptime": rng.randrange(10, 90_000),
                }
                for _ in range(5)
            ]
            data = {"average": round(rng.uniform(5, 60), 2), "processes": rng.randrange(180, 260), "sorted": processes}
            data["name"] = "cpu"
        elif kind == 1:
            data = {"used": round(rng.uniform(20, 70), 2), "name": "memory"}
        elif kind == 2:
            data = {"time": 3600 + n // 4, "name": "uptime"}
        else:
            data = {"x": rng.uniform(-50, 50), "y": rng.uniform(-50, 50), "yaw": rng.uniform(-3.14, 3.14)}
            data["name"] = "position"
        rid = new_record_id()
        record = {"date": stamp_ns / 1e9, **data, "robot_name": "robot-007", "run_id": "42", "schema_version": 1}
        record["record_id"] = rid
        out.append(OutgoingRecord(rid, f"/dc/measurement/{data['name']}", stamp_ns, record))
    return out


def measure(records: list[OutgoingRecord], batch: int) -> dict[str, float]:
    schemas = parquet.MeasurementSchemas({}, "measurement_schemas")
    sizes = {"json": 0, "gzip": 0, "parquet": 0}
    cpu = {"gzip": 0.0, "parquet": 0.0}
    objects = 0
    for start in range(0, len(records), batch):
        chunk = records[start : start + batch]
        body = b"".join((r.to_json() + "\n").encode() for r in chunk)
        sizes["json"] += len(body)
        t = time.process_time()
        sizes["gzip"] += len(gzip.compress(body, mtime=0))
        cpu["gzip"] += time.process_time() - t
        t = time.process_time()
        groups: dict[str, list[tuple[int, dict[str, Any]]]] = {}
        for i, r in enumerate(chunk):
            groups.setdefault(r.data["name"], []).append((i, r.data))
        for name, rows in groups.items():
            encoded = parquet.encode(rows, schemas.of(name), lambda i, why: None)
            assert encoded is not None and len(encoded[0]) == len(rows)
            sizes["parquet"] += len(encoded[1])
            objects += 1
        cpu["parquet"] += time.process_time() - t
    n = len(records)
    return {
        "json_B": sizes["json"] / n,
        "gzip_B": sizes["gzip"] / n,
        "parquet_B": sizes["parquet"] / n,
        "gzip_us": cpu["gzip"] / n * 1e6,
        "parquet_us": cpu["parquet"] / n * 1e6,
        "parquet_objects": objects,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--records", type=int, default=20_000)
    parser.add_argument("--batches", type=int, nargs="+", default=[100, 500, 5000])
    args = parser.parse_args()
    records = robot_records(args.records)
    print(f"{args.records} records (cpu, memory, uptime, position in turn), bytes and CPU per record")
    print("| batch | JSON lines | + gzip | Parquet (zstd) | Parquet / gzip | CPU gzip | CPU Parquet | objects |")
    print("|---|---|---|---|---|---|---|---|")
    for batch in args.batches:
        m = measure(records, batch)
        print(
            f"| {batch} | {m['json_B']:.0f} B | {m['gzip_B']:.0f} B | {m['parquet_B']:.0f} B | "
            f"{m['parquet_B'] / m['gzip_B']:.2f} | {m['gzip_us']:.1f} µs | {m['parquet_us']:.1f} µs | "
            f"{m['parquet_objects']:.0f} |"
        )


if __name__ == "__main__":
    main()
