"""measurement_server forwarding your nodes' records (a StringStamped measurement), in real processes.

CPU of measurement_server per 1,000 records at a paced 1,000/s, beside bare subscribers of the
same run (rclpy's default executor, DC's intake loop): what taking a record costs, against what
DC adds (JSON parsing, metadata, the output record, publishing it again); and beside a bare
forwarder on DC's intake loop, which publishes each record's bytes again as it took them: the
cheapest way to do the job, without reading the record.

    .venv/bin/python benchmarks/measurement_forwarding.py --runs 3
    git worktree add /tmp/before HEAD~1
    .venv/bin/python benchmarks/measurement_forwarding.py --runs 3 before=/tmp/before after=.

Processes, domain and temporary folder as in end_to_end.py (whose children this script reuses).
The forwarded records are counted by a bare intake subscriber on the output topic, so a
measurement that does not forward everything shows as lost.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import end_to_end as e2e  # a sibling script, not a package

OUTPUT = e2e.FORWARDED
RATE = 1000.0
# Bare receivers, and the cheapest way to do the same job: a forwarder publishing each record's bytes again.
KINDS = ("single", "intake", "forward")


# With --handoff: a destination_server section reading the output, so that measurement_server keeps
# every record for its acknowledgement (dc_core.handoff); no destination_server runs, so none is
# acknowledged and all stay held (10 s at 1,000/s: well within the default limits).
HANDOFF_SECTION = f"""destination_server:
  ros__parameters:
    destination_plugins: ["file"]
    file:
      plugin: "dc_destinations/File"
      inputs: ["{OUTPUT}"]
"""
HANDOFF = False


def server_params(folder: Path) -> Path:
    params = folder / "measurement_server.yaml"
    params.write_text(
        (HANDOFF_SECTION if HANDOFF else "")
        + f"""measurement_server:
  ros__parameters:
    measurement_plugins: ["forwarded"]
    run_id:
      enabled: false
    forwarded:
      plugin: "dc_measurements/StringStamped"
      topic: "{e2e.TOPIC}"
      topic_output: "{OUTPUT}"
      timer_based: false
      qos_depth: 1000
      enable_validator: false
"""
    )
    return params


def forwarding(bench: e2e.Bench, folder: Path, count: int) -> tuple[float, int]:
    """measurement_server's CPU ms per 1,000 records, and how many the counter on its output got."""
    argv = [sys.executable, "-m", "dc_measurements.server", str(server_params(folder)), "--autostart"]
    return forwarded_by(bench, e2e.Child(argv, bench.env, folder / "measurement_server.log"), count)


def forwarded_by(bench: e2e.Bench, forwarder: e2e.Child, count: int) -> tuple[float, int]:
    """CPU ms per 1,000 records of ``forwarder`` (publishing on OUTPUT), and how many the counter there got.

    The same for measurement_server and the bare forwarder: a subscriber on the output makes DDS
    deliver what is published, as in a real job.
    """
    with (
        e2e.running(bench.subscriber("intake", OUTPUT)) as counter,
        e2e.running(forwarder) as server,
        e2e.running(bench.publisher(count, RATE)) as publisher,
    ):
        if counter.wait_line(lambda line: line == "ready", e2e.START_DEADLINE_S) is None:
            raise RuntimeError("the counting subscriber did not start")
        _, cpu0, cpu1 = e2e._publish(publisher, server.pid, count, RATE)

        def forwarded() -> int:
            counts = [int(line.split()[0]) for line in counter.lines if line[:1].isdigit()]
            return counts[-1] if counts else 0

        delivered = e2e.wait_stable(forwarded, count, 60.0)
    return (cpu1 - cpu0) / max(delivered, 1) * 1e6, delivered


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "trees",
        nargs="*",
        default=["measurement_server=."],
        help="NAME=PATH of checkouts whose measurement_server is measured, in turns (default: this one)",
    )
    parser.add_argument("--seconds", type=float, default=10.0, help="length of each paced run")
    parser.add_argument("--runs", type=int, default=1, help="repeat; medians are reported")
    parser.add_argument("--domain", type=int, default=random.randint(150, 230), help="ROS_DOMAIN_ID")
    parser.add_argument("--json", default=str(e2e.REPO / "benchmarks" / "results" / "measurement_forwarding.json"))
    parser.add_argument(
        "--handoff", action="store_true", help="a destination_server reads the output: records are kept for its ack"
    )
    args = parser.parse_args()
    global HANDOFF
    HANDOFF = args.handoff
    trees = e2e.checkouts(parser, args.trees)
    count = int(args.seconds * RATE)
    cpu: dict[str, list[float]] = {kind: [] for kind in (*KINDS, *trees)}
    lost: dict[str, list[int]] = {name: [] for name in ("forward", *trees)}
    with tempfile.TemporaryDirectory(prefix="dc-bench-") as tmp:
        bench = e2e.Bench(Path(tmp), args.domain)
        bench.env["HOME"] = tmp
        for run in range(args.runs):
            for kind in KINDS:
                if kind == "forward":
                    ms, delivered = forwarded_by(bench, bench.subscriber("forward"), count)
                    lost["forward"].append(count - delivered)
                else:
                    ms = e2e.transport(bench, kind, count, RATE).cpu_ms_per_1000
                cpu[kind].append(ms)
                print(f"run {run + 1}: bare {kind:<7} {ms:5.0f} ms CPU/1000", flush=True)
            for name in list(trees) if run % 2 == 0 else list(reversed(trees)):
                folder = Path(tmp) / f"run-{run}-{name}"
                folder.mkdir()
                e2e.REPO = trees[name]  # the server child's working directory: its packages are imported
                ms, delivered = forwarding(bench, folder, count)
                cpu[name].append(ms)
                lost[name].append(count - delivered)
                print(f"run {run + 1}: {name} {ms:5.0f} ms CPU/1000, {count - delivered} lost", flush=True)
    medians = {name: statistics.median(values) for name, values in cpu.items()}
    print(f"\nmedians of {args.runs} run(s), paced {RATE:,.0f} records/s, CPU ms per 1,000 records:")
    for name, value in medians.items():
        print(f"  {name:<20} {value:6.0f}")
    for name in trees:
        for kind in KINDS:
            print(f"  {name} / bare {kind:<7} {medians[name] / medians[kind]:5.2f}x")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    document = {
        "runs": args.runs,
        "trees": {name: str(path) for name, path in trees.items()},
        "cpu_ms_per_1000": cpu,
        "medians": medians,
        "lost": lost,
    }
    Path(args.json).write_text(json.dumps(document, indent=2) + "\n")
    print(f"\nJSON: {args.json}")


if __name__ == "__main__":
    main()
